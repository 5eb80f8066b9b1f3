"""Typed containers for the per-tick quadratic program (what crosses the task/constraint/solver boundary).

The QP's decision variable is x = [q̈ (n), s⁺ (k), s⁻ (k)], q̈ the joint accelerations [rad/s²] and
s = s⁺ − s⁻ the slack of the k soft equality rows (the task), s± ≥ 0:

    minimise   ½ xᵀ P x + cᵀ x
    subject to A x = b,   l ≤ C x ≤ u,   lb ≤ x ≤ ub

Tasks return an :class:`Objective` (a cost on q̈) or an :class:`Equality` (rows on q̈, hard or soft);
constraints return an :class:`Inequality` (rows l ≤ C q̈ ≤ u, inactive rows with infinite bounds)
or :class:`Bounds` (on q̈). Their shapes do not change from tick to tick, so solvers can warm-start.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Objective:
    """½ q̈ᵀ H q̈ + cᵀ q̈."""

    H: np.ndarray
    c: np.ndarray


@dataclass(frozen=True)
class Equality:
    """A q̈ = b; soft when ``slack_l1 > 0``: A q̈ + s = b at cost slack_l1·‖s‖₁ + ½ slack_l2·‖s‖².

    The ℓ₁ part is an exact penalty: when the hard problem is feasible and slack_l1 exceeds the rows'
    Lagrange multipliers, the slack is exactly zero and the solution is the hard one.
    """

    A: np.ndarray
    b: np.ndarray
    slack_l1: float = 0.0
    slack_l2: float = 0.0

    @property
    def soft(self) -> bool:
        return self.slack_l1 > 0 or self.slack_l2 > 0


@dataclass(frozen=True)
class Inequality:
    """l ≤ C q̈ ≤ u (rows with l = −inf and u = +inf are inactive placeholders); ``dropped``: what
    did not fit in the fixed rows this tick (e.g. pairs beyond an obstacle barrier's capacity)."""

    C: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    dropped: int = 0


@dataclass(frozen=True)
class Bounds:
    """lower ≤ q̈ ≤ upper, element-wise."""

    lower: np.ndarray
    upper: np.ndarray


@dataclass
class Problem:
    """The stacked QP of one tick (see module docstring); ``n`` is the number of joints."""

    P: np.ndarray
    c: np.ndarray
    A: np.ndarray
    b: np.ndarray
    C: np.ndarray
    l: np.ndarray
    u: np.ndarray
    lb: np.ndarray
    ub: np.ndarray
    n: int
    row_names: list[str] = field(default_factory=list)  # one per row of C: the constraint's name
    row_kinds: list[str] = field(default_factory=list)  # one per row of C: its kind (Constraint.kind)

    @property
    def n_var(self) -> int:
        return int(self.P.shape[0])

    def rows_of(self, kind: str) -> np.ndarray:
        """Indices of the rows of C whose kind is ``kind`` (e.g. ``"barrier"``), in order."""
        return np.array([i for i, k in enumerate(self.row_kinds) if k == kind], dtype=np.intp)

    def is_finite(self) -> bool:
        """No NaN anywhere and no infinity outside the bounds (where ±inf means "no bound")."""
        # one concatenation per family (this runs every tick: numpy calls, not elements, are the cost)
        data = np.concatenate((self.P.ravel(), self.c, self.A.ravel(), self.b, self.C.ravel()))
        bounds = np.concatenate((self.l, self.u, self.lb, self.ub))
        return bool(np.isfinite(data).all()) and not bool(np.isnan(bounds).any())

    def violation(self, x: np.ndarray) -> float:
        """Largest violation at x of the hard rows on q̈ (l ≤ C x ≤ u and the bounds on q̈), each
        relative to 1 + |its bound|. The equality rows and the slack variables' sign are left to the
        solver: they shape the tracking, not what the constraints protect."""
        n = self.n
        Cx = self.C @ x
        # every family at once (one pass of numpy calls, not one per family: this runs every tick)
        lower, upper = np.concatenate((self.l, self.lb[:n])), np.concatenate((self.u, self.ub[:n]))
        value = np.concatenate((Cx, x[:n]))
        if np.max(np.maximum(lower - value, value - upper), initial=-np.inf) <= 0.0:
            return 0.0  # every row holds (the common case; an infinite bound is never violated)
        excess = np.concatenate((lower - value, value - upper))
        bound = np.concatenate((lower, upper))
        with np.errstate(invalid="ignore"):
            r = excess / (1.0 + np.abs(bound))
        return float(np.max(np.where(np.isfinite(bound), r, 0.0), initial=0.0))

    def residuals(self, x: np.ndarray) -> dict[str, float]:
        """Largest violation of each constraint family at x (0 when satisfied)."""
        out = {"equality": float(np.max(np.abs(self.A @ x - self.b), initial=0.0))}
        Cx = self.C @ x
        out["inequality"] = float(max(np.max(self.l - Cx, initial=0.0), np.max(Cx - self.u, initial=0.0), 0.0))
        out["bounds"] = float(max(np.max(self.lb - x, initial=0.0), np.max(x - self.ub, initial=0.0), 0.0))
        return out


@dataclass
class Solution:
    """What a solver returns: ``found`` and ``x``, its status word, iterations and solve time."""

    found: bool
    x: np.ndarray
    status: str
    iterations: int = 0
    solve_us: float = 0.0
    solver: str = ""


# A row counts as active in :func:`penalty_is_exact` within this much of its bound (relative to
# 1 + |bound|): loose enough for an ADMM answer polished to its own tolerance, and a row taken for
# active that is not can only make the test refuse (then the relaxed QP is solved: never wrong).
ACTIVE_RTOL = 1e-6
# The stationarity residual allowed, relative to ‖P x‖ + ‖c‖.
STATIONARITY_RTOL = 1e-6


def penalty_is_exact(problem: Problem, x: np.ndarray, l1: np.ndarray | float) -> bool:
    """Whether x, the solution of ``problem`` with its equality rows hard, is also the solution of
    the same QP with those rows soft at ℓ₁ weights ``l1`` (one per row, or one for all; inf: a row
    that stays hard), i.e. the slack would be zero: KKT multipliers y of the equality rows with
    |y_i| ≤ l1_i exist at x (the exact-penalty condition).

    The multipliers are found by non-negative least squares on the stationarity condition
    P x + c = Aᵀy + Σ_active ±C_iᵀλ_i + Σ_active ±e_j μ_j (λ, μ ≥ 0, y = y⁺ − y⁻), independently of
    whatever the solver reports; False when no multipliers make it hold (x is not optimal even for
    the hard problem) or when they exceed the weights (the relaxed QP gives a different answer).
    """
    from scipy.optimize import nnls

    x = np.asarray(x, float)
    g = problem.P @ x + problem.c
    scale = float(np.linalg.norm(problem.P @ x) + np.linalg.norm(problem.c))
    m = problem.A.shape[0]
    cols = [problem.A.T, -problem.A.T]
    Cx = problem.C @ x
    with np.errstate(invalid="ignore"):
        low = np.isfinite(problem.l) & (Cx - problem.l <= ACTIVE_RTOL * (1.0 + np.abs(problem.l)))
        up = np.isfinite(problem.u) & (problem.u - Cx <= ACTIVE_RTOL * (1.0 + np.abs(problem.u)))
        lb = np.isfinite(problem.lb) & (x - problem.lb <= ACTIVE_RTOL * (1.0 + np.abs(problem.lb)))
        ub = np.isfinite(problem.ub) & (problem.ub - x <= ACTIVE_RTOL * (1.0 + np.abs(problem.ub)))
    eye = np.eye(x.shape[0])
    cols += [problem.C[low].T, -problem.C[up].T, eye[:, lb], -eye[:, ub]]
    G = np.hstack(cols)
    if G.shape[1] == 0:
        return bool(np.linalg.norm(g) <= STATIONARITY_RTOL * scale)
    z, residual = nnls(G, g, maxiter=50 * G.shape[1])
    if not residual <= STATIONARITY_RTOL * max(scale, np.finfo(float).tiny):
        return False
    y = z[:m] - z[m : 2 * m]
    return bool(np.all(np.abs(y) <= np.broadcast_to(np.asarray(l1, float), (m,)) * (1.0 + 1e-9)))
