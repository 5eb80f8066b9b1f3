"""One coordinate per degree of freedom from a configuration on a Lie group: the kernels' angle view.

Continuous joints (Pinocchio's ``JointModelRUB*``: cos θ, sin θ) and planar joints (x, y, cos θ,
sin θ) store more numbers than they have degrees of freedom (nq > nv). The tick's kernels read one
coordinate per degree of freedom (joint-limit rows, the posture's target): :func:`joint_angles`
writes it once per tick (:meth:`qpctl.tick.Workspace.joint_view`), the compiled twin of
:meth:`qpctl.robot.model.RobotModel.angles`, which ``tests/test_lie_joints.py`` holds it against.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def joint_angles(q: np.ndarray, plain_q: np.ndarray, plain_v: np.ndarray, rot_q: np.ndarray, rot_v: np.ndarray,
                 out: np.ndarray) -> None:
    """out[plain_v] = q[plain_q] (coordinates that are their own: revolute, prismatic, a planar joint's
    x, y); out[rot_v] = atan2(q[rot_q + 1], q[rot_q]) (angles stored as cos θ, sin θ) [rad]."""
    for k in range(plain_q.shape[0]):
        out[plain_v[k]] = q[plain_q[k]]
    for k in range(rot_q.shape[0]):
        i = rot_q[k]
        out[rot_v[k]] = math.atan2(q[i + 1], q[i])
