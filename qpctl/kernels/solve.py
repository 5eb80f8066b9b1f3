"""Stages 4–7 of the QP tick after the state: the law's terms, the rows, DAQP's solve, the check.

The codes these return (and the tick's entry points pass on): 0 solved and accepted; 1 M not
positive definite; 2 the problem's data not finite (no solver may be trusted with it); 3 DAQP
failed (its exit flag in ``dq.flag[0]``); 4 x violates a hard row or is not finite.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from qpctl.kernels.clock import now_us
from qpctl.kernels.codes import R_BUILD_US, R_ITERATIONS, R_SOLVE_US, record_scalars
from qpctl.kernels.daqp import native_solve
from qpctl.kernels.finish import finite_problem, qp_finish
from qpctl.kernels.law import law_terms
from qpctl.kernels.rows import qp_build


@njit(cache=True)
def qp_rebuild(ws, H: np.ndarray, f: np.ndarray, rows: np.ndarray, bu: np.ndarray,  # type: ignore[no-untyped-def]
               bl: np.ndarray) -> int:
    """The QP's rows in another layout from this tick's terms (the relaxed layout after the hard one
    failed): 0, or 2 if the problem's data are not finite."""
    qp_build(ws, H, f, rows, bu, bl)
    return 0 if finite_problem(H, f, rows, bu, bl) else 2


@njit(cache=True)
def qp_terms_and_build(ws, H: np.ndarray, f: np.ndarray, rows: np.ndarray, bu: np.ndarray,  # type: ignore[no-untyped-def]
                       bl: np.ndarray) -> int:
    """The QP law's terms (the paper's, weighted) and its rows: 0; 1 if M is not positive definite;
    2 if the problem's data are not finite (no solver may be trusted with it)."""
    if not law_terms(ws, True):
        return 1
    qp_build(ws, H, f, rows, bu, bl)
    return 0 if finite_problem(H, f, rows, bu, bl) else 2


@njit(cache=True)
def qp_tick_native(ws, H: np.ndarray, f: np.ndarray, rows: np.ndarray, bu: np.ndarray,  # type: ignore[no-untyped-def]
                   bl: np.ndarray, dq, x: np.ndarray, tol: float) -> int:
    """The whole QP tick after the state, on DAQP's C API: law terms, rows, solve, check, record
    (with the build and solve times [µs]). 0: solved and accepted; 1: M not positive definite;
    2: non-finite problem (not solved); 3: DAQP failed (its exit flag in ``dq.flag[0]``; ``dq``: the
    layout's :class:`~qpctl.kernels.daqp_pack.DaqpPack`); 4: x violates a hard row or is not finite."""
    ts = ws.ts
    t0 = now_us(ts)
    code = qp_terms_and_build(ws, H, f, rows, bu, bl)
    t1 = now_us(ts)
    s = record_scalars(ws.N.shape[0], ws.a.shape[0])
    ws.rec[s + R_BUILD_US] = t1 - t0
    ws.rec[s + R_SOLVE_US] = 0.0
    if code != 0:
        return code
    ok = native_solve(dq) > 0
    ws.rec[s + R_SOLVE_US] = now_us(ts) - t1
    if not ok:
        return 3
    if not qp_finish(ws, x, rows, bu, bl, tol, False):
        return 4
    ws.rec[s + R_ITERATIONS] = dq.flag[1]
    return 0


@njit(cache=True)
def native_solve_finish(ws, rows: np.ndarray, bu: np.ndarray, bl: np.ndarray, dq,  # type: ignore[no-untyped-def]
                        x: np.ndarray, tol: float) -> int:
    """:func:`qp_tick_native` after its rows are built (the tick that set DAQP's workspace up)."""
    if native_solve(dq) <= 0:
        return 3
    if not qp_finish(ws, x, rows, bu, bl, tol, False):
        return 4
    ws.rec[record_scalars(ws.N.shape[0], ws.a.shape[0]) + R_ITERATIONS] = dq.flag[1]
    return 0
