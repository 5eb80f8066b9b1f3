"""Adapters that let any qpctl controller drive another simulator.

* :class:`JointMap` — the simulator's joint order ↔ the model's (``robot.joint_names``), by name.
* :mod:`qpctl.adapters.mujoco` — MJCF from a :class:`~qpctl.robot.model.RobotModel` and
  :class:`~qpctl.adapters.mujoco.MujocoSimulator` (imported on demand: MuJoCo is an optional
  dependency, ``pip install 'qpctl[mujoco]'``).
"""

from qpctl.adapters.joint_map import JointMap

__all__ = ["JointMap"]
