"""What the QP controller does when a tick's solve fails, on either of its paths, and the torque
clip every answer gets.

* strict mode raises :class:`~qpctl.errors.InfeasibleError` (the hard rows cannot all hold) or
  :class:`~qpctl.errors.SolverError` (any other failure), both carrying the problem and the outcome;
* otherwise the fallback chain (:mod:`qpctl.fallbacks`, ``controller.fallback``) produces q̈, which
  is made safe to command: within the joint-limit bounds on q̈ and, unless a solver produced it,
  scaled into the torque window toward gravity compensation (direction kept); τ = M q̈ + N is never
  non-finite and is clipped to the window.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from qpctl.constraints.constraints import TorqueLimit
from qpctl.errors import InfeasibleError, SolverError
from qpctl.fallbacks import (
    BRAKE,
    Attempt,
    Fallback,
    FallbackContext,
    brake_acceleration,
    make_fallback,
    run_chain,
)
from qpctl.outcome import SolveOutcome, SolveStatus, solve_status
from qpctl.qp import Problem, Solution
from qpctl.state import TickState

Window = tuple[np.ndarray, np.ndarray]


def clip_torque(window: Window | None, state: TickState, tau: np.ndarray, qdd: np.ndarray,
                info: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """The solver meets the torque rows to its tolerance; clip that residue (and any fallback's
    excess) so the commanded torque never leaves the window the drives accept (±τ_max, rate); q̈
    follows the clipped τ. Returns (τ [N·m], q̈ [rad/s²])."""
    clipped = tau if window is None else np.minimum(np.maximum(tau, window[0]), window[1])  # np.clip, cheaper
    if (clipped != tau).any():
        info["clipped"] = float(np.max(np.abs(clipped - tau)))
        tau = clipped
        qdd = np.linalg.solve(state.M, tau - state.N)
    return tau, qdd


def scale_into_window(window: Window | None, state: TickState, qdd: np.ndarray) -> np.ndarray:
    """s·q̈ with the largest s ∈ [0, 1] that keeps M s q̈ + N within the torque window (direction kept,
    unlike a per-joint clip; s = 0, gravity compensation alone, when N itself is outside it — the final
    clip then holds the window)."""
    if window is None or not np.isfinite(qdd).all():
        return qdd
    scale = 1.0  # joint by joint in Python floats: n is a handful, and numpy's per-call cost was 30 µs here
    for d, lo, hi, bias in zip((state.M @ qdd).tolist(), window[0].tolist(), window[1].tolist(), state.N.tolist()):
        if d > 0.0:
            scale = min(scale, (hi - bias) / d)
        elif d < 0.0:
            scale = min(scale, (lo - bias) / d)
    return qdd * max(scale, 0.0)


def row_ranges(problem: Problem) -> list[tuple[str, int, int]]:
    """(constraint name, first row, end row) of each run of rows of C with the same name."""
    out: list[tuple[str, int, int]] = []
    for i, name in enumerate(problem.row_names):
        if out and out[-1][0] == name and out[-1][2] == i:
            out[-1] = (name, out[-1][1], i + 1)
        else:
            out.append((name, i, i + 1))
    return out


def solution_info(problem: Problem, x: np.ndarray, info: dict[str, Any]) -> None:
    """Slack norm, active-row count and the constraint families with an active row, at the solver's x."""
    n = problem.n
    s = x[n:][np.any(problem.A[:, n:] != 0.0, axis=0)]  # the task's s⁺, s⁻ (not a constraint's own σ)
    half = s.size // 2
    slack = s[:half] - s[half:]
    info["slack_norm"] = math.sqrt(float(slack @ slack))
    Cx = problem.C @ x
    act = np.minimum(np.abs(Cx - problem.l), np.abs(Cx - problem.u)) <= 1e-6 * (1.0 + np.abs(Cx))
    xq = x[:n]
    bnd = np.minimum(np.abs(xq - problem.lb[:n]), np.abs(xq - problem.ub[:n])) <= 1e-6
    info["active"] = int(np.count_nonzero(act)) + int(np.count_nonzero(bnd))
    info["active_rows"] = sorted({name for name, lo, hi in row_ranges(problem) if act[lo:hi].any()})


class Failures:
    """A QP controller's answer to a failed solve (module docstring).

    ``fallback``: the chain's names (``controller.fallback``; built now, so that an unknown name fails
    here and not in the middle of a run); ``torque_limit()``: the controller's TorqueLimit, or None."""

    def __init__(self, fallback: Sequence[str], strict: bool, torque_limit: Callable[[], TorqueLimit | None]) -> None:
        self.names = list(fallback)
        self.strict = strict
        self.strategies: dict[str, Fallback] = {name: make_fallback(name) for name in self.names}
        self.torque_limit = torque_limit

    def reset(self) -> None:
        for strategy in self.strategies.values():
            strategy.reset()

    def window(self, t: float) -> Window | None:
        """The torques [N·m] the drives accept at t [s] (TorqueLimit.window), or None without limits."""
        limit = self.torque_limit()
        return None if limit is None else limit.window(t)

    def raise_if_strict(self, problem: Problem, word: str, info: dict[str, Any], sol: Solution | None) -> None:
        """In strict mode, a failed solve raises instead of falling back (module docstring)."""
        if not self.strict:
            return
        outcome = SolveOutcome(solve_status(word), word, int(info.get("iterations", 0)), str(info.get("solver", "")),
                               float(info.get("solve_us", 0.0)), None if sol is None else SolveOutcome.of(sol).x)
        kind = InfeasibleError if outcome.status is SolveStatus.INFEASIBLE else SolverError
        raise kind(f"the QP failed ({outcome.status.value}: {word}) with solver {outcome.solver}", status=word,
                   problem=problem, outcome=outcome)

    def fall_back(self, ctx: FallbackContext, sol: Solution | None, word: str,
                  info: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, Problem, Solution | None]:
        """The chain (:func:`qpctl.fallbacks.run_chain`, the QP having failed with ``word``) and its q̈
        made safe to command; returns (τ, q̈, the problem of the solution used, the solution: a
        fallback solver's, else ``sol``). Writes ``info["fallback_us"]``."""
        t0 = time.perf_counter()
        info["fallback_reason"] = word
        att = run_chain([self.strategies[name] for name in self.names], ctx, info)
        problem = att.problem if att.solution is not None and att.problem is not None else ctx.problem
        tau, qdd = self._finish(ctx, att, problem, info)
        info["fallback_us"] = (time.perf_counter() - t0) * 1e6
        return tau, qdd, problem, att.solution if att.solution is not None else sol

    def _finish(self, ctx: FallbackContext, att: Attempt, problem: Problem,
                info: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
        """A fallback's q̈ within the joint-limit bounds (the QP's bounds on q̈, where finite) and, unless a
        solver produced it, scaled into the torque limits; τ = M q̈ + N, never non-finite, clipped to
        the window. Returns (τ, q̈)."""
        state = ctx.state
        n = state.n
        assert att.qdd is not None
        lb, ub = problem.lb[:n], problem.ub[:n]
        qdd = np.minimum(np.maximum(att.qdd, np.where(np.isfinite(lb), lb, att.qdd)),
                         np.where(np.isfinite(ub), ub, att.qdd))
        fsol = att.solution
        if fsol is None:
            qdd = scale_into_window(ctx.window, state, qdd)
        tau = state.M @ qdd + state.N
        if not np.isfinite(tau).all():  # last line of defence: never command a non-finite torque
            info["nonfinite_replaced"] = True
            info["fallback"] = BRAKE
            fsol = None
            qdd = brake_acceleration(ctx)
            tau = state.M @ qdd + state.N
            if not np.isfinite(tau).all():
                tau = np.where(np.isfinite(tau), tau, 0.0)
                qdd = np.linalg.solve(state.M, tau - state.N)
        tau, qdd = clip_torque(ctx.window, state, tau, qdd, info)
        if fsol is not None:
            solution_info(problem, fsol.x, info)
        return tau, qdd
