"""The tick's entry points: what Python calls, each a whole stage or a whole tick after
``rigid_pass`` (:func:`qpctl.tick.rigid_pass`: Pinocchio's crba and nonLinearEffects) — which the
one-call ticks (:func:`tick_closed_form`, :func:`tick_qp`) run themselves where the workspace has
the native pass (:mod:`~qpctl.kernels.pin_native`). DESIGN.md §5; docs/tick.md has the module map.

Every kernel reads and writes the fixed-shape arrays of one :class:`~qpctl.kernels.work.TickWork`
(:mod:`qpctl.kernels.work` lists them); nothing allocates per pair or per row, and the number of
pairs changes the work inside a loop, never the number of Python calls. In tick order:

1. :func:`state` — rigid terms (:mod:`~qpctl.kernels.rigid`), self pairs
   (:mod:`~qpctl.kernels.self_pairs`), obstacles and reference at t (:mod:`~qpctl.kernels.scene`),
   link–obstacle pairs (:mod:`~qpctl.kernels.pairs`);
2. the law's terms and the closed forms (:mod:`~qpctl.kernels.law`): :func:`tick_closed_form`;
3. the QP: rows (:mod:`~qpctl.kernels.rows`), DAQP's solve (:mod:`~qpctl.kernels.daqp`), the check
   and the record (:mod:`~qpctl.kernels.finish`), chained by :mod:`~qpctl.kernels.solve`:
   :func:`tick_qp_native`; the task hard first (:mod:`~qpctl.kernels.hard_first`):
   :func:`tick_qp_native_hard_first`.

The controllers' common tick calls :func:`tick_qp_at` and :func:`tick_closed_form_at` — :func:`tick_qp`
and :func:`tick_closed_form` on the structref given by its type and address (:func:`address_entry`).

Return codes: those of :mod:`qpctl.kernels.solve`, and −1 (the dynamics overflow) or STATE_PYTHON
(the state is waiting for Python: python-fcl's pairs — shapes other than spheres, capsules, boxes
and cylinders — or a look-ahead drift; Python finishes it and calls the stage after the state).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import njit

from qpctl.kernels.borrow import borrow, struct_address
from qpctl.kernels.clearance import min_distance, min_self_distance
from qpctl.kernels.clock import now_us
from qpctl.kernels.codes import (
    BAD_SHAPE,
    CNT_LOOKAHEAD,
    FP_T,
    R_BUILD_US,
    R_RIGID_US,
    R_SLACK,
    R_STATE_US,
    STATE_PYTHON,
    record_scalars,
)
from qpctl.kernels.daqp import native_solve
from qpctl.kernels.field_rows import set_field
from qpctl.kernels.finish import qp_finish, write_record
from qpctl.kernels.hard_first import hard_next, qp_tick_native_hard_first, qp_tick_native_hard_first_from
from qpctl.kernels.law import closed_form, closed_form_tick, law_terms
from qpctl.kernels.lend import lent_at
from qpctl.kernels.pairs import find_pairs, finish_pairs
from qpctl.kernels.pin_native import rigid_native
from qpctl.kernels.rigid import rigid_terms
from qpctl.kernels.rows import qp_build
from qpctl.kernels.scene import obstacles_at, reference
from qpctl.kernels.self_pairs import self_pairs
from qpctl.kernels.solve import native_solve_finish, qp_rebuild, qp_terms_and_build, qp_tick_native

# What Python calls: the whole ticks after computeAllTerms (below), and the stages its slower paths
# call one by one (a solver other than DAQP's C API, a state Python finishes, a fallback's record,
# the simulator's clearance). qpctl.warmup.warmup compiles or loads every one of them.
__all__ = [
    "address_entry",
    "address_of",
    "closed_form",
    "closed_form_tick",
    "finish_pairs",
    "law_terms",
    "min_distance",
    "min_self_distance",
    "native_solve",
    "native_solve_finish",
    "qp_build",
    "qp_finish",
    "qp_rebuild",
    "qp_terms_and_build",
    "qp_tick_native",
    "qp_tick_native_hard_first",
    "set_field",
    "state",
    "tick_closed_form",
    "tick_closed_form_at",
    "tick_qp",
    "tick_qp_at",
    "tick_qp_native",
    "tick_qp_native_hard_first",
    "write_record",
]


@njit(cache=True)
def state(ws, q: np.ndarray, v: np.ndarray, t: float) -> int:  # type: ignore[no-untyped-def]
    """The tick's state after ``rigid_pass(q, v)``: rigid terms, obstacles and reference at t,
    pairs. Returns −1 when the dynamics overflow, else the number of pairs python-fcl must query
    (when 0, :func:`finish_pairs` has run too)."""
    for i in range(q.shape[0]):
        ws.q[i], ws.v[i] = q[i], v[i]
    ws.fpar[FP_T] = t
    if not rigid_terms(ws, v):
        return -1
    if ws.sc_pairs.shape[0]:
        self_pairs(ws)
    obstacles_at(ws, t)
    reference(ws, t)
    nfcl = find_pairs(ws)
    if nfcl == 0:
        finish_pairs(ws)
    return nfcl


@njit(cache=True)
def state_timed(ws, q: np.ndarray, v: np.ndarray, t: float, ts: np.ndarray,  # type: ignore[no-untyped-def]
                t0: float) -> tuple[int, float]:
    """:func:`state`, its time [µs] into the record, counted from ``t0`` (the clock [µs] when the stage
    before ended; negative: read it here). Returns (−1 overflow, STATE_PYTHON if Python must finish
    the state (python-fcl's pairs, or a look-ahead barrier drift), else 0; the clock at its end [µs]):
    one clock read between two stages, not two (a read is 30–80 ns on this project's machines)."""
    if t0 < 0.0:
        t0 = now_us(ts)
    st = state(ws, q, v, t)
    t1 = now_us(ts)
    ws.rec[record_scalars(ws.N.shape[0], ws.a.shape[0]) + R_STATE_US] = t1 - t0
    if st < 0:
        return -1, t1
    if st > 0 or ws.cnt[CNT_LOOKAHEAD] > 0:
        return STATE_PYTHON, t1
    return 0, t1


@njit(cache=True)
def rigid_first(ws, q: np.ndarray, v: np.ndarray, ts: np.ndarray) -> tuple[int, float]:  # type: ignore[no-untyped-def]
    """Where the workspace has the native pass (``ws.pin_native``), (q, v) into it and Pinocchio's
    rigid-body pass (:mod:`~qpctl.kernels.pin_native`), its time [µs] into the record: (0, or −1 when
    Pinocchio threw (the state's checks then refuse it); the clock at its end [µs]). Else nothing:
    Python ran ``rigid_pass`` — (0, −1.0)."""
    if ws.pin_native[0] == 0:
        return 0, -1.0
    for i in range(q.shape[0]):
        ws.q[i], ws.v[i] = q[i], v[i]
    t0 = now_us(ts)
    code = rigid_native(ws)
    t1 = now_us(ts)
    ws.rec[record_scalars(ws.N.shape[0], ws.a.shape[0]) + R_RIGID_US] = t1 - t0
    return (-1 if code else 0), t1


@njit(cache=True)
def copy_record(rec: np.ndarray, out: np.ndarray) -> None:
    """The tick's record into ``out``, a tick output's own array (as long as the record)."""
    for i in range(min(rec.shape[0], out.shape[0])):
        out[i] = rec[i]


@njit(cache=True)
def tick_closed_form(ws, q: np.ndarray, v: np.ndarray, t: float, weighted: bool,  # type: ignore[no-untyped-def]
                     out: np.ndarray) -> int:
    """State, law terms and closed form in one call, the record copied into ``out`` (the output's own
    array) when it returns 0; else ``out`` is untouched. Returns 0; −1 the dynamics overflow or a
    non-finite state; 1 M not positive definite; BAD_SHAPE: q or v is not of the robot's n joints;
    STATE_PYTHON: the state is waiting for Python (then call :func:`closed_form_tick`)."""
    n = ws.q.shape[0]
    if q.shape[0] != n or v.shape[0] != n:
        return BAD_SHAPE
    if not abs(t) < np.inf:
        return -1
    ts = ws.ts
    code, t1 = rigid_first(ws, q, v, ts)
    if code == 0:
        code, t1 = state_timed(ws, q, v, t, ts, t1)
    if code != 0:
        return code
    code = closed_form_tick(ws, weighted)
    ws.rec[record_scalars(ws.N.shape[0], ws.a.shape[0]) + R_BUILD_US] = now_us(ts) - t1
    if code == 0:
        copy_record(ws.rec, out)
    return code


@njit(cache=True)
def tick_qp_native(ws, q: np.ndarray, v: np.ndarray, t: float, H: np.ndarray, f: np.ndarray,  # type: ignore[no-untyped-def]
                   rows: np.ndarray, bu: np.ndarray, bl: np.ndarray, dq, x: np.ndarray, tol: float) -> int:
    """State and :func:`qp_tick_native` in one call: its codes, or −1 (the dynamics overflow) or
    STATE_PYTHON (the state is waiting for Python; then call :func:`qp_tick_native`)."""
    code, _ = state_timed(ws, q, v, t, ws.ts, -1.0)
    if code != 0:
        return code
    return qp_tick_native(ws, H, f, rows, bu, bl, dq, x, tol)


@njit(cache=True)
def tick_qp_native_hard_first(nq, q: np.ndarray, v: np.ndarray, t: float,  # type: ignore[no-untyped-def]
                              try_hard: bool) -> tuple[int, int]:
    """State and :func:`qp_tick_native_hard_first` in one call (``nq`` a
    :class:`~qpctl.kernels.native_qp.NativeQP`): its pair, or (−1 | STATE_PYTHON, −1) as
    :func:`tick_qp_native`."""
    ws = nq.ws
    code, t1 = state_timed(ws, q, v, t, ws.ts, -1.0)
    if code != 0:
        return code, -1
    return qp_tick_native_hard_first_from(nq, try_hard, t1)


@njit(cache=True)
def tick_qp(nq, q: np.ndarray, v: np.ndarray, t: float, try_hard: bool,  # type: ignore[no-untyped-def]
            out: np.ndarray) -> tuple[int, int, bool]:
    """The whole QP tick after ``rigid_pass`` in one call: ``nq`` (a
    :class:`~qpctl.kernels.native_qp.NativeQP`: the workspace and both QP layouts) and the state;
    the record copied into ``out`` (the output's own array: no copy in Python) when the tick solved
    and nothing is left for Python (code 0, ``hard`` ≤ 0; on other ticks Python writes it). Returns
    :func:`tick_qp_native_hard_first`'s pair and whether the next tick tries the task hard
    (:func:`~qpctl.kernels.hard_first.hard_next`, the skip rule); (BAD_SHAPE, −1, try_hard) when q or v
    is not of the robot's n joints, (−1, −1, try_hard) when the state is not finite or the dynamics
    overflow (the dispatcher has already refused any other type: no Python checks a good state)."""
    ws = nq.ws
    n = ws.q.shape[0]
    if q.shape[0] != n or v.shape[0] != n:
        return BAD_SHAPE, -1, try_hard
    if not abs(t) < np.inf:  # NaN or ±inf; q and v: the state's overflow test (rigid_terms)
        return -1, -1, try_hard
    ts = ws.ts
    code, t1 = rigid_first(ws, q, v, ts)  # (each stage's end the next one's start: one clock read between)
    if code == 0:
        code, t1 = state_timed(ws, q, v, t, ts, t1)
    if code != 0:
        return code, -1, try_hard
    code, hard = qp_tick_native_hard_first_from(nq, try_hard, t1)
    if code == 0 and hard <= 0:  # the tick Python ends without a word (else Python copies the record)
        copy_record(ws.rec, out)
    slack = ws.rec[record_scalars(ws.N.shape[0], ws.a.shape[0]) + R_SLACK]
    return code, hard, hard_next(hard == 0, code == 0, slack)


# The common tick's entry points take the structref by its address (qpctl.kernels.lend.lent_at): its
# type as a TypeRef (unboxed to nothing) and the address as an int, ~0.2 µs a call less than the
# structref itself; it is lent to the tick as every structref argument is (qpctl.kernels.lend), and q,
# v and the record are borrowed (qpctl.kernels.borrow): no stage pays an atomic count for them. The
# caller holds the structref's Python proxy and the arrays while it calls with the address.


@njit(cache=True)
def address_of(s) -> int:  # type: ignore[no-untyped-def]
    """A structref's address, for the ``*_at`` entry points (valid while its Python proxy lives)."""
    return struct_address(s)


@njit(cache=True)
def tick_qp_at(ty, addr: int, q: np.ndarray, v: np.ndarray, t: float, try_hard: bool,  # type: ignore[no-untyped-def]
               out: np.ndarray) -> tuple[int, int, bool]:
    """:func:`tick_qp` on the NativeQP of type ``ty`` at ``addr`` (:func:`address_of`)."""
    return tick_qp(lent_at(ty, addr), borrow(q), borrow(v), t, try_hard, borrow(out))


@njit(cache=True)
def tick_closed_form_at(ty, addr: int, q: np.ndarray, v: np.ndarray, t: float,  # type: ignore[no-untyped-def]
                        weighted: bool, out: np.ndarray) -> int:
    """:func:`tick_closed_form` on the TickWork of type ``ty`` at ``addr`` (:func:`address_of`)."""
    return tick_closed_form(lent_at(ty, addr), borrow(q), borrow(v), t, weighted, borrow(out))


def address_entry(kernel: Any, struct: Any, **trailing: Any) -> tuple[Any, Any, int] | None:
    """The compiled entry point of an ``*_at`` kernel (:func:`tick_qp_at`, :func:`tick_closed_form_at`)
    for ``struct`` (a structref's Python proxy) by its address, with the arguments it is called with
    before q: (entry, struct's numba type, address). Compiles (or loads from the cache) that signature
    — q and v float64 C vectors, t a float, then ``trailing``'s values' types — if it is not there yet;
    None where this numba does not expose an entry point. The entry point unboxes without checking a
    dtype or a number of dimensions: call it only on arguments checked to be those types, and only
    while ``struct`` lives (the address is its memory's)."""
    try:
        from numba import typeof
        from numba.core import types

        ty = struct._numba_type_
        arr = types.Array(types.float64, 1, "C")
        sig = (types.TypeRef(ty), types.int64, arr, arr, types.float64, *(typeof(a) for a in trailing.values()))
        if sig not in kernel.overloads:
            kernel.compile(sig)  # (the *_at kernels are never locked: only ever called through this)
        return kernel.overloads[sig].entry_point, ty, int(address_of(struct))
    except Exception:  # noqa: BLE001 — numba's internals moved: the caller takes the dispatcher
        return None
