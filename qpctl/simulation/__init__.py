"""The built-in simulator (RK4 on Pinocchio's ABA) and the trajectory record it writes."""

from qpctl.simulation.metrics import compute_metrics
from qpctl.simulation.simulator import Simulator, Trajectory, rk4_step

__all__ = ["Simulator", "Trajectory", "compute_metrics", "rk4_step"]
