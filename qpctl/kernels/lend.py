"""Lent structrefs: a kernel's view of a structref that carries no reference count.

numba counts references to a structref's memory as it does an array's (:mod:`qpctl.kernels.borrow`):
every compiled function that takes one as an argument increments its count on entry and decrements
it on return, an atomic ``lock`` instruction each. The tick passes its workspace (a
:class:`~qpctl.kernels.work.TickWork`) and its QP (a :class:`~qpctl.kernels.native_qp.NativeQP`) to
every stage, and to helpers called once per pair or row: 7 % of the compiled tick's samples were in
``NRT_incref``/``NRT_decref`` (perf, the Panda among 10 spheres, 2026-12-06).

A :class:`Lent` type is the same structref — the same fields (a structref field is lent too), read
and written the same way — whose data model holds the memory-info record as a plain pointer, which
numba's reference counting does not see. Kernels never meet the counted types: the three proxies
(``TickWork``, ``NativeQP``, ``DaqpPack``) are :class:`LentProxy` objects, which give their lent type
as their ``_numba_type_`` (what numba's dispatcher matches a call by), a proxy argument unboxes to it
(:func:`_unbox_lent`), and :func:`lent_at` makes one from an address
(:func:`qpctl.kernels.borrow.struct_address`). So every
kernel compiles for the lent types only — none twice — and no stage pays a count for them.

The rule that makes it safe is :mod:`~qpctl.kernels.borrow`'s: a lent structref must not outlive the
reference that keeps its memory — the Python proxy the caller holds for the call, or whose address
:func:`lent_at` was given. A kernel never returns one to Python (numba has no boxing for it: such a
kernel does not compile) and never assigns a structref field through one. The one structref that
holds others, ``NativeQP``, is built by :func:`qpctl.kernels.borrow.borrow_all`, which stores a lent
structref as a counted reference of its own: the NativeQP keeps its fields alive, as before.
"""

from __future__ import annotations

from typing import Any

from numba import types
from numba.core import cgutils
from numba.core.datamodel import models
from numba.experimental import structref
from numba.extending import NativeValue, intrinsic, register_model, typeof_impl, unbox


class Lent(types.StructRef):  # type: ignore[name-defined]  # numba is untyped
    """A structref type ``of`` (a :class:`numba.types.StructRef`), lent: the same fields, structref
    fields lent too, and no reference count (module docstring)."""

    def __init__(self, of: Any) -> None:
        self.of = of
        super().__init__(tuple((name, lent_type(t) if isinstance(t, types.StructRef) else t) for name, t in of._fields))


@register_model(Lent)
class LentModel(models.StructModel):  # type: ignore[misc]  # numba is untyped
    """The structref's model with its memory-info pointer as a raw pointer: the same layout
    (``{ptr}``), nothing for the reference counting to visit."""

    def __init__(self, dmm: Any, fe_typ: Any) -> None:
        super().__init__(dmm, fe_typ, [("meminfo", types.voidptr)])


structref.define_attributes(Lent)


@intrinsic
def lent_at(typingctx: Any, tyref: Any, addr: Any) -> Any:
    """The structref of type ``tyref`` (a TypeRef of a StructRef) whose memory-info record is at
    ``addr`` (:func:`qpctl.kernels.borrow.struct_address`), lent: its count untouched. Valid while
    the Python proxy the address was read from lives."""
    if not (isinstance(tyref, types.TypeRef) and isinstance(tyref.instance_type, types.StructRef)
            and isinstance(addr, types.Integer)):
        return None
    lt = lent_type(tyref.instance_type)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        out = cgutils.create_struct_proxy(lt)(context, builder)
        out.meminfo = builder.inttoptr(args[1], context.get_value_type(types.voidptr))
        return out._getvalue()

    return lt(tyref, addr), codegen


_LENT: dict[Any, Lent] = {}


def lent_type(ty: Any) -> Lent:
    """The :class:`Lent` type of the structref type ``ty`` (one object per type, kept)."""
    lt = _LENT.get(ty)
    if lt is None:
        lt = _LENT[ty] = ty if isinstance(ty, Lent) else Lent(ty)
    return lt


@unbox(Lent)
def _unbox_lent(typ: Any, obj: Any, c: Any) -> Any:
    """A structref's Python proxy as its lent type: its memory-info record's address, the count
    acquired and released at once (the proxy, which the caller holds for the call, keeps it)."""
    mi_obj = c.pyapi.object_getattr_string(obj, "_meminfo")
    mi = c.pyapi.nrt_meminfo_from_pyobject(mi_obj)
    failed = cgutils.is_null(c.builder, mi)
    with c.builder.if_then(c.builder.not_(failed)):
        c.context.nrt.decref(c.builder, types.MemInfoPointer(types.voidptr), mi)
    c.pyapi.decref(mi_obj)
    out = cgutils.create_struct_proxy(typ)(c.context, c.builder)
    out.meminfo = c.builder.bitcast(mi, c.context.get_value_type(types.voidptr))
    return NativeValue(out._getvalue(), is_error=failed)


class LentProxy(structref.StructRefProxy):  # type: ignore[misc]  # numba is untyped
    """The Python proxy of a structref that kernels take lent (module docstring): its ``_numba_type_``
    — what numba's dispatcher matches a call by, without calling Python — and its ``typeof`` are its
    :class:`Lent` type, found once when the proxy is made. ``TickWork``, ``NativeQP`` and ``DaqpPack``
    are such proxies."""

    __slots__ = ("_lent",)

    @classmethod
    def _numba_box_(cls, ty: Any, mi: Any) -> Any:
        instance = super()._numba_box_(ty, mi)
        instance._lent = lent_type(ty)
        return instance

    @property
    def _numba_type_(self) -> Any:
        return self._lent


@typeof_impl.register(LentProxy)
def _typeof(val: LentProxy, c: object) -> Any:
    """Its lent type, directly: numba's generic typeof first tries the object as a buffer, an exception
    on every kernel call (~1 µs of the dispatch, and allocations tracemalloc sees)."""
    return val._lent
