"""The brake family and the oracle (issue 22, item 3): a state is certified viable by exhibiting a
brake that the built-in simulator verifies brings the arm to rest without contact.

A brake of gain κ [1/s] is the rate-limited computed-torque stop

    τ* = N(q, q̇) − κ M(q) q̇,   τ = clip(clip(τ*, ±τ_max), τ_prev ± τ̇_max Δt),

(Pinocchio's M and N), held over each step of :class:`qpctl.simulation.Simulator` (RK4 on ABA, the
step Δt of the run). :func:`rollout` runs one from (q, q̇, τ_prev) at time t until the arm is at rest
(every |q̇ᵢ| ≤ ``REST_SPEED`` for ``REST_TIME``) or ``horizon`` ends, and reports the least clearance
(the simulator's exact world clearance, moving obstacles at their time) and whether the joint limits
held; a rest counts only where the arm clears the static obstacles and every swaying obstacle's whole
sweep by the stop's creep (:func:`rest_clear`, :mod:`qpctl.safety.sweep`: the stop goes on after the
rest, and a swaying obstacle comes back to a stopped arm for ever). :func:`certify` tries the family
:data:`BRAKE_GAINS`. A certificate proves the state viable under the simulated model (the brake is
exhibited); a state no brake of the family certifies is not proved unviable.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pinocchio as pin

from qpctl.safety.retreat import Retreat
from qpctl.safety.sweep import RestClearance
from qpctl.simulation.simulator import Simulator

#: The family of brake gains tried, hardest last [1/s].
BRAKE_GAINS = (4.0, 10.0, 25.0, 60.0)
REST_SPEED = 1e-2  # [rad/s]
REST_TIME = 0.05  # [s]


@dataclass(frozen=True)
class Certificate:
    """A brake's rollout: ``viable`` (at rest within the horizon, no contact, joint limits kept), the
    gain κ [1/s], the least clearance [m] along it, the time to rest [s] (inf: not at rest)."""

    viable: bool
    gain: float
    min_clearance: float
    t_rest: float
    steps: int


def brake_torque(robot: Any, data: pin.Data, q: np.ndarray, v: np.ndarray, tau_prev: np.ndarray, gain: float,
                 dt: float, retreat: Retreat | None = None, t: float = 0.0) -> np.ndarray:
    """The brake's torque [N·m] at (q, q̇) after τ_prev (module docstring): N − κMq̇ is Pinocchio's
    RNEA at q̈ = −κq̇, then the torque and rate limits. With a ``retreat`` steering at t [s]
    (:mod:`qpctl.safety.retreat`), RNEA at its q̈* = ω²(q* − q) − 2ωq̇ instead."""
    qdd = retreat.accel(q, v, np.empty_like(v)) if retreat is not None and retreat.steering(t) else -gain * v
    tau = pin.rnea(robot.model, data, q, v, qdd)
    tau = np.minimum(np.maximum(tau, -robot.tau_max), robot.tau_max)
    if np.isfinite(tau_prev[0]):
        w = robot.tau_rate_max * dt
        tau = np.minimum(np.maximum(tau, tau_prev - w), tau_prev + w)
    return tau


def rollout(sim: Simulator, q: np.ndarray, v: np.ndarray, tau_prev: np.ndarray, t: float, gain: float, *,
            horizon: float = 3.0, margin: float = 0.0, stop_below: float = -np.inf,
            retreat: Retreat | None = None, hold: float = 0.0) -> Certificate:
    """The brake of gain κ from (q [rad], q̇ [rad/s], τ_prev [N·m]) at t [s] in ``sim`` (its robot, dt,
    obstacles); it stops early once the clearance is below ``stop_below`` [m]. Viable: at rest with the
    clearance above ``margin`` [m] all along and every joint within its limits. With a ``retreat``, the
    retreat that brakes at gain κ once it stops steering (:mod:`qpctl.safety.retreat`). ``hold`` [s]: how
    long after the rest the drifting obstacles must stay clear of it (0: not tested)."""
    robot, dt = sim.robot, sim.dt
    data = robot.model.createData()
    sim.reset(q, v)
    tau = np.asarray(tau_prev, float)
    worst = np.inf
    still = 0.0
    limits_ok = True
    steps = round(horizon / dt)
    qq, vv = np.asarray(q, float), np.asarray(v, float)
    for k in range(steps):
        tk = t + k * dt
        worst = min(worst, sim.clearance(qq, tk))
        if worst < stop_below:
            return Certificate(False, gain, worst, np.inf, k)
        if np.any(qq < robot.q_min) or np.any(qq > robot.q_max):
            limits_ok = False
            return Certificate(False, gain, worst, np.inf, k)
        steering = retreat is not None and retreat.steering(tk)  # a retreat's rest is its brake's
        still = still + dt if np.all(np.abs(vv) <= REST_SPEED) and not steering else 0.0
        if still >= REST_TIME:
            return Certificate(limits_ok and worst > margin and rest_clear(sim, qq, vv, gain, margin, tk, hold), gain,
                               worst, k * dt, k)
        tau = brake_torque(robot, data, qq, vv, tau, gain, dt, retreat, tk)
        sim.apply(tau)
        sim.step(tk)
        qq, vv = sim.read()
        qq, vv = qq.copy(), vv.copy()
    return Certificate(False, gain, worst, np.inf, steps)


def rest_clear(sim: Simulator, q: np.ndarray, v: np.ndarray, gain: float, margin: float, t: float = 0.0,
               hold: float = 0.0) -> bool:
    """The rest test (:meth:`qpctl.safety.sweep.RestClearance.verifies`) of a brake of gain κ at rest at
    (q [rad], q̇ [rad/s]) in ``sim``'s world, its :class:`~qpctl.safety.sweep.RestClearance` kept on
    ``sim``: each joint's stop within its limits, the static obstacles and every swaying obstacle's whole
    sweep cleared by ``margin`` [m] plus the stop's creep (and the drifting obstacles over ``hold`` [s]
    after t [s])."""
    rest = getattr(sim, "_rest_clearance", None)
    if rest is None or rest.hold != hold:
        rest = sim._rest_clearance = RestClearance(sim.robot, sim.obstacles, hold)  # type: ignore[attr-defined]
    return rest.verifies(q, v, gain, margin, t)


def certify(controller: Any, q: np.ndarray, v: np.ndarray, tau_prev: np.ndarray, t: float, dt: float, *,
            gains: tuple[float, ...] = BRAKE_GAINS, horizon: float = 3.0, margin: float = 0.0,
            retreats: Sequence[tuple[Retreat, float]] = (), hold: float = 0.0) -> Certificate:
    """The first brake of the family that the built-in simulator (``controller``'s robot and obstacles,
    step ``dt`` [s]) verifies from this state, then the first of the proposed ``retreats`` ((retreat,
    the gain it brakes with) — from anywhere, e.g. the guard's stored one: the rollout here is the
    proof), or the best failed one (largest least clearance)."""
    sim = Simulator(controller, dt=dt, duration=dt)
    best: Certificate | None = None
    tries = [(g, None) for g in gains] + [(g, r) for r, g in retreats]
    for g, r in tries:
        c = rollout(sim, q, v, tau_prev, t, g, horizon=horizon, margin=margin, stop_below=margin, retreat=r,
                    hold=hold)
        if c.viable:
            return c
        if best is None or c.min_clearance > best.min_clearance:
            best = c
    assert best is not None
    return best
