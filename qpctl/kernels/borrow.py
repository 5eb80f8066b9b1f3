"""Borrowed arrays: a kernel's view of an array that carries no reference count.

numba counts references to an array's memory atomically (``NRT_incref``/``NRT_decref``, a ``lock``
instruction each): every array argument of a compiled call that is not inlined, and of an inlined
helper whose body branches, costs a pair of them — about 6 ns on this project's machines, several
hundred times a tick. :func:`borrow` returns the same array (data, shape, strides, type) without its
memory-info pointer; numba's reference counting skips a null one, so passing the borrowed array on
costs a call that returns at once instead of an atomic.

The rule that makes it safe: a borrowed array must not outlive the reference that keeps its memory —
inside a call, the argument it was borrowed from; in a structref, a Python object that lives as long
as the structref. That is how the compiled constructors of the tick's structrefs use
:func:`borrow_all` (:func:`qpctl.kernels.work.new_tick_work`, ``new_native_qp``, ``new_daqp_pack``):
:class:`qpctl.tick.Workspace` pins every array it builds its ``TickWork`` with (``_pinned``) and holds
the depth map's newest snapshot, whose grids ``set_field`` stores borrowed; ``NativeDAQP`` and
``CompiledTick`` hold the arrays of theirs. A borrowed array is never returned to Python.
"""

from __future__ import annotations

from typing import Any

from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from qpctl.kernels.lend import Lent


@intrinsic
def borrow(typingctx: Any, arr: Any) -> Any:
    """``arr`` without its memory-info pointer (module docstring): the same array, uncounted."""
    if not isinstance(arr, types.Array):
        return None
    sig = arr(arr)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        return _borrowed(context, builder, signature.args[0], args[0])

    return sig, codegen


def _borrowed(context: Any, builder: Any, aryty: Any, value: Any) -> Any:
    """The LLVM value of ``value`` (an array of ``aryty``) with a null memory-info pointer."""
    src = context.make_array(aryty)(context, builder, value=value)
    dst = context.make_array(aryty)(context, builder)
    context.populate_array(dst, data=src.data, shape=src.shape, strides=src.strides, itemsize=src.itemsize,
                           meminfo=None)
    dst.parent = cgutils.get_null_value(dst.parent.type)
    return dst._getvalue()


@intrinsic
def borrow_all(typingctx: Any, tup: Any) -> Any:
    """A tuple's arrays borrowed (:func:`borrow`), a lent structref (:class:`qpctl.kernels.lend.Lent`) as
    a counted reference of its own, its other members as they are: what a structref's compiled
    constructor stores when the Python object that builds it keeps the arrays alive — and itself keeps
    the structrefs it refers to."""
    if not isinstance(tup, types.BaseTuple):
        return None
    outty = types.Tuple([t.of if isinstance(t, Lent) else t for t in tup])

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        vals = []
        for i, (ty, oty) in enumerate(zip(signature.args[0], outty, strict=True)):
            val = builder.extract_value(args[0], i)
            if isinstance(ty, types.Array):
                val = _borrowed(context, builder, ty, val)
            else:
                if isinstance(ty, Lent):  # the same memory-info pointer, as the counted type's
                    mi = cgutils.create_struct_proxy(ty)(context, builder, value=val).meminfo
                    ref = cgutils.create_struct_proxy(oty)(context, builder)
                    ref.meminfo = builder.bitcast(mi, context.get_value_type(types.MemInfoPointer(types.voidptr)))
                    val = ref._getvalue()
                context.nrt.incref(builder, oty, val)  # returned: a reference of its own
            vals.append(val)
        return context.make_tuple(builder, outty, vals)

    return outty(tup), codegen


# -- a structref by its address --------------------------------------------------------------------
# Unboxing a structref argument costs a compiled call an attribute lookup by name and the conversion
# of a memory-info object (~0.2 µs of the one-call tick's ~0.5 µs boundary, measured on the Panda's
# packed QP); its address, a Python int, unboxes in nanoseconds, and a numba type given as a TypeRef
# argument unboxes to nothing. The address is valid as long as the Python proxy it was read from
# lives: whoever calls with it must hold that proxy (CompiledTick and PaperController do).


@intrinsic
def struct_address(typingctx: Any, s: Any) -> Any:
    """The address of a structref's memory-info record, as an integer (:func:`qpctl.kernels.lend.lent_at`
    inverts it)."""
    if not isinstance(s, types.StructRef):
        return None

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        mi = cgutils.create_struct_proxy(signature.args[0])(context, builder, value=args[0]).meminfo
        return builder.ptrtoint(mi, cgutils.intp_t)

    return types.intp(s), codegen
