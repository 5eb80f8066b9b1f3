"""The task hard first (:mod:`qpctl.controllers.relaxation`): each step of the judgement of a hard
answer, on its own, in the kernel and in Python.

Issue 23's guard: breaking the hard-first check so that it skipped the first task row passed the
suite (its only test refused a tick on which every row missed). Here each task row alone is missed,
by the kernel's :func:`~qpctl.kernels.hard_first.task_rows_hold` (DAQP's layout) and by its numpy
twin on the :class:`~qpctl.qp.Problem` of views onto the same arrays — the expected answers come from
the construction (a row moved by a known amount), not from either function; the multiplier step on
an analytic multiplier; and the policy's modes. The whole hard-first tick on a real dropped row (DAQP
at an outstretched arm) is ``tests/test_penalty.py``'s singular-configuration test.
"""

from __future__ import annotations

import numpy as np
import pytest

from qpctl.controllers.relaxation import REFUSALS, TASK_ROWS_MISSED, TaskRelaxation, task_rows_hold
from qpctl.errors import ConfigError
from qpctl.kernels import hard_first
from qpctl.qp import Problem

TOL = 1e-4


def daqp_layout(rng: np.random.Generator, n: int, n_in: int, m: int):
    """A QP in DAQP's layout (rows = [C; A], bu = [ub; u; b]) whose equality rows hold exactly at x,
    and the Problem of views onto it."""
    nv = n
    x = rng.normal(size=nv)
    rows = rng.normal(size=(n_in + m, nv))
    bu = np.concatenate([np.full(nv, np.inf), np.full(n_in, np.inf), rows[n_in:] @ x])
    bl = np.concatenate([np.full(nv, -np.inf), np.full(n_in, -np.inf), bu[nv + n_in:]])
    problem = Problem(np.eye(nv), np.zeros(nv), rows[n_in:], bu[nv + n_in:], rows[:n_in], bl[nv:nv + n_in],
                      bu[nv:nv + n_in], bl[:nv], bu[:nv], n)
    return x, rows, bu, problem


@pytest.mark.parametrize("m", [2, 3, 5, 6])
def test_each_task_row_alone_missed_is_refused(m):
    """Every row holding: both accept. Row r alone moved by 10× the tolerance of its scale: both refuse
    (and the judgement says why); by a tenth of it: both accept."""
    rng = np.random.default_rng(23 + m)
    n, n_in = 7, 9
    x, rows, bu, problem = daqp_layout(rng, n, n_in, m)
    assert hard_first.task_rows_hold(x, rows, bu, n_in, m, TOL) and task_rows_hold(problem, x, TOL)
    for r in range(m):
        b = bu[n + n_in + r]
        scale = max(1.0, abs(b), float(np.abs(rows[n_in + r]) @ np.abs(x)))
        for factor, holds in ((10.0, False), (0.1, True)):
            bu[n + n_in + r] = b + factor * TOL * scale
            assert hard_first.task_rows_hold(x, rows, bu, n_in, m, TOL) is holds, (r, factor)
            assert task_rows_hold(problem, x, TOL) is holds, (r, factor)
            judged = TaskRelaxation.judge(problem, x, np.inf, TOL)
            assert judged == ("" if holds else TASK_ROWS_MISSED), (r, factor)
        bu[n + n_in + r] = b


def test_the_penalty_step_refuses_a_multiplier_above_the_weight():
    """min ½‖x‖² s.t. x₀ = 2: the task's multiplier is 2, so the hard answer stands at ℓ₁ weight 2.5,
    is refused at 1.9 — in the kernel (DAQP's λ) and in the judgement (multipliers found by NNLS)."""
    n = 3
    problem = Problem(np.eye(n), np.zeros(n), np.eye(1, n), np.array([2.0]), np.zeros((0, n)), np.zeros(0),
                      np.zeros(0), np.full(n, -np.inf), np.full(n, np.inf), n)
    x = np.array([2.0, 0.0, 0.0])
    lam = np.concatenate([np.zeros(n), [-2.0]])  # DAQP's multipliers: the bounds', then the equality's
    assert hard_first.penalty_exact(lam, n, 1, 2.5) and not hard_first.penalty_exact(lam, n, 1, 1.9)
    assert TaskRelaxation.judge(problem, x, 2.5, TOL) == ""
    assert TaskRelaxation.judge(problem, x, 1.9, TOL) == REFUSALS[7]


def test_modes():
    """"always" never tries the hard QP; "on_failure" every tick; "auto" on DAQP's one-call tick with
    the skip rule (not after a tick on which the task gave way, until its slack is zero again), and
    for osqp every tick."""
    always = TaskRelaxation("always", "daqp", native=True)
    assert not always.try_hard(True) and not always.hard_first(True) and always.strategy == "always"
    on_failure = TaskRelaxation("on_failure", "proxqp", native=False)
    assert on_failure.try_hard(False) and on_failure.strategy == "on_failure"
    on_failure.after(False, False, True, 1.0)
    assert on_failure.try_hard(False)  # no skip rule
    auto = TaskRelaxation("auto", "daqp", native=True)
    assert auto.try_hard(True) and not auto.try_hard(False) and auto.strategy == "always"
    auto.after(True, False, True, 0.5)  # the relaxed QP's answer, the task gave way
    assert not auto.try_hard(True) and auto.hard_first(True)
    auto.after(True, False, True, 0.0)  # slack back to zero
    assert auto.try_hard(True)
    auto.after(True, False, True, 0.5)
    auto.reset()
    assert auto.try_hard(True)
    assert TaskRelaxation("auto", "osqp", native=False).try_hard(False)
    with pytest.raises(ConfigError, match="task_relaxation"):
        TaskRelaxation("sometimes", "daqp", native=True)
