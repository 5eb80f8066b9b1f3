"""MJCF robots (``robot.kind = "mjcf"``): the Pinocchio model from Pinocchio's MJCF parser, link
capsules fitted to the file's collision geoms, torque limits from its actuators.

* **Dynamics**: ``pin.buildModelFromMJCF`` (joint axes, ranges, inertias, armature; its mass matrix
  and bias forces match MuJoCo's, ``tests/test_mjcf_robot.py``). Pinocchio ignores actuators.
* **Capsules**: each body's collision geoms (``contype`` or ``conaffinity`` non-zero, as Pinocchio's
  ``buildGeomFromMJCF`` reads them), else its visual geoms, fitted as :mod:`qpctl.robot.capsules`
  fits meshes (a body whose one geom is a capsule or a sphere keeps it exactly). Fits are remembered
  per file and modification time, so a scenario that builds its robot several times fits once.
* **Torque limits** [N·m] from MuJoCo's compilation of the file: a motor's ``forcerange`` (else its
  ``ctrlrange`` × gain), a servo's ``forcerange`` (its ``ctrlrange`` is a position), times the gear;
  a joint's ``actuatorfrcrange`` (Pinocchio's effort limit) where it is tighter. Without MuJoCo
  installed, the ``actuatorfrcrange`` only.
* **Home**: the keyframe named ``home`` if the file has one (MuJoCo reads it), else Pinocchio's
  neutral configuration moved inside the joint ranges.

``--sim mujoco`` runs the same file (:class:`qpctl.adapters.mujoco.MujocoSimulator`), its position
and velocity servos turned into motors.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

from qpctl.errors import ConfigError
from qpctl.robot.capsules import CapsuleEntry, file_geometry, fit_links
from qpctl.robot.files import read_model
from qpctl.robot.model import RobotModel, frame_index


def _compiled(path: Path) -> Any | None:
    """MuJoCo's compilation of the file, or None without MuJoCo."""
    try:
        import mujoco
    except ImportError:  # pragma: no cover - exercised only without the extra
        return None
    try:
        return mujoco.MjModel.from_xml_path(str(path))
    except ValueError as exc:
        raise ConfigError(f"MuJoCo cannot compile {path.name}: {' '.join(str(exc).split())}", key="robot.mjcf") from None


def actuator_limits(mj: Any, joint_names: Sequence[str]) -> np.ndarray:
    """Torque limits [N·m] of the joints ``joint_names`` from a compiled MuJoCo model's actuators
    (module docstring; inf for a joint without a limited actuator)."""
    import mujoco

    out = np.full(len(joint_names), np.inf)
    index = {n: i for i, n in enumerate(joint_names)}
    for a in range(mj.nu):
        if int(mj.actuator_trntype[a]) not in (int(mujoco.mjtTrn.mjTRN_JOINT), int(mujoco.mjtTrn.mjTRN_JOINTINPARENT)):
            continue
        name = mj.joint(int(mj.actuator_trnid[a, 0])).name
        if name not in index:
            continue
        force = np.inf
        if mj.actuator_forcelimited[a]:
            force = float(np.max(np.abs(mj.actuator_forcerange[a])))
        motor = int(mj.actuator_biastype[a]) == int(mujoco.mjtBias.mjBIAS_NONE)
        if motor and mj.actuator_ctrllimited[a]:
            force = min(force, float(np.max(np.abs(mj.actuator_ctrlrange[a])) * abs(mj.actuator_gainprm[a, 0])))
        i = index[name]
        out[i] = min(out[i], force * abs(float(mj.actuator_gear[a, 0])))
    return out


@functools.lru_cache(maxsize=16)
def _fitted(path: str, mtime_ns: int) -> tuple[CapsuleEntry, ...]:
    fits = fit_links(file_geometry(path, key="robot.mjcf"))
    return tuple(CapsuleEntry(f.link, c) for f in fits for c in f.capsules)


def mjcf_capsules(path: str | Path) -> list[CapsuleEntry]:
    """The MJCF's link capsules, fitted to its collision geoms (module docstring), in the links' frames."""
    path = Path(path).resolve()
    return list(_fitted(str(path), path.stat().st_mtime_ns))


def from_mjcf(path: str | Path, ee_frame: str, *, gravity: Sequence[float] | None = None,
              name: str | None = None, capsules: bool = True) -> RobotModel:
    """An MJCF robot (module docstring); ``ee_frame``: a body or site whose origin is the task point;
    ``gravity`` [m/s²] replaces the file's; ``capsules=False`` leaves the robot without any."""
    path = Path(path)
    model = read_model(path, key="robot.mjcf")
    if model.nq != model.nv:
        raise ConfigError(f"{path.name} has joints whose configuration is not one number per degree of freedom "
                          f"(nq {model.nq} ≠ nv {model.nv}: a ball or free joint); only hinges and slides are "
                          "supported", key="robot.mjcf")
    if gravity is not None:
        model.gravity.linear = np.asarray(gravity, float)
    frame_index(model, ee_frame)  # UnknownFrameError lists the frames
    joint_names = [model.names[i] for i in range(1, model.njoints)]
    nv = model.nv
    lo = np.where(np.isfinite(model.lowerPositionLimit), model.lowerPositionLimit, -np.inf)[:nv]
    hi = np.where(np.isfinite(model.upperPositionLimit), model.upperPositionLimit, np.inf)[:nv]
    tau = np.where(model.effortLimit > 0, model.effortLimit, np.inf)[:nv]
    home = np.clip(pin.neutral(model), lo, hi)
    mj = _compiled(path)
    if mj is not None:
        tau = np.minimum(tau, actuator_limits(mj, joint_names))
        key = next((k for k in range(mj.nkey) if mj.key(k).name == "home"), None)
        if key is not None and mj.nq == nv and mj.njnt == nv:
            order = [mj.jnt_qposadr[mj.joint(n).id] for n in joint_names]
            home = np.asarray(mj.key_qpos[key], float)[order]
    robot = RobotModel(name=name or path.stem, model=model, ee_frame=ee_frame, task_axes=(0, 1, 2), capsules=[],
                       q_min=lo, q_max=hi, v_max=np.full(nv, np.inf), tau_max=tau, q_home=home,
                       joint_names=joint_names, mjcf=path.resolve())
    if capsules:
        robot = robot.with_link_capsules(mjcf_capsules(path), path.name, key="robot.mjcf")
    return robot
