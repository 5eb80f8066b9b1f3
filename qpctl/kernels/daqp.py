"""Stage 6 of the tick, the solve: DAQP's C API as the kernels see it.

``daqp_update_ldp`` and ``daqp_solve`` come from the ``daqp`` extension module, which exports DAQP's C
API; :class:`qpctl.solvers.daqp_native.NativeDAQP` loads its symbols (so numba can link them), sets
a workspace up once on the QP's own arrays and checks this path against ``daqp.solve`` before it is
used. Pointers are passed as integers (the same registers on LP64 ABIs). DAQP sees only the rows
that can bind (:mod:`qpctl.kernels.daqp_pack`).
"""

from __future__ import annotations

from typing import Any

from numba import njit, types

from qpctl.kernels.daqp_pack import pack, unpack

UPDATE_ALL = 1 | 2 | 4 | 8  # DAQP_UPDATE_Rinv | _M | _v | _d: new H, A, f and bounds, same working set

update_ldp: Any = types.ExternalFunction("daqp_update_ldp", types.intc(types.intc, types.intp, types.intp))
daqp_solve: Any = types.ExternalFunction("daqp_solve", types.void(types.intp, types.intp))


@njit(cache=True)
def native_solve(dq) -> int:  # type: ignore[no-untyped-def]
    """DAQP's update and solve on a workspace set up by :class:`qpctl.solvers.daqp_native.NativeDAQP`
    (``dq``, its :class:`~qpctl.kernels.daqp_pack.DaqpPack`; the layout's arrays changed in place), on
    the layout's rows with a finite bound: DAQP's exit flag (> 0 solved); x in the result's array, the
    multipliers by layout index in ``dq.lam``."""
    cnt = pack(dq, False)
    update_ldp(UPDATE_ALL, dq.work, dq.problem)
    daqp_solve(dq.result, dq.work)
    unpack(dq, cnt)
    return dq.flag[0]
