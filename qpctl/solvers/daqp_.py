"""DAQP fast path: DAQP's own ``solve`` called directly, its arrays kept from tick to tick.

DAQP (a dual active-set solver) suits this package's QPs: a dozen variables, a few dozen rows, most
of them inactive. Called directly it took 25–45 µs a tick on the Panda canopy, against ~130 µs
through qpsolvers (which rebuilds and checks every array on every call) and ~100–200 µs for
proxsuite's augmented-Lagrangian iterations; the solutions agree with quadprog's to 3e-7.

Layout (DAQP's convention): the first ``n_var`` entries of the bounds are simple bounds on x; then
the inequality rows l ≤ C x ≤ u; then the equality rows A x = b (sense 5). Infinite bounds are
passed as they are (DAQP treats any bound beyond ±1e30 as absent). Warm start: the previous tick's
multipliers (``dual_start``) give DAQP its initial working set, so a tick whose active set did not
change takes one or two iterations. A time limit is passed as DAQP's own ``time_limit`` [s].

The compiled tick (:mod:`qpctl.tick`) writes its QP straight into arrays in this layout. Where the
native path is available (:mod:`qpctl.solvers.daqp_native`: a checked DAQP version, self-tested in
the process) its kernel calls DAQP's C API on them (:meth:`DAQPSolver.native`); otherwise
:meth:`DAQPSolver.solve_buffers` keeps one ``daqp.Model`` and ``update``s it every tick. Either way
DAQP's workspace is set up once and the working set of the previous solve is the warm start; a
failed solve starts the next tick cold.
"""

from __future__ import annotations

import time
from typing import Any

import daqp
import numpy as np

from qpctl.errors import ConfigError
from qpctl.qp import Problem, Solution
from qpctl.solvers import daqp_native
from qpctl.solvers.base import QPSolver
from qpctl.solvers.daqp_native import NativeDAQP

_SENSE_EQ = 5
STATUS = {1: "solved", 2: "solved", -1: "primal_infeasible", -2: "cycling", -3: "unbounded", -4: "max_iter",
           -5: "nonconvex", -6: "overdetermined_initial", -7: "time_limit", -8: "unsupported"}
_SETTINGS = ("primal_tol", "dual_tol", "zero_tol", "pivot_tol", "progress_tol", "cycle_tol", "iter_limit",
             "fval_bound", "eps_prox", "eta_prox", "rho_soft", "rel_subopt", "abs_subopt", "sing_tol",
             "refactor_tol", "time_limit", "eq_reduction")


class DAQPSolver(QPSolver):
    name = "daqp"
    fast_path = True

    def __init__(self, settings: dict[str, Any] | None = None) -> None:
        super().__init__(settings)
        for key in self.settings:
            if key not in _SETTINGS:
                raise ConfigError(f"daqp has no setting {key!r}; settings: {', '.join(_SETTINGS)}",
                                  key=f"controller.solver_settings.{key}")
        self._shape: tuple[int, int, int] | None = None
        self._lam: np.ndarray | None = None
        self._natives: dict[int, NativeDAQP] = {}
        self._native_ok: bool | None = None
        self.reset()

    def reset(self) -> None:
        self._shape, self._lam = None, None
        for nat in getattr(self, "_natives", {}).values():
            nat.free()  # the next tick sets DAQP up afresh: a cold start
        self._model: Any = None
        self._model_key: np.ndarray | None = None  # the H the model was set up on
        self._model_limit = 0.0

    def native(self, buffers: Any) -> NativeDAQP | None:
        """DAQP's C API set up on these QP buffers (:class:`qpctl.tick.QPBuffers`), or None where the
        native path is not available (another DAQP version, or settings its C struct lacks)."""
        nat = self._natives.get(id(buffers))
        if nat is None:
            if self._native_ok is None:
                self._native_ok = daqp_native.available() and all(k in daqp_native.SETTINGS for k in self.settings)
            if not self._native_ok:
                return None
            nat = NativeDAQP(buffers.H, buffers.f, buffers.rows, buffers.bu, buffers.bl, buffers.sense,
                             self.settings)
            self._natives[id(buffers)] = nat
        return nat

    def solve_buffers(self, H: np.ndarray, f: np.ndarray, rows: np.ndarray, bu: np.ndarray, bl: np.ndarray,
                      sense: np.ndarray) -> tuple[np.ndarray | None, str, int]:
        """Solve the QP held in DAQP's layout by these arrays (x, bounds, rows — see the module
        docstring) on a persistent ``daqp.Model`` set up on these very arrays: (x or None, status,
        iterations). The model's working set is the next tick's warm start."""
        limit = 0.0 if self.time_limit_us is None else max(self.time_limit_us * 1e-6, 1e-9)
        model = self._model
        try:
            if model is None or self._model_key is not H:
                model = daqp.Model()
                flag, _ = model.setup(H, f, rows, bu, bl, sense)
                if flag < 0:
                    self._model = None
                    return None, STATUS.get(int(flag), f"exitflag {int(flag)}"), 0
                model.settings = {**self.settings, "time_limit": limit}
                self._model, self._model_key, self._model_limit = model, H, limit
            else:
                model.update(H, f, rows, bu, bl)
                if limit != self._model_limit:
                    model.settings = {"time_limit": limit}
                    self._model_limit = limit
            x, _fval, flag, info = model.solve()
        except Exception as exc:  # noqa: BLE001 — DAQP's own error: a failed solve
            self._model = None
            return None, f"error: {type(exc).__name__}: {exc}", 0
        if flag > 0:  # 1: optimal, 2: optimal with soft constraints
            return x, "solved", info["iterations"]
        self._model = None  # the next tick starts from a fresh workspace, not a failed working set
        return None, STATUS.get(int(flag), f"exitflag {int(flag)}"), int(info.get("iterations", 0))

    def solve(self, problem: Problem) -> Solution:
        start = time.perf_counter()
        nv, n_in, n_eq = problem.n_var, problem.C.shape[0], problem.A.shape[0]
        shape = (nv, n_in, n_eq)
        if self._shape != shape:
            self._rows = np.empty((n_in + n_eq, nv))
            self._upper, self._lower = np.empty(nv + n_in + n_eq), np.empty(nv + n_in + n_eq)
            self._sense = np.zeros(nv + n_in + n_eq, dtype=np.int32)
            self._sense[nv + n_in:] = _SENSE_EQ
            self._shape, self._lam = shape, None
        rows, up, lo = self._rows, self._upper, self._lower
        rows[:n_in], rows[n_in:] = problem.C, problem.A
        up[:nv], lo[:nv] = problem.ub, problem.lb
        up[nv:nv + n_in], lo[nv:nv + n_in] = problem.u, problem.l
        up[nv + n_in:] = lo[nv + n_in:] = problem.b
        settings = self.settings
        if self.time_limit_us is not None:
            left_s = self.time_limit_us * 1e-6 - (time.perf_counter() - start)
            if left_s <= 0:
                return Solution(False, np.zeros(nv), "time_limit", solver=self.name)
            settings = {**settings, "time_limit": left_s}
        try:
            x, _fval, flag, info = daqp.solve(problem.P, problem.c, rows, up, lo, self._sense.copy(),
                                              dual_start=self._lam, **settings)
        except Exception as exc:  # noqa: BLE001 — DAQP's own error (a bad setting value, say): a failed solve
            self._lam = None
            return Solution(False, np.zeros(nv), f"error: {type(exc).__name__}: {exc}",
                            solve_us=(time.perf_counter() - start) * 1e6, solver=self.name)
        status = STATUS.get(int(flag), f"exitflag {int(flag)}")
        x = np.asarray(x, float)
        found = status == "solved" and bool(np.isfinite(x).all())
        self._lam = np.asarray(info["lam"], float).copy() if found else None
        return Solution(found, x if found else np.zeros(nv), status, int(info.get("iterations", 0)),
                        (time.perf_counter() - start) * 1e6, self.name)
