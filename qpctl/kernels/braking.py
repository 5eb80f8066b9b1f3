"""The braking-aware rows of the tick (issue 22, item 1): each obstacle-barrier row and each joint
bound also keeps the next state able to stop (:mod:`qpctl.kernels.stopping`).

**Obstacle rows.** For a pair with row c = nᵀJ_p (ḣ = c q̇ − nᵀv_obs, ḧ = c q̈ + drift) the closing
acceleration is a = −ḧ and the arm's closing speed v = −c q̇; the obstacle's own is v_o = max(0, nᵀv_obs).
The brake's means at the point along n are a share of what the drives give it there:

    A = share · min(Σₖ |yₖ| (τ_max,k − |Nₖ|)⁺, Σₖ |cₖ| q̈_max,k),   J = share · Σₖ |yₖ| τ̇_max,k,   y = M⁻¹cᵀ

(the deceleration the torque left over the bias forces gives, or the joint-acceleration limits allow;
the jerk the torque-rate limits give: issue 16's point–direction means, :mod:`qpctl.barrier_design`).
With a* the largest safe closing acceleration (:func:`~qpctl.kernels.stopping.max_closing_acceleration`,
searched within ± the best case A/share) the row becomes c q̈ ≥ max(its barrier bound, −a* − drift);
where a* is the best case itself the braking bound is slack and the row is left as it was (bit for bit).

**Joint bounds.** Joint i closing on q_max at q̇ᵢ with q̈ᵢ (and on q_min at −q̇ᵢ with −q̈ᵢ), with
A = share · min(q̈_max,i, (τ_max,i − |Nᵢ|)⁺/Mᵢᵢ) and J = share · τ̇_max,i/Mᵢᵢ: no more than the joint's
best case (|M⁻¹|ᵢᵢ ≥ 1/Mᵢᵢ), so these are conservative; Del Prete's viability bound (RA-L 2018) with
the rate limit added. The bound tightens q̈ᵢ's upper (lower) bound to a* (−a*) where a* is below the
best case.

:class:`qpctl.constraints.braking.Braking` computes the same in numpy (the Python path; the tests hold
one against the other to 1e-12).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from qpctl.kernels.codes import FP_BRK_DT, FP_BRK_MARGIN, FP_BRK_SHARE
from qpctl.kernels.small import chol_solve
from qpctl.kernels.stopping import max_closing_acceleration


@njit(cache=True)
def barrier_bound(ws, c: np.ndarray, d: float, ds: float, nvo: float, drift: float,  # type: ignore[no-untyped-def]
                  y: np.ndarray) -> float:
    """The braking lower bound on c q̈ for one pair (−inf where it is slack): c its row (its first n
    entries are read: the QP's row may carry slack columns after them), d its distance [m], ds d_safe
    [m], nvo = nᵀv_obs [m/s], drift ḧ at q̈ = 0 [m/s²]; y (n,) scratch."""
    n = ws.v.shape[0]
    v = 0.0
    for k in range(n):
        y[k] = c[k]
        v -= c[k] * ws.v[k]
    chol_solve(ws.Lm, y)
    a_tau, a_qdd, jerk = 0.0, 0.0, 0.0
    for k in range(n):
        ay = abs(y[k])
        a_tau += ay * max(ws.tau_max[k] - abs(ws.N[k]), 0.0)
        if ws.qdd_max[k] < np.inf:
            a_qdd += abs(c[k]) * ws.qdd_max[k]
        elif c[k] != 0.0:
            a_qdd = np.inf
        if ay != 0.0:
            jerk += ay * ws.tau_rate[k]
    best = min(a_tau, a_qdd)
    if not (best > 0.0 and best < np.inf):
        return -np.inf
    share = ws.fpar[FP_BRK_SHARE]
    a_star = max_closing_acceleration(d - ds, v, max(nvo, 0.0), ws.fpar[FP_BRK_DT], share * best, share * jerk,
                                      ws.fpar[FP_BRK_MARGIN], best)
    if a_star >= best:
        return -np.inf
    return -a_star - drift


@njit(cache=True)
def joint_bound(ws, i: int, h: float, v: float) -> float:  # type: ignore[no-untyped-def]
    """The largest safe closing acceleration [rad/s²] of joint i at h [rad] from its limit, closing at
    v [rad/s] (inf where the braking bound is slack)."""
    if not h < np.inf:
        return np.inf
    m = ws.M[i, i]
    best = min(ws.qdd_max[i], max(ws.tau_max[i] - abs(ws.N[i]), 0.0) / m)
    if not (best > 0.0 and best < np.inf):
        return np.inf
    share = ws.fpar[FP_BRK_SHARE]
    a_star = max_closing_acceleration(h, v, 0.0, ws.fpar[FP_BRK_DT], share * best, share * ws.tau_rate[i] / m,
                                      0.0, best)
    return np.inf if a_star >= best else a_star


@njit(cache=True)
def joint_bounds_braking(ws, i: int, low: float, high: float) -> tuple[float, float]:  # type: ignore[no-untyped-def]
    """Joint i's bounds on q̈ [rad/s²] tightened by the braking bound on either side (module docstring)."""
    q, v = ws.q[i], ws.v[i]
    up = joint_bound(ws, i, ws.q_max[i] - q, v)
    high = min(high, up)
    down = joint_bound(ws, i, q - ws.q_min[i], -v)
    low = max(low, -down)
    return low, high
