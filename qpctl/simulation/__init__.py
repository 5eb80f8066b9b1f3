"""The built-in simulator (RK4 on Pinocchio's ABA), the trajectory record it writes, and the faults of a
real arm it can apply (:class:`Faults`)."""

from qpctl.simulation.faults import Faults
from qpctl.simulation.metrics import compute_metrics
from qpctl.simulation.simulator import Simulator, Trajectory, rk4_step

__all__ = ["Faults", "Simulator", "Trajectory", "compute_metrics", "rk4_step"]
