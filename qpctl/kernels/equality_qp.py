"""Stage 6 of the tick, before DAQP: the hard QP's answer on DAQP's last working set.

The hard QP (the task's rows as equalities, :mod:`~qpctl.kernels.hard_first`) is

    min ½xᵀHx + fᵀx   s.t.   E x = e (the task's m rows),   bl ≤ C x ≤ bu,   bl ≤ x ≤ bu,

H positive definite. DAQP (a dual active-set method) ends each solve with a working set W: the
equalities and the rows and bounds it holds at one side. Given W, the answer is a linear system: the
minimum on Ē x = ē (E and W's rows, each at the bound of its side) is x* = −H⁻¹f + H⁻¹Ēᵀμ with
(Ē H⁻¹ Ēᵀ) μ = ē + Ē H⁻¹ f (two Cholesky factorisations, of H and of the p × p matrix Ē H⁻¹ Ēᵀ,
p = m + |W|). Where x* meets every row and bound outside W — exactly, no tolerance — and each of W's
multipliers has its side's sign (DAQP's convention, Hx + f + Aᵀλ = 0, λ = −μ: λ ≥ 0 at an upper
bound, ≤ 0 at a lower one), x* satisfies the KKT conditions, and the minimum of a strictly convex QP
is unique: it is the QP's answer, the one DAQP would return, and W is its working set.

The controller's QP changes little from one tick to the next, and so does its working set: on the
Panda's packaged scenes DAQP's working set is the same as the tick before on all but 7 of 6,001 ticks
(`panda_spheres`: empty on 3,722, joint 6's upper q̈ bound — its position and speed limits — on 1,711, an
obstacle's barrier row on 422).
:func:`working_set` reads W from DAQP's states (the simple bounds' in ``sense_c``, where they stay; the
rows' by layout index in ``sense_full``, unpacked after each solve), :func:`active_set_minimum`
computes x*, checks it and writes the multipliers by layout index; the hard-first tick then skips
DAQP's pack, update, solve and unpack (2.2 µs in a compiled loop on the Panda among 10 spheres, this
minimum and its checks about 1 µs) and checks the answer as it checks DAQP's
(:func:`~qpctl.kernels.hard_first.qp_tick_native_hard_first_from`). DAQP's working set is left as it
is — it is the answer's —, so the next solve warm-starts as it would have. Where x* misses a row or
bound, a multiplier has the wrong sign (W changes this tick), a side's bound is not finite, or a
factorisation fails (W's rows dependent), it returns False and DAQP solves the QP from W.

**Slack columns.** A depth map's rows give each link a slack column σ_l ≥ 0 (ℓ₁ cost 1e7, H 1e-9:
``perception.soft_weight``, docs/perception.md). Held at σ = 0 — the common tick, no leaf pushed
through — each is fixed at its bound and eliminated: the minimum is over q̈ on H's leading n × n block,
and each σ's multiplier comes from its own row of Hx + f + Aᵀλ = 0 (it must push from its side, as the
others'). A σ that DAQP left free declines (a σ near 10⁻¹⁶·f/H in a whole-H factorisation is
cancellation, not an answer). On the Panda among the ``panda_spheres`` spheres seen as a point cloud,
1,330 of 1,356 hard ticks (every 4th of 6 s) take it, DAQP's cold solve of the 14-variable QP agreeing
to 3e-13; the tick with the field 23.96 → 18.46 µs median (DAQP's solve 7.4 → 2.4 µs).

References (``tests/test_equality_qp.py``): DAQP's own cold solve of the same QP — x, λ and its
working set — where this path is taken (with and without slack columns), numpy's KKT residual, a
row or bound cut through the minimum, a multiplier of the wrong sign (a σ that should give way among
them) declining it.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from qpctl.kernels.daqp_pack import ACTIVE, IMMUTABLE, LOWER
from qpctl.kernels.small import chol_solve, chol_solve_cols, cholesky_lead, normal_solve


@njit(cache=True)
def working_set(dq, n_in: int, m: int, w: np.ndarray, low: np.ndarray) -> int:  # type: ignore[no-untyped-def]
    """The equalities and DAQP's working set of inequalities (``dq``: a DaqpPack after a solve) as
    layout indices into the bounds' arrays, ascending, in ``w`` (the m task rows first, then W) with
    ``low`` True where a constraint is held at its lower bound. Returns p = m + |W|, or −1 where more
    than ``w.shape[0]`` (= nv: more cannot be independent) would be held."""
    sc, sf = dq.sense_c, dq.sense_full
    nv = dq.rows.shape[1]
    cap = w.shape[0]
    if m > cap:
        return -1
    for r in range(m):
        w[r], low[r] = nv + n_in + r, False
    p = m
    for j in range(nv):  # the simple bounds: their states stay in DAQP's array (daqp_pack.pack)
        s = sc[j]
        if s & ACTIVE and not s & IMMUTABLE:
            if p == cap:
                return -1
            w[p], low[p] = j, (s & LOWER) != 0
            p += 1
    for r in range(n_in):  # the inequality rows, by layout index (daqp_pack.unpack)
        s = sf[nv + r]
        if s & ACTIVE and not s & IMMUTABLE:
            if p == cap:
                return -1
            w[p], low[p] = nv + r, (s & LOWER) != 0
            p += 1
    return p


@njit(cache=True)
def active_set_minimum(H: np.ndarray, f: np.ndarray, rows: np.ndarray, bu: np.ndarray, bl: np.ndarray, n_in: int,
                       m: int, w: np.ndarray, low: np.ndarray, p: int, x: np.ndarray, lam: np.ndarray, L: np.ndarray,
                       Y: np.ndarray, V: np.ndarray, G: np.ndarray, z: np.ndarray, cx: np.ndarray) -> bool:
    """The minimum of the QP (H, f; ``rows`` with bounds ``bu``, ``bl`` in DAQP's convention: the nv simple
    bounds first, then one per row) on the p constraints ``w[:p]`` held as equalities (layout indices,
    ascending after the m task rows ``n_in`` … ``n_in + m`` first; ``low``: held at the lower bound,
    else the upper), where it meets every other row and bound and each held inequality's multiplier
    has its side's sign: then True, the answer in ``x`` (nv,) and the multipliers by layout index in
    ``lam`` (DAQP's sign: Hx + f + Aᵀλ = 0; 0 outside ``w``), and each row's C x in ``cx`` (n_in,) as
    :func:`~qpctl.kernels.finish.violation` writes it (0 for a row without a bound), so that the tick's
    check of the answer reads them instead of computing them again. Else False, ``x`` and ``lam``
    untouched; ``w`` and ``low`` may be reordered either way.

    The variables after the first nf = L's order (the constraints' slack columns σ ≥ 0, H's entries
    there 1e-9 against an ℓ₁ cost of 1e7: a factorisation of the whole H would cancel −H⁻¹f ≈ −10¹⁶
    against its correction) must each be held at a bound: they are fixed there and eliminated — the
    minimum is over the first nf on the rest, and each fixed variable's multiplier comes from its row of
    Hx + f + Aᵀλ = 0 and must have its side's sign (else False: DAQP solves). Scratch, each at least:
    L (nf, nf), Y (nv, p), V (p, p), G (p, p + 2), z (nv,)."""
    nv = x.shape[0]
    nf = L.shape[0]
    if p < 0 or p > nv or not cholesky_lead(H, L, nf):
        return False
    # the fixed variables out of w (their values into z[nf:]): the held constraints kept in order
    q = m
    for c in range(m, p):
        j = w[c]
        if nf <= j < nv:
            b = bl[j] if low[c] else bu[j]
            if not np.isfinite(b):
                return False
            z[j] = b
        else:
            w[q], low[q] = j, low[c]
            q += 1
    if p - q != nv - nf or q > nf:  # a slack column not held, or more held than can be independent
        return False
    p = q
    for i in range(nf):  # z = −H⁻¹(f + H_F x_F) on the first nf
        s = -f[i]
        for j in range(nf, nv):
            s -= H[i, j] * z[j]
        z[i] = s
    chol_solve(L, z)  # (L's order: the first nf entries)
    for c in range(p):
        j = w[c]
        for i in range(nf):
            Y[i, c] = rows[j - nv, i] if j >= nv else (1.0 if i == j else 0.0)
    chol_solve_cols(L, Y, p)  # Y = H⁻¹Ēᵀ
    for c in range(p):
        j = w[c]
        b = bl[j] if low[c] else bu[j]
        if not np.isfinite(b):
            return False
        s = b  # ē − Ē z (row products written out: through a helper the checks below cost 0.9 µs more)
        if j < nv:
            s -= z[j]
        else:
            for i in range(nv):
                s -= rows[j - nv, i] * z[i]
        G[c, p + 1] = s
        for c2 in range(c + 1):  # Ē H⁻¹ Ēᵀ (no view of Y's columns: each would cost its reference count)
            if j < nv:
                s = Y[j, c2]
            else:
                s = 0.0
                for i in range(nf):
                    s += rows[j - nv, i] * Y[i, c2]
            G[c, c2] = G[c2, c] = s
    if not cholesky_lead(G, V, p):
        return False
    normal_solve(V, G, p)  # μ = (Ē H⁻¹ Ēᵀ)⁻¹ (ē − Ē z), in G's column p + 1
    for c in range(m, p):  # each held inequality pushes from its own side: λ = −μ ≥ 0 at an upper bound
        mu = G[c, p + 1]
        if not (mu >= 0.0 if low[c] else mu <= 0.0):
            return False
    for i in range(nf):
        s = z[i]
        for c in range(p):
            s += Y[i, c] * G[c, p + 1]
        z[i] = s
    # each fixed variable's multiplier: λ_j = −(H_j x + f_j + Σ_c rows_cj λ_c), λ_c = −μ_c, at its side
    for j in range(nf, nv):
        s = f[j]
        for i in range(nv):
            s += H[j, i] * z[i]
        for c in range(p):
            if w[c] >= nv:
                s -= rows[w[c] - nv, j] * G[c, p + 1]
        # its side: at bl, or at bu (z[j] is one of them exactly); both the same: an equality, any sign
        if bl[j] != bu[j] and not (-s <= 0.0 if z[j] == bl[j] else -s >= 0.0):
            return False
        Y[j, 0] = -s  # (Y's rows past nf are not used above)
    c = m  # the held inequalities, ascending: skipped by the checks below (they hold to rounding)
    for i in range(nf):  # every other simple bound and inequality row met exactly (NaN fails too)
        if c < p and w[c] == i:
            c += 1
        elif not (bl[i] <= z[i] <= bu[i]):
            return False
    for r in range(n_in):  # C x into cx as qp_finish's check computes it (it then reads them: cx_known)
        j = nv + r
        lo, hi = bl[j], bu[j]
        s = 0.0
        if lo > -np.inf or hi < np.inf:
            for i in range(nv):
                s += rows[r, i] * z[i]
        cx[r] = s
        if c < p and w[c] == j:
            c += 1
        elif not (lo <= s <= hi):
            return False
    for i in range(nv):
        x[i] = z[i]
    lam[:] = 0.0
    for c in range(p):
        lam[w[c]] = -G[c, p + 1]
    for j in range(nf, nv):
        lam[j] = Y[j, 0]
    return True
