"""qpctl — torque control of redundant arms that track a path among obstacles.

The public API: robot models, obstacles, reference paths, the per-tick state, the controllers
(``tau = controller.torque(q, v, t)``), the simulator, scenarios and errors.
"""

from qpctl.controllers.base import Controller, ControlOutput, TickStatus
from qpctl.errors import (
    ConfigError,
    InfeasibleError,
    InvalidStateError,
    QpctlError,
    SimulationError,
    SolverError,
    UnknownFrameError,
    UnknownSolverError,
)
from qpctl.geometry import DistanceEngine, Obstacle, PairSet
from qpctl.law import LawGains, LawTerms, law_terms
from qpctl.linalg import PseudoInverse, weighted_pinv
from qpctl.outcome import SolveOutcome, SolveStatus
from qpctl.paths import Reference, WaypointPath
from qpctl.robot import LinkCapsule, RobotModel, load_robot, panda, planar_arm
from qpctl.scenario import Scenario, packaged_scenarios
from qpctl.simulation import Faults, Simulator, Trajectory, compute_metrics
from qpctl.state import Dynamics, TickState

__version__ = "0.1.0"

__all__ = [
    "ConfigError",
    "ControlOutput",
    "Controller",
    "DistanceEngine",
    "Dynamics",
    "Faults",
    "InfeasibleError",
    "InvalidStateError",
    "LawGains",
    "LawTerms",
    "LinkCapsule",
    "Obstacle",
    "PairSet",
    "PseudoInverse",
    "QpctlError",
    "Reference",
    "RobotModel",
    "Scenario",
    "SimulationError",
    "Simulator",
    "SolveOutcome",
    "SolveStatus",
    "SolverError",
    "TickState",
    "TickStatus",
    "Trajectory",
    "UnknownFrameError",
    "UnknownSolverError",
    "WaypointPath",
    "compute_metrics",
    "law_terms",
    "load_robot",
    "packaged_scenarios",
    "panda",
    "planar_arm",
    "weighted_pinv",
]
