"""The terms shared by the paper's law, Hsu's law and the QP (paper eq. 7, 12, 18, 19).

Notation (DESIGN.md §2): e = x_d − x, ė = ẋ_d − ẋ, and the desired task acceleration less drift

    a = ẍ_d + K_v ė + K_p e − J̇ q̇                                         (eq. 7)

The obstacle "sensor" gives each link point within the influence distance d_i a desired velocity
u = v_ref α(d) n, α ramping from 0 at d_i to 1 at the safety distance d_s; the joint velocity that
realises them in the least-squares sense is g = (AᵀA + λ²I)⁻¹Aᵀu, A the stacked point Jacobians.

    e_N = (I − J_b⁺ J)(g − q̇),   J_b⁺ weighted by W_b = Σ_i J_iᵀ J_i        (eq. 12, 19; Ryu)

and the null-space acceleration

    q̈₀ = −M⁻¹N + K_N e_N   (paper, weighted)       q̈₀ = K_N e_N   (Hsu, unweighted)

The law is q̈ = J_W⁺(a + J̇ e_N) + (I − J_W⁺J) q̈₀, τ = M q̈ + N (eq. 18–19), with the J̇ e_N term a
switch (``jdot_en``, off by default: see the README for the measurement that chose it).
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
    if not np.any(active) or gains.v_ref == 0:
        return np.zeros(state.n)
    d = pairs.distance[active]
    alpha = np.clip((gains.d_influence - d) / (gains.d_influence - gains.d_safe), 0.0, 1.0)
    u = (gains.v_ref * alpha)[:, None] * pairs.normal[active]  # (k, 3)
    # Each pair's rows weigh α (rows and targets scaled by √α): a pair entering the influence
    # distance (α = 0) then changes g continuously instead of adding a full-weight "stay still" row.
    w = np.sqrt(alpha)[:, None, None]
    A = (w * state.pair_jac[active]).reshape(-1, state.n)
    b = (w[:, :, 0] * u).reshape(-1)
    H = A.T @ A + gains.g_damping**2 * np.eye(state.n)
    return np.linalg.solve(H, A.T @ b)


def ryu_weight(state: TickState) -> np.ndarray:
    """W_b = Σ_i J_iᵀ J_i over the links' mid-point Jacobians, plus 1e-9·tr I to keep it invertible."""
    Jl = state.link_jac.reshape(-1, state.n)
    W = Jl.T @ Jl
    return W + 1e-9 * max(float(np.trace(W)), 1.0) * np.eye(state.n)


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
