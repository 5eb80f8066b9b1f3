"""What a solve produced: a :class:`SolveStatus` and a typed, immutable :class:`SolveOutcome`.

Every solver reports failure in its own words (DAQP's exit flags, proxqp's and osqp's status
names, qpsolvers' ``found``) and the controller adds its own (an answer that breaks a hard row,
non-finite data, the tick budget spent). :func:`solve_status` maps each word to one
:class:`SolveStatus`; the word itself is kept (``SolveOutcome.word``, ``info["status"]``) for
diagnostics. :func:`checked_solve` is one solve within a tick's deadline, its answer checked
against the hard rows in our units.
"""

from __future__ import annotations

import enum
import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from qpctl.errors import ConfigError
from qpctl.qp import Problem, Solution

if TYPE_CHECKING:
    from qpctl.solvers.base import QPSolver

SOLUTION_RTOL = 1e-4  # a solution is accepted when every hard row holds to this, relative to 1 + |its bound|


class SolveStatus(str, enum.Enum):
    """How a tick's QP solve ended (a ``str``, so it serialises as its value)."""

    SOLVED = "solved"  # solved, and the answer holds every hard row (SOLUTION_RTOL)
    INFEASIBLE = "infeasible"  # the hard rows cannot all hold (primal infeasible)
    UNBOUNDED = "unbounded"  # dual infeasible (not expected: the cost is positive definite)
    MAX_ITERATIONS = "max_iterations"  # the solver's iteration limit
    TIME_LIMIT = "time_limit"  # the tick budget (or the solver's own time limit) ran out
    NUMERICAL = "numerical"  # the solver broke down (cycling, non-convex, a set-up it could not do)
    INACCURATE = "inaccurate"  # "solved", but the answer breaks a hard row in our units
    NON_FINITE = "non_finite"  # NaN/inf in the problem's data or in the answer
    PENALTY_INEXACT = "penalty_inexact"  # the hard task's answer is not the relaxed QP's (task_relaxation)
    ERROR = "error"  # the backend raised
    UNKNOWN = "unknown"  # a word no table below knows

    @property
    def found(self) -> bool:
        return self is SolveStatus.SOLVED


# Every solver's word (after its own module's translation: qpctl.solvers.*) → status.
_WORDS: dict[str, SolveStatus] = {
    # ours (the controller, the generic qpsolvers path, the compiled checks)
    "solved": SolveStatus.SOLVED,
    "failed": SolveStatus.UNKNOWN,  # qpsolvers: found is False, no reason given
    "time_limit": SolveStatus.TIME_LIMIT,
    "inaccurate": SolveStatus.INACCURATE,
    "nonfinite_problem": SolveStatus.NON_FINITE,
    "nonfinite_solution": SolveStatus.NON_FINITE,
    "penalty_inexact": SolveStatus.PENALTY_INEXACT,
    "infeasible": SolveStatus.INFEASIBLE,
    # DAQP exit flags (qpctl.solvers.daqp_.STATUS)
    "primal_infeasible": SolveStatus.INFEASIBLE,
    "cycling": SolveStatus.NUMERICAL,
    "unbounded": SolveStatus.UNBOUNDED,
    "max_iter": SolveStatus.MAX_ITERATIONS,  # proxqp too
    "nonconvex": SolveStatus.NUMERICAL,
    "overdetermined_initial": SolveStatus.NUMERICAL,
    "unsupported": SolveStatus.NUMERICAL,
    # proxqp (qpctl.solvers.proxqp_._STATUS)
    "closest_feasible": SolveStatus.INFEASIBLE,
    "dual_infeasible": SolveStatus.UNBOUNDED,
    "not_run": SolveStatus.NUMERICAL,
    # osqp (its status string, spaces as underscores)
    "solved_inaccurate": SolveStatus.SOLVED,  # osqp's own tolerance; our check then says INACCURATE
    "primal_infeasible_inaccurate": SolveStatus.INFEASIBLE,
    "dual_infeasible_inaccurate": SolveStatus.UNBOUNDED,
    "maximum_iterations_reached": SolveStatus.MAX_ITERATIONS,
    "run_time_limit_reached": SolveStatus.TIME_LIMIT,
    "problem_non_convex": SolveStatus.NUMERICAL,
    "non_convex": SolveStatus.NUMERICAL,
    "interrupted": SolveStatus.ERROR,
    "unsolved": SolveStatus.NUMERICAL,
}


def solve_status(word: str) -> SolveStatus:
    """The status of a solver's word (``"error: ..."`` and ``"exitflag N"`` included)."""
    status = _WORDS.get(word)
    if status is not None:
        return status
    if word.startswith("error"):
        return SolveStatus.ERROR
    if word.startswith("exitflag"):
        return SolveStatus.NUMERICAL
    return SolveStatus.UNKNOWN


@dataclass(frozen=True)
class SolveOutcome:
    """One solve, as the tick used it: ``status``, the solver's own ``word``, ``iterations``, the
    ``solver``'s name, ``solve_us`` [µs] (wall time of the tick's solves; 0 where not measured) and
    ``x`` — the solver's answer [q̈ (rad/s²), slack], read-only, or None when it kept none."""

    status: SolveStatus
    word: str
    iterations: int = 0
    solver: str = ""
    solve_us: float = 0.0
    x: np.ndarray | None = None

    @property
    def found(self) -> bool:
        return self.status is SolveStatus.SOLVED

    @classmethod
    def of(cls, sol: Solution, *, solve_us: float | None = None) -> SolveOutcome:
        """The outcome of a :class:`~qpctl.qp.Solution` (its x copied, read-only, when found)."""
        x = None
        if sol.found:
            x = np.array(sol.x, dtype=float)
            x.flags.writeable = False
        status = solve_status(sol.status)
        if not sol.found and status is SolveStatus.SOLVED:  # "solved" by the solver, refused by us
            status = SolveStatus.INACCURATE
        return cls(status, sol.status, int(sol.iterations), sol.solver,
                   sol.solve_us if solve_us is None else solve_us, x)


def checked_solve(solver: QPSolver, problem: Problem, deadline: float, *, check: bool = True) -> Solution:
    """One solve within what is left until ``deadline`` (a ``time.perf_counter`` time); a backend's
    exception is a failed solve (status ``"error: <type>"``). ``check``: refuse a non-finite x
    (``"nonfinite_solution"``) or one that violates a hard row by more than SOLUTION_RTOL
    (``"inaccurate"``: the solver's own test runs on its scaled problem, where a row it scaled up,
    say nᵀJ_p ≈ 1e-5 at a link's fixed base, can be violated by m/s² in our units)."""
    left_us = (deadline - time.perf_counter()) * 1e6
    if left_us <= 0:
        return Solution(False, np.zeros(problem.n_var), "time_limit", solver=solver.name)
    solver.set_time_limit(left_us if math.isfinite(left_us) else None)
    try:
        sol = solver.solve(problem)
    except ConfigError:  # bad solver settings: a configuration error, not a failed tick
        raise
    except Exception as exc:  # noqa: BLE001 — a backend's own error must not end the run
        solver.reset()
        return Solution(False, np.zeros(problem.n_var), f"error: {type(exc).__name__}", solver=solver.name)
    if not check or not sol.found:
        return sol
    if not np.isfinite(sol.x).all():
        return Solution(False, np.zeros(problem.n_var), "nonfinite_solution", sol.iterations, sol.solve_us,
                        solver.name)
    if problem.violation(sol.x) > SOLUTION_RTOL:
        return Solution(False, np.zeros(problem.n_var), "inaccurate", sol.iterations, sol.solve_us, solver.name)
    return sol

