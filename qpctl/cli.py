"""The ``qpctl`` command line: ``simulate``, ``bench``, ``sweep``, ``solvers``, ``warmup``.

Any :class:`~qpctl.errors.QpctlError` (or an ``OSError`` reading or writing files) becomes one line on
stderr and exit status 2; any other exception (a bug) one line and exit status 3, with the traceback
only when the environment sets ``QPCTL_DEBUG=1``.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from pathlib import Path

from qpctl.errors import QpctlError


def _cmd_simulate(args: argparse.Namespace) -> int:
    from qpctl.run import simulate, write_outputs
    from qpctl.scenario import Scenario

    scenario = Scenario.load(args.scenario, args.set or [])
    result = simulate(scenario, kind=args.controller, solver=args.solver, simulator=args.sim,
                      progress=not args.quiet)
    out = Path(args.out) if args.out else Path("results") / f"{scenario.name}-{result.controller.kind}"
    write_outputs(result, out, figures=not args.no_figures)
    m = result.metrics
    print(f"{scenario.name} / {m['controller']} ({m['solver']}, {m['simulator']}): "
          f"max tracking error {m['max_tracking_error']:.3g} m, max |τ| {m['max_abs_torque']:.4g} N·m, "
          f"min clearance {m['min_clearance'] if m['min_clearance'] is None else round(m['min_clearance'], 4)} m, "
          f"collided {m['collided']}, tick median {m['tick_us_median']:.0f} µs -> {out}")
    for note in m.get("simulator_notes", []):
        print(f"  {m['simulator']}: {note}")
    return 0


def _cmd_sweep(args: argparse.Namespace) -> int:
    from qpctl.errors import ConfigError

    if args.summarize:
        from qpctl.sweep.summary import summarize

        if args.spec:
            raise ConfigError("give either SPEC or --summarize DIR, not both", key="--summarize")
        written = summarize(args.summarize)
        print(f"summary of {args.summarize}: " + ", ".join(str(p) for p in written))
        return 0
    if not args.spec:
        raise ConfigError("give a sweep spec (a .toml file or a packaged name such as canopy_small), "
                          "or --summarize DIR", key="SPEC")
    if args.jobs is not None and args.jobs < 1:
        raise ConfigError(f"must be >= 1, got {args.jobs}", key="--jobs")
    from qpctl.sweep.driver import run_sweep
    from qpctl.sweep.spec import SweepSpec
    from qpctl.sweep.summary import summarize

    spec = SweepSpec.load(args.spec)
    out = Path(args.out) if args.out else Path("results") / f"sweep-{spec.name}"
    report = run_sweep(spec, out, backend=args.backend, jobs=args.jobs, address=args.address,
                       progress=not args.quiet, limit=args.limit)
    print(report.line())
    if not args.no_summary:
        written = summarize(out)
        print(f"summary: {', '.join(str(p) for p in written)}")
    return 0


def _cmd_solvers(args: argparse.Namespace) -> int:
    from qpctl.solvers import describe_solvers

    for line in describe_solvers():
        print(line)
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    from qpctl.bench.harness import main as bench_main

    return int(bench_main(quick=args.quick, out=Path(args.out)) or 0)


def _cmd_warmup(args: argparse.Namespace) -> int:
    import time

    start = time.perf_counter()
    import numba

    from qpctl.kernels import tick
    from qpctl.warmup import warmup

    times = warmup()
    cache = tick.state.stats.cache_path
    total = time.perf_counter() - start
    print(f"the tick's kernels are ready in {total:.1f} s (numba {numba.__version__}; cache: {cache}); "
          + ", ".join(f"{k} {v:.2f} s" for k, v in times.items()))
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="qpctl", description=__doc__.splitlines()[0] if __doc__ else None)
    sub = p.add_subparsers(dest="command", required=True)
    s = sub.add_parser("simulate", help="run a scenario and write trajectory.npz, metrics.json, figures")
    s.add_argument("scenario", help="path to a .toml scenario or the name of a packaged one (e.g. paper)")
    from qpctl.controllers.factory import controller_kinds

    s.add_argument("--controller", choices=controller_kinds(), help="override controller.kind")
    s.add_argument("--solver", help="override controller.solver (see `qpctl solvers`)")
    from qpctl.adapters import SIMULATORS

    s.add_argument("--sim", choices=list(SIMULATORS), help="override sim.simulator")
    s.add_argument("--out", help="output folder (default results/<scenario>-<controller>)")
    s.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a scenario key by dotted path")
    s.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=_cmd_simulate)
    b = sub.add_parser("bench", help="benchmark the controllers side by side")
    b.add_argument("--quick", action="store_true", help="a run of under two minutes")
    b.add_argument("--out", default="results/bench", help="output folder")
    b.set_defaults(func=_cmd_bench)
    sw = sub.add_parser("sweep", help="run a sweep spec (local processes or Ray) into a Parquet dataset, resumable")
    sw.add_argument("spec", nargs="?", help="path to a sweep .toml or the name of a packaged one (e.g. canopy_small)")
    sw.add_argument("--backend", choices=["local", "ray"], default="local", help="local processes (default) or Ray")
    sw.add_argument("--address", help="Ray cluster: auto or ray://host:port (default: start a local instance)")
    sw.add_argument("--jobs", type=int, help="local worker processes, or a local Ray instance's CPUs (default: cores)")
    sw.add_argument("--out", help="sweep folder (default results/sweep-<name>); rerunning into it resumes")
    sw.add_argument("--limit", type=int, help="run at most this many of the runs not yet done")
    sw.add_argument("--summarize", metavar="DIR", help="only write DIR's tables and plots (summary.md, .csv, PNGs)")
    sw.add_argument("--no-summary", action="store_true", help="skip the tables and plots after the sweep")
    sw.add_argument("--quiet", action="store_true", help="no progress bar")
    sw.set_defaults(func=_cmd_sweep)
    v = sub.add_parser("solvers", help="list the installed QP solvers and their fast paths")
    v.set_defaults(func=_cmd_solvers)
    w = sub.add_parser("warmup", help="compile the per-tick kernels into numba's on-disk cache")
    w.set_defaults(func=_cmd_warmup)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except QpctlError as exc:
        print(f"qpctl: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except OSError as exc:  # an output folder that cannot be written, a file that cannot be read
        print(f"qpctl: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("qpctl: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # a bug, but still one line (QPCTL_DEBUG=1 shows the traceback)
        if os.environ.get("QPCTL_DEBUG"):
            raise
        print(f"qpctl: internal error: {type(exc).__name__}: {_one_line(exc)} "
              "(a bug: please report it; QPCTL_DEBUG=1 shows the traceback)", file=sys.stderr)
        return 3


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).splitlines())


if __name__ == "__main__":
    sys.exit(main())
