"""The fallback chain: what produces a tick's torque when the QP fails, as small strategies
registered by name (``controller.fallback`` lists names, tried in order).

* ``"closed-form"`` — the paper law (eq. 19) when it is safe: no link within d_safe and its q̈ meets
  every barrier row of the tick's QP (status ``within_d_safe`` or ``barrier_violated`` otherwise);
* ``"safe-stop"`` — the brake corrected by a small QP that keeps the barrier rows as well as the
  torque limits allow (:class:`SafeStop`);
* ``"brake"`` — q̈ = k_v (g − q̇): to rest, links near obstacles backing away along g;
* any solver name (``qpctl solvers``) — that solver on the tick's QP with the task slack.

A strategy finds the rows it needs by their kind in the tick's :class:`~qpctl.qp.Problem`
(``problem.rows_of(BARRIER)``), not by the class that contributed them: a user's constraint with
``kind = BARRIER`` is kept by the safe stop and checked by the closed form like the obstacle
barrier. Register another with :func:`register_fallback`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from qpctl.constraints.constraints import BARRIER
from qpctl.law import LawGains, LawTerms, closed_form_acceleration
from qpctl.outcome import checked_solve
from qpctl.qp import Problem, Solution
from qpctl.solvers.base import QPSolver, make_solver
from qpctl.solvers.daqp_ import DAQPSolver
from qpctl.state import TickState

CLOSED_FORM = "closed-form"
BRAKE = "brake"
SAFE_STOP = "safe-stop"


@dataclass
class FallbackContext:
    """What a strategy may read about the failed tick."""

    state: TickState
    terms: LawTerms
    gains: LawGains
    problem: Problem  # the tick's QP as it was solved (hard or with the task slack)
    window: tuple[np.ndarray, np.ndarray] | None  # the torques the drives accept now [N·m] (None: no limits)
    deadline: float = np.inf  # time.perf_counter() time the tick budget ends
    build_relaxed: Callable[[], Problem] | None = None  # the tick's QP with the task slack (None: problem is)
    # the paper law's q̈ on this tick's state and terms, computed by the compiled tick's kernel
    # (qpctl.kernels.law.closed_form); None: ClosedForm computes it with numpy (qpctl.law)
    paper_qdd: Callable[[], np.ndarray] | None = None
    _relaxed: Problem | None = field(default=None, repr=False)

    def relaxed(self) -> Problem:
        """The tick's QP with the task slack (built once, on demand)."""
        if self._relaxed is None:
            self._relaxed = self.problem if self.build_relaxed is None else self.build_relaxed()
        return self._relaxed


@dataclass(frozen=True)
class Attempt:
    """One strategy's answer: q̈ [rad/s²] (None: it failed), ``word`` — its name when it produced q̈,
    else why not; a solver's ``solution`` and the ``problem`` it solved."""

    qdd: np.ndarray | None
    word: str
    solution: Solution | None = None
    problem: Problem | None = None


class Fallback(ABC):
    """A strategy of the chain; instances belong to one controller (they may keep warm starts)."""

    name: str = ""

    @abstractmethod
    def __call__(self, ctx: FallbackContext) -> Attempt:
        """q̈ for this tick, or why not."""

    def reset(self) -> None:
        """Forget warm starts (a new run)."""


def brake_acceleration(ctx: FallbackContext) -> np.ndarray:
    """q̈ = k_v (g − q̇) [rad/s²]: to rest, links near obstacles backing away along g."""
    g = ctx.terms.g if np.all(np.isfinite(ctx.terms.g)) else np.zeros(ctx.state.n)
    return ctx.gains.kv * (g - ctx.state.v)


class Brake(Fallback):
    name = BRAKE

    def __call__(self, ctx: FallbackContext) -> Attempt:
        return Attempt(brake_acceleration(ctx), BRAKE)


class ClosedForm(Fallback):
    """The paper law where it is safe (see module docstring)."""

    name = CLOSED_FORM

    def __call__(self, ctx: FallbackContext) -> Attempt:
        if ctx.paper_qdd is not None:  # the compiled tick's kernel: 9 µs a call against numpy's 65 (Panda)
            qdd = ctx.paper_qdd()
        else:
            try:
                qdd, _ = closed_form_acceleration(ctx.state, ctx.terms, ctx.gains, weighted=True)
            except (np.linalg.LinAlgError, ValueError, FloatingPointError):
                qdd = np.full(ctx.state.n, np.nan)
        why = self.unsafe(ctx, qdd)
        return Attempt(None, why) if why else Attempt(qdd, CLOSED_FORM)

    @staticmethod
    def unsafe(ctx: FallbackContext, qdd: np.ndarray) -> str:
        """"" when q̈ may be used, else why not."""
        if not np.isfinite(qdd).all():
            return "nonfinite"
        if ctx.state.clearance < ctx.gains.d_safe:
            return "within_d_safe"
        rows = ctx.problem.rows_of(BARRIER)
        lo = ctx.problem.l[rows]
        lhs = ctx.problem.C[rows, : ctx.state.n] @ qdd
        with np.errstate(invalid="ignore"):
            if np.any(lhs < lo - 1e-6 * (1.0 + np.abs(lo))):
                return "barrier_violated"
        return ""


class SafeStop(Fallback):
    """The brake's q̈ corrected by a small QP (DAQP, tens of µs) that keeps the barrier rows as well
    as the torque limits allow:

        min ½‖M(q̈ − q̈_brake)‖² + ½ρ‖t‖²  s.t.  C_bar q̈ + t ≥ l_bar, t ≥ 0,
                                             M q̈ + N in the torque window (±τ_max, the rate limit),
                                             joint-limit bounds on q̈,

    with ρ = WEIGHT · tr(MᵀM)/n: where the barriers cannot all hold (the tick's QP was infeasible) it
    decelerates the approach as hard as the torque limits allow, which the brake's fixed direction,
    scaled into the limits, does not."""

    name = SAFE_STOP
    WEIGHT = 1e6  # barrier slack weight, relative to the mean diagonal of MᵀM

    def __init__(self) -> None:
        self.solver = DAQPSolver()

    def reset(self) -> None:
        self.solver.reset()

    def __call__(self, ctx: FallbackContext) -> Attempt:
        state, problem, n = ctx.state, ctx.problem, ctx.state.n
        qb = brake_acceleration(ctx)
        H = state.M.T @ state.M
        rows = problem.rows_of(BARRIER)
        live = rows[np.isfinite(problem.l[rows])]  # the rows in force (an unused pair's slot has l = −inf)
        C_bar, l_bar = problem.C[live, :n], problem.l[live]
        k = l_bar.size
        nv = n + k
        P = np.zeros((nv, nv))
        P[:n, :n] = H
        P[n:, n:] = self.WEIGHT * max(float(np.trace(H)) / n, 1e-12) * np.eye(k)
        window = ctx.window
        C = np.zeros((k + (n if window is not None else 0), nv))
        C[:k, :n], C[:k, n:] = C_bar, np.eye(k)
        lower, upper = [l_bar], [np.full(k, np.inf)]
        if window is not None:
            C[k:, :n] = state.M
            lower.append(window[0] - state.N)
            upper.append(window[1] - state.N)
        lb = np.concatenate([problem.lb[:n], np.zeros(k)])  # the joint-limit bounds; t ≥ 0
        ub = np.concatenate([problem.ub[:n], np.full(k, np.inf)])
        safe = Problem(P, np.concatenate([-H @ qb, np.zeros(k)]), np.zeros((0, nv)), np.zeros(0), C,
                       np.concatenate(lower), np.concatenate(upper), lb, ub, n)
        if not safe.is_finite():
            return Attempt(None, "infeasible")
        sol = self.solver.solve(safe)
        return Attempt(sol.x[:n], SAFE_STOP) if sol.found else Attempt(None, "infeasible")


class SolverFallback(Fallback):
    """Another solver on the tick's QP with the task slack (so that only hard rows can conflict),
    within what is left of the tick budget."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.solver: QPSolver = make_solver(name)

    def reset(self) -> None:
        self.solver.reset()

    def __call__(self, ctx: FallbackContext) -> Attempt:
        problem = ctx.relaxed()
        if not problem.is_finite():
            return Attempt(None, "nonfinite_problem", None, problem)
        sol = checked_solve(self.solver, problem, ctx.deadline)
        return Attempt(sol.x[: ctx.state.n] if sol.found else None, self.name if sol.found else sol.status, sol,
                       problem)


# name → factory of a controller's own instance; names not here are solver names (SolverFallback)
FALLBACKS: dict[str, Callable[[], Fallback]] = {CLOSED_FORM: ClosedForm, SAFE_STOP: SafeStop, BRAKE: Brake}


def register_fallback(name: str, factory: Callable[[], Fallback]) -> None:
    """Make ``name`` usable in ``controller.fallback`` (``factory()`` builds a controller's instance)."""
    FALLBACKS[name] = factory


def make_fallback(name: str) -> Fallback:
    """The strategy called ``name``: a registered one, else that solver (UnknownSolverError if none)."""
    factory = FALLBACKS.get(name)
    return factory() if factory is not None else SolverFallback(name)


def run_chain(chain: Sequence[Fallback], ctx: FallbackContext, info: dict[str, Any]) -> Attempt:
    """Try the strategies in order; the first q̈ wins, the brake when every one fails. Writes
    ``info["fallback"]`` (what produced q̈), ``info["fallback_tried"]`` ("name:why" of those that
    failed) and ``info["budget_exhausted"]`` when a solver ran out of time."""
    tried: list[str] = []
    for strategy in chain:
        att = strategy(ctx)
        if att.qdd is not None:
            break
        tried.append(f"{strategy.name}:{att.word}")
        if att.word == "time_limit":
            info["budget_exhausted"] = True
    else:
        att = Attempt(brake_acceleration(ctx), BRAKE)
    info["fallback"] = att.word
    if tried:
        info["fallback_tried"] = tried
    return att
