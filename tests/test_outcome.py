"""A solve's outcome (issue 15, item 5): every solver's word maps to a SolveStatus, the outcome is a
frozen record, ticks report ``info["solve_status"]`` beside the word, and a strict controller raises
InfeasibleError / SolverError carrying the problem and the outcome instead of falling back."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from qpctl import InfeasibleError, LawGains, Obstacle, SolverError, WaypointPath, planar_arm
from qpctl.controllers.base import TickStatus
from qpctl.controllers.qp import QPConfig, QPController
from qpctl.outcome import SolveOutcome, SolveStatus, solve_status
from qpctl.qp import Problem, Solution
from qpctl.solvers.daqp_ import STATUS as DAQP_STATUS
from qpctl.solvers.proxqp_ import _STATUS as PROXQP_STATUS
from qpctl.solvers.proxqp_ import ProxQPSolver
from qpctl.tasks.tasks import PostureTask

Q0 = np.array([np.pi, np.pi / 2, 0.0])  # links 2 and 3 hang down along x = −1
PATH = WaypointPath([[-1.0, -2.0], [1.0, -1.5]], duration=1.0)
RUSHING = [Obstacle("sphere", [-0.8, -1.5, 0.0], radius=0.1)]  # link 3 at d_safe
V_RUSH = np.array([0.0, 0.0, 5.0])  # swinging into it faster than 400 N·m can stop: the QP is infeasible
# osqp's status strings (OSQP 1.x), as qpctl.solvers.osqp_ reports them (spaces as underscores)
OSQP_WORDS = ["solved", "solved inaccurate", "primal infeasible", "primal infeasible inaccurate", "dual infeasible",
              "dual infeasible inaccurate", "maximum iterations reached", "run time limit reached",
              "problem non convex", "interrupted", "unsolved"]


class _Posture(PostureTask):
    """A task the compiled assembly does not know: the tick takes the Python path (control())."""


def make_qp(path: str, obstacles=(), *, strict: bool = False, **cfg) -> QPController:
    ctrl = QPController(planar_arm(tau_max=400.0), PATH, list(obstacles), LawGains(), QPConfig(**cfg), strict=strict)
    if path == "python":
        ctrl.add_task(_Posture(Q0, 1e-3))
    return ctrl


@pytest.mark.parametrize("word", [*DAQP_STATUS.values(), *PROXQP_STATUS.values(),
                                  *(w.replace(" ", "_") for w in OSQP_WORDS),
                                  "time_limit", "inaccurate", "nonfinite_problem", "nonfinite_solution",
                                  "penalty_inexact", "error: RuntimeError", "exitflag -12"])
def test_every_solver_word_has_a_status(word):
    assert solve_status(word) is not SolveStatus.UNKNOWN


def test_status_of_words():
    assert solve_status("primal_infeasible") is SolveStatus.INFEASIBLE
    assert solve_status("max_iter") is solve_status("maximum_iterations_reached") is SolveStatus.MAX_ITERATIONS
    assert solve_status("run_time_limit_reached") is solve_status("time_limit") is SolveStatus.TIME_LIMIT
    assert solve_status("nonfinite_problem") is SolveStatus.NON_FINITE
    assert solve_status("failed") is SolveStatus.UNKNOWN  # qpsolvers gives no reason
    assert SolveStatus.SOLVED == "solved" and SolveStatus.SOLVED.found and not SolveStatus.INFEASIBLE.found


def test_outcome_is_an_immutable_record():
    x = np.arange(3.0)
    out = SolveOutcome.of(Solution(True, x, "solved", 4, 12.0, "daqp"))
    assert (out.status, out.word, out.iterations, out.solver, out.solve_us) == (SolveStatus.SOLVED, "solved", 4,
                                                                                "daqp", 12.0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        out.status = SolveStatus.INFEASIBLE  # type: ignore[misc]
    assert out.x is not None and not out.x.flags.writeable
    x[0] = 9.0
    assert out.x[0] == 0.0  # a copy
    failed = SolveOutcome.of(Solution(False, np.zeros(3), "primal_infeasible", 7, 1.0, "daqp"))
    assert failed.status is SolveStatus.INFEASIBLE and failed.x is None and not failed.found


@pytest.mark.parametrize("path", ["compiled", "python"])
def test_ticks_report_the_status_beside_the_word(path):
    ctrl = make_qp(path)
    out = ctrl.step(Q0, np.zeros(3), 0.1)
    assert out.status is TickStatus.SOLVED
    assert out.info["status"] == "solved" and out.info["solve_status"] is SolveStatus.SOLVED
    last = ctrl.last_outcome
    assert last is not None and last.found and last.solver == out.info["solver"]
    np.testing.assert_allclose(last.x[: ctrl.n], out.qdd, rtol=1e-9, atol=1e-9)  # no torque clip here
    ctrl = make_qp(path, RUSHING)
    out = ctrl.step(Q0, V_RUSH, 0.1)
    assert out.status is TickStatus.FALLBACK
    assert out.info["status"] == "primal_infeasible" and out.info["solve_status"] is SolveStatus.INFEASIBLE


@pytest.mark.parametrize("path", ["compiled", "python"])
def test_strict_mode_raises_infeasible_error_with_the_problem(path):
    ctrl = make_qp(path, RUSHING, strict=True)
    with pytest.raises(InfeasibleError) as err:
        ctrl.step(Q0, V_RUSH, 0.1)
    exc = err.value
    assert isinstance(exc.problem, Problem) and exc.problem.rows_of("barrier").size > 0
    assert exc.outcome.status is SolveStatus.INFEASIBLE and exc.outcome.word == exc.status == "primal_infeasible"
    assert exc.outcome.solver == "daqp" and not exc.outcome.found
    ctrl.strict = False  # the same tick falls back
    assert ctrl.step(Q0, V_RUSH, 0.1).info["fallback"]


@pytest.mark.parametrize("path", ["compiled", "python"])
def test_strict_mode_raises_solver_error_for_other_failures(monkeypatch, path):
    monkeypatch.setattr(ProxQPSolver, "solve", lambda self, problem: Solution(
        False, np.zeros(problem.n_var), "max_iter", 1000, 0.0, self.name))
    ctrl = make_qp(path, solver="proxqp", strict=True)
    with pytest.raises(SolverError) as err:
        ctrl.step(Q0, np.zeros(3), 0.1)
    assert not isinstance(err.value, InfeasibleError)
    assert err.value.outcome.status is SolveStatus.MAX_ITERATIONS and err.value.problem is not None
