"""OSQP fast path: set up once with a fixed sparsity pattern, ``update`` each tick, warm-started, polished.

The pattern covers every entry of the equality and inequality blocks (zeros kept as explicit
entries) plus an identity block for the bounds, so the matrices' values change but never their
structure; the problem is set up again only if the QP's shape changes.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import osqp
import scipy.sparse as sp

from qpctl.errors import ConfigError
from qpctl.qp import Problem, Solution
from qpctl.solvers.base import QPSolver

NO_TIME_LIMIT_S = 1e10  # OSQP's default time_limit [s] (it must be positive: this is "none")


def _dense_pattern_csc(rows: int, cols: int) -> sp.csc_matrix:
    """A CSC matrix with every entry structurally present (data in column-major order)."""
    indptr = np.arange(0, rows * cols + 1, rows)
    indices = np.tile(np.arange(rows), cols)
    return sp.csc_matrix((np.ones(rows * cols), indices, indptr), shape=(rows, cols))


class OSQPSolver(QPSolver):
    name = "osqp"
    fast_path = True

    def __init__(self, settings: dict[str, Any] | None = None) -> None:
        super().__init__(settings)
        self._solver: Any = None
        self._shape: tuple[int, int, int] | None = None
        self._time_limit_s = float(self.settings.get("time_limit", NO_TIME_LIMIT_S))  # in force [s]

    def reset(self) -> None:
        self._solver, self._shape = None, None
        self._time_limit_s = float(self.settings.get("time_limit", NO_TIME_LIMIT_S))

    def _setup_pattern(self, nv: int, rows: int) -> None:
        self._P = sp.triu(_dense_pattern_csc(nv, nv), format="csc")
        self._P.sort_indices()
        # upper triangle in CSC order: column j holds rows 0..j
        self._p_rows = np.concatenate([np.arange(j + 1) for j in range(nv)])
        self._p_cols = np.concatenate([np.full(j + 1, j) for j in range(nv)])
        self._A = sp.vstack([_dense_pattern_csc(rows, nv), sp.identity(nv, format="csc")], format="csc")
        self._A.sort_indices()

    def _values(self, problem: Problem) -> tuple[np.ndarray, np.ndarray]:
        Pvals = problem.P[self._p_rows, self._p_cols]
        # column j of [A; C; I] holds the dense block's column j, then the identity's 1
        top = np.vstack([problem.A, problem.C, np.ones((1, problem.n_var))])
        return Pvals, top.ravel(order="F")

    def solve(self, problem: Problem) -> Solution:
        start = time.perf_counter()
        nv = problem.n_var
        lo = np.concatenate([problem.b, problem.l, problem.lb])
        hi = np.concatenate([problem.b, problem.u, problem.ub])
        shape = (nv, problem.A.shape[0], problem.C.shape[0])
        if self._solver is None or self._shape != shape:
            self._setup_pattern(nv, shape[1] + shape[2])
            Pvals, Avals = self._values(problem)
            P, A = self._P.copy(), self._A.copy()
            P.data[:] = Pvals
            A.data[:] = Avals
            self._solver = osqp.OSQP()
            try:
                self._solver.setup(P, problem.c, A, lo, hi, verbose=False, warm_starting=True, **self.settings)
            except (TypeError, ValueError) as exc:
                raise ConfigError(f"osqp rejected the settings {self.settings}: {exc}",
                                  key="controller.solver_settings") from None
            self._shape = shape
        else:
            Pvals, Avals = self._values(problem)
            self._solver.update(q=problem.c, l=lo, u=hi, Px=Pvals, Ax=Avals)
        limit_s = float(self.settings.get("time_limit", NO_TIME_LIMIT_S))
        if self.time_limit_us is not None:
            limit_s = min(limit_s, (self.time_limit_us - (time.perf_counter() - start) * 1e6) * 1e-6)
            if limit_s <= 0:
                return Solution(False, np.zeros(nv), "time_limit", 0, (time.perf_counter() - start) * 1e6,
                                self.name)
        if limit_s != self._time_limit_s:
            self._solver.update_settings(time_limit=limit_s)
            self._time_limit_s = limit_s
        res = self._solver.solve(raise_error=False)
        status = str(res.info.status)
        if status == "run time limit reached":
            status = "time_limit"
        x = np.asarray(res.x, float) if res.x is not None else np.full(nv, np.nan)
        ok = status in ("solved", "solved inaccurate") and bool(np.isfinite(x).all())
        return Solution(ok, x if ok else np.zeros(nv), status.replace(" ", "_"), int(res.info.iter),
                        (time.perf_counter() - start) * 1e6, self.name)
