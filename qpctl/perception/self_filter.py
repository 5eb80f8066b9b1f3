"""Self-filtering: where the robot was when a frame was taken, so that it never becomes an obstacle.

A depth frame is stamped when the camera exposed it, tens of milliseconds before the map worker sees
it; the arm has moved since. :class:`JointHistory` keeps the last joint positions the controller
recorded (a ring, thread-safe: the control loop writes, the worker reads) and returns q at the
frame's stamp by linear interpolation; :class:`SelfFilter` turns that q into the robot's link
capsules (Pinocchio's forward kinematics) inflated by a margin. A point inside one of them, or within
a radius of the grasp target (the fruit is not an obstacle to the gripper that picks it), is dropped
(:mod:`qpctl.kernels.depth`).
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np
import pinocchio as pin

from qpctl.errors import PerceptionError
from qpctl.robot.model import RobotModel


class JointHistory:
    """The last ``capacity`` (t [s], q) the controller recorded, in time order."""

    def __init__(self, n: int, capacity: int = 512,
                 interpolate: Callable[[np.ndarray, np.ndarray, float], np.ndarray] | None = None) -> None:
        self.n = int(n)  # a configuration's entries (nq)
        self._interpolate = interpolate  # RobotModel.interpolate where q is not a vector (continuous joints)
        self._t = np.full(capacity, np.nan)
        self._q = np.zeros((capacity, self.n))
        self._count = 0
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return min(self._count, len(self._t))

    def record(self, t: float, q: np.ndarray) -> None:
        """Add q [rad] at t [s] (t must not be older than the last one recorded)."""
        cap = len(self._t)
        with self._lock:
            if self._count and t < self._t[(self._count - 1) % cap]:
                raise PerceptionError(f"joint history: time went backwards ({t} after "
                                      f"{self._t[(self._count - 1) % cap]})")
            self._t[self._count % cap] = t
            self._q[self._count % cap] = q
            self._count += 1

    def at(self, t: float) -> np.ndarray | None:
        """q at t, linear between the two records around it; the newest (oldest) record after (before)
        the history's span; None when nothing is recorded."""
        with self._lock:
            k = len(self)
            if k == 0:
                return None
            cap = len(self._t)
            start = (self._count - k) % cap
            order = (start + np.arange(k)) % cap
            ts, qs = self._t[order], self._q[order]
        i = int(np.searchsorted(ts, t))
        if i <= 0:
            return qs[0].copy()
        if i >= k:
            return qs[-1].copy()
        w = (t - ts[i - 1]) / (ts[i] - ts[i - 1]) if ts[i] > ts[i - 1] else 1.0
        if self._interpolate is not None:
            return self._interpolate(qs[i - 1], qs[i], w)
        return (1 - w) * qs[i - 1] + w * qs[i]


class SelfFilter:
    """The robot's link capsules at a configuration, inflated by ``margin`` [m], as the kernels take
    them: segments (L, 2, 3) [m] in the base frame and radii (L,) [m]."""

    def __init__(self, robot: RobotModel, margin: float) -> None:
        self.robot = robot
        self.margin = float(margin)
        self._data = robot.model.createData()
        caps = robot.capsules
        self.radii = np.array([c.radius + self.margin for c in caps], float)
        self._p = np.array([[c.p0, c.p1] for c in caps], float).reshape(len(caps), 2, 3)
        self._joints = [c.joint_id for c in caps]

    def segments(self, q: np.ndarray) -> np.ndarray:
        """(L, 2, 3) capsule axes [m] at q [rad] (Pinocchio's forward kinematics)."""
        pin.forwardKinematics(self.robot.model, self._data, np.asarray(q, float))
        out = np.empty_like(self._p)
        for i, j in enumerate(self._joints):
            M = self._data.oMi[j]
            out[i] = self._p[i] @ M.rotation.T + M.translation
        return out
