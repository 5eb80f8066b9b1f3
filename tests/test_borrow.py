"""Borrowed arrays (qpctl.kernels.borrow): the same memory without numba's reference count.

The property that makes them cheap is checked directly: the array's memory-info pointer, read by an
intrinsic written here, is null for a borrowed array and for every array of a tick's workspace, and
not for an ordinary one. The workspace's arrays stay alive as long as the workspace (its ``_pinned``
tuple), whatever becomes of its attributes.
"""

from __future__ import annotations

import gc
import weakref

import numpy as np
from numba import njit, types
from numba.extending import intrinsic

from qpctl import Scenario
from qpctl.kernels.borrow import borrow, borrow_all
from qpctl.kernels.work import FIELDS


@intrinsic
def meminfo_of(typingctx, arr):  # type: ignore[no-untyped-def]
    """The array's memory-info pointer as an integer (0: none)."""
    if not isinstance(arr, types.Array):
        return None

    def codegen(context, builder, signature, args):  # type: ignore[no-untyped-def]
        ary = context.make_array(signature.args[0])(context, builder, value=args[0])
        return builder.ptrtoint(ary.meminfo, context.get_value_type(types.intp))

    return types.intp(arr), codegen


@njit
def _meminfos(a):  # type: ignore[no-untyped-def]
    b = borrow(a)
    return meminfo_of(a), meminfo_of(b), meminfo_of(b[1])


@njit
def _write_borrowed(a):  # type: ignore[no-untyped-def]
    b = borrow(a)
    b[1, 2] = 7.5
    return b.shape[0], b.shape[1], b.strides[0], b.strides[1], b[2, 3]


@njit
def _all(t):  # type: ignore[no-untyped-def]
    u = borrow_all(t)
    return meminfo_of(t[0]), meminfo_of(u[0]), u[1], meminfo_of(u[2]), u[2][1]


@njit
def _workspace_meminfos(ws):  # type: ignore[no-untyped-def]
    return meminfo_of(ws.q), meminfo_of(ws.M), meminfo_of(ws.rec), meminfo_of(ws.fd_dist)


def test_borrow_drops_the_meminfo_and_keeps_the_memory() -> None:
    a = np.arange(12.0).reshape(3, 4)
    counted, borrowed, row = _meminfos(a)
    assert counted != 0 and borrowed == 0 and row == 0  # a view of a borrowed array is borrowed too
    f = np.asfortranarray(np.arange(12.0).reshape(3, 4))
    for arr in (a, f):
        nx, ny, s0, s1, v = _write_borrowed(arr)
        assert (nx, ny, s0, s1) == (*arr.shape, *arr.strides)
        assert v == arr[2, 3] and arr[1, 2] == 7.5  # reads and writes go to the caller's memory


def test_borrow_all_borrows_the_arrays_and_passes_the_rest() -> None:
    x, y = np.ones(3), np.array([1, 5, 2], np.int64)
    m0, m1, k, m2, y1 = _all((x, 4, y))
    assert m0 != 0 and m1 == 0 and m2 == 0 and k == 4 and y1 == 5


def test_the_workspace_arrays_are_borrowed_and_pinned() -> None:
    ctrl = Scenario.load("panda_spheres").build_controller("qp", "daqp")
    ws = ctrl.qp_path().ws
    assert _workspace_meminfos(ws.work) == (0, 0, 0, 0)
    assert len(ws._pinned) == len(FIELDS)
    q, v = ctrl.robot.q_home.copy(), np.zeros(ctrl.robot.nv)
    tau = ctrl.torque(q, v, 0.0).copy()
    alive = weakref.ref(ws.Lm)  # M's Cholesky factor: written by the kernels every tick, unread by Python
    ws.Lm = None  # the attribute gone: only the workspace's pinned tuple holds the array the kernels write
    gc.collect()
    assert alive() is not None
    _ = [np.full((7, 7), np.nan) for _ in range(100)]  # memory that a freed array would be reused for
    alive()[:] = np.nan  # type: ignore[index]
    assert np.array_equal(ctrl.torque(q, v, 0.0), tau)
    lm, M = np.tril(alive()), ws.M.copy()  # type: ignore[arg-type]
    assert np.allclose(lm @ lm.T, M, rtol=0, atol=1e-12 * np.abs(M).max())
