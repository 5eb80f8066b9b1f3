"""Stack tasks and constraints into the tick's QP (the layout of :mod:`qpctl.qp`).

The layout (variables, rows) is fixed on the first build and kept while the set of tasks and
constraints is unchanged, so the QP has the same shape on every tick and solvers can warm-start.
What does not change from tick to tick (the slack variables' columns, costs and bounds, the
placeholder rows) is kept in a template that each build copies and fills.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from qpctl.constraints.constraints import Constraint, ObstacleBarrier
from qpctl.law import LawTerms
from qpctl.qp import Bounds, Equality, Inequality, Objective, Problem
from qpctl.state import TickState
from qpctl.tasks.tasks import Task


class Formulation:
    """Turns tasks (costs, soft/hard rows) and constraints (rows, bounds) into a :class:`Problem`."""

    def __init__(self, n: int, tasks: Sequence[Task], constraints: Sequence[Constraint]) -> None:
        self.n = n
        self.tasks = list(tasks)
        self.constraints = list(constraints)
        self.n_in = sum(c.rows for c in self.constraints)
        self.row_names = [c.name for c in self.constraints for _ in range(c.rows)]
        self.row_kinds = [c.kind for c in self.constraints for _ in range(c.rows)]
        # (name, first row, end row) of each constraint with rows, for per-tick diagnostics
        ends = np.cumsum([c.rows for c in self.constraints]).tolist()
        self.row_ranges = [(c.name, e - c.rows, e) for c, e in zip(self.constraints, ends) if c.rows]
        # the ObstacleBarrier's rows of C (what the tests look at; the fallbacks find every barrier's
        # rows by kind: Problem.rows_of)
        self.barrier_rows = next((slice(lo, hi) for name, lo, hi in self.row_ranges
                                  if name == ObstacleBarrier.name), slice(0, 0))
        self._templates: dict[tuple[Any, ...], tuple[np.ndarray, ...]] = {}
        self._evaluated: tuple[TickState, LawTerms, Any] | None = None

    def _evaluate(self, state: TickState, terms: LawTerms) -> tuple[list[Objective], list[Equality], list[Any]]:
        """Every task's and constraint's output at this tick (computed once per tick, even if the
        problem is built twice, hard then relaxed)."""
        if self._evaluated is not None and self._evaluated[0] is state and self._evaluated[1] is terms:
            return self._evaluated[2]
        objectives: list[Objective] = []
        eqs: list[Equality] = []
        for task in self.tasks:
            out = task.compute(state, terms)
            if isinstance(out, Objective):
                objectives.append(out)
            else:
                eqs.append(out)
        rows = [con.compute(state, terms) for con in self.constraints]
        result = (objectives, eqs, rows)
        self._evaluated = (state, terms, result)
        return result

    def dropped(self, state: TickState, terms: LawTerms) -> int:
        """What the constraints left out at this tick (:attr:`~qpctl.qp.Inequality.dropped`: pairs
        beyond the obstacle barrier's capacity)."""
        _, _, rows = self._evaluate(state, terms)
        return sum(out.dropped for out in rows if isinstance(out, Inequality))

    def penalty_weights(self, state: TickState, terms: LawTerms) -> np.ndarray:
        """The ℓ₁ slack weight of each equality row at this tick (inf for a row that is hard
        whether or not the problem is relaxed): see :func:`qpctl.qp.penalty_is_exact`."""
        _, eqs, _ = self._evaluate(state, terms)
        return np.concatenate([np.full(e.A.shape[0], e.slack_l1 if e.soft else np.inf) for e in eqs] or [np.zeros(0)])

    def _template(self, eqs: list[Equality], relax: bool) -> tuple[np.ndarray, ...]:
        """(P, q, A, b, C, l, u, lb, ub) with every tick-independent entry set: the slack columns of A
        (±I), their costs (ℓ₁ in q, ℓ₂ on P's diagonal, at least 1e-9 so that P is positive definite
        on the slack block even when slack_l2 = 0 — some solvers need it), s± ≥ 0, the constraints'
        slack columns σ ≥ 0 (:meth:`Constraint.slack_columns`, in their rows of C, after s±; kept with
        the task hard too), and the placeholder bounds (±inf)."""
        key = (relax, tuple((e.A.shape[0], e.soft, e.slack_l1, e.slack_l2) for e in eqs))
        cached = self._templates.get(key)
        if cached is not None:
            return cached
        # the constraints' own slack columns (Constraint.slack_columns: one or more per constraint with a
        # ``slack``), after the task's: read here, once per template, not every tick
        sl = [(r0, c.rows, col, w) for c, r0 in zip(self.constraints, np.cumsum([0] + [c.rows for c in self.constraints]))
              if c.slack is not None and c.rows for entries, weights in [c.slack_columns()]
              for col, w in zip(entries.T, weights, strict=True)]
        n = self.n
        n_soft = sum(e.A.shape[0] for e in eqs if e.soft) if relax else 0
        n_eq = sum(e.A.shape[0] for e in eqs)
        nv = n + 2 * n_soft + len(sl)
        P = np.zeros((nv, nv))
        q = np.zeros(nv)
        A = np.zeros((n_eq, nv))
        r, s = 0, n
        for e in eqs:
            k = e.A.shape[0]
            if e.soft and relax:
                idx_p = np.arange(s, s + k)
                idx_m = np.arange(s + n_soft, s + n_soft + k)
                A[r : r + k, s : s + k] = np.eye(k)
                A[r : r + k, s + n_soft : s + n_soft + k] = -np.eye(k)
                q[idx_p] = q[idx_m] = e.slack_l1
                P[idx_p, idx_p] = P[idx_m, idx_m] = e.slack_l2
                s += k
            r += k
        C = np.zeros((self.n_in, nv))
        for j, (r0, rows, entries, weights) in enumerate(sl):
            col = n + 2 * n_soft + j
            q[col], P[col, col] = weights
            C[r0 : r0 + rows, col] = entries
        for i in range(n, nv):
            P[i, i] = max(P[i, i], 1e-9)
        lb = np.full(nv, -np.inf)
        lb[n:] = 0.0  # s⁺, s⁻, σ ≥ 0
        template = (P, q, A, np.zeros(n_eq), C, np.full(self.n_in, -np.inf),
                    np.full(self.n_in, np.inf), lb, np.full(nv, np.inf))
        self._templates[key] = template
        return template

    def build(self, state: TickState, terms: LawTerms, *, relax: bool = True) -> Problem:
        """The tick's QP; with ``relax=False`` soft equalities are kept hard (no slack variables)."""
        n = self.n
        objectives, eqs, rows = self._evaluate(state, terms)
        P, q, A, b, C, lo, hi, lb, ub = (a.copy() for a in self._template(eqs, relax))
        for obj in objectives:
            P[:n, :n] += obj.H
            q[:n] += obj.c
        r = 0
        for e in eqs:
            k = e.A.shape[0]
            A[r : r + k, :n] = e.A
            b[r : r + k] = e.b
            r += k
        r = 0
        for out in rows:
            if isinstance(out, Inequality):
                k = out.C.shape[0]
                C[r : r + k, :n] = out.C
                lo[r : r + k] = out.lower
                hi[r : r + k] = out.upper
                r += k
            elif isinstance(out, Bounds):
                np.maximum(lb[:n], out.lower, out=lb[:n])
                np.minimum(ub[:n], out.upper, out=ub[:n])
        return Problem(P, q, A, b, C, lo, hi, lb, ub, n, self.row_names, self.row_kinds)
