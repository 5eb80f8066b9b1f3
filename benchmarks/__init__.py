"""Benchmarks: the QP against the closed forms, per solver, on the same ticks; run by ``qpctl bench``.

* :mod:`qpctl.bench.scenes` — the benchmark scenes: the paper's, seeded random planar scenes, and
  the Panda reaching fruit in a canopy of branches and leaves (also tiled into larger orchards).
* :mod:`qpctl.bench.timing` — record the states of a closed-loop run, then time every controller's
  tick on those same states in interleaved order.
* :mod:`qpctl.bench.suites` — the suites: closed-loop quality, same-tick timing, scaling.
* :mod:`qpctl.bench.report` — ``results.json``, the Markdown tables and the plots.
* :mod:`qpctl.bench.harness` — :func:`~qpctl.bench.harness.main`, what ``qpctl bench`` calls.
"""
