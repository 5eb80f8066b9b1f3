"""The QP's two layouts on DAQP's C API as one compiled argument: :class:`NativeQP`.

The one-call tick (:func:`qpctl.kernels.tick.tick_qp`) reads, besides the state, the tick's workspace
(a :class:`~qpctl.kernels.work.TickWork`), both layouts of the QP (the task hard, and relaxed: H, f,
rows, bu, bl in DAQP's convention), DAQP's workspace for each (a
:class:`~qpctl.kernels.daqp_pack.DaqpPack`: its structs, exit flags and packed rows), the answers,
the hard QP's multipliers, the check's tolerance and the task's ℓ₁ slack weight. Passed one by one
they were 23 arguments, and numba's dispatcher types and unboxes each on every call (measured here:
3.6 µs for a call of the 28 arguments against 1.3 µs for five); in one structref they cost what one
does, and the workspace inside it saves the unboxing of a second structref (~0.1 µs a call). Built
once per controller (:class:`qpctl.controllers.qp_compiled.CompiledTick`), holding the same numpy
arrays as the layouts (:class:`qpctl.tick.QPBuffers`) and :class:`qpctl.solvers.daqp_native.NativeDAQP`.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numba.core import types
from numba.experimental import structref

from qpctl.kernels.borrow import borrow_all
from qpctl.kernels.lend import LentProxy


@structref.register
class NativeQPType(types.StructRef):  # type: ignore[name-defined]  # numba is untyped
    def preprocess_fields(self, fields: tuple[tuple[str, types.Type], ...]) -> tuple[tuple[str, types.Type], ...]:
        return tuple((name, types.unliteral(typ)) for name, typ in fields)  # type: ignore[attr-defined]


class NativeQP(LentProxy):
    """Both QP layouts and their DAQP structs (fields: :data:`FIELDS`)."""


FIELDS = (
    "ws",  # the tick's workspace (a TickWork): one compiled argument for the whole one-call tick
    # the task hard (n variables): H, f, rows, bu, bl; its DAQP workspace (a DaqpPack: the structs'
    # addresses, [exit flag, iterations], the packed rows), answer x and multipliers λ
    "Hh", "fh", "rowsh", "buh", "blh", "dqh", "xh", "lamh",
    # the relaxed QP (n + 2m variables), the same without λ
    "Hr", "fr", "rowsr", "bur", "blr", "dqr", "xr",
    "tol",  # the answer's check: every hard row to this, relative to 1 + |its bound| (SOLUTION_RTOL)
    "l1",  # the task's ℓ₁ slack weight (the exact-penalty test of the hard answer)
    # the hard QP's answer on DAQP's last working set (qpctl.kernels.equality_qp), its own scratch
    # (nv: the hard layout's variables, n of them the robot's q̈, the rest slack columns): the held
    # constraints' layout indices and sides (nv,), H's leading Cholesky factor (n, n), H⁻¹Ēᵀ (nv, nv),
    # the held rows' Cholesky factor (nv, nv) and normal matrix with two vectors (nv, nv + 2), a vector (nv,)
    "eq_w", "eq_low", "eq_L", "eq_Y", "eq_V", "eq_G", "eq_z",
)


def _make_proxy() -> None:
    structref.define_proxy(NativeQP, NativeQPType, list(FIELDS))


_make_proxy()


def shortcut_scratch(nv: int, n: int) -> tuple[np.ndarray, ...]:
    """The arrays of :data:`FIELDS`' last seven (the working-set shortcut's scratch) for nv variables of
    which the first n are the robot's q̈ (the rest, slack columns, are fixed at their bounds there:
    :func:`~qpctl.kernels.equality_qp.active_set_minimum` factors H's leading n × n block into L)."""
    return (np.zeros(nv, np.int64), np.zeros(nv, np.bool_), np.zeros((n, n)), np.zeros((nv, nv)),
            np.zeros((nv, nv)), np.zeros((nv, nv + 2)), np.zeros(nv))


@njit(cache=True)
def new_native_qp(*fields):  # type: ignore[no-untyped-def]
    """A NativeQP of ``fields`` (in FIELDS order), by a cached compiled constructor."""
    return NativeQP(*borrow_all(fields))
