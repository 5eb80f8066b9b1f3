"""DAQP on the rows that can bind: the QP's layout packed before each solve (:class:`DaqpPack`).

A tick's QP layout holds a row for every slot it may need: one per link–obstacle pair the barrier can
take (the nearest ``capacity``), one per self-collision pair, the field's rows. Most are empty on a
given tick — zero rows with bounds ±∞ (on the Panda among 10 spheres 28 of the 51 general rows).
DAQP forms its LDP for every row it is given: the rows' products with R⁻¹ (``daqp_update_M``), their
norms (``daqp_normalize_M``), d = b + M v (``daqp_update_d``), the bound checks — two thirds of its
time on these problems. A row with both bounds infinite can never be violated nor enter the working
set, so dropping it changes nothing DAQP computes for the others: :func:`pack` copies the rows with a
finite bound, in their order, to the front of arrays of the layout's size and sets the problem's
``m``; :func:`unpack` gives the multipliers and the constraints' states back by layout index.
:func:`qpctl.kernels.daqp.native_solve` runs the three around DAQP's update and solve.

The working set is DAQP's warm start: it lives in the workspace's ``sense`` array, by row index. The
packed indices move when a slot fills or empties, so the states are kept by layout index
(``sense_full``) and copied in before and out after each solve; a slot that holds no row keeps what
DAQP's own zero-row mark would keep (``DAQP_ZERO_ROW_MARK`` / ``_SENSE`` of DAQP's constants.h: the
active, lower, immutable and soft bits; an equality found from the bounds is released). DAQP's
``sense`` is this object's array (:class:`qpctl.solvers.daqp_native.NativeDAQP` points the workspace
at it after the set-up), so nothing is copied from C. The set-up itself sees the packed rows padded
to the layout's full size, so DAQP sizes every array for the largest ``m``.

References (``tests/test_daqp_pack.py``): the same solves on the full layout by a second DAQP
workspace — x, λ and the iteration counts equal, bit for bit, over closed-loop ticks.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numba.core import types
from numba.experimental import structref

from qpctl.kernels.borrow import borrow_all
from qpctl.kernels.lend import LentProxy

# DAQP's constraint states (include/constants.h, DAQP 0.11)
ACTIVE, LOWER, IMMUTABLE, SOFT, AUTO_EQUALITY = 1, 2, 4, 8, 128


@structref.register
class DaqpPackType(types.StructRef):  # type: ignore[name-defined]  # numba is untyped
    def preprocess_fields(self, fields: tuple[tuple[str, types.Type], ...]) -> tuple[tuple[str, types.Type], ...]:
        return tuple((name, types.unliteral(typ)) for name, typ in fields)  # type: ignore[attr-defined]


class DaqpPack(LentProxy):
    """One DAQP workspace on one QP layout, packed (fields: :data:`FIELDS`)."""


FIELDS = (
    "work", "problem", "result",  # DAQP's workspace, problem and result structs (addresses)
    "flag",  # (2,) int32: the result's [exit flag, iterations], a view of the struct
    "m_view",  # (1,) int32: the problem struct's m, a view of it
    "rows", "bu", "bl",  # the layout's general rows (m_g, nv) and bounds [simple; general] (DAQP's convention)
    "rows_c", "bu_c", "bl_c",  # the packed rows and bounds DAQP reads (the layout's shapes)
    "idx",  # (m_g,) int: the layout index of each packed general row
    "sense_full",  # (m,) int32: each layout row's DAQP state between solves
    "sense_c",  # (m,) int32: DAQP's own state array (the workspace points at it), packed
    "lam_c",  # (m,) DAQP's multipliers, packed (the result struct points at it)
    "lam",  # (m,) the multipliers by layout index
)


def _make_proxy() -> None:
    structref.define_proxy(DaqpPack, DaqpPackType, list(FIELDS))


_make_proxy()


@njit(cache=True)
def new_daqp_pack(*fields):  # type: ignore[no-untyped-def]
    """A DaqpPack of ``fields`` (in FIELDS order), by a cached compiled constructor."""
    return DaqpPack(*borrow_all(fields))


@njit(cache=True)
def idle_state(s: int) -> int:
    """What a row's state becomes while its slot holds no row: DAQP's ZERO_ROW_SENSE(ZERO_ROW_MARK(s))
    after daqp_normalize_M's release of an equality it found from the bounds."""
    if s & AUTO_EQUALITY:
        s &= ~(ACTIVE | IMMUTABLE)
    return s & (ACTIVE | LOWER | IMMUTABLE | SOFT)


@njit(cache=True)
def pack(dq, pad: bool) -> int:  # type: ignore[no-untyped-def]
    """The layout's rows with a finite bound to the front of the packed arrays, their states into
    DAQP's, and the problem's m; with ``pad`` (the set-up: ``sense_full`` holds the layout's states)
    the simple bounds' states reset too, and the rest filled with empty rows up to the layout's size,
    m the layout's. Returns the number of packed general rows."""
    rows, bu, bl = dq.rows, dq.bu, dq.bl
    rows_c, bu_c, bl_c, idx, sf, sc = dq.rows_c, dq.bu_c, dq.bl_c, dq.idx, dq.sense_full, dq.sense_c
    mg, nv = rows.shape[0], rows.shape[1]
    ms = bu.shape[0] - mg
    for j in range(ms):  # the simple bounds stay in place (their states too, but at the set-up)
        bu_c[j], bl_c[j] = bu[j], bl[j]
        if pad:
            sc[j] = sf[j]
    cnt = 0
    for i in range(mg):
        j = ms + i
        if bl[j] > -np.inf or bu[j] < np.inf:
            for c in range(nv):
                rows_c[cnt, c] = rows[i, c]
            bu_c[ms + cnt], bl_c[ms + cnt] = bu[j], bl[j]
            sc[ms + cnt] = sf[j]
            idx[cnt] = i
            cnt += 1
        else:
            sf[j] = idle_state(sf[j])
    m = ms + cnt
    if pad:
        for p in range(cnt, mg):
            for c in range(nv):
                rows_c[p, c] = 0.0
            bu_c[ms + p], bl_c[ms + p] = np.inf, -np.inf
            sc[ms + p] = 0
        m = ms + mg
    dq.m_view[0] = m
    return cnt


@njit(cache=True)
def unpack(dq, cnt: int) -> None:  # type: ignore[no-untyped-def]
    """DAQP's states and multipliers of the packed rows back by layout index (λ 0 for the rest)."""
    sf, sc, idx, lam, lam_c = dq.sense_full, dq.sense_c, dq.idx, dq.lam, dq.lam_c
    ms = dq.bu.shape[0] - dq.rows.shape[0]
    for j in range(ms):
        lam[j] = lam_c[j]
    for j in range(ms, lam.shape[0]):
        lam[j] = 0.0
    for p in range(cnt):
        sf[ms + idx[p]] = sc[ms + p]
        lam[ms + idx[p]] = lam_c[ms + p]

