"""The task hard first, or relaxed: the one place that decides which QP a tick solves and whether the
hard QP's answer stands (``controller.task_relaxation``, :class:`~qpctl.controllers.qp.QPConfig`).

The task rows J q̈ + s = a carry a slack s at an ℓ₁ weight, an exact penalty: while the task is
feasible the relaxed QP's answer has s = 0 and is the hard QP's (no slack variables: n unknowns
instead of n + 2m). So a tick may solve the hard QP first and keep its answer where it is the relaxed
QP's too, and solve the relaxed QP otherwise. The hard answer stands when, in this order,

1. the solver solved it;
2. its task rows hold (:func:`task_rows_hold`: DAQP may drop a nearly dependent equality row, the
   planar arm outstretched, and report the rest solved);
3. every task multiplier is within the ℓ₁ weight (the exact-penalty condition, so the relaxed QP
   gives the same answer: DAQP's own multipliers in the compiled tick,
   :func:`qpctl.kernels.hard_first.penalty_exact`, else :func:`qpctl.qp.penalty_is_exact`);
4. the other hard rows hold (the check every answer passes: :func:`qpctl.kernels.finish.qp_finish`,
   :func:`qpctl.outcome.checked_solve`).

Otherwise the relaxed QP is solved on the same tick, except when the problem's data are not finite
(no solver may be trusted with them). DAQP's compiled tick runs these steps inside one kernel
(:func:`qpctl.kernels.hard_first.qp_tick_native_hard_first`); the other paths in Python, through
:meth:`TaskRelaxation.judge`. Both report the refusal in the same words (:data:`REFUSALS`).

Modes: ``"always"`` — the relaxed QP every tick; ``"on_failure"`` — the hard QP first every tick;
``"auto"`` — the hard QP first inside DAQP's compiled tick (where the two solves cost least),
``"on_failure"`` for osqp (ADMM converges slowly and its polishing fails with the ℓ₁ slack),
``"always"`` otherwise. Under ``"auto"`` the hard QP is skipped after a tick on which the task gave
way (the slack non-zero, or the hard answer refused) until the slack is back to zero: one refusal per
stretch of an infeasible task, not one per tick.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from qpctl.errors import ConfigError
from qpctl.kernels.hard_first import hard_next
from qpctl.qp import Problem, penalty_is_exact

MODES = ("auto", "always", "on_failure")
_hard_next = hard_next.py_func  # the skip rule as the kernels run it, in Python here (no compiled signature)

#: The hard QP's refusals, by the code the compiled tick returns for it (3: the solver's own word).
REFUSALS = {4: "inaccurate", 7: "penalty_inexact"}
TASK_ROWS_MISSED = "inaccurate"  # step 2 failed: the task rows do not hold (the solver dropped one)


def check_mode(mode: str) -> str:
    if mode not in MODES:
        raise ConfigError(f"must be {', '.join(MODES[:-1])} or {MODES[-1]}, got {mode!r}",
                          key="controller.task_relaxation")
    return mode


def task_rows_hold(problem: Problem, x: np.ndarray, tol: float) -> bool:
    """Whether x meets the problem's equality (task) rows A x = b within ``tol`` relative to the
    larger of 1, |b| and |A_i|·|x| — the numpy twin of :func:`qpctl.kernels.hard_first.task_rows_hold`
    (step 2 of the module docstring)."""
    Ax = problem.A @ x
    mag = np.abs(problem.A) @ np.abs(x)
    return bool(np.all(np.abs(Ax - problem.b) <= tol * np.maximum(np.maximum(1.0, np.abs(problem.b)), mag)))


class TaskRelaxation:
    """Which QP a tick solves first, and what happened to the hard one (module docstring).

    ``mode``: the configured one; ``solver``: the solver's name; ``native``: whether the path can run
    a tick on DAQP's C API in one kernel call (where ``"auto"`` takes the task hard first)."""

    def __init__(self, mode: str, solver: str, native: bool) -> None:
        self.mode = check_mode(mode)
        self.native = native
        self.always_hard = mode == "on_failure" or (mode == "auto" and solver == "osqp")
        self._try_hard = True
        # the skip rule applies to the one-call ticks (after(True, ...) below, read by the fast tick)
        self.skip_rule = not self.always_hard and mode == "auto" and native

    @property
    def strategy(self) -> str:
        """"on_failure" (the hard QP first) or "always" on the ticks that are not one kernel call."""
        return "on_failure" if self.always_hard else "always"

    def hard_first(self, one_call: bool) -> bool:
        """Whether this tick is one of the task hard first (``one_call``: it runs in one kernel call on
        DAQP's C API), whether or not the skip rule then skips the hard QP."""
        return self.always_hard or (self.mode == "auto" and self.native and one_call)

    def try_hard(self, one_call: bool) -> bool:
        """Whether this tick solves the hard QP first."""
        if self.always_hard:
            return True
        return self.hard_first(one_call) and self._try_hard

    def after(self, one_call: bool, used_hard: bool, solved: bool, slack: float) -> None:
        """Note the tick's outcome: the skip rule's memory (module docstring; ``"auto"`` on DAQP)."""
        if not self.always_hard and self.hard_first(one_call):
            self._try_hard = bool(_hard_next(used_hard, solved, slack))

    def reset(self) -> None:
        self._try_hard = True

    @staticmethod
    def judge(problem: Problem, x: np.ndarray, l1: np.ndarray | float, tol: float) -> str:
        """"" when the hard QP's answer x (found and checked against the hard rows) stands, else the
        refusal: steps 2 and 3 of the module docstring, on the problem's arrays."""
        if not task_rows_hold(problem, x, tol):
            return TASK_ROWS_MISSED
        if np.isfinite(l1).any() and not penalty_is_exact(problem, x, l1):
            return REFUSALS[7]
        return ""

    @staticmethod
    def report(info: dict[str, Any], hard_first: bool, used_hard: bool, refusal: str,
               relaxed_iterations: int | None) -> None:
        """The tick's info entries when a hard-first tick's answer came from the relaxed QP:
        ``relaxed``, ``hard_status`` (the hard QP's refusal, when it was tried) and the iterations of
        both solves (when they were two calls)."""
        if not hard_first or used_hard:
            return
        info["relaxed"] = True
        if refusal:
            info["hard_status"] = refusal
        if relaxed_iterations is not None:
            info["iterations"] = int(info.get("iterations", 0)) + relaxed_iterations
