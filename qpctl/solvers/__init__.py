"""QP solvers behind one interface, chosen by name in configuration.

* ``proxqp`` — fast path: a dense proxsuite problem object built once and updated every tick,
  warm-started with the previous primal and dual solution.
* ``osqp`` — fast path: an OSQP problem set up once with a fixed sparsity pattern, ``update``d
  every tick, warm-started, solution polished.
* ``daqp`` — fast path: DAQP's dual active-set ``solve`` called directly with arrays kept from tick
  to tick, warm-started with the previous multipliers (the fastest on these small dense QPs).
* every other solver that :mod:`qpsolvers` finds installed (``quadprog``, ``clarabel``,
  ...) — the generic path: a :class:`qpsolvers.Problem` built and solved every tick. The fast-path
  names can be forced through it too with the prefix ``qpsolvers:`` (e.g. ``qpsolvers:proxqp``).
"""

from qpctl.solvers.base import QPSolver, available_solvers, describe_solvers, make_solver

__all__ = ["QPSolver", "available_solvers", "describe_solvers", "make_solver"]
