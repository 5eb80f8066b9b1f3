"""The terms shared by the paper's law, Hsu's law and the QP (paper eq. 6, 7, 12, 18, 19).

The reading adopted (DESIGN.md §2; the OCR's ``J^1`` is J⁺). n joints, m task coordinates;
e = x_d − x, ė = ẋ_d − ẋ.

    a    = ẍ_d + K_v ė + K_p e − J̇ q̇                                          (7), (9)
    J_W⁺ = W⁻¹Jᵀ(J W⁻¹ Jᵀ)⁻¹, damped by SVD near a singularity                   (5), (6)
    u_k  = v_ref α(d_k) n_k,  α = clip((d_i − d_k)/(d_i − d_s), 0, 1)          reference velocity of
                                                                               link point k ("sensor")
    g    = argmin Σ_k α_k ‖J_k q̇ − u_k‖² + λ²‖q̇‖²  = (AᵀA + λ²I)⁻¹Aᵀb          A, b: rows √α_k J_k, √α_k u_k
    e_N  = (I − J_b⁺ J)(g − q̇),  J_b⁺ weighted by W_b = Σ_i J_iᵀ J_i            (12), (19); Ryu
    q̈₀   = −M⁻¹N + K_N e_N  (paper, W = MᵀM)     q̈₀ = K_N e_N  (Hsu, W = W_b = I)     (18), (19)
    q̈    = J_W⁺ a + (I − J_W⁺ J) q̈₀,   τ = M q̈ + N                             (7), (19)

Why these choices (measured by ``python -m reproduction``; README "Paper reproduction"):

* **Eq. (11) holds exactly.** J J_W⁺ = I and J(I − J_W⁺J) = 0, so J q̈ = a and, with ẍ = J q̈ + J̇ q̇,
  ë + K_v ė + K_p e = 0 whatever q̈₀ is: e → 0 exponentially for any Hurwitz s² + k_v s + k_p.
* **The J⁺J̇e_N term of eq. (18) is off by default** (``LawGains.jdot_en``). Since J e_N ≡ 0,
  J ė_N = −J̇ e_N: eq. (17) gets the term by differentiating that identity. Added to the command it
  puts J̇ e_N into the task, ë + K_v ė + K_p e = −J̇ e_N, which breaks eq. (11) while e_N ≠ 0; and it
  cannot speed up e_N's decay, because the null-space projector annihilates it ((I − J⁺J)J⁺ = 0 in
  Hsu's law; in the paper's it only moves the range part of ė_N from J_b⁺ to J_W⁺). Measured on the
  paper scenario: the peak tracking error grows about a hundredfold, the final ‖e_N‖ and the start
  torque are unchanged.
* **The sign of −M⁻¹N** is the one that lowers torque: with W = MᵀM, τ = M q̈ + N is then the
  least-‖τ‖ torque that realises J q̈ = a (Kazerounian–Nedungadi). The price, which no sign or
  weighting can avoid with one degree of redundancy: the torque term and K_N e_N act on the same
  null space, so the paper law's e_N does not vanish under gravity (eq. 19's "e_N → 0" holds for
  Hsu's law, not for this one) and its torque moves fast in the first ~0.3 s while K_N reins in the
  self-motion the torque term starts.
* **Ryu's weighting is what makes g work.** P_b = I − J_b⁺J is the W_b-orthogonal projector onto the
  null space; were W_b the same matrix as g's normal equations, P_b g would be exactly the
  null-space velocity that best realises the links' reference velocities. The unweighted projection
  of the same g (Hsu) is not: it can point a link *into* the obstacle that g pushes it away from.
  W_b over the links' mid-points (the paper's Σ_{i=1}^n, fixed) approximates that; using the sensor's
  own points instead measured worse, so the mid-points stay.
* **Each pair's least-squares rows weigh α** (rows and target scaled by √α), so a pair entering the
  influence distance changes g continuously; with equal weights a pair at α = 0 added a "hold
  still" row at full weight and g jumped. The onset is continuous but stiff (dg/dα ∝ 1/λ²), which
  still shows as single-tick torque-rate spikes when a pair enters the sensor's reach.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from qpctl.errors import ConfigError
from qpctl.linalg import weighted_pinv
from qpctl.paths import Reference
from qpctl.state import TickState


@dataclass(frozen=True)
class LawGains:
    """Gains and obstacle-sensor settings of the closed-form laws (and of the QP's targets).

    kp [1/s²], kv [1/s]: task PD gains (s² + kv s + kp Hurwitz: both > 0).
    kn [1/s]: null-space velocity gain.
    v_ref [m/s]: magnitude of the links' obstacle-avoiding reference velocity.
    obstacle_v_ref [m/s]: per-obstacle override of v_ref (by obstacle index; NaN keeps v_ref);
    filled by the controller from :attr:`Obstacle.v_ref`.
    d_influence [m], d_safe [m]: the sensor's reach and the safety distance (0 ≤ d_safe < d_influence).
    g_damping [m]: damping of the least squares that turns link velocities into g.
    pinv_eps: σ_min/σ_max below which a pseudo-inverse is damped and the tick reported singular.
    jdot_en: add the paper's J⁺J̇e_N term (eq. 18).
    """

    kp: float = 100.0
    kv: float = 20.0
    kn: float = 10.0
    v_ref: float = 0.5
    d_influence: float = 0.3
    d_safe: float = 0.05
    g_damping: float = 0.05
    pinv_eps: float = 1e-3
    jdot_en: bool = False
    obstacle_v_ref: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        for name in ("kp", "kv"):
            val = getattr(self, name)
            if not (np.isfinite(val) and val > 0):
                raise ConfigError(f"must be a positive number (s² + kv s + kp Hurwitz), got {val}",
                                  key=f"controller.{name}")
        for name in ("kn", "v_ref", "d_safe", "g_damping"):
            val = getattr(self, name)
            if not (np.isfinite(val) and val >= 0):
                raise ConfigError(f"must be a number >= 0, got {val}", key=f"controller.{name}")
        if not (np.isfinite(self.d_influence) and self.d_influence > self.d_safe):
            raise ConfigError(f"must exceed d_safe = {self.d_safe}, got {self.d_influence}",
                              key="controller.d_influence")
        if not (0 < self.pinv_eps < 1):
            raise ConfigError(f"must be in (0, 1), got {self.pinv_eps}", key="controller.pinv_eps")


@dataclass(frozen=True)
class LawTerms:
    """What a law needs at one tick (n joints, m task coordinates)."""

    ref: Reference
    e: np.ndarray  # (m,) x_d − x [m]
    edot: np.ndarray  # (m,) ẋ_d − ẋ [m/s]
    a: np.ndarray  # (m,) task acceleration target, J̇ e_N included when switched on [m/s²]
    g: np.ndarray  # (n,) obstacle reference joint velocity [rad/s]
    e_null: np.ndarray  # (n,) null-space velocity error [rad/s]
    qdd0: np.ndarray  # (n,) null-space acceleration target [rad/s²]
    singular: bool  # a pseudo-inverse was damped this tick


def reference_velocity(state: TickState, gains: LawGains) -> np.ndarray:
    """g [rad/s]: the joint velocity that best realises u = v_ref α(d) n at every link point within d_i."""
    pairs = state.pairs
    active = pairs.distance < gains.d_influence if len(pairs) else np.zeros(0, bool)
    if not active.any():
        return np.zeros(state.n)
    v_ref: float | np.ndarray = gains.v_ref  # per active pair when obstacles have their own
    if gains.obstacle_v_ref:
        own = np.asarray(gains.obstacle_v_ref)[pairs.obstacle[active]]
        v_ref = np.where(np.isnan(own), gains.v_ref, own)
    if not np.any(v_ref):
        return np.zeros(state.n)
    d = pairs.distance[active]
    alpha = np.clip((gains.d_influence - d) / (gains.d_influence - gains.d_safe), 0.0, 1.0)
    u = (v_ref * alpha)[:, None] * pairs.normal[active]  # (k, 3)
    # Each pair's rows weigh α (rows and targets scaled by √α): a pair entering the influence
    # distance (α = 0) then changes g continuously instead of adding a full-weight "stay still" row.
    w = np.sqrt(alpha)[:, None, None]
    A = (w * state.pair_jac[active]).reshape(-1, state.n)
    b = (w[:, :, 0] * u).reshape(-1)
    H = A.T @ A
    H.flat[:: state.n + 1] += gains.g_damping**2  # + λ² I
    return np.linalg.solve(H, A.T @ b)


def ryu_weight(state: TickState) -> np.ndarray:
    """W_b = Σ_i J_iᵀ J_i over the links' mid-point Jacobians, plus 1e-9·tr I to keep it invertible."""
    Jl = state.link_jac.reshape(-1, state.n)
    W = Jl.T @ Jl
    W.flat[:: state.n + 1] += 1e-9 * max(float(np.trace(W)), 1.0)  # + 1e-9·tr(W)·I
    return W


def law_terms(state: TickState, ref: Reference, gains: LawGains, *, weighted: bool) -> LawTerms:
    """Evaluate a, g, e_N and q̈₀ for the weighted (paper) or unweighted (Hsu) law."""
    n = state.n
    e = ref.x - state.x
    edot = ref.xd - state.xdot
    a = ref.xdd + gains.kv * edot + gains.kp * e - state.drift
    g = reference_velocity(state, gains)
    if weighted:
        Wb = ryu_weight(state)
        Jb = weighted_pinv(state.J, np.linalg.cholesky(Wb), eps=gains.pinv_eps)
    else:
        Jb = weighted_pinv(state.J, None, eps=gains.pinv_eps)
    e_null = (np.eye(n) - Jb.matrix @ state.J) @ (g - state.v)
    if gains.jdot_en:
        a = a + state.jdot() @ e_null
    if weighted:
        qdd0 = -np.linalg.solve(state.M, state.N) + gains.kn * e_null
    else:
        qdd0 = gains.kn * e_null
    return LawTerms(ref, e, edot, a, g, e_null, qdd0, Jb.singular)


def closed_form_acceleration(state: TickState, terms: LawTerms, gains: LawGains, *,
                             weighted: bool) -> tuple[np.ndarray, bool]:
    """q̈ = J_W⁺ a + (I − J_W⁺ J) q̈₀ with W = MᵀM (paper) or W = I (Hsu); returns (q̈, singular)."""
    P = weighted_pinv(state.J, state.M if weighted else None, eps=gains.pinv_eps)
    Jp = P.matrix
    qdd = Jp @ terms.a + terms.qdd0 - Jp @ (state.J @ terms.qdd0)
    return qdd, P.singular or terms.singular
