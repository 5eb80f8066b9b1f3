"""Joint order between a simulator and a robot model, matched by name.

A controller speaks in the model's joint order (``robot.joint_names``, Pinocchio's); a simulator
has its own. :class:`JointMap` is the permutation between the two, built from the two name lists,
and refuses to guess: a joint of the model that the simulator lacks — or, unless allowed, a joint of
the simulator the model does not know — is a :class:`~qpctl.errors.ConfigError` that lists both
sets.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from qpctl.errors import ConfigError


@dataclass(frozen=True)
class JointMap:
    """``sim_index[i]`` is the simulator's index of the model's joint ``model_names[i]``.

    Attributes:
        model_names: joint names in the model's (the controller's) order.
        sim_names: joint names in the simulator's order.
        sim_index: (n,) int, position of each model joint in ``sim_names``.
    """

    model_names: tuple[str, ...]
    sim_names: tuple[str, ...]
    sim_index: np.ndarray

    @classmethod
    def from_names(cls, sim_joint_names: Sequence[str], model_joint_names: Sequence[str], *,
                   allow_extra: bool = False) -> JointMap:
        """Match the simulator's joints to the model's by name.

        Args:
            sim_joint_names: the simulator's joints, in its order.
            model_joint_names: the model's joints (``robot.joint_names``), in the controller's order.
            allow_extra: accept simulator joints the model does not have (they are left alone:
                never read, never driven — e.g. a gripper's fingers or a free-floating object).

        Raises:
            ConfigError: a model joint is missing from the simulator, a name is repeated, or (without
                ``allow_extra``) the simulator has joints the model does not; the message lists both sets.
        """
        sim = tuple(str(s) for s in sim_joint_names)
        model = tuple(str(s) for s in model_joint_names)
        problems = []
        for label, names in (("simulator", sim), ("model", model)):
            repeated = sorted({n for n in names if names.count(n) > 1})
            if repeated:
                problems.append(f"the {label} repeats {', '.join(repeated)}")
        missing = [n for n in model if n not in sim]
        extra = [n for n in sim if n not in model]
        if missing:
            problems.append(f"missing from the simulator: {', '.join(missing)}")
        if extra and not allow_extra:
            problems.append(f"unknown to the model: {', '.join(extra)}")
        if problems:
            raise ConfigError(
                "the simulator's joints do not match the robot model's ("
                + "; ".join(problems)
                + f"). Simulator joints: [{', '.join(sim)}]; model joints (robot.joint_names): "
                + f"[{', '.join(model)}]",
                key="joint_map",
            )
        index = np.array([sim.index(n) for n in model], dtype=int)
        return cls(model, sim, index)

    @property
    def n(self) -> int:
        """Number of model joints."""
        return len(self.model_names)

    @property
    def identity(self) -> bool:
        """The two orders coincide (no permutation, no extra simulator joints)."""
        return len(self.sim_names) == self.n and bool(np.all(self.sim_index == np.arange(self.n)))

    def to_model(self, sim_values: np.ndarray) -> np.ndarray:
        """Values in the simulator's joint order (len(sim_names),) → the model's order (n,)."""
        return np.asarray(sim_values, float)[self.sim_index]

    def to_sim(self, model_values: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Values in the model's order (n,) → the simulator's; extra joints keep ``out``'s entries (0)."""
        if out is None:
            out = np.zeros(len(self.sim_names))
        out[self.sim_index] = model_values
        return out
