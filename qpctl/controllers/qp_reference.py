"""The QP controller's reference path: any tasks and constraints, the problem stacked in Python.

The state comes from the same kernels (a :class:`~qpctl.state.TickState` of copies); the law's terms
from :func:`qpctl.law.law_terms`; the QP from :class:`~qpctl.formulation.Formulation`, solved through
:class:`~qpctl.qp.Problem`, the answer checked (:func:`qpctl.outcome.checked_solve`), with the task
hard first where :class:`~qpctl.controllers.relaxation.TaskRelaxation` says so. It is the path of
custom tasks and constraints, and the reference the tests hold the compiled path against.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from functools import partial
from typing import Any

import numpy as np

from qpctl.constraints.constraints import TorqueLimit
from qpctl.controllers.base import ControlOutput, TickStatus
from qpctl.controllers.qp_failure import Failures, clip_torque, solution_info
from qpctl.controllers.relaxation import TaskRelaxation
from qpctl.fallbacks import FallbackContext
from qpctl.formulation import Formulation
from qpctl.law import LawGains, LawTerms, law_terms
from qpctl.outcome import SOLUTION_RTOL, checked_solve, solve_status
from qpctl.paths import Reference
from qpctl.qp import Problem, Solution
from qpctl.solvers.base import QPSolver
from qpctl.state import TickState


class ReferenceTick:
    """The QP on a :class:`TickState` (module docstring). ``formulation()`` the controller's current
    one; ``solvers``: the hard QP's and the relaxed one's; ``reference(state)``: x_d, ẋ_d, ẍ_d at the
    state (the controller's: orientation rows included); ``budget_us()``: the tick budget [µs]."""

    def __init__(self, formulation: Callable[[], Formulation], solvers: tuple[QPSolver, QPSolver], mode: str,
                 budget_us: Callable[[], float], gains: LawGains, failures: Failures,
                 reference: Callable[[TickState], Reference], torque_limit: Callable[[], TorqueLimit | None]) -> None:
        self.formulation, self.solvers, self.budget_us = formulation, solvers, budget_us
        self.gains, self.failures, self.reference, self.torque_limit = gains, failures, reference, torque_limit
        self.relax = TaskRelaxation(mode, solvers[1].name, native=False)
        self.last_problem: Problem | None = None
        self.last: Solution | None = None

    def reset(self) -> None:
        self.relax.reset()

    def control(self, state: TickState, start: float | None = None) -> ControlOutput:
        """The tick on ``state``: build the QP from the tasks and constraints, solve it, check the answer,
        τ = M q̈ + N; when the solve fails, the fallback chain (or, in strict mode, its error).
        ``start``: when the tick began (the budget counts from it; now, when None)."""
        t0 = time.perf_counter()
        budget = self.budget_us()
        deadline = (t0 if start is None else start) + budget * 1e-6 if budget > 0 else np.inf
        ref = self.reference(state)
        terms = law_terms(state, ref, self.gains, weighted=True)
        problem, solved, info = self._build_and_solve(state, terms, deadline, t0)
        form = self.formulation()
        sol: Solution | None = solved
        window = self.failures.window(state.t)
        if solved.found:
            qdd = solved.x[: state.n]
            tau, qdd = clip_torque(window, state, state.M @ qdd + state.N, qdd, info)
            solution_info(problem, solved.x, info)
        else:
            self.last_problem, self.last = problem, solved
            self.failures.raise_if_strict(problem, solved.status, info, solved)
            hard = self.relax.try_hard(False) and not info.get("relaxed")  # the chain's solvers get the slack
            ctx = FallbackContext(state, terms, self.gains, problem, window, deadline,
                                  partial(form.build, state, terms, relax=True) if hard else None)
            tau, qdd, problem, sol = self.failures.fall_back(ctx, solved, solved.status, info)
        dropped = form.dropped(state, terms)
        if dropped:
            info["pairs_dropped"] = dropped
        self.last_problem, self.last = problem, sol
        limit = self.torque_limit()
        if limit is not None:  # the torque commanded [N·m] at t [s]: the next tick's rate limit is about it
            limit.remember(tau, state.t)
        return ControlOutput(tau=tau, qdd=qdd, ref=ref, x=state.x, e_null=terms.e_null, clearance=state.clearance,
                             singular=terms.singular, info=info,
                             status=TickStatus.FALLBACK if "fallback" in info else TickStatus.SOLVED)

    def _build_and_solve(self, state: TickState, terms: LawTerms, deadline: float,
                         t0: float) -> tuple[Problem, Solution, dict[str, Any]]:
        """The tick's QP built and solved, the answer checked (:meth:`_solve`); the task hard first
        when the relaxation says so, relaxed when that fails. Returns (problem, solution, info: status
        words, iterations, solver, build and solve times [µs] from ``t0``)."""
        form = self.formulation()
        hard_first = self.relax.try_hard(False)
        hard, soft = self.solvers
        problem = form.build(state, terms, relax=not hard_first)
        t1 = time.perf_counter()
        l1 = form.penalty_weights(state, terms) if hard_first else None
        sol = self._solve(hard if hard_first else soft, problem, deadline, l1)
        t2 = time.perf_counter()
        info: dict[str, Any] = {"status": sol.status, "iterations": sol.iterations, "solver": sol.solver,
                                "build_us": (t1 - t0) * 1e6, "solve_us": (t2 - t1) * 1e6}
        if hard_first and not sol.found and sol.status != "nonfinite_problem":  # let the task give way
            refusal, iterations = sol.status, sol.iterations
            problem = form.build(state, terms, relax=True)
            t3 = time.perf_counter()
            sol = self._solve(soft, problem, deadline)
            info.update(status=sol.status, build_us=info["build_us"] + (t3 - t2) * 1e6,
                        solve_us=info["solve_us"] + (time.perf_counter() - t3) * 1e6, iterations=iterations)
            self.relax.report(info, True, False, refusal, sol.iterations)
        if sol.status == "time_limit":
            info["budget_exhausted"] = True
        info["solve_status"] = solve_status(sol.status)
        return problem, sol, info

    @staticmethod
    def _solve(solver: QPSolver, problem: Problem, deadline: float, l1: np.ndarray | None = None) -> Solution:
        """One solve (:func:`qpctl.outcome.checked_solve`) of a finite problem ("nonfinite_problem"
        otherwise: no solver can be trusted with NaN data, e.g. a degenerate distance query); with the
        task's ℓ₁ weights ``l1`` (the task hard), an answer stands only if it is the relaxed QP's too
        (:meth:`TaskRelaxation.judge`)."""
        if not problem.is_finite():
            return Solution(False, np.zeros(problem.n_var), "nonfinite_problem", solver=solver.name)
        sol = checked_solve(solver, problem, deadline)
        if sol.found and l1 is not None:
            refusal = TaskRelaxation.judge(problem, sol.x, l1, SOLUTION_RTOL)
            if refusal:
                return Solution(False, np.zeros(problem.n_var), refusal, sol.iterations, sol.solve_us, sol.solver)
        return sol
