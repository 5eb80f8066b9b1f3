"""DAQP's C API called from the compiled tick: no Python between the QP's rows and its solution.

``daqp.Model`` (the Python wrapper) costs 5–7 µs a tick around 1–4 µs of DAQP's own work: it wraps
five arrays in memoryviews on every ``update`` and builds a dict and two array copies on every
``solve``. :class:`NativeDAQP` instead sets DAQP's workspace up once (through ``ctypes``) on the
very arrays the tick's kernels write (:class:`qpctl.tick.QPBuffers`), and the kernel
:func:`qpctl.kernels.solve.qp_tick_native` calls ``daqp_update_ldp`` and ``daqp_solve`` itself
(:mod:`qpctl.kernels.daqp`); their symbols come from the ``daqp`` extension module, which exports
DAQP's C API.

The structs passed in (``DAQPProblem``, ``DAQPResult``, ``DAQPSettings``) follow DAQP's
``include/types.h`` and ``include/api.h``; the workspace (``DAQPWorkspace``) is allocated here
(:data:`WORK_BYTES`, several times its size) and handed to DAQP; two of its fields are touched: its
settings pointer, found by where ``allocate_daqp_settings`` writes it, and its constraint-state
pointer (``sense``), pointed at an array of ours after each set-up so that the compiled solve can
keep the states by the layout's row index (:mod:`qpctl.kernels.daqp_pack`; the workspace's n, m and
ms before it are checked every time). This path is used
only with a DAQP version it was checked against (:data:`CHECKED_VERSIONS`) and after a self-test in
the process (:func:`available`: the same solutions as ``daqp.solve`` on random QPs with bounds,
inequalities and equalities); otherwise :class:`~qpctl.solvers.daqp_.DAQPSolver` uses ``daqp.Model``.
"""

from __future__ import annotations

import ctypes as C
import importlib.metadata
from typing import Any

import numpy as np

from qpctl.kernels.daqp import native_solve
from qpctl.kernels.daqp_pack import new_daqp_pack, pack

CHECKED_VERSIONS = ("0.11.0",)
WORK_BYTES = 1 << 14  # DAQPWorkspace is ~300 bytes; its arrays are DAQP's own (malloc)
# DAQPWorkspace's sense pointer (include/types.h: qp, n, m, ms, M, dupper, dlower, Rinv, v, sense), checked
# at every set-up against the n, m and ms it holds at 8, 12 and 16
_SENSE_OFFSET = 64

_dp = C.POINTER(C.c_double)
_ip = C.POINTER(C.c_int)


class _Problem(C.Structure):
    _fields_ = [("n", C.c_int), ("m", C.c_int), ("ms", C.c_int), ("H", _dp), ("f", _dp), ("A", _dp),
                ("bupper", _dp), ("blower", _dp), ("sense", _ip), ("break_points", _ip), ("nh", C.c_int),
                ("problem_type", C.c_int)]


class _Result(C.Structure):
    _fields_ = [("x", _dp), ("lam", _dp), ("fval", C.c_double), ("soft_slack", C.c_double), ("exitflag", C.c_int),
                ("iter", C.c_int), ("nodes", C.c_int), ("solve_time", C.c_double), ("setup_time", C.c_double)]


class _Settings(C.Structure):
    _fields_ = [("primal_tol", C.c_double), ("dual_tol", C.c_double), ("zero_tol", C.c_double),
                ("pivot_tol", C.c_double), ("progress_tol", C.c_double), ("cycle_tol", C.c_int),
                ("iter_limit", C.c_int), ("fval_bound", C.c_double), ("eps_prox", C.c_double),
                ("eta_prox", C.c_double), ("rho_soft", C.c_double), ("rel_subopt", C.c_double),
                ("abs_subopt", C.c_double), ("sing_tol", C.c_double), ("refactor_tol", C.c_double),
                ("time_limit", C.c_double)]


SETTINGS = tuple(str(f[0]) for f in _Settings._fields_)

_lib: Any = None
_available: bool | None = None
_settings_offset: int | None = None


def _library() -> Any:
    """DAQP's shared library (the ``daqp`` extension module), its symbols made visible to numba."""
    global _lib
    if _lib is None:
        import daqp
        import llvmlite.binding as llvm

        llvm.load_library_permanently(daqp.__file__)
        lib = C.CDLL(daqp.__file__)
        lib.setup_daqp.argtypes = [C.c_void_p, C.c_void_p, C.c_void_p]
        lib.setup_daqp.restype = C.c_int
        lib.allocate_daqp_settings.argtypes = [C.c_void_p]
        lib.allocate_daqp_settings.restype = None
        lib.free_daqp_workspace.argtypes = [C.c_void_p]
        lib.free_daqp_workspace.restype = None
        lib.free_daqp_ldp.argtypes = [C.c_void_p]
        lib.free_daqp_ldp.restype = None
        lib.daqp_update_ldp.argtypes = [C.c_int, C.c_void_p, C.c_void_p]
        lib.daqp_update_ldp.restype = C.c_int
        lib.daqp_solve.argtypes = [C.c_void_p, C.c_void_p]
        lib.daqp_solve.restype = None
        _lib = lib
    return _lib


def _ptr(a: np.ndarray, typ: Any = _dp) -> Any:
    return a.ctypes.data_as(typ)


class NativeDAQP:
    """One DAQP workspace, set up on the arrays of one QP layout (DAQP's convention: H (nv, nv),
    f (nv), rows (m − ms, nv), bu, bl, sense (m) with the first ms = nv bounds simple).

    ``settings``: DAQP settings by name (:data:`SETTINGS`). Call :meth:`setup` once the arrays hold
    a tick's QP; the kernel then updates and solves in place, x in :attr:`x`, the exit flag and the
    iteration count in :attr:`flag` (a numpy view of the result struct's two ints).
    """

    def __init__(self, H: np.ndarray, f: np.ndarray, rows: np.ndarray, bu: np.ndarray, bl: np.ndarray,
                 sense: np.ndarray, settings: dict[str, Any] | None = None) -> None:
        self.lib = _library()
        nv, m = H.shape[0], bu.shape[0]
        self.sense0 = sense  # the layout's states (its equalities): a cold start's
        # DAQP reads packed copies of the rows and bounds (qpctl.kernels.daqp_pack); H and f are the layout's
        self.rows_c, self.bu_c, self.bl_c = np.zeros_like(rows), np.zeros(m), np.zeros(m)
        self.sense_c, self.sense_full = np.zeros(m, np.int32), sense.astype(np.int32)
        self.lam_c, self.idx = np.zeros(m), np.zeros(rows.shape[0], np.int64)
        self._arrays = (H, f, rows, bu, bl, sense)  # kept alive: DAQP holds their addresses
        self.problem = _Problem(nv, m, nv, _ptr(H), _ptr(f), _ptr(self.rows_c), _ptr(self.bu_c), _ptr(self.bl_c),
                                _ptr(self.sense_c, _ip), None, 0, 0)
        self.work = np.zeros(WORK_BYTES, np.uint8)
        self.x, self.lam = np.zeros(nv), np.zeros(m)
        self.result = _Result(_ptr(self.x), _ptr(self.lam_c), 0.0, 0.0, 0, 0, 0, 0.0, 0.0)
        raw = (C.c_char * C.sizeof(_Result)).from_address(C.addressof(self.result))
        assert _Result.iter.offset == _Result.exitflag.offset + 4
        self.flag = np.frombuffer(raw, np.int32, 2, _Result.exitflag.offset)  # type: ignore[call-overload]  # [exit flag, iterations]
        raw_p = (C.c_char * C.sizeof(_Problem)).from_address(C.addressof(self.problem))
        self.m_view = np.frombuffer(raw_p, np.int32, 1, _Problem.m.offset)  # type: ignore[call-overload]
        self.addresses = (int(self.work.ctypes.data), C.addressof(self.problem), C.addressof(self.result))
        self.dq = new_daqp_pack(*self.addresses, self.flag, self.m_view, rows, bu, bl, self.rows_c, self.bu_c,
                                self.bl_c, self.idx, self.sense_full, self.sense_c,
                                self.lam_c, self.lam)
        # what qpctl.kernels.solve.qp_tick_native takes after the workspace (and before the tolerance)
        self.kernel_args = (H, f, rows, bu, bl, self.dq, self.x)
        self.settings = dict(settings or {})
        self.ready = False
        self._time_limit = 0.0
        self._daqp_sense = 0  # DAQP's own state array, given back to it before it frees the workspace

    def setup(self) -> int:
        """(Re)build DAQP's workspace from the arrays' current QP (a cold start: the layout's states);
        DAQP's exit flag (negative: the QP could not be set up, e.g. H not positive definite). DAQP
        sees the rows with a finite bound first, padded to the layout's size (so it sizes its arrays
        for every row), and its state array is then this object's ``sense_c``."""
        self.free()
        work = self.work.ctypes.data
        self.lib.allocate_daqp_settings(work)
        s = self._settings_struct()
        for key, val in self.settings.items():
            setattr(s, key, val)
        s.time_limit = self._time_limit
        self.sense_full[:] = self.sense0
        cnt = pack(self.dq, True)
        passed = self.sense_c.copy()
        flag = int(self.lib.setup_daqp(C.addressof(self.problem), work, None))
        self.ready = flag >= 0
        if not self.ready:  # setup_daqp freed its settings: a clean, zeroed workspace again
            self.work[:] = 0
            return flag
        words = self.work[:_SENSE_OFFSET + 8]
        n, m, ms = (int(words[k:k + 4].view(np.int32)[0]) for k in (8, 12, 16))
        own = int(words[_SENSE_OFFSET : _SENSE_OFFSET + 8].view(np.uint64)[0])
        daqp_sense = np.ctypeslib.as_array(C.cast(own, _ip), (m,)) if own else passed
        # each packed row's active and immutable bits as passed (the equalities 5), except where DAQP's
        # set-up marks a row it finds empty (ZERO_ROW) or an equality it finds from the bounds
        got, sent = daqp_sense[ms : ms + cnt], passed[ms : ms + cnt]
        kept = ((got & 2048) == 0) & ((sent != 0) | (self.bu_c[ms : ms + cnt] != self.bl_c[ms : ms + cnt]))
        if (n, m, ms) != (self.problem.n, self.problem.m, self.problem.ms) or not own or \
                not np.array_equal(got[kept] & 5, sent[kept] & 5):
            self.free()
            raise RuntimeError(f"DAQP's workspace is not laid out as DAQPWorkspace of DAQP {CHECKED_VERSIONS}")
        self.sense_c[:] = daqp_sense
        self._daqp_sense = own
        words[_SENSE_OFFSET:].view(np.uint64)[0] = self.sense_c.ctypes.data  # DAQP's states: sense_c
        return flag

    def _settings_struct(self) -> _Settings:
        assert _settings_offset is not None  # found when the native path was checked (available())
        address = int(self.work[_settings_offset : _settings_offset + 8].view(np.uint64)[0])
        return _Settings.from_address(address)

    def set_time_limit(self, seconds: float) -> None:
        """DAQP's own time limit [s] for the next solves (0: none)."""
        if seconds != self._time_limit:
            self._time_limit = seconds
            if self.ready:
                self._settings_struct().time_limit = seconds

    def free(self) -> None:
        if self.ready:
            work = self.work.ctypes.data
            if self._daqp_sense:  # its own state array back, for DAQP to free
                self.work[_SENSE_OFFSET:_SENSE_OFFSET + 8].view(np.uint64)[0] = self._daqp_sense
                self._daqp_sense = 0
            self.lib.free_daqp_workspace(work)  # its settings too
            self.lib.free_daqp_ldp(work)
            self.work[:] = 0
            self.ready = False

    def __del__(self) -> None:
        try:
            self.free()
        except Exception:  # noqa: BLE001, S110 — interpreter shutdown: nothing left to free into
            pass


def _find_settings_offset() -> int | None:
    """Where DAQPWorkspace keeps its settings pointer: the one word ``allocate_daqp_settings`` writes
    into a zeroed workspace, pointing at DAQP's defaults."""
    lib = _library()
    work = np.zeros(WORK_BYTES, np.uint8)
    lib.allocate_daqp_settings(work.ctypes.data)
    words = np.flatnonzero(work.view(np.uint64))
    if words.size != 1:
        return None
    offset = int(words[0]) * 8
    s = _Settings.from_address(int(work.view(np.uint64)[words[0]]))
    ok = s.primal_tol == 1e-6 and s.dual_tol == 1e-12 and s.iter_limit > 0
    lib.free_daqp_workspace(work.ctypes.data)
    return offset if ok else None


def available() -> bool:
    """Whether the native path may be used in this process: a checked DAQP version, the settings
    pointer found, and the same solutions as ``daqp.solve`` on random QPs in the tick's layout."""
    global _available, _settings_offset
    if _available is None:
        _available = False
        try:
            if importlib.metadata.version("daqp") in CHECKED_VERSIONS:
                _settings_offset = _find_settings_offset()
                _available = _settings_offset is not None and _self_test()
        except Exception:  # noqa: BLE001 — anything unexpected: the Python wrapper it is
            _available = False
    return _available


def _self_test() -> bool:
    import daqp

    rng = np.random.default_rng(1)
    nv, n_in, n_eq = 9, 12, 2
    H, f, rows = np.zeros((nv, nv)), np.zeros(nv), np.zeros((n_in + n_eq, nv))
    bu, bl = np.zeros(nv + n_in + n_eq), np.zeros(nv + n_in + n_eq)
    sense = np.zeros(nv + n_in + n_eq, np.int32)
    sense[nv + n_in :] = 5
    native = NativeDAQP(H, f, rows, bu, bl, sense)
    for trial in range(20):
        A = rng.normal(size=(nv, nv))
        H[:] = A @ A.T + nv * np.eye(nv)
        f[:], rows[:] = rng.normal(size=nv), rng.normal(size=rows.shape)
        bu[:nv], bl[:nv] = np.inf, -np.inf
        bu[:3], bl[:3] = 0.3, -0.3
        bu[nv : nv + n_in], bl[nv : nv + n_in] = rng.uniform(0.2, 1.0, n_in), -np.inf
        bu[nv + n_in :] = bl[nv + n_in :] = rng.normal(size=n_eq) * 0.1
        empty = nv + rng.choice(n_in, size=int(rng.integers(0, n_in // 2)), replace=False)  # slots without a row
        rows[empty - nv], bu[empty], bl[empty] = 0.0, np.inf, -np.inf
        if not native.ready and native.setup() < 0:
            return False
        flag = native_solve(native.dq)
        x, _fval, ref_flag, _info = daqp.solve(H, f, rows, bu, bl, sense.copy())
        if (flag > 0) != (ref_flag > 0) or (flag > 0 and not np.allclose(native.x, x, rtol=1e-9, atol=1e-12)):
            return False
        if trial == 10:
            native.setup()  # a cold start mid-way, as after a failed tick
    native.free()
    return True
