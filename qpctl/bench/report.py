"""What a benchmark run writes: the machine block, ``results.md`` (Markdown tables) and the plots.

``results.json`` is the dictionary built by :func:`qpctl.bench.harness.run`; this module formats it.
:func:`performance_section` is docs/performance.md's "## Performance" section, from a ``results.json``:

    python -m qpctl.bench.report results/bench/results.json [--demo-wall-s SECONDS]
"""

from __future__ import annotations

import importlib.metadata
import os
import platform
import sys
from pathlib import Path
from typing import Any

import numpy as np

from qpctl.bench.timing import BLOCK

PACKAGES = ("numpy", "numba", "pin", "python-fcl", "qpsolvers", "proxsuite", "osqp", "daqp", "quadprog", "clarabel",
            "scipy")

#: Targets of issue #10 (wall-clock tick times [µs] on the same recorded ticks, controllers interleaved;
#: checked for the default QP, daqp, and the paper law): the limit of each, see
#: :func:`qpctl.bench.harness._targets`.
TARGETS = {
    "spheres_qp_median_us": 30.0,  # Panda + 10 spheres, QP median
    "spheres_qp_p99_us": 80.0,  # Panda + 10 spheres, QP p99
    "spheres_paper_median_us": 15.0,  # Panda + 10 spheres, paper law median
    "free_qp_median_us": 16.0,  # Panda, no obstacles, QP median (issue #10's figure for TSID's tick)
    "canopy_over_spheres": 1.3,  # Panda canopy QP median ÷ Panda + 10 spheres QP median
    "paper_arm_qp_median_us": 20.0,  # planar paper arm, QP median
    "scaling_over_first": 1.5,  # 1000 obstacles ÷ 10 obstacles, QP median
    "qp_over_floor": 12.0,  # Panda + 10 spheres, QP median ÷ computeAllTerms' median
    "paper_over_floor": 6.0,  # Panda + 10 spheres, paper law median ÷ computeAllTerms' median
    "harvest_over_position": 1.25,  # panda_harvest, approach task + self rows ÷ position task, QP median (issue 11)
}
#: Issue 23's tighter tick targets on the Panda + 10 spheres (medians [µs], same ticks as above), drawn
#: beside issue #10's in ``tick_times.png``; the report's prose states whether they were met.
TARGETS_23 = {"spheres_qp_median_us": 16.0, "spheres_paper_median_us": 10.0}
#: TSID's tick on the nearest task without obstacles (the Panda's end-effector position task on the
#: panda_spheres path, posture, actuation and joint position/speed/acceleration bounds; eiquadprog-fast),
#: measured by ``benchmarks/tsid_tick.py`` beside qpctl's QP on the same states, not by this benchmark.
TSID_US = 9.8
TSID_CREDIT = ("TSID 1.10 built from its sdists against pin 4.1, side by side with qpctl's QP (15.7–16.1 µs "
               "with its 10 spheres) on the same panda_spheres states in one process, three runs of 2,500 "
               "ticks, idle 2-core Intel Xeon, 2026-12-03 (`benchmarks/tsid_tick.py`, a scratch environment; "
               "issue #10's earlier figure was 16 µs, issue 23's 23 µs); on 2026-12-06 the same script gave "
               "TSID 11.5–13.1 µs against qpctl's 12.8–14.5 µs (TSID ÷ qpctl 0.90, the floor 3.4–3.9 µs; "
               "0.61–0.64 on 2026-12-03), after the equality shortcut 0.89–0.95 (0.84–0.90 the code "
               "before, alternated, the floor 5.2–5.5 µs), after the answer on DAQP's last working set "
               "0.89–0.97, median 0.935 (0.87–1.04, median 0.94, the code before, eight runs each alternated, "
               "the floor 4.1–6.2 µs), after the data's check by its bits and the answer's row products reused "
               "0.92–1.03, median 0.99 (0.88–1.03, median 1.00, the code before, fourteen runs each alternated, "
               "the floor 3.5–5.3 µs); not measured by this benchmark")


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
            versions[name] = None  # type: ignore[assignment]  # not installed: null in results.json
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
#: Per-tick breakdown columns (qpctl.bench.timing.BREAKDOWN), repeated here so that formatting a
#: results.json needs no import of the library.
BREAKDOWN = (("pinocchio_us", "Pinocchio"), ("state_kernel_us", "state kernel"), ("law_rows_us", "law + rows"),
             ("solve_us", "solve"), ("other_us", "other"))
TARGET_GROUPS = ("spheres", "free", "canopy", "paper")
FLOOR = "floor"
TARGET_QP = "qp-daqp"


def _f(x: Any, digits: int = 1) -> str:
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return "–"
    return f"{x:,.{digits}f}"


def _g(x: Any) -> str:
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return "–"
    return f"{x:.3g}"


def _x(x: Any, digits: int = 2) -> str:
    return "–" if x is None or not np.isfinite(x) else f"{x:.{digits}f}×"


def _table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def machine_line(res: dict[str, Any]) -> str:
    m = res["machine"]
    pk = m["packages"]
    load = res.get("load_average", {})
    return (f"{m['cpu']}, {m['cores']} cores, Python {m['python']}; numpy {pk.get('numpy')}, numba {pk.get('numba')}, "
            f"pin {pk.get('pin')}, python-fcl {pk.get('python-fcl')}, daqp {pk.get('daqp')}, "
            f"proxsuite {pk.get('proxsuite')}, osqp {pk.get('osqp')}, quadprog {pk.get('quadprog')}, "
            f"clarabel {pk.get('clarabel')}, qpsolvers {pk.get('qpsolvers')}; "
            f"load average (1, 5, 15 min) {load.get('start')} at start, {load.get('end')} at end")


def _timing_rows(first: str, block: dict[str, Any], *, cpu_median: bool = True, paper: bool = False) -> list[list[str]]:
    rows = []
    for label, r in block["controllers"].items():
        bd = r.get("breakdown_median", {})
        row = [first, label, _f(r["wall"]["median"]), _f(r["wall"]["p99"])]
        row += [_f(r["cpu"]["median"])] if cpu_median else []
        row += [_f(r["cpu"]["p99"]), _x(r.get("ratio_to_floor"), 1)]
        row += [_x(r.get("ratio_to_paper"))] if paper else []
        row += [_f(bd.get(key)) for key, _ in BREAKDOWN]
        rows.append(row)
    return rows


def _timing_header(first: str, *, cpu_median: bool = True, paper: bool = False) -> list[str]:
    return ([first, "controller", "median µs", "p99 µs"] + (["CPU median µs"] if cpu_median else [])
            + ["CPU p99 µs", "÷ floor"] + (["÷ paper"] if paper else []) + [f"{t} µs" for _, t in BREAKDOWN])


def scene_groups_table(res: dict[str, Any], groups: tuple[str, ...] | None = None, *, cpu_median: bool = True) -> str:
    """Same ticks per scene group (the four target scenes first): wall and CPU time, ÷ floor, stages."""
    sg = res.get("scene_groups", {})
    keys = [g for g in (groups if groups is not None else list(sg)) if g in sg]
    rows = [row for g in keys for row in _timing_rows(sg[g]["title"], sg[g], cpu_median=cpu_median)]
    return _table(_timing_header("scene", cpu_median=cpu_median), rows)


def scene_groups_line(res: dict[str, Any], groups: tuple[str, ...] | None = None) -> str:
    sg = res.get("scene_groups", {})
    keys = [g for g in (groups if groups is not None else list(sg)) if g in sg]
    parts = []
    for g in keys:
        b = sg[g]
        pairs = "" if b.get("pairs_median") is None else f", {b['pairs_median']:.0f} link–obstacle pairs (median)"
        names = ", ".join(b["scenes"]) if len(b["scenes"]) <= 2 else f"{b['scenes'][0]} … {b['scenes'][-1]}"
        parts.append(f"{b['title']}: {names}, {b['ticks']} ticks{pairs}")
    line = "; ".join(parts) + "."
    changed = [(sg[g]["title"], sg[g]["floor_blocks"]) for g in keys if sg[g].get("floor_blocks", {}).get("speed_change")]
    if changed:
        line += (" **The machine changed speed during " + "; ".join(
            f"{title} (the floor's {BLOCK}-tick blocks {fb['p10_us']:.1f}–{fb['p90_us']:.1f} µs, 10th–90th percentile)"
            for title, fb in changed) + "**: those times mix two speeds; their ratios to the floor (same blocks) "
            "hold better than their µs.")
    return line


def same_ticks_table(res: dict[str, Any]) -> str:
    """Same ticks aggregated per robot (every scene of that robot)."""
    rows = [row for robot, block in res["same_ticks"].items() for row in _timing_rows(robot, block, paper=True)]
    return _table(_timing_header("robot", paper=True), rows)


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


def scaling_table(res: dict[str, Any], *, compact: bool = False) -> str:
    sc = res.get("scaling") or {}
    if not sc:
        return "(not run)"
    first = sc["counts_list"][0]
    rows = []
    for count, block in sc["counts"].items():
        row = [str(count), _f(block["pairs_median"], 0)]
        for label in sc["controllers"]:
            r = block["controllers"][label]
            row += [_f(r["wall"]["median"]), _f(r["wall"]["p99"])]
            row += [] if compact else [_f(r["cpu"]["median"])]
            row += [_f(r["breakdown_median"].get("state_kernel_us")), _x(r["relative_to_first"])]
        rows.append(row)
    header = ["obstacles", "pairs within d_influence (median)"]
    for label in sc["controllers"]:
        header += [f"{label} median µs", f"{label} p99 µs"] + ([] if compact else [f"{label} CPU median µs"])
        header += [f"{label} state kernel µs", f"{label} ÷ {first} obstacles"]
    return _table(header, rows)


def targets_table(res: dict[str, Any]) -> str:
    rows = [[t["target"], t["measured"], {True: "met", False: "**missed**", None: "not measured"}[t["met"]]]
            for t in res["targets"]]
    return _table(["target (issue #10)", "measured", ""], rows)


STAGE_LEGEND = (
    "Wall time of one `step()` [µs] (median, p99) and the thread's CPU time (the same without the time slices "
    "other processes took), every controller on the same recorded states, interleaved in blocks of 25 ticks (the order rotating; each "
    "block opens with one untimed tick replaying the controller's previous state, to bring its data back into "
    "the cache without changing its warm start — that tick's time after the other controllers' blocks is "
    "`cold_wall` in results.json). "
    "**floor** = `pin.computeAllTerms(model, data, q, v)` alone, timed on the same states in the same blocks; "
    "**÷ floor** = median tick ÷ the floor's median tick (the figure that carries across machines). Stage "
    "columns are medians of the per-tick values reported in `out.info`: Pinocchio = `rigid_us` "
    "(crba and nonLinearEffects: on the native library inside the compiled tick's kernel, "
    "`qpctl.kernels.pin_native`, else `qpctl.tick.rigid_pass` before it); state kernel = `state_us − rigid_us` (link points and Jacobians, "
    "link–obstacle pairs and distances, barrier drift); law + rows = `build_us` (the law's terms and, for the "
    "QP, its cost and rows written in place; for paper/hsu the terms and the closed form); solve = `solve_us` "
    "(the solver and the check of its answer, QP only); other = wall − the rest (the Python around the kernel, "
    "numba's call, the output record, the timers). Medians of the parts do not add up exactly to the median tick.")


def _plots_line(res: dict[str, Any]) -> str:
    out = res.get("out", ".")
    return (f"Plots in `{out}/`: `tick_times.png` (distribution of the tick's wall time per controller on the "
            f"Panda + 10 spheres, the floor included, with the {TARGETS['spheres_qp_median_us']:g} µs QP and "
            f"{TARGETS['spheres_paper_median_us']:g} µs paper-law targets of issue #10 and issue 23's "
            f"{TARGETS_23['spheres_qp_median_us']:g} and {TARGETS_23['spheres_paper_median_us']:g} µs), "
            "`stages.png` (median stages per "
            "controller on the four target scenes), `scaling.png` (tick against obstacle count).")


def markdown(res: dict[str, Any]) -> str:
    """The whole report (what ``results.md`` holds)."""
    cfg = res["config"]
    sc = res.get("scaling") or {}
    parts = [
        f"# qpctl benchmark ({'quick' if cfg['quick'] else 'full'} run)",
        f"Command: `{res['command']}`; {res['duration_s']:.0f} s wall time. Machine: {machine_line(res)}.",
        cfg.get("covers", ""),
        "## Targets (issue #10)",
        targets_table(res),
        (f"TSID's tick on the nearest task without obstacles: {TSID_US:g} µs, {TSID_CREDIT}. "
         "Wall times on a shared machine: the CPU-time columns below show what other processes added."),
        "## Same ticks: compute time per tick [µs], per scene group",
        STAGE_LEGEND,
        scene_groups_line(res),
        scene_groups_table(res),
        "## Same ticks, per robot (every scene of the robot)",
        same_ticks_table(res),
    ]
    if sc:
        parts += [(f"## Scaling with the scene: Panda canopy tiled to more obstacles, grid broad phase on "
                   f"({sc['scene']}, same states)"), scaling_table(res)]
    parts += [
        "## Closed loop: quality per controller (built-in RK4 simulator)",
        (f"Success = the task point ends within {res['quality']['reach_tolerance']} m of the target and no "
         "link ever touches an obstacle (least exact distance ≥ 0)."),
        quality_table(res),
        _plots_line(res),
    ]
    return "\n\n".join(p for p in parts if p) + "\n"


def performance_section(res: dict[str, Any], *, demo_wall_s: float | None = None) -> str:
    """docs/performance.md's "## Performance" section (without its heading) from a ``results.json``: how it was
    measured (command, machine, load, wall times), the per-stage table of the four target scenes, the
    targets, the scaling table, and the plots. ``demo_wall_s``: ``make demo``'s wall time, if known."""
    cfg = res["config"]
    walls = f"Wall time of this run: {res['duration_s']:.0f} s"
    if demo_wall_s is not None:
        walls += f"; of `make demo`: {demo_wall_s:.0f} s"
    parts = [
        f"Measured with `{res['command']}` on {machine_line(res)}. {walls}.",
        cfg.get("covers", ""),
        "Per stage, same ticks, the four target scenes (" + scene_groups_line(res, TARGET_GROUPS)[:-1] + "):",
        scene_groups_table(res, TARGET_GROUPS, cpu_median=False),
        STAGE_LEGEND,
        "Targets of issue #10:",
        targets_table(res),
        f"TSID's tick on the nearest task without obstacles: {TSID_US:g} µs, {TSID_CREDIT}.",
    ]
    sc = res.get("scaling") or {}
    if sc:
        parts += [f"Scaling: the Panda canopy ({sc['scene']}) tiled to more obstacles, grid broad phase on, same states:",
                  scaling_table(res, compact=True)]
    parts.append(_plots_line(res))
    return "\n\n".join(p for p in parts if p) + "\n"


# -- plots ----------------------------------------------------------------------------------------
def _dist_group(res: dict[str, Any], times: dict[str, Any]) -> str | None:
    groups = times.get("scene_groups", {})
    return "spheres" if "spheres" in groups else next(iter(groups), None)


def write_plots(res: dict[str, Any], times: dict[str, Any], out: Path) -> list[Path]:
    """tick_times.png (ECDF of the tick's wall time per controller on the Panda + 10 spheres, the floor
    included, log x, the targets marked), stages.png (median stages per controller, target scenes),
    scaling.png (tick against obstacle count)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    group = _dist_group(res, times)
    if group is not None:
        fig, ax = plt.subplots(figsize=(8, 5))
        for label, t in times["scene_groups"][group].items():
            w = np.sort(t.wall[np.isfinite(t.wall)])
            if w.size == 0:
                continue
            style = {"color": "k", "lw": 2.0} if label == FLOOR else {"lw": 1.4}
            ax.step(w, np.arange(1, w.size + 1) / w.size, where="post", label=label, **style)
        # issue #10's targets labelled at the bottom, issue 23's (15 and 16 µs sit close) higher up
        for us, what, ls, y in ((TARGETS["spheres_qp_median_us"], "QP target (#10)", "--", 0.02),
                                (TARGETS["spheres_paper_median_us"], "paper-law target (#10)", ":", 0.02),
                                (TARGETS_23["spheres_qp_median_us"], "QP target (#23)", "--", 0.52),
                                (TARGETS_23["spheres_paper_median_us"], "paper-law target (#23)", ":", 0.52)):
            ax.axvline(us, color="0.3", ls=ls, lw=1.0)
            ax.text(us, y, f" {what} {us:g} µs", rotation=90, va="bottom", ha="right", fontsize=8, color="0.3")
        ax.set_xscale("log")
        ax.set_ylim(0, 1.0)
        ax.set_xlabel("tick wall time [µs] (log)")
        ax.set_ylabel("fraction of ticks ≤ x")
        title = res["scene_groups"][group]["title"]
        ax.set_title(f"{title}: distribution of the tick time, same ticks ({res['scene_groups'][group]['ticks']})")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8, loc="lower right")
        fig.tight_layout()
        path = out / "tick_times.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)

    sg = res.get("scene_groups", {})
    keys = [g for g in TARGET_GROUPS if g in sg] or list(sg)
    if keys:
        cols = min(len(keys), 2)
        rows_ = -(-len(keys) // cols)
        fig, axes = plt.subplots(rows_, cols, figsize=(6.5 * cols, 4.6 * rows_), squeeze=False)
        colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
        for ax, g in zip(axes.flat, keys):
            ctrl = sg[g]["controllers"]
            labels = list(ctrl)
            bottom = np.zeros(len(labels))
            for i, (key, title) in enumerate(BREAKDOWN):
                vals = np.array([ctrl[lb]["wall"]["median"] if lb == FLOOR and key == "pinocchio_us"
                                 else ctrl[lb]["breakdown_median"].get(key) for lb in labels], dtype=float)
                vals = np.maximum(np.nan_to_num(vals), 0.0)
                ax.bar(labels, vals, bottom=bottom, label=title, color=colours[i % len(colours)])
                bottom += vals
            # the compiled tick's scale: the slow solvers are clipped, their totals printed on their bars
            fast = [b for lb, b in zip(labels, bottom) if lb in (FLOOR, "paper", "hsu", TARGET_QP)]
            top = 2.2 * max(fast) if fast else 0.0
            if top > 0 and bottom.max() > top:
                ax.set_ylim(0, top)
                for x, total in enumerate(bottom):
                    if total > top:
                        ax.text(x, top * 0.97, f"{total:,.0f} µs", ha="center", va="top", fontsize=7, rotation=90,
                                color="w")
            ax.set_ylabel("median [µs]")
            ax.set_title(f"{sg[g]['title']}: where the tick goes (medians)", fontsize=10)
            ax.tick_params(axis="x", rotation=30)
            ax.legend(fontsize=7, loc="upper left")
        for ax in list(axes.flat)[len(keys):]:
            ax.set_visible(False)
        fig.tight_layout()
        path = out / "stages.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)

    sc = res.get("scaling") or {}
    if sc:
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
        ax.set_title("Panda canopy tiled, grid broad phase on, same states")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        path = out / "scaling.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)
    return written


if __name__ == "__main__":  # python -m qpctl.bench.report results/bench/results.json [--demo-wall-s S]
    import argparse
    import json

    ap = argparse.ArgumentParser(description="docs/performance.md's Performance section from a results.json")
    ap.add_argument("results")
    ap.add_argument("--demo-wall-s", type=float, default=None, help="`make demo`'s wall time [s], if known")
    args = ap.parse_args()
    print(performance_section(json.loads(Path(args.results).read_text()), demo_wall_s=args.demo_wall_s))
