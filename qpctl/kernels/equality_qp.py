"""Stage 6 of the tick, before DAQP: the hard QP's answer where no inequality binds.

The hard QP (the task's rows as equalities, :mod:`~qpctl.kernels.hard_first`) is

    min ½xᵀHx + fᵀx   s.t.   E x = e (the task's m rows),   bl ≤ C x ≤ bu,   bl ≤ x ≤ bu,

H positive definite. Its minimum on the equalities alone is x* = −H⁻¹f + H⁻¹Eᵀμ with
(E H⁻¹ Eᵀ) μ = e + E H⁻¹ f (two Cholesky factorisations, of H and of the m × m matrix E H⁻¹ Eᵀ).
Where x* meets every other row and bound — exactly, no tolerance — it is the QP's answer: the KKT
conditions hold with every inequality's multiplier zero, and the minimum of a strictly convex QP is
unique. DAQP (a dual active-set method) would reach the same point: its working set would end with the
equalities alone. :func:`equality_minimum` computes x*, checks it, and gives the multipliers in DAQP's
convention (Hx + f + Aᵀλ = 0: λ = −μ on the equalities, 0 elsewhere); the hard-first tick then skips
DAQP's pack, update, solve and unpack (2.2 µs in a compiled loop on the Panda among 10 spheres, this
minimum and its checks about 1 µs) and checks the answer as it checks DAQP's (:func:`~qpctl.kernels.hard_first.qp_tick_native_hard_first_from`). Where a row or
bound would be violated, or either factorisation fails, it returns False and DAQP solves the QP.

On the Panda's packaged scenes no inequality binds on about 60 % of the ticks (`info["active"]` 0).
It is tried only where the last answer had no inequality binding (:func:`inequality_active`, DAQP's
working set): a tick after one with a binding row goes to DAQP directly, so that the minimum is
computed in vain (about 1 µs) only on the ticks where a row starts to bind. DAQP's working set is then
already the equalities alone, as its own solve would leave it at this answer: the next solve
warm-starts as it would have.

References (``tests/test_equality_qp.py``): DAQP's own solve of the same QP — x and λ — where this
path is taken, and a violated row or bound declining it.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from qpctl.kernels.daqp_pack import ACTIVE, IMMUTABLE
from qpctl.kernels.small import chol_solve, cholesky, normal_solve


@njit(cache=True)
def equality_minimum(H: np.ndarray, f: np.ndarray, rows: np.ndarray, bu: np.ndarray, bl: np.ndarray, n_in: int,
                     m: int, x: np.ndarray, lam: np.ndarray, L: np.ndarray, Y: np.ndarray, V: np.ndarray,
                     G: np.ndarray, z: np.ndarray) -> bool:
    """The minimum of the QP (H, f; ``rows`` with bounds ``bu``, ``bl`` in DAQP's convention: the nv simple
    bounds first, then one per row) on its equality rows ``n_in`` … ``n_in + m`` alone, where it meets
    every inequality row (0 … ``n_in``) and simple bound: then True, the answer in ``x`` (nv,) and the
    multipliers by layout index in ``lam`` (DAQP's sign: Hx + f + Aᵀλ = 0). Else False, ``x`` and
    ``lam`` untouched. Scratch: L (nv, nv), Y (nv, m), V (m, m), G (m, m + 2), z (nv,)."""
    nv = x.shape[0]
    if not cholesky(H, L):
        return False
    for i in range(nv):
        z[i] = -f[i]
    chol_solve(L, z)  # z = −H⁻¹f
    for i in range(nv):
        for r in range(m):
            Y[i, r] = rows[n_in + r, i]
    chol_solve(L, Y)  # Y = H⁻¹Eᵀ
    for p in range(m):
        s = bu[nv + n_in + p]  # e − E z
        for i in range(nv):
            s -= rows[n_in + p, i] * z[i]
        G[p, m + 1] = s
        for q in range(p + 1):
            s = 0.0
            for i in range(nv):
                s += rows[n_in + p, i] * Y[i, q]
            G[p, q] = G[q, p] = s  # E H⁻¹ Eᵀ
    if not cholesky(G, V):
        return False
    normal_solve(V, G, m)  # μ = (E H⁻¹ Eᵀ)⁻¹ (e − E z), in G's column m + 1
    mu = G[:, m + 1]
    for i in range(nv):
        s = z[i]
        for r in range(m):
            s += Y[i, r] * mu[r]
        z[i] = s
    for i in range(nv):  # every simple bound and inequality row met exactly (NaN fails too)
        if not (bl[i] <= z[i] <= bu[i]):
            return False
    for r in range(n_in):
        lo, hi = bl[nv + r], bu[nv + r]
        if lo > -np.inf or hi < np.inf:
            s = 0.0
            for i in range(nv):
                s += rows[r, i] * z[i]
            if not (lo <= s <= hi):
                return False
    for i in range(nv):
        x[i] = z[i]
    lam[:] = 0.0
    for r in range(m):
        lam[nv + n_in + r] = -mu[r]
    return True


@njit(cache=True)
def inequality_active(dq) -> bool:  # type: ignore[no-untyped-def]
    """Whether DAQP's working set (``dq.sense_full``) holds a row or bound other than the equalities:
    the last answer had an inequality binding, and this one likely has too (then the hard-first tick
    goes to DAQP directly rather than try :func:`equality_minimum` first)."""
    sf = dq.sense_full
    for j in range(sf.shape[0]):
        if sf[j] & ACTIVE and not sf[j] & IMMUTABLE:
            return True
    return False
