"""proxsuite fast path: one dense ProxQP problem object reused across ticks, explicitly warm-started.

Bounds on x are passed as identity rows of C rather than proxsuite's ``box_constraints``; and the
warm start passes the previous (x, y, z) explicitly (``InitialGuess.WARM_START``): with proxsuite
0.8's ``WARM_START_WITH_PREVIOUS_RESULT``, an update that changes only the bounds was seen to
return the previous solution after 0 iterations, i.e. a wrong answer.
"""

from __future__ import annotations

import time
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
    INNER_PER_OUTER = 20  # inner iterations per outer one under a time limit (see _iteration_caps)

    def __init__(self, settings: dict[str, Any] | None = None) -> None:
        super().__init__(settings)
        self._qp: Any = None
        self._shape: tuple[int, int, int] | None = None
        self._warm: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        # Running estimate of one inner iteration's wall time [µs], the solve call's overhead
        # included (so on the safe side); see _iteration_caps.
        self.us_per_iter = 10.0
        self._max_iter, self._max_iter_in = 10000, 1500  # the configured caps (set with the settings)

    def _iteration_caps(self, elapsed_us: float) -> tuple[int, int, bool]:
        """(max_iter, max_iter_in, whether the time limit lowered them) for this solve.

        proxsuite has no time limit, and its iteration caps are nested: ``max_iter`` outer iterations
        of at most ``max_iter_in`` inner ones each. A well-posed tick needs about 3 inner iterations
        per outer one; an infeasible one can take the full 1500 per outer iteration (seconds). So the
        time left buys K = (time left) / us_per_iter inner iterations, spent as at most
        INNER_PER_OUTER inner iterations per outer one and K / INNER_PER_OUTER outer ones: the
        product, the worst case, stays within the limit.
        """
        if self.time_limit_us is None:
            return self._max_iter, self._max_iter_in, False
        total = int((self.time_limit_us - elapsed_us) / self.us_per_iter)
        inner = min(self._max_iter_in, self.INNER_PER_OUTER)
        outer = total // inner
        if outer >= self._max_iter and inner == self._max_iter_in:
            return self._max_iter, self._max_iter_in, False
        return min(outer, self._max_iter), inner, True

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
        C = np.vstack([problem.C, np.eye(nv)])
        lo = np.concatenate([problem.l, problem.lb])
        hi = np.concatenate([problem.u, problem.ub])
        shape = (nv, problem.A.shape[0], C.shape[0])
        if self._qp is None or self._shape != shape:
            self._qp = proxsuite.proxqp.dense.QP(*shape)
            self._apply_settings(self._qp)
            self._qp.init(problem.P, problem.c, problem.A, problem.b, C, lo, hi)
            self._shape, self._warm = shape, None
        else:
            self._qp.update(problem.P, problem.c, problem.A, problem.b, C, lo, hi)
        t_solve = time.perf_counter()
        max_iter, max_iter_in, capped = self._iteration_caps((t_solve - start) * 1e6)
        if max_iter < 1:  # the time limit is spent before the first iteration
            return Solution(False, np.zeros(nv), "time_limit", 0, (t_solve - start) * 1e6, self.name)
        self._qp.settings.max_iter, self._qp.settings.max_iter_in = max_iter, max_iter_in
        if self._warm is None:
            self._qp.solve(np.zeros(nv), np.zeros(shape[1]), np.zeros(shape[2]))
        else:
            self._qp.solve(*self._warm)
        res = self._qp.results
        if res.info.iter >= 5:
            per = (time.perf_counter() - t_solve) * 1e6 / int(res.info.iter)
            self.us_per_iter = float(np.clip(0.7 * self.us_per_iter + 0.3 * per, 0.5, 1e4))
        status = _STATUS.get(res.info.status.name, res.info.status.name)
        if capped and status == "max_iter":
            status = "time_limit"
        x = np.array(res.x)
        found = status == "solved" and bool(np.all(np.isfinite(x)))
        self._warm = (x, np.array(res.y), np.array(res.z)) if found else None
        return Solution(found, x if found else np.zeros(nv), status, int(res.info.iter),
                        (time.perf_counter() - start) * 1e6, self.name)
