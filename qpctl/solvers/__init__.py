"""QP solvers behind one interface, chosen by name in configuration.

* ``proxqp`` — fast path: a dense proxsuite problem object built once and updated every tick,
  warm-started with the previous primal and dual solution.
* ``osqp`` — fast path: an OSQP problem set up once with a fixed sparsity pattern, ``update``d
  every tick, warm-started, solution polished.
* every other solver that :mod:`qpsolvers` finds installed (``daqp``, ``quadprog``, ``clarabel``,
  ...) — the generic path: a :class:`qpsolvers.Problem` built and solved every tick. The fast-path
  names can be forced through it too with the prefix ``qpsolvers:`` (e.g. ``qpsolvers:proxqp``).
"""

from qpctl.solvers.base import QPSolver, available_solvers, describe_solvers, make_solver

__all__ = ["QPSolver", "available_solvers", "describe_solvers", "make_solver"]
