"""Barrier gains and influence distance derived from what the drives allow (issue 16, item 2).

The obstacle barrier asks, of every link–obstacle pair within the influence distance, that the
clearance h = d − d_safe [m] obey

    ḧ ≥ −k₁ ḣ − k₀ h.

Its boundary, ḧ = −k₁ḣ − k₀h, is the motion the arm must be able to make when it holds the row with
equality. With a torque-rate limit that motion must be anticipated: the torque, hence ḧ, can change
only so fast, so a row that starts binding with a jump (a link entering the influence zone fast) or
whose boundary decelerates harder, or changes its deceleration faster, than the drives allow turns
the QP infeasible, and the link goes through. This module chooses the barrier so that its boundary
stays within the drives' means, for a link point closing on an obstacle at up to ``v`` [m/s]:

* **Critically damped**: k₀ = ω², k₁ = 2ω. From entry at h₀ with ḣ₀ = −v the boundary is
  h(t) = (h₀ + c t) e^{−ωt}, c = ωh₀ − v, and asks ḧ(0) = ω(2v − ωh₀).
* **No jump at entry**: the row is slack when the link enters, ḧ(0) ≤ 0 ⇔ h₀ ≥ 2v/ω. On the boundary
  from h₀ = 2v/ω, ḧ(t) = ω² v t e^{−ωt}: its peak is ωv/e (at t = 1/ω) and its peak rate ω²v (at
  entry). Hence ω ≤ e·a/v (deceleration a [m/s²]) and ω ≤ √(j/v) (jerk j [m/s³]).
* **A lead for the state at entry**: a link may enter accelerating towards the obstacle at up to a;
  bringing that to zero at jerk j takes a/j [s], covering at most v·a/j [m], plus one control period
  of latency, v·dt. The influence distance is d_safe + 2v/ω + v·a/j + v·dt.

The means (a, j) are those of a link point along a direction, from the torques and the torque rates:
q̈ = M⁻¹(τ − b), so a point's acceleration along a unit n can be raised by at most
Σᵢ |(nᵀJ_p M⁻¹)ᵢ| (τ_max,i − |gᵢ|) (the torque left over gravity), or Σᵢ |(nᵀJ_p)ᵢ| q̈_max,i under
joint-acceleration bounds, whichever is smaller; its rate by Σᵢ |(nᵀJ_p M⁻¹)ᵢ| τ̇_max,i. A share of
each (``share``, default ½) is given to the barrier, the rest left to the task and the bias forces at
speed. They are taken at the far end of every link capsule, in every direction that point can move
in (|nᵀJ_p| at least a fifth of its largest, 64 directions), on the start configuration and 15 seeded
random ones within the joint limits; each point–direction gets its own v (the approach speed, capped
by what the joint-speed limits allow that point along n) and the design keeps the smallest ω and the
largest influence distance over all of them.

The approach speed ``v`` is a design input (``controller.approach_speed`` [m/s]); ``"auto"`` takes
1.5 × the reference path's peak speed plus the fastest obstacle's speed. The design is sufficient for
the motions it models (a point closing straight at up to v), not a proof for every motion of the arm.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import pinocchio as pin

from qpctl.errors import ConfigError

#: The share of the deceleration and jerk a point can get that the barrier's design may use.
DEFAULT_SHARE = 0.5
#: ``"auto"`` approach speed: this many times the reference path's peak speed (+ the fastest obstacle's).
PATH_SPEED_FACTOR = 1.5
#: A direction counts for a point when |nᵀJ_p| is at least this fraction of the point's largest.
DIRECTION_FLOOR = 0.2
N_DIRECTIONS = 64
N_CONFIGURATIONS = 16


@dataclass(frozen=True)
class BarrierDesign:
    """The barrier's gains and influence distance, and what they were derived from (units in brackets)."""

    k0: float  # [1/s²]
    k1: float  # [1/s]
    d_influence: float  # [m]
    omega: float  # ω = √k₀ [1/s]
    approach_speed: float  # v [m/s]
    deceleration: float  # a [m/s²]: the barrier's share, at the point–direction that set ω
    jerk: float  # j [m/s³]: likewise
    limited_by: str  # "deceleration" or "jerk": which bound set ω

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def _directions(planar_axes: Sequence[int] | None, count: int = N_DIRECTIONS) -> np.ndarray:
    """Unit directions: on the circle of the task plane for a planar arm, else a Fibonacci sphere."""
    if planar_axes is not None and len(planar_axes) == 2:
        a = np.linspace(0.0, 2 * np.pi, count, endpoint=False)
        out = np.zeros((count, 3))
        out[:, planar_axes[0]], out[:, planar_axes[1]] = np.cos(a), np.sin(a)
        return out
    k = np.arange(count) + 0.5
    z = 1.0 - 2.0 * k / count
    phi = np.pi * (1.0 + 5.0**0.5) * k
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _configurations(robot: Any, q0: np.ndarray, count: int = N_CONFIGURATIONS, seed: int = 0) -> list[np.ndarray]:
    lo = np.where(np.isfinite(robot.q_min), robot.q_min, -np.pi)
    hi = np.where(np.isfinite(robot.q_max), robot.q_max, np.pi)
    rng = np.random.default_rng(seed)
    return [np.asarray(q0, float)] + [robot.random_configuration(rng, lo, hi) for _ in range(count - 1)]


def drive_means(robot: Any, q0: np.ndarray, v: float, dt: float, *, share: float = DEFAULT_SHARE
                ) -> list[tuple[float, float, float]]:
    """(v, a, j) for every link point, direction and sampled configuration (see the module's text):
    the approach speed capped by the joint-speed limits, and the barrier's share of the deceleration
    [m/s²] and jerk [m/s³] the drives give that point along that direction."""
    model, data = robot.model, robot.model.createData()
    n = robot.nv
    tau_max = np.asarray(robot.tau_max, float)
    rate = np.full(n, np.inf) if robot.tau_rate_max is None else np.broadcast_to(robot.tau_rate_max, (n,))
    qdd = np.full(n, np.inf) if robot.qdd_max is None else np.broadcast_to(robot.qdd_max, (n,))
    vmax = np.broadcast_to(robot.v_max, (n,))
    planar = robot.task_axes if len(robot.task_axes) == 2 else None
    dirs = _directions(planar)
    out: list[tuple[float, float, float]] = []
    for q in _configurations(robot, q0):
        M = pin.crba(model, data, q)
        M = np.triu(M) + np.triu(M, 1).T
        Minv = np.linalg.inv(M)
        g = pin.computeGeneralizedGravity(model, data, q)
        headroom = np.maximum(tau_max - np.abs(g), 0.0)
        pin.computeJointJacobians(model, data, q)
        for cap in robot.capsules:
            oMi = data.oMi[cap.joint_id]
            J = pin.getJointJacobian(model, data, cap.joint_id, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)
            r = oMi.rotation @ np.asarray(cap.p1, float)  # the far end, from the joint's origin
            Jp = J[:3] - pin.skew(r) @ J[3:]
            rows = dirs @ Jp  # nᵀJ_p for every direction
            size = np.abs(rows).sum(axis=1)
            if not size.max() > 1e-9:
                continue  # a point that cannot move (the base)
            B = rows @ Minv
            with np.errstate(invalid="ignore"):  # inf · 0 where a joint has no say along n
                a_tau = np.nansum(np.abs(B) * headroom, axis=1)
                a_qdd = np.nansum(np.abs(rows) * qdd, axis=1)
                jerk = np.nansum(np.abs(B) * rate, axis=1)
                speed = np.nansum(np.abs(rows) * vmax, axis=1)
            for k in np.flatnonzero(size >= DIRECTION_FLOOR * size.max()):
                out.append((min(v, float(speed[k])), share * min(float(a_tau[k]), float(a_qdd[k])),
                            share * float(jerk[k])))
    return out


def design(v: float, a: float, j: float, d_safe: float, dt: float) -> BarrierDesign:
    """The barrier for one point–direction: approach speed v [m/s], deceleration a [m/s²], jerk j [m/s³]
    (inf: unlimited), d_safe [m], control period dt [s]."""
    if not (v > 0 and math.isfinite(v)):
        raise ConfigError(f"the approach speed must be a finite number > 0 [m/s], got {v}",
                          key="controller.approach_speed")
    w_a, w_j = math.e * a / v, math.sqrt(j / v)
    omega = min(w_a, w_j)
    if not (math.isfinite(omega) and omega > 0):
        raise ConfigError("barrier_design = \"drives\" needs finite torque or torque-rate limits with room above "
                          "gravity (robot.tau_max, robot.tau_rate_max)", key="controller.barrier_design")
    return BarrierDesign(omega * omega, 2 * omega, _influence(v, a, j, omega, d_safe, dt), omega, v, a, j,
                         "deceleration" if w_a <= w_j else "jerk")


def _influence(v: float, a: float, j: float, omega: float, d_safe: float, dt: float) -> float:
    """The influence distance [m] for approach speed v at ω: d_safe, the entry without a jump (2v/ω),
    the lead for a link entering while accelerating (v·a/j, none without both limits), one period."""
    lead = v * a / j if math.isfinite(a) and math.isfinite(j) else 0.0
    return d_safe + 2 * v / omega + lead + v * dt


def design_for(robot: Any, q0: np.ndarray, v: float, d_safe: float, dt: float, *,
               share: float = DEFAULT_SHARE) -> BarrierDesign:
    """The robot's barrier: the smallest ω over every point–direction of :func:`drive_means`, and the
    largest influence distance that ω needs over them."""
    means = [(vv, a, j) for vv, a, j in drive_means(robot, q0, v, dt, share=share) if vv > 0]
    if not means:
        raise ConfigError("no link point of the robot can move", key="controller.barrier_design")
    designs = [design(vv, a, j, d_safe, dt) for vv, a, j in means]
    worst = min(designs, key=lambda d: d.omega)
    w = worst.omega
    d_inf = max(_influence(vv, a, j, w, d_safe, dt) for vv, a, j in means)
    return BarrierDesign(w * w, 2 * w, d_inf, w, worst.approach_speed, worst.deceleration, worst.jerk,
                         worst.limited_by)


def auto_approach_speed(path: Any, obstacles: Sequence[Any], *, samples: int = 400) -> float:
    """``"auto"``: PATH_SPEED_FACTOR × the reference path's peak speed [m/s] plus the fastest obstacle's."""
    total = float(path.starts[-1] + path.durations[-1])
    peak = max(float(np.linalg.norm(path(t).xd[:3])) for t in np.linspace(0.0, total, samples))
    obstacle = 0.0
    for o in obstacles:
        w = 2 * np.pi * float(getattr(o, "frequency", 0.0))
        obstacle = max(obstacle, float(np.linalg.norm(o.velocity) + np.linalg.norm(o.amplitude) * w))
    return PATH_SPEED_FACTOR * peak + obstacle
