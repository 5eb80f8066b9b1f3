"""The task hard first, on DAQP's C API: the QP without the task's slack (n variables instead of
n + 2m), its answer kept only where it is the relaxed QP's too, the relaxed QP solved otherwise.

The hard answer is used when DAQP solved it, its task rows hold (:func:`task_rows_hold`: DAQP may
drop a nearly dependent equality), every task multiplier is within the ℓ₁ slack weight (the
exact-penalty condition, :func:`penalty_exact`) and the other rows hold (:func:`qpctl.kernels.finish.qp_finish`).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from qpctl.kernels.clock import now_us
from qpctl.kernels.codes import IP_N_IN, R_BUILD_US, R_ITERATIONS, R_SOLVE_US, record_scalars
from qpctl.kernels.daqp import native_solve
from qpctl.kernels.equality_qp import active_set_minimum, working_set
from qpctl.kernels.finish import qp_finish
from qpctl.kernels.solve import native_solve_finish, qp_rebuild, qp_terms_and_build

SLACK_ZERO = 1e-12  # [task units] a slack norm at or below this is zero: the task did not give way


@njit(cache=True)
def hard_next(used_hard: bool, solved: bool, slack: float) -> bool:
    """The skip rule (:mod:`qpctl.controllers.relaxation`, ``"auto"`` on DAQP): whether the next
    one-call tick tries the hard QP first, after a tick that used its answer (``used_hard``), solved
    (``solved``) with the task slack's norm ``slack``: yes unless the task gave way. The one place the
    rule is written; :meth:`TaskRelaxation.after` and the one-call tick (:func:`qpctl.kernels.tick.tick_qp`)
    both call it."""
    return used_hard or (solved and slack <= SLACK_ZERO)


@njit(cache=True)
def penalty_exact(lam: np.ndarray, first: int, m: int, l1: float) -> bool:
    """Whether the hard QP's answer is the relaxed QP's too: every task row's multiplier (DAQP's
    λ of the equality rows, ``first`` … ``first + m``) within the ℓ₁ slack weight, |λ_i| ≤ l1 — the
    exact-penalty condition (:func:`qpctl.qp.penalty_is_exact`, which finds λ without the solver)."""
    for r in range(m):
        if not abs(lam[first + r]) <= l1:
            return False
    return True


@njit(cache=True)
def task_rows_hold(x: np.ndarray, rows: np.ndarray, bu: np.ndarray, n_in: int, m: int, tol: float) -> bool:
    """Whether the hard QP's x meets its task rows (rows ``n_in`` … ``n_in + m`` of ``rows``, equalities
    at ``bu``) within ``tol`` relative to the larger of 1, |b| and the row's |A_i|·|x|. DAQP may drop
    an equality row that is nearly dependent (the planar arm outstretched: the x row of J ~1e-5) and
    report the rest solved; :func:`qp_finish` checks the inequality rows only."""
    nv = x.shape[0]
    for r in range(n_in, n_in + m):
        ax = 0.0
        mag = 0.0
        for c in range(nv):
            ax += rows[r, c] * x[c]
            mag += abs(rows[r, c] * x[c])
        b = bu[nv + r]
        if not abs(ax - b) <= tol * max(1.0, abs(b), mag):
            return False
    return True


@njit(cache=True)
def qp_tick_native_hard_first(nq, try_hard: bool) -> tuple[int, int]:  # type: ignore[no-untyped-def]
    """:func:`qp_tick_native_hard_first_from` now: the build's time counted from this call."""
    return qp_tick_native_hard_first_from(nq, try_hard, now_us(nq.ws.ts))


@njit(cache=True)
def qp_tick_native_hard_first_from(nq, try_hard: bool, t0: float) -> tuple[int, int]:  # type: ignore[no-untyped-def]
    """The QP tick after the state with the task hard first (no slack variables: a smaller QP), its
    answer kept where the exact-penalty condition says the relaxed QP's is the same
    (:func:`penalty_exact`), the relaxed QP solved otherwise (or when not ``try_hard``). ``nq``: a
    :class:`~qpctl.kernels.native_qp.NativeQP` (the workspace and both layouts); each layout's arrays
    are read from it only on the path that uses them (every array a kernel reads or is passed costs
    an atomic reference count increment and decrement). Returns (code, hard): code as
    :func:`qp_tick_native`'s, for the answer used; hard: −1 not tried, 0 the hard answer used, 3 DAQP
    failed on it, 4 rejected by the check of its rows (the task rows, :func:`task_rows_hold`, or the
    others, :func:`qp_finish`), 7 not the relaxed QP's answer. ``t0``: the clock [µs] at which the
    build's time starts (the state's end, read once for both: :func:`qpctl.kernels.tick.tick_qp`).
    The hard QP's minimum on its task rows and DAQP's last working set is tried first and, where it is
    the QP's answer (every other row and bound holds, every held multiplier has its side's sign), is
    taken without DAQP (:mod:`~qpctl.kernels.equality_qp`; DAQP's flags then read solved, 0 iterations)."""
    ws = nq.ws
    ts = ws.ts
    s = record_scalars(ws.N.shape[0], ws.a.shape[0])
    build = solve = 0.0
    hard = -1
    tol = nq.tol
    if try_hard:
        rowsh, buh, blh = nq.rowsh, nq.buh, nq.blh
        code = qp_terms_and_build(ws, nq.Hh, nq.fh, rowsh, buh, blh)
        t1 = now_us(ts)
        build += t1 - t0
        if code != 0:
            ws.rec[s + R_BUILD_US], ws.rec[s + R_SOLVE_US] = build, 0.0
            return code, hard
        dqh = nq.dqh
        xh = nq.xh
        nvh = xh.shape[0]
        n_in = ws.ipar[IP_N_IN]
        m = ws.a.shape[0]
        # the minimum on the task's rows and DAQP's last working set, where it is the answer: DAQP not
        # called (equality_qp)
        shortcut = active_set_minimum(
            nq.Hh, nq.fh, rowsh, buh, blh, n_in, m, nq.eq_w, nq.eq_low,
            working_set(dqh, n_in, m, nq.eq_w, nq.eq_low), xh, nq.lamh, nq.eq_L, nq.eq_Y, nq.eq_V, nq.eq_G,
            nq.eq_z, ws.cx)
        if shortcut:
            dqh.flag[0], dqh.flag[1] = 1, 0  # DAQP's words for it: solved, no iteration
            ok = True
        else:
            ok = native_solve(dqh) > 0
        if not ok:
            hard = 3
        elif not task_rows_hold(xh, rowsh, buh, n_in, m, tol):
            hard = 4
        elif not penalty_exact(nq.lamh, nvh + n_in, m, nq.l1):
            hard = 7
        elif not qp_finish(ws, xh, rowsh, buh, blh, tol, shortcut):  # (its C x in ws.cx)
            hard = 4
        else:  # the solve and the check of its answer (the relaxed QP's below, the same)
            ws.rec[s + R_BUILD_US], ws.rec[s + R_SOLVE_US] = build, now_us(ts) - t1
            ws.rec[s + R_ITERATIONS] = dqh.flag[1]
            return 0, 0
        t0 = now_us(ts)
        solve += t0 - t1
        code = qp_rebuild(ws, nq.Hr, nq.fr, nq.rowsr, nq.bur, nq.blr)
    else:
        code = qp_terms_and_build(ws, nq.Hr, nq.fr, nq.rowsr, nq.bur, nq.blr)
    t1 = now_us(ts)
    build += t1 - t0
    ws.rec[s + R_BUILD_US], ws.rec[s + R_SOLVE_US] = build, solve
    if code != 0:
        return code, hard
    code = native_solve_finish(ws, nq.rowsr, nq.bur, nq.blr, nq.dqr, nq.xr, tol)
    ws.rec[s + R_SOLVE_US] = solve + now_us(ts) - t1  # the solve and the check of its answer
    return code, hard
