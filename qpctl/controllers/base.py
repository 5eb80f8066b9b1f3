"""The controller interface every law implements — the one thing another simulator must call.

    tau = controller.torque(q, v, t)

* ``q`` joint positions [rad] (or [m] for prismatic joints), shape (n,), in the order of
  ``controller.robot.joint_names`` (Pinocchio's order);
* ``v`` joint velocities [rad/s], shape (n,), same order;
* ``t`` time [s] on the reference path's clock;
* returns joint torques [N·m], shape (n,), same order; hold them constant over the control period.

Call it once per control period, in time order, with the measured state (no look-ahead, no
integrator stages); call :meth:`Controller.reset` before starting a new run (the QP keeps warm
starts). The law uses its own model (``controller.robot``: inertias, gravity) for M and N, so the
simulated robot must be that robot. A simulator with another joint order or extra joints maps
by name: :class:`qpctl.adapters.JointMap` (a mismatch is a ConfigError listing both sets).

:meth:`Controller.step` returns a :class:`ControlOutput` with the torque and the per-tick
diagnostics (tracking error, null-space error, singularity flag, solver statistics).
"""

from __future__ import annotations

import dataclasses
import time
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from qpctl.errors import ConfigError
from qpctl.geometry.obstacles import Obstacle
from qpctl.law import LawGains
from qpctl.paths import Reference, WaypointPath
from qpctl.robot.model import RobotModel
from qpctl.state import Dynamics, TickState


@dataclass
class ControlOutput:
    """One tick's command and diagnostics."""

    tau: np.ndarray  # (n,) joint torques [N·m]
    qdd: np.ndarray  # (n,) commanded joint accelerations [rad/s²]
    ref: Reference  # x_d, ẋ_d, ẍ_d
    x: np.ndarray  # (m,) task point position [m]
    e_null: np.ndarray  # (n,) null-space velocity error [rad/s] (zeros where the law has none)
    clearance: float  # least link–obstacle distance seen by the controller [m] (inf if none within reach)
    singular: bool  # a pseudo-inverse was damped at this tick
    compute_us: float = 0.0  # wall time of the whole tick [µs]
    info: dict[str, Any] = field(default_factory=dict)  # law-specific: QP status, iterations, timings


class Controller(ABC):
    """Base class: owns the robot, the reference path, the scene, and the per-tick state computer.

    Subclasses implement :meth:`control`, which reads a :class:`TickState` and returns a
    :class:`ControlOutput`.
    """

    kind: str = "controller"
    solver: str = "closed-form"

    def __init__(self, robot: RobotModel, path: WaypointPath, obstacles: Sequence[Obstacle] = (),
                 gains: LawGains | None = None, *, broadphase: bool | None = None) -> None:
        self.robot = robot
        self.path = path
        self.obstacles = list(obstacles)
        self.gains = gains or LawGains()
        if any(o.v_ref is not None for o in self.obstacles):
            own = tuple(float("nan") if o.v_ref is None else float(o.v_ref) for o in self.obstacles)
            self.gains = dataclasses.replace(self.gains, obstacle_v_ref=own)
        if path.dim != robot.m:
            raise ConfigError(f"path points have {path.dim} coordinates but the robot's task has {robot.m}",
                              key="path.waypoints")
        self.dynamics = Dynamics(robot, self.obstacles, cutoff=self.cutoff, broadphase=broadphase)
        self.last: ControlOutput | None = None

    @property
    def cutoff(self) -> float:
        """Distance [m] beyond which link–obstacle pairs are not queried."""
        return self.gains.d_influence

    @property
    def n(self) -> int:
        return self.robot.nv

    def torque(self, q: np.ndarray, v: np.ndarray, t: float) -> np.ndarray:
        """Joint torques [N·m] for state (q, v) at time t [s] (see module docstring)."""
        return self.step(q, v, t).tau

    def step(self, q: np.ndarray, v: np.ndarray, t: float) -> ControlOutput:
        """One control tick: compute the state once, then the law; records wall time in ``compute_us``."""
        start = time.perf_counter()
        state = self.dynamics.compute(q, v, t)
        t_state = time.perf_counter()
        out = self.control(state)
        end = time.perf_counter()
        out.compute_us = (end - start) * 1e6
        out.info.setdefault("state_us", (t_state - start) * 1e6)  # = rigid_us + distance_us + bookkeeping
        out.info.update(state.timing)  # rigid_us (Pinocchio, Jacobians), distance_us (python-fcl)
        out.info["pairs"] = len(state.pairs)
        self.last = out
        return out

    @abstractmethod
    def control(self, state: TickState) -> ControlOutput:
        """The law: torques from the state of this tick."""

    def reset(self) -> None:
        """Forget anything kept between ticks (warm starts, filters)."""
        self.last = None
