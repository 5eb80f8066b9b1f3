"""Fixed-step simulation: the controller is sampled once per step, its torque held (zero-order hold)
while RK4 (as in the paper) integrates q̇ = v, v̇ = ABA(q, v, τ) from Pinocchio.

The world's clearance is measured over every link–obstacle pair (exact, not limited to the
controller's influence distance; :class:`qpctl.tick.WorldClearance`), outside the controller's timing.

With :class:`~qpctl.simulation.faults.Faults` the controller is fed what a real one would measure and
its commands pass through imperfect drives, while the integration uses the true robot (mass errors,
payload) and the clearance the true obstacles; the recorded q, q̇, task point x and clearance are the
truth, ``tau`` the torque that acted and ``tau_command`` the controller's.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

from qpctl.controllers.base import Controller
from qpctl.errors import ConfigError, SimulationError
from qpctl.geometry.obstacles import Obstacle
from qpctl.simulation.faults import Faults, FaultState
from qpctl.tick import WorldClearance

INTEGRATORS = ("rk4", "euler")


def rk4_step(f: Callable[[np.ndarray, np.ndarray], np.ndarray], q: np.ndarray, v: np.ndarray,
             dt: float) -> tuple[np.ndarray, np.ndarray]:
    """One classical Runge–Kutta step of q̇ = v, v̇ = f(q, v)."""
    k1q, k1v = v, f(q, v)
    k2q, k2v = v + 0.5 * dt * k1v, f(q + 0.5 * dt * k1q, v + 0.5 * dt * k1v)
    k3q, k3v = v + 0.5 * dt * k2v, f(q + 0.5 * dt * k2q, v + 0.5 * dt * k2v)
    k4q, k4v = v + dt * k3v, f(q + dt * k3q, v + dt * k3v)
    return (q + dt / 6 * (k1q + 2 * k2q + 2 * k3q + k4q), v + dt / 6 * (k1v + 2 * k2v + 2 * k3v + k4v))


def euler_step(f: Callable[[np.ndarray, np.ndarray], np.ndarray], q: np.ndarray, v: np.ndarray,
               dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Semi-implicit Euler: v ← v + dt f(q, v), q ← q + dt v."""
    v1 = v + dt * f(q, v)
    return q + dt * v1, v1


@dataclass
class Trajectory:
    """Recorded arrays (DESIGN.md §4); T samples, n joints, m task coordinates."""

    t: np.ndarray
    q: np.ndarray
    v: np.ndarray
    tau: np.ndarray
    x: np.ndarray
    x_ref: np.ndarray
    xd_ref: np.ndarray
    xdd_ref: np.ndarray
    clearance: np.ndarray
    e_null: np.ndarray
    tick_us: np.ndarray
    singular: np.ndarray
    infos: list[dict[str, Any]] = field(default_factory=list, repr=False)
    # with an orientation task: the task frame's orientation and its reference, quaternions (x, y, z, w)
    quat: np.ndarray | None = None
    quat_ref: np.ndarray | None = None
    orientation_error_deg: np.ndarray | None = None  # (T,) the angle between them (approach: the axis's)
    self_clearance: np.ndarray | None = None  # (T,) least distance between the self-collision pairs [m]
    tau_command: np.ndarray | None = None  # (T, n) the controller's command, with faults (tau: what acted)

    ARRAYS = ("t", "q", "v", "tau", "x", "x_ref", "xd_ref", "xdd_ref", "clearance", "e_null", "tick_us",
              "singular")
    OPTIONAL = ("quat", "quat_ref", "orientation_error_deg", "self_clearance", "tau_command")

    def save(self, path: str | Path) -> None:
        arrays = {k: getattr(self, k) for k in self.ARRAYS}
        arrays.update({k: getattr(self, k) for k in self.OPTIONAL if getattr(self, k) is not None})
        np.savez_compressed(path, **arrays)

    @classmethod
    def load(cls, path: str | Path) -> Trajectory:
        with np.load(path) as data:
            return cls(**{k: data[k] for k in cls.ARRAYS + cls.OPTIONAL if k in data.files})


MAX_TICKS = 5_000_000  # one run's recorded ticks (the trajectory is kept in memory: ~1 GB for the Panda)


def check_ticks(duration: float, dt: float) -> None:
    """:class:`ConfigError` (``sim.duration``) if a run of ``duration`` [s] at ``dt`` [s] would record
    more than MAX_TICKS ticks."""
    if not (np.isfinite(dt) and dt > 0):
        return  # the step's own check reports it
    ticks = duration / dt
    if not ticks <= MAX_TICKS:
        raise ConfigError(f"{duration} s at dt = {dt} s is {ticks:.3g} ticks; one run records at most "
                          f"{MAX_TICKS:,} (split it, or raise sim.dt)", key="sim.duration")


def measured_self_pairs(controller: Controller) -> tuple[tuple[int, int], ...]:
    """The link pairs whose distance a simulator records as the self clearance: the controller's
    self-collision pairs, or those a default SelfCollisionBarrier would keep (for every law)."""
    from qpctl.constraints.constraints import SelfCollisionBarrier
    from qpctl.geometry.self_collision import self_collision_pairs

    for c in getattr(controller, "constraints", ()):
        if isinstance(c, SelfCollisionBarrier):
            return c.pairs
    if len(controller.robot.capsules) < 3:
        return ()
    return self_collision_pairs(controller.robot, SELF_D_SAFE).pairs


SELF_D_SAFE = 0.02  # [m] QPConfig.self_d_safe's default, for the pairs measured under other laws


def finish_trajectory(traj: Trajectory, controller: Controller) -> Trajectory:
    """The task's position columns only in x, x_ref, ẋ_ref, ẍ_ref (the orientation rows' coordinates are
    centred at each tick's orientation: not a trajectory), and, with an orientation task, the frame's
    orientation and its reference as quaternions and the angle between them, from the recorded q
    and the path (after the run, outside the tick's timing)."""
    robot = controller.robot
    if not robot.m_orientation:
        return traj
    from qpctl.orientation import orientation_error_deg

    m_p = robot.m_position
    for name in ("x", "x_ref", "xd_ref", "xdd_ref"):
        setattr(traj, name, np.ascontiguousarray(getattr(traj, name)[:, :m_p]))
    model, data = robot.model, robot.model.createData()
    T = traj.t.size
    traj.quat, traj.quat_ref, traj.orientation_error_deg = np.zeros((T, 4)), np.zeros((T, 4)), np.zeros(T)
    for k in range(T):
        pin.framesForwardKinematics(model, data, traj.q[k])
        R = data.oMf[robot.ee_frame_id].rotation
        R_d = controller.path.orientation(float(traj.t[k]))[0]  # type: ignore[attr-defined]
        traj.quat[k] = pin.Quaternion(R).coeffs()
        traj.quat_ref[k] = pin.Quaternion(R_d).coeffs()
        traj.orientation_error_deg[k] = orientation_error_deg(robot, R, R_d)
    return traj


class Simulator:
    """Runs a controller on the robot it controls, in the scene it knows.

    Args:
        controller: any :class:`~qpctl.controllers.base.Controller`.
        dt: step [s] (the control period too).
        duration: simulated time [s].
        integrator: ``"rk4"`` (default, the paper's) or ``"euler"`` (semi-implicit).
        progress: show a progress bar.
        faults: what is not ideal (:class:`~qpctl.simulation.faults.Faults`; None or all off: nothing).
        obstacles: the true obstacles, where the controller was built on another map of them
            (``faults.perceived(obstacles, robot.task_axes)``); default: the controller's.
    """

    def __init__(self, controller: Controller, *, dt: float = 1e-3, duration: float = 5.0,
                 integrator: str = "rk4", progress: bool = False, faults: Faults | None = None,
                 obstacles: Sequence[Obstacle] | None = None) -> None:
        if not (np.isfinite(dt) and dt > 0):
            raise ConfigError(f"must be a positive number of seconds, got {dt}", key="sim.dt")
        if not (np.isfinite(duration) and duration > 0):
            raise ConfigError(f"must be a positive number of seconds, got {duration}", key="sim.duration")
        check_ticks(duration, dt)
        if integrator not in INTEGRATORS:
            raise ConfigError(f"unknown integrator {integrator!r}; one of {', '.join(INTEGRATORS)}",
                              key="sim.integrator")
        self.controller = controller
        self.robot = controller.robot
        self.dt = float(dt)
        self.duration = float(duration)
        self.integrator = rk4_step if integrator == "rk4" else euler_step
        self.progress = progress
        self._data = self.robot.model.createData()
        self.faults = faults if faults is not None and faults.active else None
        self.fault_counts: dict[str, int] = {}  # after a run with faults: commands lost, saturated ticks
        truth = list(controller.obstacles if obstacles is None else obstacles)
        if self.faults is not None:
            if self.faults.obstacle_noise and obstacles is None:
                raise ConfigError("the simulator needs the true obstacles (Simulator(..., obstacles=...)) and a "
                                  "controller built on faults.perceived(obstacles, robot.task_axes)",
                                  key="faults.obstacle_noise")
            truth = self.faults.world(truth, self.robot.task_axes)
        self.obstacles = truth
        self._world = WorldClearance(self.robot, truth, measured_self_pairs(controller))

    def clearance(self, q: np.ndarray, t: float) -> float:
        """Exact least distance [m] between any link and any obstacle at (q, t)."""
        return self._world(q, t)

    def run(self, q0: np.ndarray, v0: np.ndarray | None = None) -> Trajectory:
        """Simulate from (q0 [rad], v0 [rad/s], default rest) at t = 0 for ``duration``."""
        if self.faults is not None:
            return self._run_with_faults(q0, v0, self.faults)
        n = self.robot.nv
        q = np.asarray(q0, float).copy()
        v = np.zeros(n) if v0 is None else np.asarray(v0, float).copy()
        steps = round(self.duration / self.dt) + 1
        m = self.robot.m
        rec = {k: np.zeros((steps, n)) for k in ("q", "v", "tau", "e_null")}
        rec.update({k: np.zeros((steps, m)) for k in ("x", "x_ref", "xd_ref", "xdd_ref")})
        t_arr, clear, tick_us = np.zeros(steps), np.zeros(steps), np.zeros(steps)
        self_clear = np.full(steps, np.inf)
        singular = np.zeros(steps, bool)
        infos: list[dict[str, Any]] = []
        model, data = self.robot.model, self._data
        ctrl = self.controller
        if ctrl.warm:  # kernels loaded, workspace built, solver set up: not in the first tick
            ctrl.reset()
        else:
            ctrl.warmup()  # (ends in reset())
        tau = np.zeros(n)

        def accel(qq: np.ndarray, vv: np.ndarray) -> np.ndarray:
            return pin.aba(model, data, qq, vv, tau)

        iterator: Any = range(steps)
        if self.progress:
            from tqdm import tqdm

            iterator = tqdm(iterator, desc=f"simulate {ctrl.kind}", unit="tick", leave=False)
        for k in iterator:
            t = k * self.dt
            out = ctrl.step(q, v, t)
            tau = out.tau
            if not np.all(np.isfinite(tau)):
                raise SimulationError(f"controller {ctrl.kind} returned non-finite torque at t = {t:.4f} s")
            t_arr[k] = t
            rec["q"][k], rec["v"][k], rec["tau"][k], rec["e_null"][k] = q, v, tau, out.e_null
            rec["x"][k], rec["x_ref"][k] = out.x, out.ref.x
            rec["xd_ref"][k], rec["xdd_ref"][k] = out.ref.xd, out.ref.xdd
            clear[k] = self.clearance(q, t)
            self_clear[k] = self._world.self_clearance
            tick_us[k] = out.compute_us
            singular[k] = out.singular
            infos.append(out.info)
            if k + 1 < steps:
                q, v = self.integrator(accel, q, v, self.dt)
                if not (np.all(np.isfinite(q)) and np.all(np.isfinite(v))):
                    raise SimulationError(f"state diverged at t = {t + self.dt:.4f} s")
        traj = Trajectory(t_arr, rec["q"], rec["v"], rec["tau"], rec["x"], rec["x_ref"], rec["xd_ref"],
                          rec["xdd_ref"], clear, rec["e_null"], tick_us, singular, infos)
        if len(self._world.ws.sc_pairs):
            traj.self_clearance = self_clear
        return finish_trajectory(traj, ctrl)

    def _run_with_faults(self, q0: np.ndarray, v0: np.ndarray | None, faults: Faults) -> Trajectory:
        """:meth:`run` through the faults: the controller steps on the measured state, the drives turn
        its command into the applied torque, RK4 integrates the true robot (the payload's model from
        ``payload_time`` on); the record holds the truth (module docstring)."""
        n, m, robot = self.robot.nv, self.robot.m, self.robot
        q = np.asarray(q0, float).copy()
        v = np.zeros(n) if v0 is None else np.asarray(v0, float).copy()
        steps = round(self.duration / self.dt) + 1
        rec = {k: np.zeros((steps, n)) for k in ("q", "v", "tau", "tau_command", "e_null")}
        rec.update({k: np.zeros((steps, m)) for k in ("x", "x_ref", "xd_ref", "xdd_ref")})
        t_arr, clear, tick_us = np.zeros(steps), np.zeros(steps), np.zeros(steps)
        self_clear = np.full(steps, np.inf)
        singular = np.zeros(steps, bool)
        infos: list[dict[str, Any]] = []
        before, after = faults.simulated_models(robot)
        models = {False: (before, before.createData()), True: (after, after.createData())}
        kin = robot.model.createData()  # the task point's true position (kinematics: no mass involved)
        ee, axes, m_p = robot.ee_frame_id, list(robot.task_axes), robot.m_position
        ctrl = self.controller
        if ctrl.warm:
            ctrl.reset()
        else:
            ctrl.warmup()
        state = FaultState(faults, n, self.dt)
        tau = np.zeros(n)
        model, data = models[False]

        def accel(qq: np.ndarray, vv: np.ndarray) -> np.ndarray:
            return pin.aba(model, data, qq, vv, tau)

        iterator: Any = range(steps)
        if self.progress:
            from tqdm import tqdm

            iterator = tqdm(iterator, desc=f"simulate {ctrl.kind} (faults)", unit="tick", leave=False)
        for k in iterator:
            t = k * self.dt
            qm, vm = state.measure(q, v)
            out = ctrl.step(qm, vm, t)
            if not np.all(np.isfinite(out.tau)):
                raise SimulationError(f"controller {ctrl.kind} returned non-finite torque at t = {t:.4f} s")
            tau = state.actuate(out.tau)
            t_arr[k] = t
            rec["q"][k], rec["v"][k], rec["tau"][k], rec["tau_command"][k] = q, v, tau, out.tau
            rec["e_null"][k] = out.e_null
            pin.framesForwardKinematics(robot.model, kin, q)
            rec["x"][k] = out.x  # (an orientation task's rows: finish_trajectory keeps the position's only)
            rec["x"][k, :m_p] = kin.oMf[ee].translation[axes]
            ref = out.ref
            rec["x_ref"][k], rec["xd_ref"][k], rec["xdd_ref"][k] = ref.x, ref.xd, ref.xdd
            clear[k] = self.clearance(q, t)
            self_clear[k] = self._world.self_clearance
            tick_us[k] = out.compute_us
            singular[k] = out.singular
            infos.append(out.info)
            if k + 1 < steps:
                model, data = models[bool(faults.payload_mass) and t >= faults.payload_time]
                q, v = self.integrator(accel, q, v, self.dt)
                if not (np.all(np.isfinite(q)) and np.all(np.isfinite(v))):
                    raise SimulationError(f"state diverged at t = {t + self.dt:.4f} s")
        self.fault_counts = {"missed_commands": state.missed, "saturated_ticks": state.saturated}
        traj = Trajectory(t_arr, rec["q"], rec["v"], rec["tau"], rec["x"], rec["x_ref"], rec["xd_ref"],
                          rec["xdd_ref"], clear, rec["e_null"], tick_us, singular, infos,
                          tau_command=rec["tau_command"])
        if len(self._world.ws.sc_pairs):
            traj.self_clearance = self_clear
        return finish_trajectory(traj, ctrl)
