"""Solver interface, registry and the generic qpsolvers path."""

from __future__ import annotations

import importlib
import time
import warnings
from abc import ABC, abstractmethod
from typing import Any

import numpy as np

from qpctl.errors import ConfigError, UnknownSolverError
from qpctl.qp import Problem, Solution

# Settings applied unless configuration says otherwise: tight enough for the exact-reduction
# guarantee (the QP equals the paper law to 1e-6 relative when no inequality is active).
DEFAULT_SETTINGS: dict[str, dict[str, Any]] = {
    "proxqp": {"eps_abs": 1e-9, "eps_rel": 0.0, "max_iter": 1000},
    "osqp": {"eps_abs": 1e-5, "eps_rel": 1e-5, "max_iter": 4000, "polishing": True, "polish_refine_iter": 5},
    "clarabel": {"tol_gap_abs": 1e-9, "tol_gap_rel": 1e-9, "tol_feas": 1e-9},
}

# The registry of fast paths: one module each (qpctl/solvers/<name>_.py, imported when first made, and
# only used when qpsolvers finds the backend installed), one line here — "module:Class", and what it
# does (``qpctl solvers``). First in listings; every other qpsolvers backend takes the generic path.
FAST_PATH_SOLVERS: dict[str, tuple[str, str]] = {
    "daqp": ("qpctl.solvers.daqp_:DAQPSolver", "fast path (called directly, warm-started working set, own time limit)"),
    "proxqp": ("qpctl.solvers.proxqp_:ProxQPSolver", "fast path (problem reused, warm-started primal-dual)"),
    "osqp": ("qpctl.solvers.osqp_:OSQPSolver", "fast path (fixed sparsity, updated, warm-started, polished)"),
}
FAST_PATH_NOTES = {name: note for name, (_, note) in FAST_PATH_SOLVERS.items()}
FAST_PATHS = tuple(FAST_PATH_SOLVERS)
DEFAULT_SOLVER = "daqp"  # the fastest on this package's QPs (README, "Performance"), with its own time limit

# The generic path's backends that take a wall-time limit [s], and the name of that setting.
TIME_LIMIT_SETTING = {"clarabel": "time_limit", "osqp": "time_limit", "highs": "time_limit",
                      "scs": "time_limit_secs"}


class QPSolver(ABC):
    """Solves the stacked :class:`~qpctl.qp.Problem` of a tick."""

    name: str = ""
    fast_path: bool = False
    # Wall-time limit of the next solves [µs] (None: none); the controller sets it from its tick budget.
    time_limit_us: float | None = None

    def __init__(self, settings: dict[str, Any] | None = None) -> None:
        self.settings = dict(DEFAULT_SETTINGS.get(self.name, {}))
        self.settings.update(settings or {})

    @abstractmethod
    def solve(self, problem: Problem) -> Solution:
        """Solve; never raises for a failed solve (``found`` is False and ``status`` says why)."""

    def reset(self) -> None:
        """Drop warm-start data (the problem's shape changed, or a new run starts)."""

    def set_time_limit(self, us: float | None) -> None:
        """Limit the next solves to ``us`` microseconds of wall time (None or inf: no limit).

        Backends with a time limit get it as their setting (osqp, daqp, clarabel, highs, scs); proxqp
        turns it into an iteration cap from its measured cost per iteration; the others (quadprog, ...)
        cannot be stopped, and the controller checks the clock before it tries anything else.
        A solve stopped by the limit reports ``found = False`` and status ``"time_limit"``.
        """
        self.time_limit_us = None if us is None or not np.isfinite(us) else max(float(us), 0.0)


def _installed() -> list[str]:
    import qpsolvers

    return list(qpsolvers.available_solvers)


def available_solvers() -> list[str]:
    """Solver names usable in ``controller.solver`` (fast paths first)."""
    inst = _installed()
    names = [n for n in FAST_PATHS if n in inst]
    names += [n for n in inst if n not in FAST_PATHS]
    return names


def describe_solvers() -> list[str]:
    """One line per installed solver: name and path (what ``qpctl solvers`` prints)."""
    lines = []
    for name in available_solvers():
        path = FAST_PATH_NOTES.get(name, "generic qpsolvers path")
        default = "  (default)" if name == DEFAULT_SOLVER else ""
        lines.append(f"{name:<12} {path}{default}")
    return lines



class GenericSolver(QPSolver):
    """Any qpsolvers backend: rows with two infinite bounds are dropped, double-sided rows split."""

    def __init__(self, backend: str, settings: dict[str, Any] | None = None) -> None:
        self.name = backend
        super().__init__(settings)
        self.backend = backend

    def solve(self, problem: Problem) -> Solution:
        import qpsolvers

        start = time.perf_counter()
        C, lo, hi = problem.C, problem.l, problem.u
        up, dn = np.isfinite(hi), np.isfinite(lo)
        G = np.vstack([C[up], -C[dn]])
        h = np.concatenate([hi[up], -lo[dn]])
        lb = np.where(np.isfinite(problem.lb), problem.lb, -1e20 if self.backend == "quadprog" else -np.inf)
        ub = np.where(np.isfinite(problem.ub), problem.ub, 1e20 if self.backend == "quadprog" else np.inf)
        P, A = problem.P, problem.A
        if self.backend in qpsolvers.sparse_solvers and self.backend not in qpsolvers.dense_solvers:
            # sparse-only backends (clarabel, osqp, ...) get CSC matrices, as qpsolvers would convert them
            # itself, with a warning on every call
            from scipy import sparse

            P, A, G = sparse.csc_matrix(P), sparse.csc_matrix(A), sparse.csc_matrix(G)
        qp = qpsolvers.Problem(P, problem.c, G if G.shape[0] else None, h if h.size else None,
                               A if A.shape[0] else None, problem.b if problem.b.size else None, lb, ub)
        settings = dict(self.settings)
        key = TIME_LIMIT_SETTING.get(self.backend)
        if key and self.time_limit_us is not None:
            left_s = self.time_limit_us * 1e-6 - (time.perf_counter() - start)
            if left_s <= 0:
                return Solution(False, np.zeros(problem.n_var), "time_limit", solver=self.name)
            settings[key] = left_s
        try:
            with warnings.catch_warnings():  # osqp's note that raise_error's default will change
                warnings.simplefilter("ignore", PendingDeprecationWarning)
                sol = qpsolvers.solve_problem(qp, solver=self.backend, **settings)
        except Exception as exc:  # noqa: BLE001 — a backend's own error: reported as a failed solve
            return Solution(False, np.zeros(problem.n_var), f"error: {type(exc).__name__}: {exc}",
                            solve_us=(time.perf_counter() - start) * 1e6, solver=self.name)
        us = (time.perf_counter() - start) * 1e6
        found = bool(sol.found) and sol.x is not None and bool(np.isfinite(sol.x).all())
        iters = 0
        extras = getattr(sol, "extras", {}) or {}
        for key in ("iter", "iterations", "n_iter"):
            if key in extras:
                try:
                    iters = int(extras[key])
                except (TypeError, ValueError):
                    pass
        x = np.asarray(sol.x, float) if found else np.zeros(problem.n_var)
        status = "solved" if found else "failed"
        if not found and self.time_limit_us is not None and us >= self.time_limit_us:
            status = "time_limit"
        return Solution(found, x, status, iters, us, self.name)


def make_solver(name: str, settings: dict[str, Any] | None = None) -> QPSolver:
    """The solver called ``name``; :class:`UnknownSolverError` lists the available ones."""
    if not isinstance(name, str):
        raise ConfigError(f"solver name must be a string, got {name!r}", key="controller.solver")
    inst = _installed()
    force_generic = name.startswith("qpsolvers:")
    base = name.split(":", 1)[1] if force_generic else name
    if base not in inst:
        raise UnknownSolverError(name, available_solvers())
    if not force_generic and base in FAST_PATH_SOLVERS:
        module, _, cls = FAST_PATH_SOLVERS[base][0].partition(":")
        solver: QPSolver = getattr(importlib.import_module(module), cls)(settings)
        return solver
    return GenericSolver(base, settings)
