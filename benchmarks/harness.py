"""The benchmark harness: ``qpctl bench [--quick] [--out DIR]`` (``make bench``, ``make bench-quick``).

1. Closed loop: every controller (``paper``, ``hsu``, ``qp`` with each installed solver) on the paper's
   scenario, N seeded random planar scenes and N seeded Panda canopy scenes.
2. Same ticks: on each scene, every controller timed on the states of the ``qp-proxqp`` closed-loop
   run, interleaved; aggregated per robot (planar arm, Panda). Headline: QP tick ÷ paper-law tick.
3. Scaling: the first canopy scene tiled to 10, 100, 1000 obstacles (broad phase on), the paper law
   and the proxqp QP timed on the same states.

Writes ``results.json`` (machine, seeds, every number), ``results.md`` (the tables) and PNG plots to
the output folder. Timings are never asserted anywhere: they are measurements of this machine.
"""

from __future__ import annotations

import json
import sys
import time
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks import report
from benchmarks.scenes import BenchScene, canopy_scene, paper_scene, planar_scene
from benchmarks.suites import (
    REACH_TOLERANCE,
    ClosedLoop,
    ControllerSpec,
    closed_loop,
    controller_specs,
    same_ticks,
    scaling,
)
from benchmarks.timing import STAGES, TickTimes, summary
from qpctl.solvers import available_solvers

ROBOT_OF_FAMILY = {"paper": "planar3", "planar": "planar3", "canopy": "panda"}
ORCHARD_SEED = 0  # seed of the obstacles tiled around the canopy in the scaling suite


@dataclass(frozen=True)
class BenchConfig:
    """What a run covers. Seeds: planar scene i uses ``seed + i``, canopy scene i ``seed + 100 + i``."""

    quick: bool = False
    paper: bool = True  # include the paper's scenario
    planar_scenes: int = 6
    canopy_scenes: int = 6
    seed: int = 0
    solvers: tuple[str, ...] | None = None  # None: every installed solver
    closed_loop_solvers: tuple[str, ...] | None = None  # QP solvers run in closed loop (None: ``solvers``)
    max_ticks: int | None = None  # cut every run to this many ticks (None: the scene's duration)
    timing_stride: int = 1  # time every k-th recorded state in the same-tick suite
    scaling_counts: tuple[int, ...] = (10, 100, 1000)
    states_from: str = "qp-proxqp"  # whose closed-loop states the same-tick suites replay
    progress: bool = True

    @property
    def planar_seeds(self) -> list[int]:
        return [self.seed + i for i in range(self.planar_scenes)]

    @property
    def canopy_seeds(self) -> list[int]:
        return [self.seed + 100 + i for i in range(self.canopy_scenes)]


FULL = BenchConfig()
#: Under two minutes: one scene of each kind at full length; in closed loop the closed forms and the
#: proxqp and daqp QPs only; every solver still timed on the same ticks (every 4th state).
QUICK = BenchConfig(quick=True, planar_scenes=1, canopy_scenes=1, closed_loop_solvers=("proxqp", "daqp"),
                    timing_stride=4)


def scenes(cfg: BenchConfig) -> list[BenchScene]:
    out = [paper_scene()] if cfg.paper else []
    out += [planar_scene(s) for s in cfg.planar_seeds]
    out += [canopy_scene(s) for s in cfg.canopy_seeds]
    return out


def _progress(items: list[Any], desc: str, on: bool) -> Any:
    if not on:
        return items
    from tqdm import tqdm

    return tqdm(items, desc=desc, unit="run")


def _timing_block(t: TickTimes) -> dict[str, Any]:
    slowest = np.argsort(t.cpu)[-5:][::-1]
    return {"wall": summary(t.wall), "cpu": summary(t.cpu),
            "stages_median": {s: summary(t.stages[s])["median"] for s in STAGES},
            "iterations": summary(t.iterations), "ticks_with_page_faults": int(np.count_nonzero(t.faults)),
            # the five slowest ticks (CPU time): a solver stalling shows in its iterations, a machine
            # stalling in page faults or in wall time far above CPU time
            "slowest": [{"tick": int(k), "cpu_us": float(t.cpu[k]), "wall_us": float(t.wall[k]),
                         "solve_us": float(t.stages["solve_us"][k]), "iterations": float(t.iterations[k]),
                         "page_faults": int(t.faults[k])} for k in slowest]}


def _quality_summary(runs: list[ClosedLoop], families: dict[str, str]) -> dict[str, dict[str, Any]]:
    out: dict[str, dict[str, Any]] = {}
    for fam in dict.fromkeys(families.values()):
        out[fam] = {}
        labels = dict.fromkeys(r.controller for r in runs if families[r.scene] == fam)
        for label in labels:
            ms = [r.metrics for r in runs if families[r.scene] == fam and r.controller == label]
            ok = [m for m in ms if "error" not in m]

            def agg(key: str, fn: Any, ok: list[dict[str, Any]] = ok) -> float | None:
                vals = [m[key] for m in ok if m.get(key) is not None]
                return float(fn(vals)) if vals else None

            out[fam][label] = {
                "runs": len(ms), "successes": sum(bool(m["success"]) for m in ms),
                "failed_runs": len(ms) - len(ok),
                "rms_tracking_error_median": agg("rms_tracking_error", np.median),
                "max_tracking_error_max": agg("max_tracking_error", np.max),
                "max_abs_torque_median": agg("max_abs_torque", np.median),
                "max_abs_torque_rate_median": agg("max_abs_torque_rate", np.median),
                "min_clearance_min": agg("min_clearance", np.min),
                "tick_us_median": agg("tick_us_median", np.median),
                "tick_us_p99": agg("tick_us_p99", np.median),
            }
    return out


def _states_source(runs: list[ClosedLoop], scene: str, preferred: str) -> ClosedLoop | None:
    """The closed-loop run whose states the same-tick suites replay: ``preferred``'s, else (if it
    failed) the paper law's, else None."""
    for label in (preferred, "paper"):
        run = next((r for r in runs if r.scene == scene and r.controller == label), None)
        if run is not None and run.states is not None:
            return run
    return None


def _targets(res: dict[str, Any]) -> list[dict[str, Any]]:
    t = report.TARGETS
    out = []
    panda = res["same_ticks"].get("panda", {}).get("controllers", {})
    for label in ("qp-proxqp", "qp-daqp"):  # the proxsuite fast path, and the fastest one
        qp = panda.get(label)
        if qp is None:
            continue
        out.append({"target": f"{label}: median tick ≤ {t['ratio_to_paper']}× the paper-law tick (same ticks)",
                    "measured": f"{qp['ratio_to_paper']:.2f}×", "met": qp["ratio_to_paper"] <= t["ratio_to_paper"]})
        out.append({"target": f"{label}: median tick < {t['median_us']:.0f} µs",
                    "measured": f"{qp['wall']['median']:.0f} µs", "met": qp["wall"]["median"] < t["median_us"]})
        out.append({"target": f"{label}: p99 tick < {t['p99_us']:.0f} µs", "measured":
                    f"{qp['wall']['p99']:.0f} µs (CPU time: {qp['cpu']['p99']:.0f} µs)",
                    "met": qp["wall"]["p99"] < t["p99_us"]})
    sc = res.get("scaling", {})
    counts = sc.get("counts_list", [])
    if counts and 1000 in counts and "qp-proxqp" in sc.get("controllers", []):
        ratio = sc["counts"]["1000"]["controllers"]["qp-proxqp"]["relative_to_first"]
        out.append({"target": f"1000 obstacles: median QP tick < {t['scaling_1000_over_10']}× the "
                              f"{counts[0]}-obstacle figure", "measured": f"{ratio:.2f}×",
                    "met": ratio < t["scaling_1000_over_10"]})
    return out


def run(cfg: BenchConfig, out: Path, *, command: str = "qpctl bench") -> dict[str, Any]:
    """Run every suite of ``cfg`` and write results.json, results.md and the plots into ``out``."""
    started = time.time()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    solvers = list(cfg.solvers) if cfg.solvers is not None else available_solvers()
    specs = controller_specs(solvers)
    loop_solvers = solvers if cfg.closed_loop_solvers is None else [s for s in cfg.closed_loop_solvers
                                                                   if s in solvers]
    loop_specs = controller_specs(loop_solvers)
    all_scenes = scenes(cfg)
    families = {s.name: s.family for s in all_scenes}
    load_start = report.load_average()

    # 1. closed loop
    runs: list[ClosedLoop] = []
    jobs = [(s, spec) for s in all_scenes for spec in loop_specs]
    for scene, spec in _progress(jobs, "closed loop", cfg.progress):
        runs.append(closed_loop(scene, spec, max_ticks=cfg.max_ticks))

    # 2. same ticks, per scene, aggregated per robot
    per_robot: dict[str, dict[str, list[TickTimes]]] = {}
    for scene in _progress(all_scenes, "same ticks", cfg.progress):
        source = _states_source(runs, scene.name, cfg.states_from)
        if source is None:
            continue
        times = same_ticks(scene, specs, source.states.every(cfg.timing_stride), progress=cfg.progress)
        robot = ROBOT_OF_FAMILY[scene.family]
        for label, t in times.items():
            per_robot.setdefault(robot, {}).setdefault(label, []).append(t)
    same: dict[str, Any] = {}
    tick_times: dict[str, Any] = {"same_ticks": {}}
    for robot, by_label in per_robot.items():
        merged = {label: TickTimes.concatenate(parts) for label, parts in by_label.items()}
        tick_times["same_ticks"][robot] = merged
        base = merged["paper"]
        block = {}
        for label, t in merged.items():
            b = _timing_block(t)
            b["ratio_to_paper"] = float(np.median(t.wall) / np.median(base.wall))
            b["ratio_to_paper_cpu"] = float(np.median(t.cpu) / np.median(base.cpu))
            b["paired_ratio_median"] = float(np.median(t.wall / base.wall))
            block[label] = b
        same[robot] = {"ticks": int(base.wall.size), "pairs_median": float(np.median(base.pairs)),
                       "controllers": block}

    # 3. scaling
    canopies = [s for s in all_scenes if s.family == "canopy"]
    scaling_res: dict[str, Any] = {}
    scene = canopies[0] if canopies and cfg.scaling_counts else None
    source = _states_source(runs, scene.name, cfg.states_from) if scene is not None else None
    if scene is not None and source is not None:
        sspecs = [ControllerSpec("paper")] + [ControllerSpec("qp", s) for s in ("proxqp", "daqp") if s in solvers]
        counts = sorted(set(cfg.scaling_counts) | {len(scene.obstacles)})
        counts = [c for c in counts if c >= len(scene.obstacles)]
        sc = scaling(scene, counts, sspecs, source.states.every(cfg.timing_stride), seed=ORCHARD_SEED,
                     progress=cfg.progress)
        scaling_res = {"scene": scene.name, "states_from": source.controller, "counts_list": counts,
                       "orchard_seed": ORCHARD_SEED,
                       "controllers": [s.label for s in sspecs], "counts": {}}
        for count in counts:
            block = {label: _timing_block(t) for label, t in sc[count].items()}
            for label in block:
                block[label]["relative_to_first"] = float(np.median(sc[count][label].wall)
                                                          / np.median(sc[counts[0]][label].wall))
            scaling_res["counts"][str(count)] = {
                "pairs_median": float(np.median(sc[count]["paper"].pairs)), "controllers": block}
        tick_times["scaling"] = sc

    res: dict[str, Any] = {
        "command": command,
        "machine": report.machine(),
        "load_average": {"start": load_start, "end": report.load_average()},
        "config": {**asdict(cfg), "solvers": solvers, "closed_loop_solvers": loop_solvers,
                   "planar_seeds": cfg.planar_seeds, "canopy_seeds": cfg.canopy_seeds},
        "scenes": {s.name: {"family": s.family, "robot": s.robot.name, "seed": s.seed, "obstacles": len(s.obstacles),
                            "duration_s": s.duration, "dt_s": s.dt, "target": s.target.tolist()} for s in all_scenes},
        "quality": {"reach_tolerance": REACH_TOLERANCE,
                    "runs": [{"scene": r.scene, "controller": r.controller, **r.metrics} for r in runs],
                    "summary": _quality_summary(runs, families)},
        "same_ticks": same,
        "scaling": scaling_res,
    }
    res["targets"] = _targets(res)
    res["duration_s"] = time.time() - started
    (out / "results.json").write_text(json.dumps(res, indent=2, default=_json_default) + "\n")
    (out / "results.md").write_text(report.markdown(res))
    if same and scaling_res:
        report.write_plots(res, tick_times, out)
    return res


def _json_default(x: Any) -> Any:
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.floating,)):
        return float(x)
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")


def main(quick: bool = False, out: Path | str = Path("results/bench")) -> int:
    """What ``qpctl bench`` runs: the full benchmark (or the quick one) into ``out``."""
    cfg = QUICK if quick else FULL
    command = "qpctl bench" + (" --quick" if quick else "") + f" --out {out}"
    with warnings.catch_warnings():  # qpsolvers' per-call notes (dense → sparse, osqp's raise_error)
        warnings.filterwarnings("ignore", message="Converted matrix")
        warnings.filterwarnings("ignore", category=PendingDeprecationWarning, module="osqp")
        res = run(cfg, Path(out), command=command)
    print(report.markdown(res))
    print(f"written: {Path(out) / 'results.json'}, {Path(out) / 'results.md'}, plots", file=sys.stderr)
    return 0


__all__ = ["FULL", "QUICK", "BenchConfig", "main", "run"]
