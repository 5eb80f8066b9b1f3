"""Tasks of the QP controller: each returns a cost (Objective) or rows (Equality) on q̈."""

from qpctl.tasks.tasks import AccelerationTask, EndEffectorTask, PostureTask, Task

__all__ = ["AccelerationTask", "EndEffectorTask", "PostureTask", "Task"]
