"""Hard constraints on q̈ that no closed form can hold (DESIGN.md §2, "QP law").

* :class:`TorqueLimit` — −τ_max ≤ M q̈ + N ≤ τ_max, and the torque-rate limit |τ − τ_prev| ≤ τ̇_max dt.
* :class:`JointLimit` — joint positions and speeds kept inside their limits by second-order
  (position) and first-order (speed) barriers expressed as bounds on q̈, within the acceleration limits.
* :class:`ObstacleBarrier` — for each (link, obstacle) pair within the influence distance,
  ḧ + k₁ḣ + k₀h ≥ 0 with h = d − d_s, ḣ = nᵀ(J_p q̇ − v_obs), ḧ = nᵀJ_p q̈ + (∂ḣ/∂q q̇ + ∂ḣ/∂t).
  The drift in brackets is :meth:`TickState.barrier_drift` (``drift="exact"``, the default: closed
  form for spheres and capsules, a look-ahead finite difference for boxes and cylinders), which
  includes the normal's rotation and the witness points sliding over the surfaces, or the rigid-point
  approximation nᵀ(J̇_p q̇ − a_obs) of DESIGN.md §2 (``drift="rigid"``), which leaves out a term of
  order ρω² (ρ the distance from the link's joint, ω its angular rate) and so lets a fast-turning
  link settle a few millimetres inside d_s. A fixed number of rows: inactive rows have −inf bounds.
* :class:`SelfCollisionBarrier` — the same rows between pairs of the arm's own link capsules
  (:mod:`qpctl.geometry.self_collision` says which), both moving: ḣ = nᵀ(J_p − J_q)q̇ and the exact
  drift of two rotating capsules (:func:`qpctl.kernels.self_pairs.self_pairs`).
"""

from __future__ import annotations

import contextlib
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence

import numpy as np

from qpctl.constraints.braking import Braking
from qpctl.errors import ConfigError
from qpctl.kernels.drives import REACH_SHARE
from qpctl.law import LawTerms
from qpctl.qp import Bounds, Inequality
from qpctl.state import TickState


def _positive(name: str, value: float) -> float:
    if not (np.isfinite(value) and value > 0):
        raise ConfigError(f"must be a positive number, got {value}", key=name)
    return float(value)


# Row kinds (Constraint.kind): what the fallback chain looks rows up by in the tick's Problem
# (Problem.rows_of), whatever class contributed them.
BARRIER = "barrier"  # ḧ + k₁ḣ + k₀h ≥ 0 rows keeping links off obstacles: the safe stop keeps them,
#                      the closed-form fallback must meet them
TORQUE = "torque"
JOINT_LIMITS = "joint_limits"
SELF_COLLISION = "self_collision"


class Constraint(ABC):
    """A constraint returns a fixed number of rows (``rows``) or bounds on q̈ every tick, and keeps
    nothing from one tick to the next that the controller reads back (what a tick leaves out, say
    pairs beyond capacity, is in its output: :attr:`Inequality.dropped`).

    ``kind`` names what its rows are (one of the kinds above, or the user's own word): a user's
    barrier class sets ``kind = BARRIER`` and the safe stop keeps its rows like the obstacle
    barrier's."""

    name: str = "constraint"
    kind: str = "constraint"
    rows: int = 0  # rows of C it contributes (0 for Bounds)
    #: (ℓ₁, ℓ₂) weights of its slack columns σⱼ ≥ 0 (C q̈ + Σⱼ cⱼσⱼ ≥ l, cⱼ the columns of
    #: :meth:`slack_columns`; cost Σⱼ ℓ₁σⱼ + ½ℓ₂σⱼ²), or None: hard rows. Fixed for the constraint's life (the
    #: QP's layout has it).
    slack: tuple[float, float] | None = None

    def slack_columns(self) -> tuple[np.ndarray, np.ndarray]:
        """(rows, k) the entries of its k slack columns in each row (a row of zeros: the row is hard) and
        (k, 2) each column's (ℓ₁, ℓ₂) weights; read once, with the layout. By default one column all rows
        share, at :attr:`slack`'s weights."""
        assert self.slack is not None
        return np.ones((self.rows, 1)), np.array([self.slack], float)

    @abstractmethod
    def compute(self, state: TickState, terms: LawTerms) -> Inequality | Bounds:
        """The constraint at this tick."""


class TorqueLimit(Constraint):
    """The drives' limits on τ = M q̈ + N, n rows: |τ| ≤ τ_max [N·m] and, once a torque τ_prev was
    commanded at t_prev, |τ − τ_prev| ≤ τ̇_max (t − t_prev) with τ̇_max [N·m/s] the torque-rate limit
    (:meth:`window`). The controller records each tick's commanded torque with :meth:`remember`
    (after any fallback) and forgets it on reset."""

    name = "torque_limits"
    kind = TORQUE

    def __init__(self, tau_max: np.ndarray, tau_rate_max: np.ndarray | float | None = None) -> None:
        tau_max = np.asarray(tau_max, float).reshape(-1)
        if np.any(np.isnan(tau_max)) or np.any(tau_max <= 0):
            raise ConfigError(f"torque limits must be positive, got {tau_max.tolist()}", key="robot.tau_max")
        rate = np.broadcast_to(np.asarray(np.inf if tau_rate_max is None else tau_rate_max, float),
                               tau_max.shape).copy()
        if np.any(np.isnan(rate)) or np.any(rate <= 0):
            raise ConfigError(f"torque-rate limits must be positive, got {rate.tolist()}", key="robot.tau_rate_max")
        self.tau_max, self.tau_rate_max = tau_max, rate
        self.rows = tau_max.size
        self.previous = np.full(tau_max.size, np.nan)  # [N·m] the torque commanded last (NaN: none yet)
        self.t_previous = np.full(1, np.nan)  # [s] when

    def window(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) [N·m]: the torques that may be commanded at t [s] (where the rate window and ±τ_max
        do not meet — the limits changed — the torque limit wins)."""
        lo, hi = -self.tau_max, self.tau_max.copy()
        dt = t - self.t_previous[0]
        if dt > 0:  # False for NaN: nothing commanded yet
            w = self.tau_rate_max * dt
            lo2, hi2 = np.maximum(lo, self.previous - w), np.minimum(hi, self.previous + w)
            meet = lo2 <= hi2
            lo, hi = np.where(meet, lo2, lo), np.where(meet, hi2, hi)
        return lo, hi

    def remember(self, tau: np.ndarray, t: float) -> None:
        """The torque [N·m] commanded at t [s]: the next tick's rate limit is about it."""
        self.previous[:] = tau
        self.t_previous[0] = t

    def forget(self) -> None:
        self.previous[:] = np.nan
        self.t_previous[0] = np.nan

    def compute(self, state: TickState, terms: LawTerms) -> Inequality:
        lo, hi = self.window(state.t)
        return Inequality(state.M, lo - state.N, hi - state.N)


class JointLimit(Constraint):
    """Position limits by ḧ + k₁ḣ + k₀h ≥ 0 (h = q − q_min, q_max − q), speed limits by
    ḣ + k_v h ≥ 0 (h = v_max ∓ q̇), both as bounds on q̈ [rad/s²], then within ±q̈_max, the drives'
    acceleration limits.

    Where the two bounds cross (a state already outside its limits) both are set to their mean;
    where that asks for more than q̈_max, both become the limit on that side.
    """

    name = "joint_limits"
    kind = JOINT_LIMITS

    def __init__(self, q_min: np.ndarray, q_max: np.ndarray, v_max: np.ndarray, *, k0: float = 100.0,
                 k1: float = 20.0, kv: float = 50.0, qdd_max: np.ndarray | float | None = None,
                 angles: Callable[[np.ndarray], np.ndarray] | None = None, braking: Braking | None = None) -> None:
        self.q_min, self.q_max, self.v_max = (np.asarray(a, float) for a in (q_min, q_max, v_max))
        # a configuration (nq) → one coordinate per degree of freedom (RobotModel.angles), where they
        # differ; the limits are on those coordinates (±inf on continuous and planar joints)
        self.angles = angles
        self.qdd_max = np.broadcast_to(np.asarray(np.inf if qdd_max is None else qdd_max, float),
                                       self.q_min.shape).copy()
        if np.any(np.isnan(self.qdd_max)) or np.any(self.qdd_max <= 0):
            raise ConfigError(f"acceleration limits must be positive, got {self.qdd_max.tolist()}",
                              key="robot.qdd_max")
        self.k0 = _positive("controller.joint_k0", k0)
        self.k1 = _positive("controller.joint_k1", k1)
        self.kv = _positive("controller.velocity_gain", kv)
        self.braking = braking  # the bounds braking-aware too (qpctl.constraints.braking)
        # with every limit finite no ∞ − ∞ (NaN) can arise: skip the guard (it costs more than the rows)
        self._finite = bool(np.isfinite(np.concatenate([self.q_min, self.q_max, self.v_max])).all())

    def compute(self, state: TickState, terms: LawTerms) -> Bounds:
        q, v = (state.q if self.angles is None else self.angles(state.q)), state.v
        with contextlib.nullcontext() if self._finite else np.errstate(invalid="ignore"):
            lo = np.maximum(-self.k1 * v - self.k0 * (q - self.q_min), -self.kv * (self.v_max + v))
            hi = np.minimum(-self.k1 * v + self.k0 * (self.q_max - q), self.kv * (self.v_max - v))
        if not self._finite:
            lo = np.where(np.isnan(lo), -np.inf, lo)
            hi = np.where(np.isnan(hi), np.inf, hi)
        if self.braking is not None:
            lo, hi = self.braking.joint_limits(q, v, self.q_min, self.q_max, state.M, state.N, lo, hi)
        cross = lo > hi
        if cross.any():
            mid = 0.5 * (lo + hi)
            lo, hi = np.where(cross, mid, lo), np.where(cross, mid, hi)
        a = self.qdd_max
        lo2, hi2 = np.maximum(lo, -a), np.minimum(hi, a)
        cross = lo2 > hi2
        if cross.any():
            edge = np.clip(0.5 * (lo + hi), -a, a)
            lo2, hi2 = np.where(cross, edge, lo2), np.where(cross, edge, hi2)
        return Bounds(lo2, hi2)


class ObstacleBarrier(Constraint):
    """nᵀJ_p q̈ ≥ −k₁ḣ − k₀h − nᵀJ̇_p q̇ + nᵀa_obs for up to ``capacity`` nearest pairs within d_i.

    k₀ [1/s²] and k₁ [1/s] set how fast the arm may approach: h ≥ 0 is kept when h(0) ≥ 0 and
    s² + k₁s + k₀ is Hurwitz with real roots (k₁² ≥ 4k₀ avoids overshoot into the safety margin).
    """

    name = "obstacles"
    kind = BARRIER

    def __init__(self, capacity: int, d_safe: float, *, k0: float = 400.0, k1: float = 40.0,
                 drift: str = "exact", braking: Braking | None = None, d_influence: float = np.inf) -> None:
        if drift not in ("exact", "rigid"):
            raise ConfigError(f"must be exact or rigid, got {drift!r}", key="controller.barrier_drift")
        self.drift = drift
        if capacity < 1:
            raise ConfigError(f"must be >= 1, got {capacity}", key="controller.max_pairs")
        self.rows = int(capacity)
        self.d_safe = float(d_safe)
        self.k0 = _positive("controller.barrier_k0", k0)
        self.k1 = _positive("controller.barrier_k1", k1)
        # braking-aware rows (qpctl.constraints.braking); the pairs beyond d_influence [m] (found within
        # the braking cutoff) then get only the braking bound
        self.braking, self.d_influence = braking, float(d_influence)
        self._empty: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # (C, lower, upper) of no pair

    def compute(self, state: TickState, terms: LawTerms) -> Inequality:
        n = state.n
        if self._empty is None or self._empty[0].shape[1] != n:
            self._empty = (np.zeros((self.rows, n)), np.full(self.rows, -np.inf), np.full(self.rows, np.inf))
        C, lower, upper = (a.copy() for a in self._empty)
        pairs = state.pairs
        k = len(pairs)
        if k == 0:
            return Inequality(C, lower, upper)
        order = np.argsort(pairs.distance)[: self.rows]
        nrm = pairs.normal[order]  # (r, 3)
        Jp = state.pair_jac[order]  # (r, 3, n)
        rows = np.einsum("ri,rin->rn", nrm, Jp)
        h = pairs.distance[order] - self.d_safe
        nvo = np.einsum("ri,ri->r", nrm, pairs.v_obstacle[order])
        hdot = rows @ state.v - nvo
        if self.drift == "exact":
            drift = state.barrier_drift()[order]
        else:
            drift = np.einsum("ri,ri->r", nrm, state.pair_drift[order] - pairs.a_obstacle[order])
        rhs = -self.k1 * hdot - self.k0 * h - drift
        if self.braking is not None:
            d = pairs.distance[order]
            rhs = np.where(d < self.d_influence, rhs, -np.inf)
            for i in range(order.size):
                rhs[i] = max(rhs[i], self.braking.barrier_lower(rows[i], float(d[i]), self.d_safe, float(nvo[i]),
                                                                float(drift[i]), state.v, state.M, state.N))
        r = order.size
        C[:r] = rows
        lower[:r] = rhs
        return Inequality(C, lower, upper, dropped=max(k - self.rows, 0))


class SelfCollisionBarrier(Constraint):
    """ḧ + k₁ḣ + k₀(h − d_s) ≥ 0 for each of ``pairs`` (capsule indices) nearer than ``cutoff`` [m],
    one row per pair; h the distance between the two capsules [m], d_s [m]. The cutoff is the
    controller's influence distance, at most d_s + REACH: a pair farther apart has no row (its rows
    would bind only at approach speeds above k₀/k₁·REACH = 1 m/s with the default gains) and costs
    the tick only its distance. Inside d_s the push apart asks no more than :func:`reach_cap` of what
    the acceleration limits of ``joints`` (the controller's :class:`JointLimit`; None: no cap) give:
    with the arm nearly straight a pair's distance hardly moves with the joints, and the full
    k₀(d_s − h) asked one joint for more than its limit, tick after tick. (Not the torque window: a
    row beyond the rate limit's reach is issue 22's, and capping it there measured worse behind the
    verified backup.)"""

    name = "self_collision"
    kind = SELF_COLLISION  # not BARRIER: the fallbacks keep the obstacle rows only (as before kinds existed)
    REACH = 0.1  # [m] beyond d_s

    def __init__(self, pairs: Sequence[tuple[int, int]], d_safe: float, *, k0: float = 400.0,
                 k1: float = 40.0, joints: JointLimit | None = None) -> None:
        if not pairs:
            raise ConfigError("needs at least one pair of links", key="controller.self_collision_pairs")
        if not (np.isfinite(d_safe) and d_safe >= 0):
            raise ConfigError(f"must be a distance >= 0, got {d_safe}", key="controller.self_d_safe")
        self.pairs = tuple((int(i), int(j)) for i, j in pairs)
        self.rows = len(self.pairs)
        self.d_safe = float(d_safe)
        self.k0 = _positive("controller.barrier_k0", k0)
        self.k1 = _positive("controller.barrier_k1", k1)
        self.cutoff = np.inf  # set by the controller: its influence distance
        self.joints = joints

    def compute(self, state: TickState, terms: LawTerms) -> Inequality:
        sp = state.self_pairs
        if sp is None or sp.distance.shape[0] != self.rows:
            raise ValueError("this TickState was built without this constraint's self-collision pairs")
        near = sp.distance < self.cutoff
        C = np.where(near[:, None], sp.row, 0.0)
        lower = np.where(near, -self.k1 * sp.hdot - self.k0 * (sp.distance - self.d_safe) - sp.drift, -np.inf)
        inside = np.flatnonzero(near & (sp.distance < self.d_safe))
        if inside.size and self.joints is not None:
            lower[inside] = np.minimum(lower[inside], reach_cap(state, C[inside], qdd_max=self.joints.qdd_max))
        return Inequality(C, lower, np.full(self.rows, np.inf))


def reach_cap(state: TickState, rows: np.ndarray, *, torque: TorqueLimit | None = None,
              qdd_max: np.ndarray | None = None) -> np.ndarray:
    """What each of ``rows`` (k, n) inside its margin asks at most of c q̈ this tick (k,):
    ℓ − ρ(ℓ − ℓ₋), [ℓ₋, ℓ] its range over ``torque``'s window at state.t (q̈ = M⁻¹(τ − N)) and within
    ±``qdd_max`` [rad/s²], each range alone (None: not that one; ρ = REACH_SHARE); inf where neither
    bounds it. The compiled tick's :func:`qpctl.kernels.drives.box_cap` (the self rows: ``qdd_max``
    alone) and :func:`~qpctl.kernels.drives.row_range` (the field's rigid rows: ``torque`` alone)."""
    least, most = np.full(rows.shape[0], -np.inf), np.full(rows.shape[0], np.inf)
    if torque is not None:
        lo, hi = torque.window(state.t)
        y = np.linalg.solve(state.M, rows.T)  # (n, k): M⁻¹cᵀ per row
        with np.errstate(invalid="ignore"):
            a = np.where(y != 0.0, y * (lo - state.N)[:, None], 0.0)
            b = np.where(y != 0.0, y * (hi - state.N)[:, None], 0.0)
        least, most = np.minimum(a, b).sum(axis=0), np.maximum(a, b).sum(axis=0)
    if qdd_max is not None:
        with np.errstate(invalid="ignore"):  # 0·∞ where a joint has no acceleration limit: not used
            s = np.where(rows != 0.0, np.abs(rows) * qdd_max, 0.0).sum(axis=1)
        least, most = np.maximum(least, -s), np.minimum(most, s)
    with np.errstate(invalid="ignore"):
        cap = most - REACH_SHARE * (most - least)
    return np.where(np.isnan(cap), np.inf, cap)
