"""``qpctl bench``: the tick-time benchmark (DESIGN.md §4) and the seeded scene families it shares
with ``qpctl sweep``.

* :mod:`qpctl.bench.scenes` — the scenes: the paper's, the Panda with 10 spheres, the same with no
  obstacles, seeded random planar scenes and Panda canopies, and an orchard of tiled canopies;
* :mod:`qpctl.bench.timing` — tick times on recorded states, the floor (``pin.computeAllTerms``);
* :mod:`qpctl.bench.suites` — closed loop, same ticks, scaling;
* :mod:`qpctl.bench.harness` — a whole run (``qpctl bench [--quick]``) into ``results.json``;
* :mod:`qpctl.bench.report` — its Markdown and plots, and the Performance page (docs/performance.md).

The studies built on them (harvesting, robustness, latency, profiles, simulators, sweep throughput)
are applications in the top-level ``benchmarks/`` folder.
"""
