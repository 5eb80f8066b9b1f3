"""Stage 5 of the tick, the QP's rows: its cost and rows written in place in DAQP's layout.

x = [q̈ (n), s⁺ (k), s⁻ (k)]; the bounds on x (nv), then the inequality rows (n_in), then the equality
rows (m): rows = [C; A], bu = [ub; u; b], bl = [lb; l; b] (:class:`qpctl.tick.QPBuffers`, which sets
the slack columns and the inactive rows' infinite bounds once). Each constraint family writes its
block: the task (EndEffectorTask), the torque window (TorqueLimit), the joint bounds (JointLimit),
the obstacle barrier (ObstacleBarrier), the self-collision rows (SelfCollisionBarrier) and the
depth map's field rows (FieldBarrier, :mod:`qpctl.kernels.field_rows`); a new
family is a function here (or a module of its own) and a call in :func:`qp_build`, its first row in
``ipar`` (the ``IP_*_ROW0`` codes).

References (``tests/test_kernels.py``): :class:`qpctl.formulation.Formulation` with the tasks and
constraints of :mod:`qpctl.tasks` and :mod:`qpctl.constraints`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from qpctl.kernels.braking import barrier_bound, joint_bounds_braking
from qpctl.kernels.codes import (
    CNT_DROPPED,
    CNT_PAIRS,
    FP_BK0,
    FP_BK1,
    FP_DAMP,
    FP_DAMP_KD,
    FP_DI,
    FP_DS,
    FP_JK0,
    FP_JK1,
    FP_JKV,
    FP_PKD,
    FP_PKP,
    FP_SCUT,
    FP_SDS,
    FP_SK0,
    FP_SK1,
    FP_T,
    FP_WACC,
    FP_WPOST,
    IP_BARRIER_ROW0,
    IP_BRAKING,
    IP_CAPACITY,
    IP_DAMPING,
    IP_DRIFT_RIGID,
    IP_FIELD_ROW0,
    IP_JOINT_LIMITS,
    IP_N_IN,
    IP_POSTURE,
    IP_SELF_ROW0,
    IP_TORQUE_ROW0,
)
from qpctl.kernels.drives import box_cap, torque_window_at
from qpctl.kernels.field_rows import field_rows


@njit(cache=True)
def nearest_first(d: np.ndarray, k: int, order: np.ndarray) -> np.ndarray:
    """``order[:k]`` = the indices of d[:k] by increasing d, ties in index order (numpy's stable
    argsort): an insertion sort in place for the few pairs of a tick, numpy's mergesort beyond 64."""
    if k > 64:
        order[:k] = np.argsort(d[:k], kind="mergesort")
        return order
    for u in range(k):
        val = d[u]
        w = u - 1
        while w >= 0 and d[order[w]] > val:
            order[w + 1] = order[w]
            w -= 1
        order[w + 1] = u
    return order


@njit(cache=True)
def joint_bounds(ws, lo: np.ndarray, hi: np.ndarray) -> None:  # type: ignore[no-untyped-def]
    """JointLimit's bounds on q̈ [rad/s²]: ḧ + k₁ḣ + k₀h ≥ 0 on the positions, ḣ + k_v h ≥ 0 on the
    speeds; ∞ − ∞ (NaN) counts as no bound; braking-aware, each tightened so that the next state can
    still stop before the limit (IP_BRAKING, :mod:`qpctl.kernels.braking`); crossed bounds both become
    their mean. Then within
    ±q̈_max, the drive's acceleration limit; where the position or speed barrier asks for more than
    that, both bounds become the limit on that side (the most the drive may do)."""
    k0, k1, kv = ws.fpar[FP_JK0], ws.fpar[FP_JK1], ws.fpar[FP_JKV]
    braking = ws.ipar[IP_BRAKING] != 0
    for i in range(lo.shape[0]):
        q, v = ws.q[i], ws.v[i]
        low = max(-k1 * v - k0 * (q - ws.q_min[i]), -kv * (ws.v_max[i] + v))
        high = min(-k1 * v + k0 * (ws.q_max[i] - q), kv * (ws.v_max[i] - v))
        if math.isnan(low):
            low = -np.inf
        if math.isnan(high):
            high = np.inf
        if braking:  # the next state able to stop before the limit (qpctl.kernels.braking)
            low, high = joint_bounds_braking(ws, i, low, high)
        if low > high:
            low = high = 0.5 * (low + high)
        a = ws.qdd_max[i]
        low2, high2 = max(low, -a), min(high, a)
        if low2 > high2:
            low2 = high2 = min(max(0.5 * (low + high), -a), a)
        lo[i], hi[i] = low2, high2


@njit(cache=True)
def qp_build(ws, H: np.ndarray, f: np.ndarray, rows: np.ndarray, bu: np.ndarray,  # type: ignore[no-untyped-def]
             bl: np.ndarray) -> None:
    """The tick's cost and rows, in place (the slack columns, their costs and bounds, and the
    inactive rows' infinite bounds are set once by qpctl.tick and not touched here)."""
    n, m = ws.N.shape[0], ws.a.shape[0]
    nv = H.shape[0]
    n_in = ws.ipar[IP_N_IN]
    M = ws.M
    wacc = ws.fpar[FP_WACC]
    # ½ w‖M(q̈ − q̈₀)‖²: H = w MᵀM, f = −w MᵀM q̈₀ (AccelerationTask)
    for i in range(n):
        for j in range(i + 1):
            s = 0.0
            for k in range(n):
                s += M[k, i] * M[k, j]
            H[i, j] = H[j, i] = wacc * s
    for i in range(n):
        s = 0.0
        for j in range(n):
            s += H[i, j] * ws.qdd0[j]
        f[i] = -s
    if ws.ipar[IP_POSTURE] != 0:  # ½ w‖q̈ − (K_p(q_ref − q) − K_d q̇)‖² (PostureTask)
        w, pkp, pkd = ws.fpar[FP_WPOST], ws.fpar[FP_PKP], ws.fpar[FP_PKD]
        for i in range(n):
            H[i, i] += w
            f[i] += -w * (pkp * (ws.q_ref[i] - ws.q[i]) - pkd * ws.v[i])
    if ws.ipar[IP_DAMPING] != 0:  # ½ w‖q̈ + K_d q̇‖², w = ρ tr(MᵀM)/n (DampingTask)
        trmm = 0.0
        for i in range(n):
            for k in range(n):
                trmm += M[k, i] * M[k, i]
        w, kd = ws.fpar[FP_DAMP] * trmm / n, ws.fpar[FP_DAMP_KD]
        for i in range(n):
            H[i, i] += w
            f[i] += w * kd * ws.v[i]
    # J q̈ + s = a (EndEffectorTask)
    e0 = nv + n_in
    for r in range(m):
        w = ws.task_w[r]
        for k in range(n):
            rows[n_in + r, k] = w * ws.J[r, k]
        bu[e0 + r] = bl[e0 + r] = w * ws.a[r]
    # −τ_max ≤ M q̈ + N ≤ τ_max and |M q̈ + N − τ_prev| ≤ τ̇_max dt (TorqueLimit)
    t0 = ws.ipar[IP_TORQUE_ROW0]
    if t0 >= 0:
        # (held: a field read in the loop costs atomic reference counts each time)
        N, tau_max, tau_rate, tau_prev = ws.N, ws.tau_max, ws.tau_rate, ws.tau_prev
        dt = ws.fpar[FP_T] - ws.t_prev[0]
        for i in range(n):
            for k in range(n):
                rows[t0 + i, k] = M[i, k]
            lo, hi = torque_window_at(tau_max[i], tau_rate[i], tau_prev[i], dt)
            bl[nv + t0 + i] = lo - N[i]
            bu[nv + t0 + i] = hi - N[i]
    # joint position and speed limits as bounds on q̈ (JointLimit)
    if ws.ipar[IP_JOINT_LIMITS] != 0:
        joint_bounds(ws, bl[:n], bu[:n])
    # ḧ + k₁ḣ + k₀h ≥ 0 for the nearest pairs (ObstacleBarrier)
    b0 = ws.ipar[IP_BARRIER_ROW0]
    if b0 >= 0:
        barrier_rows(ws, rows[b0:b0 + ws.ipar[IP_CAPACITY]], bl[nv + b0:nv + b0 + ws.ipar[IP_CAPACITY]])
    # the same between the arm's own links (SelfCollisionBarrier)
    s0 = ws.ipar[IP_SELF_ROW0]
    if s0 >= 0:
        P = ws.sc_pairs.shape[0]
        self_rows(ws, rows[s0:s0 + P], bl[nv + s0:nv + s0 + P])
    # the depth map's field rows (FieldBarrier; qpctl.kernels.field_rows)
    f0 = ws.ipar[IP_FIELD_ROW0]
    if f0 >= 0:
        R = ws.fd_d.shape[0] + ws.fd_vb.shape[0]  # the pairs' rows, then the soft speed rows
        field_rows(ws, rows[f0:f0 + R], bl[nv + f0:nv + f0 + R])


@njit(cache=True)
def barrier_rows(ws, C: np.ndarray, lower: np.ndarray) -> None:  # type: ignore[no-untyped-def]
    """nᵀJ_p q̈ ≥ −k₁ḣ − k₀h − drift for the nearest pairs, as many as there are rows (the rest
    inactive: zero rows, −∞ bounds); h = d − d_s, ḣ = nᵀ(J_p q̇ − v_obs). Braking-aware (IP_BRAKING),
    each bound is raised to the braking bound where that is higher (:mod:`qpctl.kernels.braking`;
    ws.w1 is its scratch), and the pairs beyond d_i (found within the braking cutoff) have only it."""
    n = ws.N.shape[0]
    k = ws.cnt[CNT_PAIRS]
    cap = C.shape[0]
    order = nearest_first(ws.pr_d, k, ws.order)
    used = min(k, cap)
    ws.cnt[CNT_DROPPED] = k - used
    k0, k1, ds = ws.fpar[FP_BK0], ws.fpar[FP_BK1], ws.fpar[FP_DS]
    rigid = ws.ipar[IP_DRIFT_RIGID] != 0
    braking, di = ws.ipar[IP_BRAKING] != 0, ws.fpar[FP_DI]
    for r in range(used):
        p = order[r]
        j = ws.pr_obs[p]
        nx, ny, nz = ws.pr_n[p, 0], ws.pr_n[p, 1], ws.pr_n[p, 2]
        Jp = ws.pr_jac[p]
        hdot = 0.0
        for c in range(n):
            val = nx * Jp[0, c] + ny * Jp[1, c] + nz * Jp[2, c]
            C[r, c] = val
            hdot += val * ws.v[c]
        vo = ws.ob_v[j]
        hdot -= nx * vo[0] + ny * vo[1] + nz * vo[2]
        if rigid:
            ao = ws.ob_a[j]
            dr = ws.pr_drift[p]
            drift = nx * (dr[0] - ao[0]) + ny * (dr[1] - ao[1]) + nz * (dr[2] - ao[2])
        else:
            drift = ws.pr_bdrift[p]
        if not braking:
            lower[r] = -k1 * hdot - k0 * (ws.pr_d[p] - ds) - drift
            continue
        # braking-aware (qpctl.kernels.braking): the pairs found beyond d_i have only the braking bound
        low = -k1 * hdot - k0 * (ws.pr_d[p] - ds) - drift if ws.pr_d[p] < di else -np.inf
        lower[r] = max(low, barrier_bound(ws, C[r], ws.pr_d[p], ds, nx * vo[0] + ny * vo[1] + nz * vo[2], drift,
                                          ws.w1))
    for r in range(used, cap):
        for c in range(n):
            C[r, c] = 0.0
        lower[r] = -np.inf


@njit(cache=True)
def self_rows(ws, C: np.ndarray, lower: np.ndarray) -> None:  # type: ignore[no-untyped-def]
    """ḧ + k₁ḣ + k₀(h − d_s) ≥ 0 for the self-collision pairs within their cutoff (the rest inactive:
    zero rows, −∞ bounds), as the obstacle barrier's rows (:func:`barrier_rows`). Inside d_s, with
    the joint limits on, the push apart asks at most ℓ − ρ(ℓ − ℓ₋) of the row's range within ±q̈_max
    (:func:`qpctl.kernels.drives.box_cap`): at a nearly straight arm the push asked one joint for more
    than its acceleration limit and the QP stayed infeasible at rest."""
    n = ws.v.shape[0]
    k0, k1, ds, cut = ws.fpar[FP_SK0], ws.fpar[FP_SK1], ws.fpar[FP_SDS], ws.fpar[FP_SCUT]
    box = ws.ipar[IP_JOINT_LIMITS] != 0
    for r in range(C.shape[0]):
        d = ws.sc_d[r]
        if d < cut:
            for c in range(n):
                C[r, c] = ws.sc_row[r, c]
            lower[r] = -k1 * ws.sc_hdot[r] - k0 * (d - ds) - ws.sc_drift[r]
            if box and d < ds:
                cap = box_cap(ws, C[r])
                if cap < lower[r]:  # noqa: PLR1730
                    lower[r] = cap
        else:
            for c in range(n):
                C[r, c] = 0.0
            lower[r] = -np.inf
