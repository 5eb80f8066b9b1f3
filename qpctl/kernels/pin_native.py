"""Stage 1 of the tick inside the compiled tick: Pinocchio's rigid-body pass (crba in the world
convention, nonLinearEffects) through the native library's ``qpr_pass`` (``qpctl/native/rigid_pass.cpp``),
called by its address — the same libpinocchio functions :func:`qpctl.tick.rigid_pass` calls through
the bindings, without the interpreter between them and the kernel.

The address and the handle are two integers in the workspace (``TickWork.pin_native``; 0: the
library is not used and Python ran ``rigid_pass`` before the kernel). Calling through an address
rather than a linked symbol keeps the kernels cacheable and lets them run where the library could
not be built.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic


@intrinsic
def call_address4(typingctx: Any, fn: Any, a: Any, b: Any, c: Any, d: Any) -> Any:
    """``int fn(uintptr_t, uintptr_t, uintptr_t, uintptr_t)`` called at the address ``fn`` (every
    argument a 64-bit integer)."""
    args = (fn, a, b, c, d)
    if not all(isinstance(x, types.Integer) and x.bitwidth == 64 for x in args):
        return None
    sig = types.intc(*args)

    def codegen(context: Any, builder: Any, signature: Any, llargs: Any) -> Any:
        i64 = ir.IntType(64)
        fnty = ir.FunctionType(ir.IntType(32), [i64] * 4)
        ptr = builder.inttoptr(llargs[0], fnty.as_pointer())
        return builder.call(ptr, list(llargs[1:]))

    return sig, codegen


@njit(cache=True)
def rigid_native(ws) -> int:  # type: ignore[no-untyped-def]
    """crba and nonLinearEffects at the workspace's (q, v) with its model's gravity, into the native
    Data its Pinocchio views read: 0, or 1 when Pinocchio threw. Only where ``ws.pin_native[0]`` ≠ 0."""
    return call_address4(ws.pin_native[0], ws.pin_native[1], ws.q.ctypes.data, ws.v.ctypes.data,
                         ws.gravity.ctypes.data)


@njit(cache=True)
def rigid_at(ws, q: np.ndarray, v: np.ndarray) -> int:  # type: ignore[no-untyped-def]
    """(q, v) into the workspace, then :func:`rigid_native` (the Python paths' call: one dispatch);
    2 when q or v is not of the workspace's length, 3 when the workspace has no native pass."""
    if q.shape[0] != ws.q.shape[0] or v.shape[0] != ws.v.shape[0]:
        return 2
    if ws.pin_native[0] == 0:
        return 3
    for i in range(q.shape[0]):
        ws.q[i], ws.v[i] = q[i], v[i]
    return rigid_native(ws)
