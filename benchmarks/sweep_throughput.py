"""Sweep throughput (``make sweep-throughput``): runs/min of the sweep engine, 1 and 2 local workers and Ray.

    python -m benchmarks.sweep_throughput [--spec canopy_1k] [--runs 100] [--out results/sweep-throughput]

The first ``--runs`` runs of ``--spec`` (default: 100 runs of ``canopy_1k``, 1.5 s Panda canopy runs,
every law) are swept three times into fresh folders: local backend with 1 worker, with 2 workers, and
a local Ray instance with 2 CPUs. Each wall time includes starting the workers (the Ray instance's
``ray.init`` is timed apart and also shown included). Writes ``throughput.json`` and
``throughput.md`` (the throughput table of docs/sweeps.md and its 10⁵-run projection) into ``--out``.
Timings are measurements of this machine at this load (the load average is recorded), never asserted.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from qpctl.bench import report
from qpctl.sweep.driver import run_sweep
from qpctl.sweep.spec import SweepSpec
from qpctl.sweep.store import read_dataset

PROJECTION_RUNS = 100_000
PROJECTION_NODES = ((1, 2), (10, 16), (100, 16))  # (nodes, cores each)


def wait_quiet(max_wait: float, *, threshold: float = 0.15, sample: float = 5.0) -> float | None:
    """Wait (at most ``max_wait`` seconds) until the machine's busy cores over ``sample`` seconds fall below
    ``threshold``; return the last sample (None without /proc/stat)."""
    deadline = time.monotonic() + max_wait
    while True:
        b0 = _busy_cpu_s()
        time.sleep(sample)
        b1 = _busy_cpu_s()
        if b0 is None or b1 is None:
            return None
        cores = (b1 - b0) / sample
        if cores < threshold or time.monotonic() > deadline:
            return cores


def _measure(spec: SweepSpec, runs: int, backend: str, jobs: int) -> dict[str, Any]:
    folder = Path(tempfile.mkdtemp(prefix=f"throughput-{backend}{jobs}-"))
    try:
        init_s = 0.0
        if backend == "ray":
            import ray

            t0 = time.perf_counter()
            ray.init(address="local", num_cpus=jobs, include_dashboard=False, log_to_driver=False,
                     configure_logging=False)
            init_s = time.perf_counter() - t0
        load = report.load_average()
        busy0 = _busy_cpu_s()
        try:
            rep = run_sweep(spec, folder, backend=backend, jobs=jobs, progress=False, limit=runs)
        finally:
            if backend == "ray":
                import ray

                ray.shutdown()
        busy = _busy_cpu_s() - busy0 if busy0 is not None else None
        rows = read_dataset(folder).to_pylist()
        inside = sum(r["wall_s"] for r in rows)  # seconds inside the runs themselves, summed over workers
        cpu = sum(r["cpu_s"] for r in rows)  # CPU seconds inside the runs: what a run costs on a core of its own
        # cores kept busy by everything else on the machine meanwhile (other users; our driver, pickling, Ray)
        others = (busy - cpu) / rep.wall_s if busy is not None else None
        write_ms = _write_ms(spec, rows)
        return {"backend": backend, "workers": jobs, "driver_write_ms": write_ms, "runs": rep.ran, "failed": rep.failed, "wall_s": rep.wall_s,
                "init_s": init_s, "runs_per_min": 60.0 * rep.ran / rep.wall_s,
                "runs_per_min_with_init": 60.0 * rep.ran / (rep.wall_s + init_s),
                "run_s_mean": inside / len(rows), "cpu_s_mean": cpu / len(rows), "other_cores": others, "worker_s_per_run": jobs * rep.wall_s / rep.ran,
                "load_average_start": load, "load_average_end": report.load_average()}
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def _write_ms(spec: SweepSpec, rows: list[dict[str, Any]]) -> float:
    """The driver's cost of storing one finished run [ms]: ``rows`` written again into a fresh store."""
    from qpctl.sweep.store import RunStore

    folder = Path(tempfile.mkdtemp(prefix="throughput-write-"))
    try:
        store = RunStore(folder, spec)
        store.open(len(rows))
        t0 = time.perf_counter()
        for r in rows:
            store.write(r)
        return 1e3 * (time.perf_counter() - t0) / len(rows)
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def _busy_cpu_s() -> float | None:
    """CPU seconds the whole machine has spent busy (not idle, not waiting) since boot (/proc/stat)."""
    try:
        fields = [float(x) for x in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]
    except (OSError, ValueError, IndexError):
        return None
    idle = fields[3] + (fields[4] if len(fields) > 4 else 0.0)
    return (sum(fields[:8]) - idle) / os.sysconf("SC_CLK_TCK")


def markdown(res: dict[str, Any]) -> str:
    m = {(r["backend"], r["workers"]): r for r in res["measurements"]}
    one, two, ray = m.get(("local", 1)), m.get(("local", 2)), m.get(("ray", 2))
    lines = [(f"Measured by `{res['command']}`: the first {res['runs']} runs of `{res['spec']}` "
              f"({res['machine']['cpu']}, {res['machine']['cores']} cores; load average (1, 5, 15 min) at start "
              f"{res['load_average_start']}, at end {res['load_average_end']})."), "",
             ("| backend | workers | runs | wall [s] | runs/min | worker-seconds per run | mean run, wall [s] | "
              "mean run, CPU [s] | other cores busy | load average at start |"),
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in res["measurements"]:
        wall = f"{r['wall_s']:.1f}" + (f" (+ {r['init_s']:.1f} ray.init)" if r["init_s"] else "")
        lines.append(f"| {r['backend']} | {r['workers']} | {r['runs']} | {wall} | {r['runs_per_min']:.0f} | "
                     f"{r['worker_s_per_run']:.2f} | {r['run_s_mean']:.2f} | {r['cpu_s_mean']:.2f} | "
                     f"{'–' if r['other_cores'] is None else format(r['other_cores'], '.2f')} | "
                     f"{r['load_average_start']} |")
    lines += ["", ("Worker-seconds per run: workers × wall ÷ runs (what a run costs a worker, start-up and "
                   "waiting included). Mean run: inside the run function, wall-clock and CPU time. Other cores "
                   "busy: the machine's busy CPU time during the sweep (/proc/stat) less the runs' own, ÷ wall — "
                   "other users' processes, and the driver, worker start-up and Ray's own processes."), ""]
    if one and two:
        lines.append(f"- 2 local workers ÷ 1: **{two['runs_per_min'] / one['runs_per_min']:.2f}×** the runs/min.")
    if two and ray:
        per_run = (ray["wall_s"] - two["wall_s"]) * ray["workers"] / ray["runs"]
        lines.append(f"- Ray (a local instance with 2 CPUs) against 2 local workers: {ray['runs_per_min']:.0f} "
                     f"against {two['runs_per_min']:.0f} runs/min, {1e3 * per_run:+.0f} ms of worker time per run "
                     f"(wall difference × 2 ÷ runs), plus {ray['init_s']:.1f} s once for `ray.init`.")
    if two:
        write_s = two["driver_write_ms"] / 1e3
        cpu = two["cpu_s_mean"]
        cost = two["worker_s_per_run"]
        proj = ", ".join(f"{n} node{'s' if n > 1 else ''} × {c} cores: "
                         f"{_hours(PROJECTION_RUNS * cpu / (n * c))}–{_hours(PROJECTION_RUNS * cost / (n * c))}"
                         for n, c in PROJECTION_NODES)
        cap = 1.0 / write_s
        lines.append(f"- Projection to {PROJECTION_RUNS:,} such runs, one worker per core, from {cpu:.2f} s "
                     f"(a run's CPU time: cores of its own) to {cost:.2f} s (the measured worker-seconds per run "
                     f"of 2 local workers) per run: {proj}; plus each node's worker start-up (seconds). The "
                     f"driver stores each finished run itself ({1e3 * write_s:.1f} ms per row, measured), which "
                     f"caps one sweep at about {cap:.0f} runs/s: {PROJECTION_RUNS:,} runs take at least "
                     f"{_hours(PROJECTION_RUNS * write_s)} of driver time, so past about "
                     f"{cap * cpu:.0f} cores (runs of {cpu:.2f} s) the driver, not the cluster, sets the pace.")
    return "\n".join(lines) + "\n"


def _hours(seconds: float) -> str:
    if seconds >= 3600:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 60:.0f} min" if seconds >= 120 else f"{seconds:.0f} s"


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.sweep_throughput", description=__doc__.splitlines()[0])
    p.add_argument("--spec", default="canopy_1k")
    p.add_argument("--runs", type=int, default=100)
    p.add_argument("--out", default="results/sweep-throughput")
    p.add_argument("--backends", default="local1,local2,ray2", help="comma-separated: local1, local2, ray2")
    p.add_argument("--wait-quiet", type=float, default=0.0, metavar="SECONDS",
                   help="before each measurement wait up to this long for the machine to be idle (busy < 0.15 cores)")
    args = p.parse_args(argv)
    spec = SweepSpec.load(args.spec)
    res: dict[str, Any] = {"command": "python -m benchmarks.sweep_throughput " + " ".join(
        sys.argv[1:] if argv is None else argv), "spec": spec.name, "runs": args.runs, "machine": report.machine(),
        "load_average_start": report.load_average(), "measurements": []}
    for b in args.backends.split(","):
        backend, jobs = b.rstrip("0123456789"), int(b[len(b.rstrip("0123456789")):] or 1)
        idle = wait_quiet(args.wait_quiet) if args.wait_quiet > 0 else None
        print(f"measuring {backend} with {jobs} worker(s) …", file=sys.stderr)
        res["measurements"].append(_measure(spec, args.runs, backend, jobs) | {"busy_cores_before": idle})
    res["load_average_end"] = report.load_average()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "throughput.json").write_text(json.dumps(res, indent=2) + "\n")
    text = markdown(res)
    (out / "throughput.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    os.environ.setdefault("MPLBACKEND", "Agg")
    sys.exit(main())
