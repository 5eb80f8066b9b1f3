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
    """l ≤ C q̈ ≤ u (rows with l = −inf and u = +inf are inactive placeholders)."""

    C: np.ndarray
    lower: np.ndarray
    upper: np.ndarray


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
    row_names: list[str] = field(default_factory=list)  # one per row of C

    @property
    def n_var(self) -> int:
        return int(self.P.shape[0])

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
