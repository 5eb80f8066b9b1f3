"""The lean brake rollout (issue 22, item 2): the oracle's brake and the built-in simulator's RK4,
with Pinocchio called directly on preallocated arrays, the step's arithmetic in compiled kernels
(:mod:`qpctl.kernels.rollout`) and the world clearance of the simulator's own
:class:`qpctl.tick.WorldClearance` — no :class:`~qpctl.simulation.Simulator` object stepped.

Per step at (q, q̇, t) after τ_prev, exactly as :func:`qpctl.safety.oracle.rollout` does it:

    clearance(q, t);  τ = clip(clip(RNEA(q, q̇, −κq̇), ±τ_max), τ_prev ± τ̇_max Δt)
    (q, q̇) ← RK4 of q̇ = v, v̇ = ABA(q, v, τ) over Δt          (simulation.simulator.rk4_step's stages)

The arithmetic is rk4_step's operations in the same order, so the states equal the simulator's (the
tests hold them to 1e-12 against the oracle); a robot with continuous or planar joints integrates on
its configuration space through ``robot.integrate`` as the simulator does.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pinocchio as pin

from qpctl.kernels import rollout as K
from qpctl.safety.oracle import REST_SPEED, REST_TIME, Certificate
from qpctl.tick import WorldClearance


class BrakeRollout:
    """Brake rollouts of one robot in one world at step ``dt`` [s] (module docstring).

    Args:
        robot: the controller's :class:`~qpctl.robot.RobotModel` (its model, limits, capsules).
        world: the exact world clearance (a simulator's ``world``; its obstacles move with t).
        dt: the step [s] (the run's: the guarantee is about the simulator's own integration).
    """

    def __init__(self, robot: Any, world: WorldClearance, dt: float) -> None:
        self.robot, self.world, self.dt = robot, world, float(dt)
        model = robot.model
        self.model, self.data = model, model.createData()
        n = robot.nv
        self.tau_max = np.asarray(robot.tau_max, float)
        rate = robot.tau_rate_max if robot.tau_rate_max is not None else np.full(n, np.inf)
        self.window = np.asarray(rate, float) * self.dt
        self.q_min, self.q_max = np.asarray(robot.q_min, float), np.asarray(robot.q_max, float)
        self.lie = bool(robot.lie)
        self.tau, self.qdd = np.zeros(n), np.zeros(n)
        self._kq, self._ka = np.zeros((4, n)), np.zeros((4, n))  # the stages' k·q (velocities), k·v
        self._qs, self._vs, self._dq, self._dv = np.zeros(model.nq), np.zeros(n), np.zeros(n), np.zeros(n)
        self._angles = np.zeros(n)

    def torque(self, q: np.ndarray, v: np.ndarray, tau_prev: np.ndarray, gain: float) -> np.ndarray:
        """The brake's torque [N·m] at (q, q̇) after τ_prev into ``self.tau`` (oracle.brake_torque)."""
        np.multiply(v, -gain, out=self.qdd)
        self.tau[:] = pin.rnea(self.model, self.data, q, v, self.qdd)
        K.clip_brake(self.tau, self.tau_max, tau_prev, self.window)
        return self.tau

    def _stage(self, q: np.ndarray, v: np.ndarray, h: float, i: int) -> None:
        """Stage i + 1 from stage i: its velocity kq[i+1] = v + h·ka[i], its acceleration ABA(q ⊕ h·kq[i], ·)."""
        kq, ka, qs, vs = self._kq, self._ka, self._qs, self._vs
        K.stage(q, v, kq[i], ka[i], h, self._dq, qs, vs)
        if self.lie:
            qs[:] = self.robot.integrate(q, self._dq)
        kq[i + 1] = vs
        ka[i + 1] = pin.aba(self.model, self.data, qs, vs, self.tau)

    def step(self, q: np.ndarray, v: np.ndarray) -> None:
        """One RK4 step of the held ``self.tau`` over dt; (q, v) updated in place (rk4_step's stages)."""
        dt = self.dt
        self._kq[0] = v
        self._ka[0] = pin.aba(self.model, self.data, q, v, self.tau)
        self._stage(q, v, 0.5 * dt, 0)
        self._stage(q, v, 0.5 * dt, 1)
        self._stage(q, v, dt, 2)
        K.combine(self._kq, dt / 6, self._dq)
        K.combine(self._ka, dt / 6, self._dv)
        if self.lie:
            q[:] = self.robot.integrate(q, self._dq)
        else:
            q += self._dq
        v += self._dv

    def successor(self, q: np.ndarray, v: np.ndarray, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(q₁, q̇₁): ``tau`` [N·m] held over one step from (q, q̇), as the simulator steps it (new arrays)."""
        qq, vv = np.array(q, float), np.array(v, float)
        self.tau[:] = tau
        self.step(qq, vv)
        return qq, vv

    def run(self, q: np.ndarray, v: np.ndarray, tau_prev: np.ndarray, t: float, gain: float, *,
            horizon: float = 3.0, margin: float = 0.0, stop_below: float = -np.inf) -> Certificate:
        """The brake of gain κ [1/s] from (q, q̇ [rad/s], τ_prev [N·m]) at t [s]: the
        :class:`~qpctl.safety.oracle.Certificate` :func:`qpctl.safety.oracle.rollout` gives (the
        arguments mean the same; a state that is not finite ends it, not viable). Inputs unchanged."""
        dt, world = self.dt, self.world
        qq, vv, prev = np.array(q, float), np.array(v, float), np.array(tau_prev, float)
        worst, still = np.inf, 0.0
        steps = round(horizon / dt)
        for k in range(steps):
            worst = min(worst, world(qq, t + k * dt))
            code = K.state_code(self.robot.angles(qq, self._angles) if self.lie else qq, vv, self.q_min,
                                self.q_max, REST_SPEED)
            if worst < stop_below or code == K.OUTSIDE:
                return Certificate(False, gain, worst, np.inf, k)
            still = still + dt if code == K.AT_REST else 0.0
            if still >= REST_TIME:
                return Certificate(worst > margin, gain, worst, k * dt, k)
            self.torque(qq, vv, prev, gain)
            prev[:] = self.tau
            self.step(qq, vv)
        return Certificate(False, gain, worst, np.inf, steps)
