"""A scenario's orientation tasks, one per task frame: which keys give them, and their rotations.

Without ``[[tasks]]`` (or where the first table names no ``task``) the first task frame's orientation
is ``controller.task`` (with ``controller.task_mask``, ``controller.approach_axis``) and its rotations
``path.orientations``, ``path.approach``, ``path.start_orientation``. A ``[[tasks]]`` table takes the
same keys for its own frame: ``task``, ``task_mask``, ``approach_axis``, ``orientations``,
``approach``, ``start_orientation`` (:class:`qpctl.paths.TaskConfig`). A key the table's task cannot
take (an orientation on a position task, an approach axis on a pose) is a ConfigError naming it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from qpctl.errors import ConfigError
from qpctl.robot.frame_orientation import FrameOrientation
from qpctl.robot.model import RobotModel

# each key and the task kinds that take it (the same for controller./path. and for a [[tasks]] table)
KEY_KINDS = {"task_mask": ("pose",), "approach_axis": ("approach",), "orientations": ("pose",),
             "approach": ("approach",), "start_orientation": ("pose", "approach")}


def own_task(data: dict[str, Any], i: int) -> bool:
    """Whether task frame ``i``'s orientation is its ``[[tasks]]`` table's (else, for the first frame,
    the ``[controller]``'s and ``[path]``'s keys)."""
    tasks = data["tasks"]
    return i < len(tasks) and (i > 0 or tasks[0]["task"] is not None)


def keys_of(data: dict[str, Any], i: int) -> tuple[dict[str, Any], str]:
    """(the table, its key prefix) holding task frame ``i``'s rotations."""
    return (data["tasks"][i], f"tasks[{i}].") if own_task(data, i) else (data["path"], "path.")


def task_orientation(data: dict[str, Any], i: int, task_axes: tuple[int, ...]) -> FrameOrientation:
    """Task frame ``i``'s own orientation task, from its ``[[tasks]]`` table (checked: each key on a
    task that takes it; a pose's ``task_mask`` keeps the shared position axes)."""
    t, where = data["tasks"][i], f"tasks[{i}]."
    kind = t["task"] or "position"
    if kind not in ("position", "pose", "approach"):
        raise ConfigError(f"must be position, pose or approach, got {kind!r}", key=f"{where}task")
    if i == 0 and data["controller"]["task"] != "position":
        raise ConfigError(f"and controller.task = {data['controller']['task']!r} both give the first task frame's "
                          "orientation: give one of them", key=f"{where}task")
    for key, kinds in KEY_KINDS.items():
        if t[key] is not None and kind not in kinds:
            raise ConfigError(f"applies to a task = {' or '.join(kinds)} only (this task is {kind!r})",
                              key=f"{where}{key}")
    if kind == "position":
        return FrameOrientation()
    axes: tuple[int, ...] = (0, 1, 2)
    mask = t["task_mask"]
    if mask is not None:
        if len(mask) != 6 or any(v not in (0.0, 1.0) for v in mask):
            raise ConfigError(f"needs 6 entries of 0 or 1 (x, y, z, rx, ry, rz), got {mask}", key=f"{where}task_mask")
        if tuple(a for a in range(3) if mask[a]) != tuple(task_axes):
            raise ConfigError(f"its position entries {mask[:3]} must be the position axes every task frame shares "
                              f"({list(task_axes)}: robot.task_axes or controller.task_mask)", key=f"{where}task_mask")
        axes = tuple(a for a in range(3) if mask[3 + a])
    axis = t["approach_axis"] if t["approach_axis"] is not None else (0.0, 0.0, 1.0)
    return FrameOrientation.make(kind, axes, axis, prefix=where)


def with_task_orientations(data: dict[str, Any], robot: RobotModel) -> RobotModel:
    """``robot`` with each ``[[tasks]]`` table's own orientation task on its frame."""
    for i, t in enumerate(data["tasks"]):
        if own_task(data, i):
            robot = robot.with_frame_orientation(i, task_orientation(data, i, tuple(robot.task_axes)))
            continue
        for key, kinds in KEY_KINDS.items():  # the first table without a task of its own: none of its keys
            if t[key] is not None:
                raise ConfigError(f"applies to a task = {' or '.join(kinds)} only (this task is 'position': give "
                                  f"tasks[{i}].task)", key=f"tasks[{i}].{key}")
    return robot


def _rotation(quat: list[float], key: str) -> np.ndarray:
    import pinocchio as pin

    qv = np.asarray(quat, float)
    if qv.shape != (4,) or not np.all(np.isfinite(qv)) or np.linalg.norm(qv) < 1e-9:
        raise ConfigError(f"needs quaternions (x, y, z, w) of 4 finite numbers, not all 0; got {quat}", key=key)
    return pin.Quaternion(qv[3], qv[0], qv[1], qv[2]).normalized().matrix()


def frame_rotations(data: dict[str, Any], robot: RobotModel, q0: np.ndarray, count: int, i: int) -> np.ndarray:
    """(count, 3, 3) task frame ``i``'s rotations on the path: the start (``start_orientation``, or the
    frame's at q0), then one per waypoint (``orientations`` for a pose, ``approach`` for an approach;
    held if absent), from the table :func:`keys_of` names."""
    import pinocchio as pin

    from qpctl.orientation import approach_rotations

    p, where = keys_of(data, i)
    o = robot.frame_orientation(i)
    if p["start_orientation"] is not None:
        R0 = _rotation(p["start_orientation"], f"{where}start_orientation")
    else:
        pdata = robot.model.createData()
        pin.framesForwardKinematics(robot.model, pdata, q0)
        R0 = pdata.oMf[robot.task_frame_ids[i]].rotation.copy()
    given = p["orientations"] if o.kind == "pose" else p["approach"]
    key = f"{where}orientations" if o.kind == "pose" else f"{where}approach"
    if given is None:
        return np.array([R0] * count)
    if len(given) != count - 1:
        raise ConfigError(f"needs one entry per waypoint ({count - 1}), got {len(given)}", key=key)
    if o.kind == "pose":
        return np.array([R0] + [_rotation(qv, key) for qv in given])
    if any(len(d) != 3 for d in given):
        raise ConfigError("needs approach directions of 3 numbers (world frame)", key=key)
    try:
        return approach_rotations(R0, np.asarray(o.approach_axis), np.array(given))
    except ConfigError as exc:
        raise ConfigError(str(exc).split(": ", 1)[-1], key=key) from None


def path_rotations(data: dict[str, Any], robot: RobotModel, q0: np.ndarray, count: int) -> np.ndarray:
    """The PosePath's rotations: (count, 3, 3) with one oriented task frame, (F, count, 3, 3) with F."""
    sets = [frame_rotations(data, robot, q0, count, i) for i in robot.oriented_frames]
    return sets[0] if len(sets) == 1 else np.array(sets)
