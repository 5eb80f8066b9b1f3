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
from typing import Any

import numpy as np
import pinocchio as pin

from qpctl.controllers.base import Controller
from qpctl.errors import ConfigError, SimulationError
from qpctl.geometry.obstacles import Obstacle
from qpctl.simulation.faults import Faults, FaultState
from qpctl.simulation.loop import SimulatorBase
from qpctl.simulation.trajectory import (  # noqa: F401  (re-exported: their historical home)
    MAX_TICKS,
    SELF_D_SAFE,
    Trajectory,
    check_ticks,
    finish_trajectory,
    measured_self_pairs,
)

INTEGRATORS = ("rk4", "euler")


Integrate = Callable[[np.ndarray, np.ndarray], np.ndarray]


def _add(q: np.ndarray, dv: np.ndarray) -> np.ndarray:
    return q + dv


def rk4_step(f: Callable[[np.ndarray, np.ndarray], np.ndarray], q: np.ndarray, v: np.ndarray,
             dt: float, integrate: Integrate = _add) -> tuple[np.ndarray, np.ndarray]:
    """One classical Runge–Kutta step of q̇ = v, v̇ = f(q, v); ``integrate(q, dv)`` is q ⊕ dv on the
    configuration space (``pin.integrate`` for continuous or planar joints, q + dv otherwise): the
    stages' configurations are q ⊕ (c dt k), the step's q ⊕ (dt/6 Σ wᵢkᵢ) — RK4 in the tangent space
    at q (Munthe-Kaas' RK-MK to first order in the commutator, exact for the abelian groups of
    continuous and planar joints' rotations)."""
    k1q, k1v = v, f(q, v)
    k2q, k2v = v + 0.5 * dt * k1v, f(integrate(q, 0.5 * dt * k1q), v + 0.5 * dt * k1v)
    k3q, k3v = v + 0.5 * dt * k2v, f(integrate(q, 0.5 * dt * k2q), v + 0.5 * dt * k2v)
    k4q, k4v = v + dt * k3v, f(integrate(q, dt * k3q), v + dt * k3v)
    return (integrate(q, dt / 6 * (k1q + 2 * k2q + 2 * k3q + k4q)), v + dt / 6 * (k1v + 2 * k2v + 2 * k3v + k4v))


def euler_step(f: Callable[[np.ndarray, np.ndarray], np.ndarray], q: np.ndarray, v: np.ndarray,
               dt: float, integrate: Integrate = _add) -> tuple[np.ndarray, np.ndarray]:
    """Semi-implicit Euler: v ← v + dt f(q, v), q ← q ⊕ dt v."""
    v1 = v + dt * f(q, v)
    return integrate(q, dt * v1), v1


class Simulator(SimulatorBase):
    """Runs a controller on the robot it controls, in the scene it knows: RK4 (or semi-implicit
    Euler) on Pinocchio's ABA, the torque held over the step.

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

    name = "builtin"

    def __init__(self, controller: Controller, *, dt: float = 1e-3, duration: float = 5.0,
                 integrator: str = "rk4", progress: bool = False, faults: Faults | None = None,
                 obstacles: Sequence[Obstacle] | None = None) -> None:
        super().__init__(controller, dt=dt, duration=duration, progress=progress)
        if integrator not in INTEGRATORS:
            raise ConfigError(f"unknown integrator {integrator!r}; one of {', '.join(INTEGRATORS)}",
                              key="sim.integrator")
        self.integrator = rk4_step if integrator == "rk4" else euler_step
        self._data = self.robot.model.createData()
        self.faults = faults if faults is not None and faults.active else None
        self.faulty = self.faults is not None
        self.fault_counts: dict[str, int] = {}  # after a run with faults: commands lost, saturated ticks
        truth = list(controller.obstacles if obstacles is None else obstacles)
        if self.faults is not None:
            if self.faults.obstacle_noise and obstacles is None:
                raise ConfigError("the simulator needs the true obstacles (Simulator(..., obstacles=...)) and a "
                                  "controller built on faults.perceived(obstacles, robot.task_axes)",
                                  key="faults.obstacle_noise")
            truth = self.faults.world(truth, self.robot.task_axes)
        self.obstacles = truth
        self._integrate: Integrate = self.robot.integrate if self.robot.lie else _add
        self._q = self.robot.q_home.copy()
        self._v = np.zeros(self.robot.nv)
        self._tau = np.zeros(self.robot.nv)
        self._models = {False: (self.robot.model, self._data)}
        self._state: FaultState | None = None
        self._t = 0.0

    @classmethod
    def from_scenario(cls, controller: Controller, scenario: Any, *, progress: bool = False,
                      faults: Faults | None = None, obstacles: Sequence[Obstacle] | None = None) -> Simulator:
        """The built-in simulator for the scenario's ``[sim]`` (``dt``, ``duration``, ``integrator``),
        with its faults and true obstacles if given; ``sim.model`` is not used (the built-in simulator
        integrates the controller's own model)."""
        sim = scenario.data["sim"]
        return cls(controller, dt=sim["dt"], duration=sim["duration"], integrator=sim["integrator"],
                   progress=progress, faults=faults, obstacles=obstacles)

    def reset(self, q0: np.ndarray, v0: np.ndarray | None = None) -> None:
        """Start at (q0: a configuration (nq), v0 [rad/s] (nv), default rest), zero torque; with faults,
        fresh fault draws."""
        n = self.robot.nv
        self._q = np.asarray(q0, float).copy()
        self._v = np.zeros(n) if v0 is None else np.asarray(v0, float).copy()
        self._tau = np.zeros(n)
        self._t = 0.0
        if self.faults is not None:
            before, after = self.faults.simulated_models(self.robot)
            self._models = {False: (before, before.createData()), True: (after, after.createData())}
            self._state = FaultState(self.faults, n, self.dt, self.robot)
        else:
            self._models = {False: (self.robot.model, self._data)}

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        return self._q, self._v

    def measure(self, q: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return (q, v) if self._state is None else self._state.measure(q, v)

    def actuate(self, tau_command: np.ndarray) -> np.ndarray:
        return tau_command if self._state is None else self._state.actuate(tau_command)

    def apply(self, tau: np.ndarray) -> None:
        self._tau = tau

    def step(self, t: float) -> None:
        faults = self.faults
        payload = faults is not None and bool(faults.payload_mass) and t >= faults.payload_time
        model, data = self._models[payload]
        tau = self._tau

        def accel(qq: np.ndarray, vv: np.ndarray) -> np.ndarray:
            return pin.aba(model, data, qq, vv, tau)

        self._q, self._v = self.integrator(accel, self._q, self._v, self.dt, self._integrate)
        self._t = t + self.dt
        if not (np.all(np.isfinite(self._q)) and np.all(np.isfinite(self._v))):
            raise SimulationError(f"state diverged at t = {t + self.dt:.4f} s")

    def run(self, q0: np.ndarray, v0: np.ndarray | None = None) -> Trajectory:
        """Simulate from (q0 [rad], v0 [rad/s], default rest) at t = 0 for ``duration``; with faults the
        controller steps on the measured state, the drives turn its command into the applied torque,
        RK4 integrates the true robot (the payload's model from ``payload_time`` on); the record holds
        the truth (module docstring)."""
        traj = super().run(q0, v0)
        if self._state is not None:
            self.fault_counts = {"missed_commands": self._state.missed,
                                 "saturated_ticks": self._state.saturated}
        return traj
