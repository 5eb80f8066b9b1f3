"""Benchmarks: the QP against the closed forms, per solver, on the same ticks; run by ``qpctl bench``.

* :mod:`benchmarks.scenes` — the benchmark scenes: the paper's, seeded random planar scenes, and
  the Panda reaching fruit in a canopy of branches and leaves (also tiled into larger orchards).
* :mod:`benchmarks.timing` — record the states of a closed-loop run, then time every controller's
  tick on those same states in interleaved order.
* :mod:`benchmarks.suites` — the suites: closed-loop quality, same-tick timing, scaling.
* :mod:`benchmarks.report` — ``results.json``, the Markdown tables and the plots.
* :mod:`benchmarks.harness` — :func:`~benchmarks.harness.main`, what ``qpctl bench`` calls.
"""
