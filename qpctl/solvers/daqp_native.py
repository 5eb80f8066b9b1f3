"""DAQP's C API called from the compiled tick: no Python between the QP's rows and its solution.

``daqp.Model`` (the Python wrapper) costs 5–7 µs a tick around 1–4 µs of DAQP's own work: it wraps
five arrays in memoryviews on every ``update`` and builds a dict and two array copies on every
``solve``. :class:`NativeDAQP` instead sets DAQP's workspace up once (through ``ctypes``) on the
very arrays the tick's kernels write (:class:`qpctl.tick.QPBuffers`), and the kernel
:func:`qpctl.kernels.solve.qp_tick_native` calls ``daqp_update_ldp`` and ``daqp_solve`` itself
(:mod:`qpctl.kernels.daqp`); their symbols come from the ``daqp`` extension module, which exports
DAQP's C API.

The structs passed in (``DAQPProblem``, ``DAQPResult``, ``DAQPSettings``) follow DAQP's
``include/types.h`` and ``include/api.h``; the workspace (``DAQPWorkspace``) is never read here,
only allocated (:data:`WORK_BYTES`, several times its size) and handed to DAQP, except for its
settings pointer, which is found by where ``allocate_daqp_settings`` writes it. This path is used
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

CHECKED_VERSIONS = ("0.11.0",)
WORK_BYTES = 1 << 14  # DAQPWorkspace is ~300 bytes; its arrays are DAQP's own (malloc)

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
        self._arrays = (H, f, rows, bu, bl, sense)  # kept alive: DAQP holds their addresses
        self.problem = _Problem(nv, m, nv, _ptr(H), _ptr(f), _ptr(rows), _ptr(bu), _ptr(bl), _ptr(sense, _ip),
                                None, 0, 0)
        self.work = np.zeros(WORK_BYTES, np.uint8)
        self.x, self.lam = np.zeros(nv), np.zeros(m)
        self.result = _Result(_ptr(self.x), _ptr(self.lam), 0.0, 0.0, 0, 0, 0, 0.0, 0.0)
        raw = (C.c_char * C.sizeof(_Result)).from_address(C.addressof(self.result))
        assert _Result.iter.offset == _Result.exitflag.offset + 4
        self.flag = np.frombuffer(raw, np.int32, 2, _Result.exitflag.offset)  # type: ignore[call-overload]  # [exit flag, iterations]
        self.addresses = (int(self.work.ctypes.data), C.addressof(self.problem), C.addressof(self.result))
        # what qpctl.kernels.solve.qp_tick_native takes after the workspace (and before the tolerance)
        self.kernel_args = (H, f, rows, bu, bl, *self.addresses, self.flag, self.x)
        self.settings = dict(settings or {})
        self.ready = False
        self._time_limit = 0.0

    def setup(self) -> int:
        """(Re)build DAQP's workspace from the arrays' current QP (a cold start); DAQP's exit flag
        (negative: the QP could not be set up, e.g. H not positive definite)."""
        self.free()
        work = self.work.ctypes.data
        self.lib.allocate_daqp_settings(work)
        s = self._settings_struct()
        for key, val in self.settings.items():
            setattr(s, key, val)
        s.time_limit = self._time_limit
        flag = int(self.lib.setup_daqp(C.addressof(self.problem), work, None))
        self.ready = flag >= 0
        if not self.ready:  # setup_daqp freed its settings: a clean, zeroed workspace again
            self.work[:] = 0
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
        if not native.ready and native.setup() < 0:
            return False
        flag = native_solve(*native.addresses, native.flag)
        x, _fval, ref_flag, _info = daqp.solve(H, f, rows, bu, bl, sense.copy())
        if (flag > 0) != (ref_flag > 0) or (flag > 0 and not np.allclose(native.x, x, rtol=1e-9, atol=1e-12)):
            return False
        if trial == 10:
            native.setup()  # a cold start mid-way, as after a failed tick
    native.free()
    return True
