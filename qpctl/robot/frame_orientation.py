"""One task frame's orientation rows: what a frame's orientation task holds (:mod:`qpctl.orientation`).

A :class:`FrameOrientation` is ``"none"`` (position rows only), ``"pose"`` (the frame's rotation
about the world axes ``axes``, the log map of R_d Rᵀ) or ``"approach"`` (the direction of
``approach_axis``, a unit vector in the task frame, 2 rows, the roll about it free). The robot holds
one per task frame (:meth:`qpctl.robot.model.RobotModel.frame_orientation`); the rows of every
oriented frame follow all the position rows, frame after frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from qpctl.errors import ConfigError

KINDS = ("none", "pose", "approach")


@dataclass(frozen=True)
class FrameOrientation:
    """A task frame's orientation task: ``kind``, a pose's world ``axes``, an approach's ``approach_axis``."""

    kind: str = "none"
    axes: tuple[int, ...] = ()
    approach_axis: tuple[float, float, float] = (0.0, 0.0, 1.0)

    @classmethod
    def make(cls, kind: str, axes: Sequence[int] = (0, 1, 2), approach_axis: Sequence[float] = (0.0, 0.0, 1.0), *,
             prefix: str = "controller.") -> FrameOrientation:
        """Checked: ``kind`` one of none, pose, approach (``prefix + "task"``), a non-zero approach axis
        (normalised; ``prefix + "approach_axis"``), distinct pose axes among 0–2 (``prefix + "task_mask"``)."""
        if kind not in KINDS:
            raise ConfigError(f"must be position, pose or approach, got {kind!r}", key=f"{prefix}task")
        ax = tuple(int(a) for a in axes)
        axis = np.asarray(approach_axis, float).reshape(-1)
        if axis.shape != (3,) or not np.all(np.isfinite(axis)) or np.linalg.norm(axis) < 1e-9:
            raise ConfigError(f"must be a non-zero 3-vector, got {list(approach_axis)}", key=f"{prefix}approach_axis")
        if kind == "pose" and (len(set(ax)) != len(ax) or any(not 0 <= a <= 2 for a in ax)):
            raise ConfigError(f"pose axes must be distinct among 0, 1, 2, got {list(ax)}", key=f"{prefix}task_mask")
        unit = axis / np.linalg.norm(axis)
        return cls(kind, ax if kind == "pose" else (), (float(unit[0]), float(unit[1]), float(unit[2])))

    @property
    def rows(self) -> int:
        """Its rows: 0, ``len(axes)`` (pose) or 2 (approach)."""
        return {"none": 0, "pose": len(self.axes), "approach": 2}[self.kind]

    def basis(self) -> np.ndarray:
        """(2, 3) two unit vectors of the task frame orthogonal to ``approach_axis`` and to each other:
        the directions, rotating with the gripper, of the approach task's two rows."""
        a = np.asarray(self.approach_axis, float)
        seed = np.eye(3)[int(np.argmin(np.abs(a)))]
        b1 = np.cross(a, seed)
        b1 /= np.linalg.norm(b1)
        return np.array([b1, np.cross(a, b1)])

    def codes(self) -> np.ndarray:
        """The compiled tick's row codes (qpctl.kernels.work's ``ori_rows``): a pose's world axes 0–2,
        an approach's rows 3, 4."""
        return np.array(self.axes if self.kind == "pose" else (3, 4) if self.kind == "approach" else (), np.int64)
