"""Robot models on Pinocchio: the paper's planar arm, any URDF, and the Franka Panda."""

from qpctl.robot.model import LinkCapsule, RobotModel, load_robot, panda, planar_arm

__all__ = ["LinkCapsule", "RobotModel", "load_robot", "panda", "planar_arm"]
