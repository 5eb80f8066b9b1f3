"""The ``qpctl`` command line: ``simulate``, ``replay``, ``bench``, ``sweep``, ``solvers``, ``warmup``, ``fit-capsules``.

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
    write_outputs(result, out, figures=not args.no_figures, replay=not args.no_replay)
    m = result.metrics
    print(f"{scenario.name} / {m['controller']} ({m['solver']}, {m['simulator']}): "
          f"max tracking error {m['max_tracking_error']:.3g} m, max |τ| {m['max_abs_torque']:.4g} N·m, "
          f"min clearance {m['min_clearance'] if m['min_clearance'] is None else round(m['min_clearance'], 4)} m, "
          f"collided {m['collided']}, tick median {m['tick_us_median']:.0f} µs -> {out}")
    for note in m.get("simulator_notes", []):
        print(f"  {m['simulator']}: {note}")
    return 0


def _cmd_replay(args: argparse.Namespace) -> int:
    from qpctl.errors import ConfigError
    from qpctl.replay import REPLAY_FILE, from_run_dir, write_replay

    if args.at is not None and not args.screenshot:
        raise ConfigError("sets the time of --screenshot; give --screenshot PNG too", key="--at")
    out = Path(args.out) if args.out else Path(args.run_dir) / REPLAY_FILE
    stats = write_replay(from_run_dir(args.run_dir), out, fps=args.fps)
    print(f"{out}: {stats.bytes / 1e6:.2f} MB, {stats.frames} frames, robot drawn with its {stats.robot_drawn_as}, "
          f"written in {stats.seconds:.2f} s")
    if args.screenshot:
        from qpctl.replay.browser import render

        width, _, height = args.size.partition("x")
        if not (width.isdigit() and height.isdigit() and int(width) > 0 and int(height) > 0):
            raise ConfigError(f"must be WIDTHxHEIGHT in pixels, e.g. 1280x800, got {args.size!r}", key="--size")
        shot = render(out, at=args.at, width=int(width), height=int(height), params={"notices": "0"})
        Path(args.screenshot).write_bytes(shot.png)
        from qpctl.plots import compact_png

        compact_png(Path(args.screenshot), octree=True)  # 256 colours: a third of the size, small enough for a README
        problems = shot.errors + [f"requested {url}" for url in shot.requests]
        print(f"{args.screenshot}: at t = {shot.state.get('time')} s (frame {shot.state.get('frame')}), "
              f"{len(problems)} console errors or outside requests" + (": " + "; ".join(problems) if problems else ""))
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


def _cmd_fit_capsules(args: argparse.Namespace) -> int:
    from qpctl.errors import ConfigError
    from qpctl.robot.capsules import fit_robot, write_capsules

    if args.max_capsules not in (1, 2, 3):
        raise ConfigError(f"must be 1, 2 or 3, got {args.max_capsules}", key="--max-capsules")
    path, fits = fit_robot(args.robot, skip=args.skip or (), max_capsules=args.max_capsules)
    command = " ".join(["qpctl fit-capsules", args.robot]
                       + (["--max-capsules", str(args.max_capsules)] if args.max_capsules != 3 else [])
                       + [f"--skip {s}" for s in args.skip or ()])
    out = write_capsules(fits, args.out, robot=args.robot if args.robot == "panda" else path.stem,
                         source=str(path), command=command)
    for fit in fits:
        print(fit.line())
    worst = max(fits, key=lambda f: f.ratio)
    print(f"{sum(len(f.capsules) for f in fits)} capsules on {len(fits)} links of {path.name}; largest volume ratio "
          f"{worst.ratio:.2f} ({worst.link}) -> {out}")
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
    s.add_argument("--no-replay", action="store_true", help="skip the replay page (replay.html)")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=_cmd_simulate)
    r = sub.add_parser("replay", help="write a run folder's replay page (RUN_DIR/replay.html), optionally a screenshot")
    r.add_argument("run_dir", metavar="RUN_DIR", help="the output folder of qpctl simulate")
    r.add_argument("--out", help="the page to write (default RUN_DIR/replay.html)")
    r.add_argument("--fps", type=float, default=30.0, help="display frames per second (default 30)")
    r.add_argument("--screenshot", metavar="PNG", help="also render the page in headless Chromium into PNG")
    r.add_argument("--at", type=float, help="the screenshot's time [s] (default: as the page opens)")
    r.add_argument("--size", default="1280x800", help="the screenshot's window, WIDTHxHEIGHT (default 1280x800)")
    r.set_defaults(func=_cmd_replay)
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
    fc = sub.add_parser("fit-capsules", help="fit collision capsules to a robot's link meshes into a TOML file")
    fc.add_argument("robot", help="panda, a .urdf or MJCF .xml file, or package://example-robot-data/robots/<file>")
    fc.add_argument("--out", required=True, help="the capsules file to write (robot.capsules reads it)")
    fc.add_argument("--max-capsules", type=int, default=3, help="capsules per link at most: 1, 2 or 3 (default 3: "
                    "a third only where two exceed twice the link's convex hull)")
    fc.add_argument("--skip", action="append", metavar="LINK", help="leave this link without capsules (repeatable)")
    fc.set_defaults(func=_cmd_fit_capsules)
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
