"""Lent structrefs (qpctl.kernels.lend): kernels take the tick's structrefs without reference counts,
through numba's compiled dispatch, and the one structref that holds others still counts them."""

from __future__ import annotations

import gc
import re

import numpy as np
import pytest
from numba import njit, typeof

from qpctl import Scenario
from qpctl.kernels.lend import Lent


@njit
def _tolerance(nq):  # type: ignore[no-untyped-def]
    return nq.tol


@pytest.fixture(scope="module")
def packed():  # type: ignore[no-untyped-def]
    ctrl = Scenario.load("panda_spheres").build_controller("qp", "daqp")
    ctrl.warmup()
    path = ctrl.qp_path()
    return ctrl, path.packed, path.ws.work, path.hard.nat.dq


def test_a_stage_takes_the_workspace_without_an_atomic_count(packed):
    """The proxies are typed lent (the NativeQP's workspace and pack fields too), and a tick stage
    compiled for the lent workspace has no reference-count increment of it on entry; compiled for
    the counted type, as every stage was before, the same function's code has one (so the check can
    tell)."""
    from qpctl.kernels.field_rows import speed_rows

    _, nq, work, dq = packed
    assert isinstance(nq._numba_type_, Lent) and isinstance(nq._numba_type_.field_dict["ws"], Lent)
    assert isinstance(work._numba_type_, Lent) and isinstance(dq._numba_type_, Lent)
    rows = np.zeros((4, 7))
    increments = {}
    for name, ws_type in (("lent", work._numba_type_), ("counted", work._type)):
        stage = njit(speed_rows.py_func)  # (a stage that calls a helper per row) not cached: its own code to read
        sig = (ws_type, typeof(rows), typeof(rows[:, 0].copy()))
        stage.compile(sig)
        increments[name] = len(re.findall(r"call void @NRT_incref\(ptr %arg\.ws", stage.inspect_llvm(sig)))
    assert increments["lent"] == 0 and increments["counted"] >= 1, increments


def test_a_native_qp_holds_a_reference_to_its_workspace_and_packs(packed):
    """new_native_qp stores counted references of its own (borrow_all): building one from the lent
    proxies adds one to the workspace's and each pack's count, dropping it gives them back — the
    NativeQP keeps what it refers to alive, as before the structrefs were lent."""
    from qpctl.kernels.native_qp import new_native_qp

    ctrl, _, work, dq = packed
    path = ctrl.qp_path()
    nat_r = path.relaxed.nat
    before = (work._meminfo.refcount, dq._meminfo.refcount, nat_r.dq._meminfo.refcount)
    other = new_native_qp(work, *path.native_args)
    assert (work._meminfo.refcount, dq._meminfo.refcount, nat_r.dq._meminfo.refcount) == tuple(b + 1 for b in before)
    assert other._meminfo.refcount == 1
    del other
    gc.collect()
    assert (work._meminfo.refcount, dq._meminfo.refcount, nat_r.dq._meminfo.refcount) == before


def test_a_call_with_a_proxy_is_matched_in_numbas_compiled_dispatch(packed):
    """The proxies give numba's dispatcher their lent type as ``_numba_type_``, which it matches a call
    by without Python: after the first call a kernel taking a NativeQP never goes through the
    dispatcher's Python fallback (with the counted type there, every call did: ~20 µs)."""
    _, nq, _, _ = packed
    first = _tolerance(nq)

    def refuse(*args, **kwargs):  # type: ignore[no-untyped-def]
        raise AssertionError("the call went through numba's Python dispatch")

    _tolerance._compile_for_args = refuse
    try:
        assert _tolerance(nq) == first and np.isfinite(first)
    finally:
        del _tolerance._compile_for_args
