"""What a benchmark run writes: the machine block, ``results.md`` (Markdown tables) and the plots.

``results.json`` is the dictionary built by :func:`benchmarks.harness.run`; this module formats it.
"""

from __future__ import annotations

import importlib.metadata
import os
import platform
import sys
from pathlib import Path
from typing import Any

import numpy as np

PACKAGES = ("numpy", "pin", "python-fcl", "qpsolvers", "proxsuite", "osqp", "daqp", "quadprog", "scipy")

#: Targets of issue 4 (wall-clock tick times [µs] of the Panda in a 10-obstacle canopy; checked for the
#: proxqp and daqp fast paths).
TARGETS = {"ratio_to_paper": 1.5, "median_us": 100.0, "p99_us": 300.0, "scaling_1000_over_10": 3.0}


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo (or the platform's description)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine() -> dict[str, Any]:
    """CPU, cores, OS, Python and the versions of the packages that do the work."""
    versions = {}
    for name in PACKAGES:
        try:
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            versions[name] = None
    return {
        "cpu": cpu_model(),
        "cores": os.cpu_count(),
        "platform": platform.platform(),
        "python": sys.version.split()[0],
        "packages": versions,
    }


def load_average() -> list[float] | None:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


# -- Markdown -------------------------------------------------------------------------------------
def _f(x: Any, digits: int = 1) -> str:
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return "–"
    return f"{x:.{digits}f}"


def _g(x: Any) -> str:
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return "–"
    return f"{x:.3g}"


def _table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def machine_line(res: dict[str, Any]) -> str:
    m = res["machine"]
    pk = m["packages"]
    load = res.get("load_average", {})
    return (f"{m['cpu']}, {m['cores']} cores, Python {m['python']}; numpy {pk.get('numpy')}, pin {pk.get('pin')}, "
            f"python-fcl {pk.get('python-fcl')}, proxsuite {pk.get('proxsuite')}, osqp {pk.get('osqp')}, "
            f"daqp {pk.get('daqp')}, quadprog {pk.get('quadprog')}, qpsolvers {pk.get('qpsolvers')}; "
            f"load average {load.get('start')} at start, {load.get('end')} at end")


def same_ticks_table(res: dict[str, Any]) -> str:
    rows = []
    for robot, block in res["same_ticks"].items():
        for label, r in block["controllers"].items():
            st = r["stages_median"]
            rows.append([robot, label, _f(r["wall"]["median"]), _f(r["wall"]["p99"]), _f(r["wall"]["max"]),
                         _f(r["cpu"]["median"]), _f(r["cpu"]["p99"]), _f(r["ratio_to_paper"], 2),
                         _f(st.get("rigid_us")), _f(st.get("distance_us")), _f(st.get("build_us")),
                         _f(st.get("solve_us"))])
    return _table(["robot", "controller", "median µs", "p99 µs", "max µs", "CPU median µs", "CPU p99 µs",
                   "÷ paper (median)", "rigid µs", "distance µs", "QP build µs", "QP solve µs"], rows)


def quality_table(res: dict[str, Any]) -> str:
    rows = []
    for family, block in res["quality"]["summary"].items():
        for label, s in block.items():
            rows.append([family, label, f"{s['successes']}/{s['runs']}", _g(s["rms_tracking_error_median"]),
                         _g(s["max_tracking_error_max"]), _f(s["max_abs_torque_median"]),
                         _f(s["max_abs_torque_rate_median"], 0), _g(s["min_clearance_min"]),
                         _f(s["tick_us_median"]), _f(s["tick_us_p99"])])
    return _table(["scenes", "controller", "success", "RMS tracking error [m] (median)",
                   "max tracking error [m] (worst)", "peak |τ| [N·m] (median)", "peak |τ̇| [N·m/s] (median)",
                   "min clearance [m] (worst)", "tick median µs", "tick p99 µs"], rows)


def scaling_table(res: dict[str, Any]) -> str:
    sc = res["scaling"]
    rows = []
    for count, block in sc["counts"].items():
        row = [str(count), _f(block["pairs_median"], 0)]
        for label in sc["controllers"]:
            r = block["controllers"][label]
            row += [_f(r["wall"]["median"]), _f(r["wall"]["p99"]), _f(r["cpu"]["median"]),
                    _f(r["stages_median"].get("distance_us")), _f(r["relative_to_first"], 2)]
        rows.append(row)
    header = ["obstacles", "pairs within cutoff (median)"]
    for label in sc["controllers"]:
        header += [f"{label} median µs", f"{label} p99 µs", f"{label} CPU median µs", f"{label} distance µs",
                   f"{label} ÷ {sc['counts_list'][0]} obstacles"]
    return _table(header, rows)


def targets_table(res: dict[str, Any]) -> str:
    rows = [[t["target"], t["measured"], "met" if t["met"] else "**missed**"] for t in res["targets"]]
    return _table(["target (Panda canopy of 10 obstacles; scaling: tiled to 1000)", "measured", ""], rows)


STAGE_LEGEND = ("Wall time of `step()` (median / p99 / max) and the thread's CPU time (the same without the "
                "time slices other processes took); stages are medians: rigid = Pinocchio terms and "
                "Jacobians, distance = python-fcl (bound, broad phase, exact queries), QP build = the law's "
                "terms (a, g, e_N, q̈₀) + tasks + constraints (barrier drift included) + stacking, QP solve = "
                "the solver call. \"÷ paper\" = median tick ÷ the paper law's median tick on the same states.")


def markdown(res: dict[str, Any]) -> str:
    """The whole report (what ``results.md`` holds)."""
    cfg = res["config"]
    parts = [
        f"# qpctl benchmark ({'quick' if cfg['quick'] else 'full'} run)",
        f"Command: `{res['command']}`; {res['duration_s']:.0f} s. Machine: {machine_line(res)}.",
        (f"Seeds: planar scenes {cfg['planar_seeds']}, canopy scenes {cfg['canopy_seeds']}; "
         f"same-tick states from each scene's `{cfg['states_from']}` closed-loop run"
         + (f", one state in {cfg['timing_stride']}" if cfg["timing_stride"] > 1 else "") + "."),
        "## Same ticks: compute time per tick [µs], all controllers on identical states",
        STAGE_LEGEND,
        same_ticks_table(res),
        "## Targets",
        targets_table(res),
        (f"## Scaling with the scene: Panda canopy tiled to more obstacles, broad phase on "
         f"({res['scaling']['scene']}, same states)"),
        scaling_table(res),
        "## Closed loop: quality per controller (built-in RK4 simulator)",
        (f"Success = the task point ends within {res['quality']['reach_tolerance']} m of the target and no "
         "link ever touches an obstacle (least exact distance ≥ 0)."),
        quality_table(res),
    ]
    return "\n\n".join(parts) + "\n"


# -- plots ----------------------------------------------------------------------------------------
def write_plots(res: dict[str, Any], times: dict[str, Any], out: Path) -> list[Path]:
    """Tick-time distributions per robot, stage breakdown, scaling curve (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    robots = list(res["same_ticks"])
    fig, axes = plt.subplots(1, len(robots), figsize=(6 * len(robots), 4.5), squeeze=False)
    for ax, robot in zip(axes[0], robots):
        labels = list(times["same_ticks"][robot])
        data = [times["same_ticks"][robot][lb].wall for lb in labels]
        ax.boxplot(data, whis=(1, 99), showfliers=False)
        ax.set_xticks(range(1, len(labels) + 1), labels, rotation=30)
        ax.set_yscale("log")
        ax.set_ylabel("tick wall time [µs] (box: quartiles, whiskers: 1–99 %)")
        ax.set_title(f"{robot}: same ticks")
        ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    path = out / "tick_times.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    written.append(path)

    fig, axes = plt.subplots(1, len(robots), figsize=(6 * len(robots), 4.5), squeeze=False)
    stages = ("rigid_us", "distance_us", "build_us", "solve_us")
    for ax, robot in zip(axes[0], robots):
        ctrl = res["same_ticks"][robot]["controllers"]
        labels = list(ctrl)
        bottom = np.zeros(len(labels))
        for stage in stages:
            vals = np.array([ctrl[lb]["stages_median"].get(stage) or 0.0 for lb in labels])
            ax.bar(labels, vals, bottom=bottom, label=stage[:-3])
            bottom += vals
        other = np.array([ctrl[lb]["wall"]["median"] for lb in labels]) - bottom
        ax.bar(labels, np.maximum(other, 0), bottom=bottom, label="law + rest")
        ax.set_ylabel("median [µs]")
        ax.set_title(f"{robot}: where the tick goes")
        ax.tick_params(axis="x", rotation=30)
        ax.legend(fontsize=8)
    fig.tight_layout()
    path = out / "stages.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    written.append(path)

    sc = res["scaling"]
    fig, ax = plt.subplots(figsize=(6, 4.5))
    counts = [int(c) for c in sc["counts"]]
    for label in sc["controllers"]:
        med = [sc["counts"][str(c)]["controllers"][label]["wall"]["median"] for c in counts]
        p99 = [sc["counts"][str(c)]["controllers"][label]["wall"]["p99"] for c in counts]
        line, = ax.plot(counts, med, "o-", label=f"{label} median")
        ax.plot(counts, p99, "s--", color=line.get_color(), alpha=0.6, label=f"{label} p99")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("obstacles in the scene")
    ax.set_ylabel("tick wall time [µs]")
    ax.set_title("Panda canopy, broad phase on, same states")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path = out / "scaling.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    written.append(path)
    return written


def headline_table(res: dict[str, Any]) -> str:
    """Per robot: each controller's median / p99 wall tick and CPU median on the same ticks, and ÷ paper."""
    rows = []
    for robot, block in res["same_ticks"].items():
        for label, r in block["controllers"].items():
            rows.append([robot, label, _f(r["wall"]["median"], 0), _f(r["wall"]["p99"], 0), _f(r["cpu"]["median"], 0),
                         _f(r["cpu"]["p99"], 0), f"{r['ratio_to_paper']:.2f}×"])
    return _table(["robot", "controller", "median µs", "p99 µs", "CPU median µs", "CPU p99 µs", "÷ paper law"], rows)


def compact_scaling_table(res: dict[str, Any]) -> str:
    sc = res["scaling"]
    rows = []
    for count, block in sc["counts"].items():
        row = [count, _f(block["pairs_median"], 0)]
        for label in sc["controllers"]:
            r = block["controllers"][label]
            row += [_f(r["wall"]["median"], 0), f"{r['relative_to_first']:.2f}×"]
        rows.append(row)
    header = ["obstacles", "pairs within cutoff"]
    for label in sc["controllers"]:
        header += [f"{label} median µs", f"{label} ÷ {sc['counts_list'][0]} obstacles"]
    return _table(header, rows)


def performance_section(res: dict[str, Any]) -> str:
    """The tables of the README's "## Performance" section (the prose around them is written by hand)."""
    return "\n\n".join([f"Machine: {machine_line(res)}.", headline_table(res), targets_table(res),
                        compact_scaling_table(res), quality_table(res)]) + "\n"


if __name__ == "__main__":  # python -m benchmarks.report results/bench/results.json
    import json

    print(performance_section(json.loads(Path(sys.argv[1]).read_text())))
