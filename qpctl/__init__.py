"""qpctl — torque control of redundant arms that track a path among obstacles.

The front door (everything else is reachable by its module, and may change):

* controllers, one interface ``tau = controller.torque(q, v, t)`` (``controller.step`` for the
  diagnostics): :class:`QPController` and its :class:`QPConfig`; the closed-form laws
  :class:`PaperController` (the paper's inertia-weighted law) and :class:`HsuController`
  (Hsu–Hauser–Sastry's unweighted one), with :class:`LawGains`; a QP solve's outcome
  (:class:`SolveStatus`, :class:`SolveOutcome`);
* the QP's tasks and constraints, to compose a controller in code;
* the world: robots (:func:`panda`, :func:`planar_arm`, :func:`load_robot`), :class:`Obstacle`,
  reference paths (:class:`WaypointPath`, :class:`PosePath`);
* running it: :class:`Scenario` (TOML files, packaged ones by name), :func:`simulate`, the built-in
  :class:`Simulator` and its :class:`Trajectory`, :class:`Faults`;
* solvers by name: :func:`available_solvers`;
* the errors, all :class:`QpctlError`.
"""

from qpctl.constraints import (
    Constraint,
    JointLimit,
    ObstacleBarrier,
    SelfCollisionBarrier,
    TorqueLimit,
)
from qpctl.controllers.base import Controller, ControlOutput, TickStatus
from qpctl.controllers.closed_form import HsuController, PaperController
from qpctl.controllers.qp import QPConfig, QPController
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
from qpctl.geometry import Obstacle
from qpctl.law import LawGains
from qpctl.outcome import SolveOutcome, SolveStatus
from qpctl.paths import PosePath, WaypointPath
from qpctl.robot import RobotModel, load_robot, panda, planar_arm
from qpctl.run import RunResult, simulate, write_outputs
from qpctl.scenario import Scenario, packaged_scenarios
from qpctl.simulation import Faults, Simulator, Trajectory
from qpctl.solvers import available_solvers
from qpctl.tasks import AccelerationTask, DampingTask, EndEffectorTask, PostureTask, Task

__version__ = "0.1.0"

__all__ = [  # noqa: RUF022 — grouped as the docstring, not sorted
    # controllers
    "Controller", "ControlOutput", "TickStatus", "QPController", "QPConfig", "PaperController",
    "HsuController", "LawGains", "SolveStatus", "SolveOutcome",
    # the QP's tasks and constraints
    "Task", "AccelerationTask", "EndEffectorTask", "PostureTask", "DampingTask",
    "Constraint", "TorqueLimit", "JointLimit", "ObstacleBarrier", "SelfCollisionBarrier",
    # the world
    "RobotModel", "load_robot", "panda", "planar_arm", "Obstacle", "WaypointPath", "PosePath",
    # running it
    "Scenario", "packaged_scenarios", "simulate", "write_outputs", "RunResult", "Simulator", "Trajectory",
    "Faults", "available_solvers",
    # errors
    "QpctlError", "ConfigError", "InvalidStateError", "UnknownFrameError", "UnknownSolverError", "SolverError",
    "InfeasibleError", "SimulationError",
]
