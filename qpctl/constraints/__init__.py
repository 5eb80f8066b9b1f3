"""Constraints of the QP controller: each returns rows (Inequality) or bounds (Bounds) on q̈."""

from qpctl.constraints.constraints import (
    BARRIER,
    Constraint,
    JointLimit,
    ObstacleBarrier,
    SelfCollisionBarrier,
    TorqueLimit,
)

__all__ = ["BARRIER", "Constraint", "JointLimit", "ObstacleBarrier", "SelfCollisionBarrier", "TorqueLimit"]
