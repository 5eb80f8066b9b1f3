"""Constraints of the QP controller: each returns rows (Inequality) or bounds (Bounds) on q̈."""

from qpctl.constraints.constraints import (
    Constraint,
    JointLimit,
    ObstacleBarrier,
    SelfCollisionBarrier,
    TorqueLimit,
)

__all__ = ["Constraint", "JointLimit", "ObstacleBarrier", "SelfCollisionBarrier", "TorqueLimit"]
