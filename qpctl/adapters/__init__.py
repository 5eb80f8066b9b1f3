"""Adapters that let any qpctl controller drive another simulator, behind one interface.

* :class:`SimulatorBase` — the interface every simulator implements (reset, read, apply, step,
  obstacle positions) and the one recording loop (:func:`record_run`) that fills the trajectory
  behind ``trajectory.npz`` and ``metrics.json`` for all of them (:mod:`qpctl.simulation.loop`).
* :data:`SIMULATORS` — the registry behind ``--sim`` / ``sim.simulator``: a new simulator is one
  module with a :class:`SimulatorBase` subclass and one line here.
* :class:`JointMap` — the simulator's joint order ↔ the model's (``robot.joint_names``), by name.
* :mod:`qpctl.adapters.mujoco` (``pip install 'qpctl[mujoco]'``), :mod:`qpctl.adapters.pybullet`
  (``pip install 'qpctl[pybullet]'``) and :mod:`qpctl.adapters.drake` (``pip install 'qpctl[drake]'``),
  imported on demand: optional dependencies.
"""

from __future__ import annotations

import importlib

from qpctl.adapters.joint_map import JointMap
from qpctl.errors import ConfigError
from qpctl.simulation.loop import SimulatorBase, record_run

# name → (module, class, the pip extra that brings its simulator; None: always there)
SIMULATORS: dict[str, tuple[str, str, str | None]] = {
    "builtin": ("qpctl.simulation.simulator", "Simulator", None),
    "mujoco": ("qpctl.adapters.mujoco", "MujocoSimulator", "mujoco"),
    "pybullet": ("qpctl.adapters.pybullet", "PybulletSimulator", "pybullet"),
    "drake": ("qpctl.adapters.drake", "DrakeSimulator", "drake"),
}


def simulator_class(name: str) -> type[SimulatorBase]:
    """The :class:`SimulatorBase` subclass registered as ``name``.

    Raises:
        ConfigError (key ``sim.simulator``): an unknown name (the message lists the known ones), or a
            simulator whose package is not installed (the message says which extra to install).
    """
    if name not in SIMULATORS:
        raise ConfigError(f"unknown simulator {name!r}; one of {', '.join(SIMULATORS)}", key="sim.simulator")
    module, cls, extra = SIMULATORS[name]
    try:
        return getattr(importlib.import_module(module), cls)  # type: ignore[no-any-return]
    except ImportError as exc:  # the optional extra is not installed: the user's to fix, not a bug
        raise ConfigError(f"{name} is not installed ({exc}); pip install 'qpctl[{extra}]' (or {extra})",
                          key="sim.simulator") from None


__all__ = ["SIMULATORS", "JointMap", "SimulatorBase", "record_run", "simulator_class"]
