"""proxsuite fast path: one dense ProxQP problem object reused across ticks, explicitly warm-started.

Bounds on x are passed as identity rows of C rather than proxsuite's ``box_constraints``; and the
warm start passes the previous (x, y, z) explicitly (``InitialGuess.WARM_START``): with proxsuite
0.8's ``WARM_START_WITH_PREVIOUS_RESULT``, an update that changes only the bounds was seen to
return the previous solution after 0 iterations, i.e. a wrong answer.

The dense backend is the primal-dual LDLᵀ: proxsuite's automatic choice (the primal one, for more
rows than variables) took twice the iterations and time on this package's QPs (Panda canopy:
median 12 → 6 iterations, ~140 → ~60 µs per solve; same solutions to the 1e-9 tolerance).
"""

from __future__ import annotations

import time
from collections import deque
from typing import Any

import numpy as np
import proxsuite

from qpctl.errors import ConfigError
from qpctl.qp import Problem, Solution
from qpctl.solvers.base import QPSolver

_STATUS = {
    "PROXQP_SOLVED": "solved",
    "PROXQP_MAX_ITER_REACHED": "max_iter",
    "PROXQP_PRIMAL_INFEASIBLE": "primal_infeasible",
    "PROXQP_SOLVED_CLOSEST_PRIMAL_FEASIBLE": "closest_feasible",
    "PROXQP_DUAL_INFEASIBLE": "dual_infeasible",
    "PROXQP_NOT_RUN": "not_run",
}


class ProxQPSolver(QPSolver):
    name = "proxqp"
    fast_path = True
    INNER_PER_OUTER = 10  # inner iterations per outer one under a time limit (see _solve_within)
    FIRST_CALL_OUTER = 30  # outer iterations of the first call under a time limit (p99 of a tick: ~28)

    def __init__(self, settings: dict[str, Any] | None = None) -> None:
        super().__init__(settings)
        self._qp: Any = None
        self._shape: tuple[int, int, int] | None = None
        self._warm: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        # Estimate of one inner iteration's wall time [µs], a call's overhead included: 1.5 × the
        # median of the last measurements (a preempted call does not starve the ticks after it).
        self.us_per_iter = 10.0
        self._recent: deque[float] = deque(maxlen=15)
        self._max_iter, self._max_iter_in = 10000, 1500  # the configured caps (set with the settings)

    def reset(self) -> None:
        self._qp, self._shape, self._warm = None, None, None

    def _apply_settings(self, qp: Any) -> None:
        for key, val in self.settings.items():
            if not hasattr(qp.settings, key):
                raise ConfigError(f"proxqp has no setting {key!r}", key=f"controller.solver_settings.{key}")
            setattr(qp.settings, key, val)
        qp.settings.initial_guess = proxsuite.proxqp.InitialGuess.WARM_START
        self._max_iter, self._max_iter_in = int(qp.settings.max_iter), int(qp.settings.max_iter_in)

    def solve(self, problem: Problem) -> Solution:
        start = time.perf_counter()
        nv = problem.n_var
        shape = (nv, problem.A.shape[0], problem.C.shape[0] + nv)
        if self._shape != shape:  # [C; I] and its bounds are filled in place from then on
            self._C, self._lo, self._hi = np.zeros((shape[2], nv)), np.empty(shape[2]), np.empty(shape[2])
            self._C[problem.C.shape[0]:] = np.eye(nv)
        n_in = problem.C.shape[0]
        C, lo, hi = self._C, self._lo, self._hi
        C[:n_in] = problem.C
        lo[:n_in], lo[n_in:] = problem.l, problem.lb
        hi[:n_in], hi[n_in:] = problem.u, problem.ub
        if self._qp is None or self._shape != shape:
            self._qp = proxsuite.proxqp.dense.QP(*shape, False, proxsuite.proxqp.dense.HessianType.Dense,
                                                 proxsuite.proxqp.dense.DenseBackend.PrimalDualLDLT)
            self._apply_settings(self._qp)
            self._qp.init(problem.P, problem.c, problem.A, problem.b, C, lo, hi)
            self._shape, self._warm = shape, None
        else:
            self._qp.update(problem.P, problem.c, problem.A, problem.b, C, lo, hi)
        if self.time_limit_us is None:
            self._qp.settings.max_iter, self._qp.settings.max_iter_in = self._max_iter, self._max_iter_in
            self._first_call(nv, shape)
            res = self._qp.results
            status, iters = _STATUS.get(res.info.status.name, res.info.status.name), int(res.info.iter)
        else:
            status, iters = self._solve_within(nv, shape, start + self.time_limit_us * 1e-6)
            res = self._qp.results
        x = np.array(res.x)
        found = status == "solved" and bool(np.isfinite(x).all())
        self._warm = (x, np.array(res.y), np.array(res.z)) if found else None
        return Solution(found, x if found else np.zeros(nv), status, iters,
                        (time.perf_counter() - start) * 1e6, self.name)

    def _first_call(self, nv: int, shape: tuple[int, int, int]) -> None:
        self._qp.settings.initial_guess = proxsuite.proxqp.InitialGuess.WARM_START
        if self._warm is None:
            self._qp.solve(np.zeros(nv), np.zeros(shape[1]), np.zeros(shape[2]))
        else:
            self._qp.solve(*self._warm)

    def _solve_within(self, nv: int, shape: tuple[int, int, int], deadline: float) -> tuple[str, int]:
        """Solve in calls whose worst case fits the time left to ``deadline`` [perf_counter s];
        returns (status, inner iterations).

        proxsuite has no time limit and nests its caps (``max_iter`` outer iterations of up to
        ``max_iter_in`` inner ones): a well-posed tick needs 1 to 3 inner iterations per outer one,
        an infeasible one stalls at the full 1500 per outer one (seconds per tick). The time left buys
        K = (time left) / us_per_iter inner iterations; a call spends them as at most INNER_PER_OUTER
        inner iterations per outer one and K / INNER_PER_OUTER outer ones, so its worst case is K.
        The first call stops after FIRST_CALL_OUTER outer iterations (enough for 99 % of ticks): if
        its inner loops ran to their cap, the tick is stalled (infeasible) and reported at once as
        "stalled" — an inner iteration then costs 2–4× a normal one, so waiting for the budget to run
        out would overrun it; otherwise the solve resumes from its (x, y, z) with what time is left,
        sized by the larger of the running estimate and what this tick's calls cost per iteration
        (a slow tick does not get a second oversized call).
        """
        inner_cap = min(self._max_iter_in, self.INNER_PER_OUTER)
        outer_done = iters = 0
        per_iter = self.us_per_iter  # within this tick: never below what its own calls cost
        while True:
            budget = int((deadline - time.perf_counter()) * 1e6 / per_iter)
            outer = min(self._max_iter - outer_done, budget // inner_cap)
            if outer_done == 0:
                outer = min(outer, self.FIRST_CALL_OUTER)
            if outer < 1:
                return ("time_limit" if outer_done < self._max_iter else "max_iter"), iters
            self._qp.settings.max_iter, self._qp.settings.max_iter_in = outer, inner_cap
            t0 = time.perf_counter()
            if outer_done == 0:
                self._first_call(nv, shape)
            else:
                res = self._qp.results
                self._qp.solve(np.array(res.x), np.array(res.y), np.array(res.z))
            info = self._qp.results.info
            n_in, n_out = int(info.iter), max(int(info.iter_ext), 1)
            if n_in >= 1:
                per = (time.perf_counter() - t0) * 1e6 / n_in
                per_iter = max(per_iter, per)
                if n_in >= 5:
                    self._recent.append(per)
                    self.us_per_iter = float(np.clip(1.5 * np.median(self._recent), 0.5, 1e4))
            iters += n_in
            outer_done += n_out
            status = _STATUS.get(info.status.name, info.status.name)
            if status != "max_iter" or outer_done >= self._max_iter:
                return status, iters
            if 2 * n_in > inner_cap * n_out:  # the inner loops run to their cap: stalled, not converging
                return "stalled", iters
