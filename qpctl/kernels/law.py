"""Stage 4 of the tick, the law: a, g, e_N, q̈₀ of :mod:`qpctl.law` (paper eq. 7, 12, 18, 19) and
the closed forms, the paper's q̈ = J_M⁺ a + (I − J_M⁺J) q̈₀ or Hsu's, with τ = M q̈ + N.

References (``tests/test_kernels.py``): :func:`qpctl.law.law_terms`, the controllers' numpy
``control`` and :func:`qpctl.linalg.weighted_pinv`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from qpctl.kernels.codes import (
    CNT_PAIRS,
    FLAG_SINGULAR_CF,
    FLAG_SINGULAR_TERMS,
    FP_DI,
    FP_DS,
    FP_GDAMP,
    FP_KN,
    FP_KP,
    FP_KV,
    FP_PINV_EPS,
    FP_VREF,
    IP_JDOT_EN,
)
from qpctl.kernels.finish import torque_of, write_record
from qpctl.kernels.small import (
    add_trace_ridge,
    chol_solve,
    cholesky,
    gram_lower,
    pinv_t,
    pinv_t_apply,
    pinv_t_normal,
    solve_lower,
    solve_lower_t,
)


@njit(cache=True)
def reference_velocity(ws) -> None:  # type: ignore[no-untyped-def]
    """g [rad/s]: the joint velocity that best realises u = v_ref α(d) n at every link point within d_i
    (rows and targets weighed by √α; damped least squares, λ = g_damping). An obstacle whose own
    v_ref is 0 keeps its rows, asking its links to hold still; g = 0 when no pair is within d_i or
    every such pair's v_ref is 0 (qpctl.law.reference_velocity)."""
    n = ws.g.shape[0]
    di, ds = ws.fpar[FP_DI], ws.fpar[FP_DS]
    v_ref = ws.fpar[FP_VREF]
    pr_d, pr_obs, pr_n, pr_jac, ob_vref = ws.pr_d, ws.pr_obs, ws.pr_n, ws.pr_jac, ws.ob_vref
    H, rhs, A = ws.S, ws.g, ws.gA
    rhs[:] = 0.0
    any_moving = False
    k = 0  # the weighted rows √α J_c, packed as A's columns (then H = A Aᵀ)
    for r in range(ws.cnt[CNT_PAIRS]):
        d = pr_d[r]
        if not d < di:
            continue
        own = ob_vref[pr_obs[r]]
        vr = v_ref if math.isnan(own) else own
        any_moving = any_moving or vr != 0.0
        alpha = min(max((di - d) / (di - ds), 0.0), 1.0)
        w = math.sqrt(alpha)
        for c in range(3):
            b = w * ((vr * alpha) * pr_n[r, c])
            for i in range(n):
                ai = w * pr_jac[r, c, i]
                A[i, k] = ai
                rhs[i] += ai * b
            k += 1
    if not any_moving:
        rhs[:] = 0.0
        return
    gram_lower(A, k, H)
    lam2 = ws.fpar[FP_GDAMP] ** 2
    for i in range(n):
        H[i, i] += lam2
    if not cholesky(H, ws.Lb):  # λ = 0 and too few rows: regularise as W_b is
        add_trace_ridge(H)
        cholesky(H, ws.Lb)
    chol_solve(ws.Lb, rhs)


@njit(cache=True)
def _jacobian_t(ws) -> np.ndarray:  # type: ignore[no-untyped-def]
    """The task Jacobian's transpose into the scratch ``ws.Bt`` (n, m), returned."""
    Bt = ws.Bt
    for i in range(Bt.shape[0]):
        for r in range(Bt.shape[1]):
            Bt[i, r] = ws.J[r, i]
    return Bt


@njit(cache=True)
def _weighted_pinv(ws, L: np.ndarray, out: np.ndarray, mode: int) -> bool:  # type: ignore[no-untyped-def]
    """out (n, m) = J_W⁺ of the task Jacobian: mode 0 unweighted, 2 with W = MᵀM (L is M's Cholesky
    factor): the closed forms' J_M⁺ and J⁺. Returns whether the damping was used."""
    Bt = _jacobian_t(ws)
    if mode == 2:
        chol_solve(L, Bt)  # J̃ᵀ = M⁻¹ Jᵀ
    singular, _ratio = pinv_t_normal(Bt, ws.fpar[FP_PINV_EPS], ws.Vm, out, ws.Gm)
    if mode == 2:
        chol_solve(L, out)  # M⁻¹ J̃⁺
    return singular


@njit(cache=True)
def _null_error(ws, mode: int) -> bool:  # type: ignore[no-untyped-def]
    """e_N = (I − J_b⁺J)(g − q̇) into ``ws.e_null``, J_b⁺ the task Jacobian's pseudo-inverse weighted
    by W_b = L_b L_bᵀ (mode 1) or unweighted (mode 0): where the normal equations are certainly
    undamped, J_b⁺ (J y) as one right-hand side, L_b⁻ᵀ B (BᵀB)⁻¹ J y with B = L_b⁻¹ Jᵀ
    (:func:`~qpctl.kernels.small.pinv_t_apply`), without forming J_b⁺; else J_b⁺ itself, damped
    (:func:`_weighted_pinv`'s). Returns whether the damping was used."""
    Bt = _jacobian_t(ws)
    n, m = Bt.shape
    if mode == 1:
        solve_lower(ws.Lb, Bt)  # B = J̃ᵀ = L⁻¹ Jᵀ
    gv, Jgv, z = ws.w1, ws.w3, ws.e_null
    for i in range(n):
        gv[i] = ws.g[i] - ws.v[i]
    for r in range(m):
        s = 0.0
        for i in range(n):
            s += ws.J[r, i] * gv[i]
        Jgv[r] = s
    singular = False
    if pinv_t_apply(Bt, ws.fpar[FP_PINV_EPS], ws.Vm, ws.Gm, Jgv, z):
        if mode == 1:
            solve_lower_t(ws.Lb, z)  # L⁻ᵀ J̃⁺ J y
    else:  # near the damping threshold: J_b⁺ in full, damped (pinv_t), then its product
        singular, _ratio = pinv_t(Bt, ws.fpar[FP_PINV_EPS], ws.Vm, ws.Jb)
        if mode == 1:
            solve_lower_t(ws.Lb, ws.Jb)
        for i in range(n):
            s = 0.0
            for r in range(m):
                s += ws.Jb[i, r] * Jgv[r]
            z[i] = s
    for i in range(n):
        z[i] = gv[i] - z[i]
    return singular


@njit(cache=True)
def law_terms(ws, weighted: bool) -> bool:  # type: ignore[no-untyped-def]
    """a, g, e_N, q̈₀ (qpctl.law) into the workspace; False if M is not positive definite."""
    n, m = ws.g.shape[0], ws.a.shape[0]
    kp, kv, kn = ws.fpar[FP_KP], ws.fpar[FP_KV], ws.fpar[FP_KN]
    for r in range(m):
        ws.e[r] = ws.ref[0, r] - ws.x[r]
        ws.edot[r] = ws.ref[1, r] - ws.xdot[r]
        ws.a[r] = ws.ref[2, r] + kv * ws.edot[r] + kp * ws.e[r] - ws.drift[r]
    if not cholesky(ws.M, ws.Lm):
        return False
    reference_velocity(ws)
    if weighted:  # Ryu's W_b = Σ J_iᵀJ_i over the links' mid-points, + 1e-9·max(tr, 1)·I
        W, A = ws.S, ws.gA
        k = 0
        for i in range(ws.link_jac.shape[0]):
            Jl = ws.link_jac[i]
            for c in range(3):
                for a in range(n):
                    A[a, k] = Jl[c, a]
                k += 1
        gram_lower(A, k, W)
        add_trace_ridge(W)
        cholesky(W, ws.Lb)
    # e_N = (I − J_b⁺J)(g − q̇)
    singular = _null_error(ws, 1 if weighted else 0)
    ws.flags[FLAG_SINGULAR_TERMS] = 1 if singular else 0
    if ws.ipar[IP_JDOT_EN] != 0:
        for r in range(m):
            s = 0.0
            for i in range(n):
                s += ws.Jdot[r, i] * ws.e_null[i]
            ws.a[r] += s
    # q̈₀ = −M⁻¹N + K_N e_N (paper), K_N e_N (Hsu)
    if weighted:
        for i in range(n):
            ws.w2[i] = ws.N[i]
        chol_solve(ws.Lm, ws.w2)
        for i in range(n):
            ws.qdd0[i] = -ws.w2[i] + kn * ws.e_null[i]
    else:
        for i in range(n):
            ws.qdd0[i] = kn * ws.e_null[i]
    return True


@njit(cache=True)
def closed_form(ws, weighted: bool) -> bool:  # type: ignore[no-untyped-def]
    """The paper's law (weighted, W = MᵀM) or Hsu's (unweighted) after :func:`law_terms`:
    q̈ = J_W⁺ a + (I − J_W⁺J) q̈₀, τ = M q̈ + N; returns whether a pseudo-inverse was damped."""
    n, m = ws.qdd.shape[0], ws.a.shape[0]
    singular = _weighted_pinv(ws, ws.Lm, ws.Jp, 2 if weighted else 0)
    Jq0 = ws.w3
    for r in range(m):
        s = 0.0
        for i in range(n):
            s += ws.J[r, i] * ws.qdd0[i]
        Jq0[r] = s
    for i in range(n):
        s1 = 0.0
        s2 = 0.0
        for r in range(m):
            s1 += ws.Jp[i, r] * ws.a[r]
            s2 += ws.Jp[i, r] * Jq0[r]
        ws.qdd[i] = s1 + ws.qdd0[i] - s2
    torque_of(ws)
    singular = singular or ws.flags[FLAG_SINGULAR_TERMS] != 0
    ws.flags[FLAG_SINGULAR_CF] = 1 if singular else 0
    return singular


@njit(cache=True)
def closed_form_tick(ws, weighted: bool) -> int:  # type: ignore[no-untyped-def]
    """Law terms, the closed form and the record: 0, or 1 when M is not positive definite."""
    if not law_terms(ws, weighted):
        return 1
    singular = closed_form(ws, weighted)
    write_record(ws, singular)
    return 0
