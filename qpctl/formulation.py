"""Stack tasks and constraints into the tick's QP (the layout of :mod:`qpctl.qp`).

The layout (variables, rows) is fixed on the first build and kept while the set of tasks and
constraints is unchanged, so the QP has the same shape on every tick and solvers can warm-start.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from qpctl.constraints.constraints import Constraint
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

    def build(self, state: TickState, terms: LawTerms, *, relax: bool = True) -> Problem:
        """The tick's QP; with ``relax=False`` soft equalities are kept hard (no slack variables)."""
        n = self.n
        H = np.zeros((n, n))
        c = np.zeros(n)
        eqs: list[Equality] = []
        for task in self.tasks:
            out = task.compute(state, terms)
            if isinstance(out, Objective):
                H += out.H
                c += out.c
            else:
                eqs.append(out)
        n_soft = sum(e.A.shape[0] for e in eqs if e.soft) if relax else 0
        n_eq = sum(e.A.shape[0] for e in eqs)
        nv = n + 2 * n_soft
        P = np.zeros((nv, nv))
        P[:n, :n] = H
        q = np.zeros(nv)
        q[:n] = c
        A = np.zeros((n_eq, nv))
        b = np.zeros(n_eq)
        r, s = 0, n
        for e in eqs:
            k = e.A.shape[0]
            A[r : r + k, :n] = e.A
            b[r : r + k] = e.b
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
        lo = np.full(self.n_in, -np.inf)
        hi = np.full(self.n_in, np.inf)
        lb = np.full(nv, -np.inf)
        ub = np.full(nv, np.inf)
        lb[n:] = 0.0  # s⁺, s⁻ ≥ 0
        r = 0
        for con in self.constraints:
            out = con.compute(state, terms)
            if isinstance(out, Inequality):
                k = out.C.shape[0]
                C[r : r + k, :n] = out.C
                lo[r : r + k] = out.lower
                hi[r : r + k] = out.upper
                r += k
            elif isinstance(out, Bounds):
                lb[:n] = np.maximum(lb[:n], out.lower)
                ub[:n] = np.minimum(ub[:n], out.upper)
        # Make P positive definite on the slack block even when slack_l2 = 0 (some solvers need it).
        for i in range(n, nv):
            P[i, i] = max(P[i, i], 1e-9)
        return Problem(P, q, A, b, C, lo, hi, lb, ub, n, self.row_names)
