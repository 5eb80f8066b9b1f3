"""The one recording loop, and the interface a simulator implements to be driven by it.

A simulator — the built-in RK4, MuJoCo, PyBullet, or a new one — is a :class:`SimulatorBase`
subclass that does five things and nothing else:

* :meth:`~SimulatorBase.reset` to (q0, v0) at t = 0, no torque applied, obstacles at their t = 0 poses;
* :meth:`~SimulatorBase.read` (q [rad], v [rad/s]) in the controller's joint order (``robot.joint_names``);
* :meth:`~SimulatorBase.apply` a torque τ [N·m] in that order, held over the next step (zero-order hold);
* :meth:`~SimulatorBase.step` from t to t + dt, moving the moving obstacles to their poses at t + dt;
* :meth:`~SimulatorBase.obstacle_positions`: where it holds the obstacles [m] (checked by the tests).

:func:`record_run` is the loop that calls the controller once per step and fills the
:class:`~qpctl.simulation.trajectory.Trajectory` that ``trajectory.npz`` and ``metrics.json`` are
made from — written once here, so every simulator records the same arrays the same way. The
built-in simulator's faults enter through two hooks that default to nothing: :meth:`~SimulatorBase.measure`
(what the controller is fed) and :meth:`~SimulatorBase.actuate` (what the drives make of its command).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import pinocchio as pin

from qpctl.config import check_fields, setting
from qpctl.controllers.base import Controller
from qpctl.errors import ConfigError, SimulationError
from qpctl.geometry.obstacles import Obstacle
from qpctl.simulation.trajectory import Trajectory, check_ticks, finish_trajectory, measured_self_pairs
from qpctl.tick import WorldClearance


@dataclass(frozen=True, kw_only=True)
class SimConfig:
    """The ``[sim]`` keys of a scenario (each declared here once; :func:`qpctl.config.schema_of`).

    dt [s], duration [s]: the control and integration step and the run's length (both > 0).
    integrator: "rk4" or "euler" (semi-implicit), the built-in simulator's.
    seed: recorded with the run (randomised scenes).
    simulator: a name in :data:`qpctl.adapters.SIMULATORS` ("builtin", "mujoco", "pybullet", "drake").
    model: the user's own model file for an adapter ("": generated from the robot).
    joint_names: the model's names of the controller's joints, in its order (None: by name or order).
    """

    dt: float = setting(1e-3, valid="seconds", unit="s")
    duration: float = setting(5.0, valid="seconds", unit="s")
    integrator: str = setting("rk4", choices=("rk4", "euler"))
    seed: int = 0
    simulator: str = "builtin"
    model: str = ""
    joint_names: list[str] | None = None

    def __post_init__(self) -> None:
        check_fields(self, "sim")


class SimulatorBase(ABC):
    """A simulator the recording loop can drive (module docstring).

    Args:
        controller: any :class:`~qpctl.controllers.base.Controller`.
        dt: the simulator's step and the control period [s] (one controller call per step).
        duration: simulated time [s].
        progress: show a tqdm progress bar.
        obstacles: the true obstacles, where they differ from the controller's map (default: its own).

    Attributes:
        notes: what the adapter changed or found in the user's model (actuators switched off, an
            inertia mismatch, …), one sentence each; ``qpctl simulate`` prints them and
            ``metrics.json`` keeps them under ``simulator_notes``.
        counts: counters of the last run (e.g. ``ctrl_clamped_ticks``), copied into ``metrics.json``.
    """

    name: ClassVar[str] = "simulator"

    def __init__(self, controller: Controller, *, dt: float = 1e-3, duration: float = 5.0,
                 progress: bool = False, obstacles: Sequence[Obstacle] | None = None) -> None:
        if not (np.isfinite(dt) and dt > 0):
            raise ConfigError(f"must be a positive number of seconds, got {dt}", key="sim.dt")
        if not (np.isfinite(duration) and duration > 0):
            raise ConfigError(f"must be a positive number of seconds, got {duration}", key="sim.duration")
        check_ticks(duration, dt)
        self.controller = controller
        self.robot = controller.robot
        self.dt = float(dt)
        self.duration = float(duration)
        self.progress = progress
        self.obstacles: list[Obstacle] = list(controller.obstacles if obstacles is None else obstacles)
        self.notes: list[str] = []
        self.counts: dict[str, int] = {}
        self._world: WorldClearance | None = None
        self.hooks: list[Any] = []  # objects with before(t, q, v) and after(k, t, q, v), called each tick

    @classmethod
    def from_scenario(cls, controller: Controller, scenario: Any, *, progress: bool = False) -> SimulatorBase:
        """This simulator for a :class:`~qpctl.scenario.Scenario`'s ``[sim]`` table (``dt``,
        ``duration``; a subclass reads the keys it knows, e.g. ``integrator``, ``model``)."""
        sim = scenario.data["sim"]
        return cls(controller, dt=sim["dt"], duration=sim["duration"], progress=progress)

    # -- what a simulator implements ------------------------------------------------------------
    @abstractmethod
    def reset(self, q0: np.ndarray, v0: np.ndarray | None = None) -> None:
        """Put the simulator at (q0 [rad], v0 [rad/s], default rest) at t = 0, with no torque applied."""

    @abstractmethod
    def read(self) -> tuple[np.ndarray, np.ndarray]:
        """(q [rad], v [rad/s]) now, in the controller's joint order (new arrays)."""

    @abstractmethod
    def apply(self, tau: np.ndarray) -> None:
        """Hold the joint torques ``tau`` [N·m] (controller's order) over the next :meth:`step`."""

    @abstractmethod
    def step(self, t: float) -> None:
        """Advance from t to t + dt [s]; the moving obstacles to their poses at t + dt. Raises
        :class:`~qpctl.errors.SimulationError` if the state diverged."""

    def obstacle_positions(self) -> np.ndarray:
        """(k, 3) positions [m] at which the simulator holds ``self.obstacles`` now (by default: where
        the scene says they are at the last stepped time — a simulator with bodies for them reads them)."""
        t = getattr(self, "_t", 0.0)
        return np.array([o.position_at(t) for o in self.obstacles]).reshape(-1, 3)

    # -- hooks of the built-in simulator's faults ----------------------------------------------
    faulty: bool = False  # measure/actuate are not the identity: record the truth and the command

    def measure(self, q: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """What the controller is fed for the true (q, v): by default exactly that."""
        return q, v

    def actuate(self, tau_command: np.ndarray) -> np.ndarray:
        """The torque that acts for the controller's command: by default the command."""
        return tau_command

    # -- shared -----------------------------------------------------------------------------------
    @property
    def world(self) -> WorldClearance:
        if self._world is None:
            self._world = WorldClearance(self.robot, self.obstacles, measured_self_pairs(self.controller))
        return self._world

    def clearance(self, q: np.ndarray, t: float) -> float:
        """Exact least link–obstacle distance [m] at (q, t), whatever the simulator (qpctl's own)."""
        return self.world(q, t)

    def run(self, q0: np.ndarray, v0: np.ndarray | None = None) -> Trajectory:
        """Simulate from (q0: a configuration (nq) or one angle per degree of freedom (nv); v0 [rad/s],
        default rest) at t = 0 for ``duration``."""
        robot = self.robot
        q0 = np.asarray(q0, float)
        if robot.lie and q0.shape == (robot.nv,):  # one angle per degree of freedom → the configuration
            q0 = robot.configuration(q0)
        if q0.shape != (robot.nq,):
            more = f" (or {robot.nv} angles)" if robot.lie else ""
            raise ConfigError(f"q0 needs {robot.nq} joint values{more}, got {q0.size}", key="robot.q0")
        self.counts = {}
        self.reset(q0, v0)
        return record_run(self)


def record_run(sim: SimulatorBase) -> Trajectory:
    """Run ``sim.controller`` on ``sim`` (already reset) for ``sim.duration``: one tick per step, the
    torque held over the step; record the arrays of DESIGN.md §4 (plus the self clearance, and with
    faults the command beside the torque that acted). The clearance is measured outside the
    controller's timing."""
    robot, ctrl = sim.robot, sim.controller
    n, m, dt = robot.nv, robot.m, sim.dt
    steps = round(sim.duration / dt) + 1
    keys = ("q", "v", "tau", "e_null") + (("tau_command",) if sim.faulty else ())
    rec = {k: np.zeros((steps, n)) for k in keys}
    rec["q"] = np.zeros((steps, robot.nq))
    rec.update({k: np.zeros((steps, m)) for k in ("x", "x_ref", "xd_ref", "xdd_ref")})
    t_arr, clear, tick_us = np.zeros(steps), np.zeros(steps), np.zeros(steps)
    self_clear = np.full(steps, np.inf)
    singular = np.zeros(steps, bool)
    infos: list[dict[str, Any]] = []
    world = sim.world
    if sim.faulty:  # the task point's true position (kinematics only)
        kin = robot.model.createData()
        m_p = robot.m_position
    if ctrl.warm:  # kernels loaded, workspace built, solver set up: not in the first tick
        ctrl.reset()
    else:
        ctrl.warmup()  # (ends in reset())
    iterator: Any = range(steps)
    if sim.progress:
        from tqdm import tqdm

        iterator = tqdm(iterator, desc=f"{sim.name} {ctrl.kind}", unit="tick", leave=False)
    for k in iterator:
        t = k * dt
        q, v = sim.read()
        qm, vm = sim.measure(q, v)
        for h in sim.hooks:  # e.g. a depth camera and its map (qpctl.perception.closed_loop)
            h.before(t, qm, vm)
        out = ctrl.step(qm, vm, t)
        if not np.all(np.isfinite(out.tau)):
            raise SimulationError(f"controller {ctrl.kind} returned non-finite torque at t = {t:.4f} s")
        tau = sim.actuate(out.tau)
        t_arr[k] = t
        rec["q"][k], rec["v"][k], rec["tau"][k], rec["e_null"][k] = q, v, tau, out.e_null
        rec["x"][k] = out.x
        if sim.faulty:
            rec["tau_command"][k] = out.tau
            pin.framesForwardKinematics(robot.model, kin, q)
            rec["x"][k, :m_p] = robot.task_positions(kin)
        rec["x_ref"][k], rec["xd_ref"][k] = out.ref.x, out.ref.xd
        rec["xdd_ref"][k] = out.ref.xdd
        clear[k] = world(q, t)
        self_clear[k] = world.self_clearance
        tick_us[k] = out.compute_us
        singular[k] = out.singular
        infos.append(out.info)
        for h in sim.hooks:
            h.after(k, t, qm, vm)
        if k + 1 < steps:
            sim.apply(tau)
            sim.step(t)
    traj = Trajectory(t_arr, rec["q"], rec["v"], rec["tau"], rec["x"], rec["x_ref"], rec["xd_ref"],
                      rec["xdd_ref"], clear, rec["e_null"], tick_us, singular, infos,
                      tau_command=rec.get("tau_command"))
    if len(world.ws.sc_pairs):
        traj.self_clearance = self_clear
    return finish_trajectory(traj, ctrl)
