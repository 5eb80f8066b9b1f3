"""The benchmark harness: ``qpctl bench [--quick] [--out DIR]`` (``make bench``, ``make bench-quick``).

Scene groups (``BenchScene.family``): ``spheres`` — the Panda + 10 spheres (the packaged
``panda_spheres`` scenario, issue #10's reference scene); ``free`` — the same Panda task with no
obstacles; ``canopy`` — N seeded Panda canopies (capsule branches, sphere leaves); ``paper`` — the
planar paper arm (the paper's scenario); ``planar`` — N seeded random planar scenes.

1. Closed loop: every controller (``paper``, ``hsu``, ``qp`` with each closed-loop solver) on every
   scene, in the built-in simulator: success, tracking, torque, clearance.
2. Same ticks: on each scene, every controller and the floor (``pin.computeAllTerms`` alone) timed on
   the states of the ``qp-daqp`` closed-loop run, interleaved in blocks; aggregated per scene group
   and per robot (planar arm, Panda). Every median also as a ratio to the floor's ("÷ floor").
3. Scaling: the first canopy scene tiled to 10, 100, 1000 obstacles (the uniform-grid broad phase on
   at every count), the paper law and the daqp and proxqp QPs timed on the same states.

Then issue #10's targets, each with what was measured and met / missed. Writes ``results.json``
(machine, load, seeds, every number), ``results.md`` (the tables) and PNG plots to the output
folder; :func:`qpctl.bench.report.performance_section` turns ``results.json`` into docs/performance.md's
"Performance" section. Timings are never asserted anywhere: they are measurements of this machine.
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

from qpctl.bench import report
from qpctl.bench.scenes import BenchScene, canopy_scene, free_scene, paper_scene, planar_scene, spheres_scene
from qpctl.bench.suites import (
    HARVEST_SCENARIO,
    REACH_TOLERANCE,
    ClosedLoop,
    ControllerSpec,
    closed_loop,
    controller_specs,
    harvest_tick_cost,
    same_ticks,
    scaling,
)
from qpctl.bench.timing import BLOCK, BREAKDOWN, FLOOR, STAGES, TickTimes, breakdown, summary
from qpctl.run import simulate
from qpctl.scenario import Scenario
from qpctl.solvers import available_solvers
from qpctl.sweep.backends import LocalBackend
from qpctl.sweep.engine import map_ordered

ROBOT_OF_FAMILY = {"spheres": "panda", "free": "panda", "canopy": "panda", "paper": "planar3", "planar": "planar3"}
#: The scene groups, in report order; the first four are issue #10's target scenes.
GROUP_TITLES = {"spheres": "Panda + 10 spheres", "free": "Panda, no obstacles", "canopy": "Panda canopy",
                "paper": "planar paper arm", "planar": "planar arm, random scenes"}
TARGET_GROUPS = ("spheres", "free", "canopy", "paper")
TARGET_QP = report.TARGET_QP  # the QP the targets are about: qp-daqp (the default solver)
ORCHARD_SEED = 0  # seed of the obstacles tiled around the canopy in the scaling suite
#: Processes of the closed-loop suite (the sweep engine's local backend). 1: the runs go one after
#: another in this process, as before the engine: their tick times are reported (quality table), and
#: parallel runs would share the cores with them; the same-tick suites after it need the states in
#: this process anyway.
CLOSED_LOOP_JOBS = 1


@dataclass(frozen=True)
class BenchConfig:
    """What a run covers. Seeds: planar scene i uses ``seed + i``, canopy scene i ``seed + 100 + i``."""

    quick: bool = False
    paper: bool = True  # the paper's scenario (the planar paper arm)
    spheres: bool = True  # the Panda + 10 spheres (panda_spheres)
    free: bool = True  # the same Panda task, no obstacles
    planar_scenes: int = 6
    canopy_scenes: int = 6
    seed: int = 0
    solvers: tuple[str, ...] | None = None  # None: every installed solver
    closed_loop_solvers: tuple[str, ...] | None = None  # QP solvers run in closed loop (None: ``solvers``)
    max_ticks: int | None = None  # cut every run to this many ticks (None: the scene's duration)
    timing_stride: int = 1  # time every k-th recorded state in the same-tick suite
    scaling_counts: tuple[int, ...] = (10, 100, 1000)
    harvest: bool = True  # issue 11's tick: panda_harvest's approach task and self rows against the position task
    states_from: str = TARGET_QP  # whose closed-loop states the same-tick suites replay
    progress: bool = True

    @property
    def planar_seeds(self) -> list[int]:
        return [self.seed + i for i in range(self.planar_scenes)]

    @property
    def canopy_seeds(self) -> list[int]:
        return [self.seed + 100 + i for i in range(self.canopy_scenes)]


#: Every scene (paper, Panda + spheres, Panda free, 6 planar, 6 canopies), every solver in closed loop
#: and on every recorded state; under ten minutes on two cores.
FULL = BenchConfig()
#: Under two minutes: the four target scenes (one canopy, seed 100) and one random planar scene (seed 0)
#: at full length; in closed loop the closed forms and the daqp and proxqp QPs only; every solver and
#: the floor timed on every recorded state; the scaling suite in full (10, 100, 1000 obstacles).
QUICK = BenchConfig(quick=True, planar_scenes=1, canopy_scenes=1, closed_loop_solvers=("daqp", "proxqp"))


def scenes(cfg: BenchConfig) -> list[BenchScene]:
    out = []
    if cfg.spheres or cfg.free:
        spheres = spheres_scene()
        out += [spheres] if cfg.spheres else []
        out += [free_scene(spheres)] if cfg.free else []
    out += [canopy_scene(s) for s in cfg.canopy_seeds]
    out += [paper_scene()] if cfg.paper else []
    out += [planar_scene(s) for s in cfg.planar_seeds]
    return out


def _seeds(seeds: list[int]) -> str:
    return f"seed {seeds[0]}" if len(seeds) == 1 else f"seeds {seeds[0]}–{seeds[-1]}"


def covers(cfg: BenchConfig, solvers: list[str], loop_solvers: list[str]) -> str:
    """One sentence: what a run of ``cfg`` covers."""
    groups = [GROUP_TITLES[f] for f, on in (("spheres", cfg.spheres), ("free", cfg.free)) if on]
    if cfg.canopy_scenes:
        groups.append(f"{cfg.canopy_scenes} Panda canop{'y' if cfg.canopy_scenes == 1 else 'ies'} "
                      f"({_seeds(cfg.canopy_seeds)})")
    if cfg.paper:
        groups.append("the planar paper arm")
    if cfg.planar_scenes:
        groups.append(f"{cfg.planar_scenes} random planar scene{'s' if cfg.planar_scenes > 1 else ''} "
                      f"({_seeds(cfg.planar_seeds)})")
    length = "full length" if cfg.max_ticks is None else f"the first {cfg.max_ticks} ticks"
    stride = ("every recorded state" if cfg.timing_stride == 1
              else f"one recorded state in {cfg.timing_stride}")
    return (f"Scenes: {', '.join(groups)}, at {length}. Closed loop: paper, hsu and the QP with "
            f"{', '.join(loop_solvers)}. Same ticks: the floor, paper, hsu and the QP with {', '.join(solvers)} "
            f"on {stride} of each scene's `{cfg.states_from}` run. Scaling: "
            + (f"{', '.join(map(str, cfg.scaling_counts))} obstacles." if cfg.scaling_counts and cfg.canopy_scenes
               else "not run."))


def _closed_loop(scene: BenchScene, spec: ControllerSpec, max_ticks: int | None) -> ClosedLoop:
    return closed_loop(scene, spec, max_ticks=max_ticks)


def _progress(items: list[Any], desc: str, on: bool) -> Any:
    if not on:
        return items
    from tqdm import tqdm

    return tqdm(items, desc=desc, unit="run")


def _timing_block(t: TickTimes) -> dict[str, Any]:
    slowest = np.argsort(t.cpu)[-5:][::-1]
    parts = breakdown(t)
    return {"wall": summary(t.wall), "cpu": summary(t.cpu),
            "cold_wall": summary(t.cold),  # the untimed re-warm ticks: a tick after the others' blocks
            "stages_median": {s: summary(t.stages[s])["median"] for s in STAGES},
            "breakdown_median": {key: summary(parts[key])["median"] for key, _ in BREAKDOWN},
            "iterations": summary(t.iterations), "ticks_with_page_faults": int(np.count_nonzero(t.faults)),
            # the five slowest ticks (CPU time): a solver stalling shows in its iterations, a machine
            # stalling in page faults or in wall time far above CPU time
            "slowest": [{"tick": int(k), "cpu_us": float(t.cpu[k]), "wall_us": float(t.wall[k]),
                         "solve_us": float(t.stages["solve_us"][k]), "iterations": float(t.iterations[k]),
                         "page_faults": int(t.faults[k])} for k in slowest]}


def _group_block(merged: dict[str, TickTimes]) -> dict[str, Any]:
    """Timing blocks of every controller of one group (or robot), with their ratios to the floor's and
    the paper law's medians (computed from the medians the blocks report)."""
    block = {label: _timing_block(t) for label, t in merged.items()}
    floor, paper = block.get(FLOOR), block.get("paper")
    for label, b in block.items():
        if floor is not None:
            b["ratio_to_floor"] = b["wall"]["median"] / floor["wall"]["median"]
            b["ratio_to_floor_cpu"] = b["cpu"]["median"] / floor["cpu"]["median"]
            b["paired_ratio_to_floor_median"] = float(np.median(merged[label].wall / merged[FLOOR].wall))
        if paper is not None:
            b["ratio_to_paper"] = b["wall"]["median"] / paper["wall"]["median"]
    some = next((t for lb, t in merged.items() if lb != FLOOR), None)
    pairs = float(np.nanmedian(some.pairs)) if some is not None and np.isfinite(some.pairs).any() else None
    ticks = int(next(iter(merged.values())).wall.size)
    out: dict[str, Any] = {"ticks": ticks, "pairs_median": pairs, "controllers": block}
    if FLOOR in merged:
        out["floor_blocks"] = floor_spread(merged[FLOOR].wall)
    return out


#: A group whose floor's block medians spread by more than this (90th ÷ 10th percentile) ran at two
#: machine speeds (the 2-core Xeon VM switches between floors of about 3.5 and 5.5 µs on the Panda).
SPEED_CHANGE = 1.15


def floor_spread(wall: np.ndarray, block: int = BLOCK) -> dict[str, float]:
    """The floor's medians over consecutive blocks of ``block`` ticks [µs]: their 10th and 90th
    percentiles and the ratio of the two (``speed_change``: above :data:`SPEED_CHANGE`)."""
    w = np.asarray(wall, float)
    meds = np.array([np.median(w[k:k + block]) for k in range(0, w.size, block) if np.isfinite(w[k:k + block]).all()])
    if meds.size == 0:
        return {"p10_us": float("nan"), "p90_us": float("nan"), "ratio": float("nan"), "speed_change": False}
    lo, hi = (float(x) for x in np.percentile(meds, [10, 90]))
    return {"p10_us": lo, "p90_us": hi, "ratio": hi / lo, "speed_change": bool(hi / lo > SPEED_CHANGE)}


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
    failed or did not run) the paper law's, else None."""
    for label in (preferred, "paper"):
        run = next((r for r in runs if r.scene == scene and r.controller == label), None)
        if run is not None and run.states is not None:
            return run
    return None


def _targets(res: dict[str, Any]) -> list[dict[str, Any]]:
    """Issue #10's targets: one row each with the limit, the measured value, and met (None: not
    measured in this run). ``met`` is ``value ≤ limit``."""
    t = report.TARGETS
    groups = res["scene_groups"]
    qp_name = f"QP ({TARGET_QP.split('-', 1)[1]})"

    def ctrl(group: str, label: str) -> dict[str, Any] | None:
        return groups.get(group, {}).get("controllers", {}).get(label)

    rows: list[dict[str, Any]] = []

    def add(key: str, target: str, limit: float, value: float | None, measured: str, unit: str) -> None:
        ok = value is not None and bool(np.isfinite(value))
        rows.append({"key": key, "target": target, "limit": limit, "unit": unit, "value": value if ok else None,
                     "measured": measured if ok else "not measured",
                     "met": bool(value <= limit) if value is not None and ok else None})

    def us(group: str, label: str, stat: str = "median") -> float | None:
        c = ctrl(group, label)
        return None if c is None else c["wall"][stat]

    sph = GROUP_TITLES["spheres"]
    v = us("spheres", TARGET_QP)
    add("spheres_qp_median", f"{sph}: {qp_name} median ≤ {t['spheres_qp_median_us']:g} µs",
        t["spheres_qp_median_us"], v, f"{v:.1f} µs" if v is not None else "", "µs")
    v = us("spheres", TARGET_QP, "p99")
    cpu = ctrl("spheres", TARGET_QP)
    add("spheres_qp_p99", f"{sph}: {qp_name} p99 ≤ {t['spheres_qp_p99_us']:g} µs", t["spheres_qp_p99_us"], v,
        f"{v:.1f} µs (CPU p99 {cpu['cpu']['p99']:.1f} µs)" if v is not None and cpu else "", "µs")
    v = us("spheres", "paper")
    add("spheres_paper_median", f"{sph}: paper law median ≤ {t['spheres_paper_median_us']:g} µs",
        t["spheres_paper_median_us"], v, f"{v:.1f} µs" if v is not None else "", "µs")
    v = us("free", TARGET_QP)
    add("free_qp_median", f"{GROUP_TITLES['free']}: {qp_name} median ≤ {t['free_qp_median_us']:g} µs "
        "(issue #10's figure for TSID's tick; TSID measured since: see below)",
        t["free_qp_median_us"], v, f"{v:.1f} µs" if v is not None else "", "µs")
    a, b = us("canopy", TARGET_QP), us("spheres", TARGET_QP)
    v = a / b if a is not None and b is not None else None
    add("canopy_over_spheres", f"{GROUP_TITLES['canopy']}: {qp_name} median ≤ {t['canopy_over_spheres']:g}× the "
        f"{sph} figure", t["canopy_over_spheres"], v, f"{v:.2f}× ({a:.1f} µs ÷ {b:.1f} µs)" if v is not None else "",
        "×")
    v = us("paper", TARGET_QP)
    add("paper_arm_qp_median", f"{GROUP_TITLES['paper'].capitalize()}: {qp_name} median ≤ "
        f"{t['paper_arm_qp_median_us']:g} µs", t["paper_arm_qp_median_us"], v,
        f"{v:.1f} µs" if v is not None else "", "µs")
    sc = res.get("scaling") or {}
    counts = sc.get("counts_list", [])
    v = None
    if len(counts) > 1 and TARGET_QP in sc.get("controllers", []):
        top = counts[-1]
        blk = sc["counts"][str(top)]["controllers"][TARGET_QP]
        v = blk["relative_to_first"]
        first = sc["counts"][str(counts[0])]["controllers"][TARGET_QP]["wall"]["median"]
        measured = f"{v:.2f}× ({blk['wall']['median']:.1f} µs ÷ {first:.1f} µs)"
    top_name, first_name = (counts[-1], counts[0]) if len(counts) > 1 else (1000, 10)
    add("scaling", f"{top_name} obstacles: {qp_name} median ≤ {t['scaling_over_first']:g}× the {first_name}-obstacle "
        "tick (Panda canopy tiled, grid broad phase)", t["scaling_over_first"], v, measured if v is not None else "",
        "×")
    hv = res.get("harvest") or {}
    v = hv.get("ratio")
    add("harvest_over_position", f"Panda harvesting (`panda_harvest`): {qp_name} with the 5-row approach task and the "
        f"self-collision rows ≤ {t['harvest_over_position']:g}× the same QP with the position task alone (same "
        "states, interleaved)", t["harvest_over_position"], v,
        f"{v:.2f}× ({hv['approach_us']:.1f} µs ÷ {hv['position_us']:.1f} µs, {hv['ticks']} states)"
        if v is not None else "", "×")
    for key, label, name in (("qp_over_floor", TARGET_QP, qp_name), ("paper_over_floor", "paper", "paper law")):
        c = ctrl("spheres", label)
        v = c.get("ratio_to_floor") if c is not None else None
        fl = ctrl("spheres", FLOOR)
        add(key, f"{sph}: {name} median ≤ {t[key]:g}× `pin.computeAllTerms`' median (same states, same run)",
            t[key], v, f"{v:.1f}× ({c['wall']['median']:.1f} µs ÷ {fl['wall']['median']:.2f} µs)"
            if v is not None and c is not None and fl is not None else "", "×")
    return rows


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
    load_start = report.load_average()
    all_scenes = scenes(cfg)
    families = {s.name: s.family for s in all_scenes}

    # 1. closed loop, through the sweep engine, in this process (CLOSED_LOOP_JOBS)
    jobs = [(s, spec, cfg.max_ticks) for s in all_scenes for spec in loop_specs]
    runs: list[ClosedLoop] = map_ordered(_closed_loop, jobs, LocalBackend(CLOSED_LOOP_JOBS),
                                         progress=cfg.progress, desc="closed loop")

    # 2. same ticks, per scene (the floor included), aggregated per scene group and per robot
    per_group: dict[str, dict[str, list[TickTimes]]] = {}
    per_robot: dict[str, dict[str, list[TickTimes]]] = {}
    group_scenes: dict[str, list[str]] = {}
    group_sources: dict[str, list[str]] = {}
    for scene in _progress(all_scenes, "same ticks", cfg.progress):
        source = _states_source(runs, scene.name, cfg.states_from)
        if source is None:
            continue
        assert source.states is not None
        times = same_ticks(scene, specs, source.states.every(cfg.timing_stride), progress=cfg.progress)
        group_scenes.setdefault(scene.family, []).append(scene.name)
        group_sources.setdefault(scene.family, []).append(source.controller)
        for label, t in times.items():
            per_group.setdefault(scene.family, {}).setdefault(label, []).append(t)
            per_robot.setdefault(ROBOT_OF_FAMILY[scene.family], {}).setdefault(label, []).append(t)
    tick_times: dict[str, Any] = {"same_ticks": {}, "scene_groups": {}}
    groups: dict[str, Any] = {}
    for fam in (f for f in GROUP_TITLES if f in per_group):
        merged = {label: TickTimes.concatenate(parts) for label, parts in per_group[fam].items()}
        tick_times["scene_groups"][fam] = merged
        groups[fam] = {"title": GROUP_TITLES[fam], "robot": ROBOT_OF_FAMILY[fam], "scenes": group_scenes[fam],
                       "states_from": group_sources[fam], **_group_block(merged)}
    same: dict[str, Any] = {}
    for robot, by_label in per_robot.items():
        merged = {label: TickTimes.concatenate(parts) for label, parts in by_label.items()}
        tick_times["same_ticks"][robot] = merged
        same[robot] = _group_block(merged)

    # 3. scaling (the grid broad phase on at every count)
    canopies = [s for s in all_scenes if s.family == "canopy"]
    scaling_res: dict[str, Any] = {}
    scene = canopies[0] if canopies and cfg.scaling_counts else None
    source = _states_source(runs, scene.name, cfg.states_from) if scene is not None else None
    if scene is not None and source is not None and source.states is not None:
        sspecs = [ControllerSpec("paper")] + [ControllerSpec("qp", s) for s in ("daqp", "proxqp") if s in solvers]
        counts = sorted(set(cfg.scaling_counts) | {len(scene.obstacles)})
        counts = [c for c in counts if c >= len(scene.obstacles)]
        sc = scaling(scene, counts, sspecs, source.states.every(cfg.timing_stride), seed=ORCHARD_SEED,
                     progress=cfg.progress)
        scaling_res = {"scene": scene.name, "states_from": source.controller, "counts_list": counts,
                       "orchard_seed": ORCHARD_SEED, "broadphase": "grid",
                       "controllers": [s.label for s in sspecs], "counts": {}}
        first = {label: summary(t.wall)["median"] for label, t in sc[counts[0]].items()}
        for count in counts:
            block = {label: _timing_block(t) for label, t in sc[count].items()}
            for label, b in block.items():
                b["relative_to_first"] = b["wall"]["median"] / first[label]
            scaling_res["counts"][str(count)] = {
                "pairs_median": float(np.nanmedian(sc[count]["paper"].pairs)), "controllers": block}
        tick_times["scaling"] = sc

    # 4. the harvesting task's tick (issue 11): approach task + self rows against the position task
    harvest_res: dict[str, Any] = {}
    if cfg.harvest:
        for _ in _progress([0], "harvest tick", cfg.progress):
            scen = Scenario.load(HARVEST_SCENARIO)
            if cfg.max_ticks:  # cut as every other run
                sim = scen.data["sim"]
                scen = Scenario.from_dict({**scen.data, "sim": {**sim, "duration": cfg.max_ticks * sim["dt"]}},
                                          source=scen.source)
            harvest_res = {"scenario": HARVEST_SCENARIO, **harvest_tick_cost(simulate(scen, kind="qp"))}

    res: dict[str, Any] = {
        "command": command,
        "out": str(out),
        "machine": report.machine(),
        "load_average": {"start": load_start, "end": report.load_average()},
        "config": {**asdict(cfg), "solvers": solvers, "closed_loop_solvers": loop_solvers,
                   "planar_seeds": cfg.planar_seeds, "canopy_seeds": cfg.canopy_seeds,
                   "covers": covers(cfg, solvers, loop_solvers)},
        "scenes": {s.name: {"family": s.family, "robot": s.robot.name, "seed": s.seed, "obstacles": len(s.obstacles),
                            "duration_s": s.duration, "dt_s": s.dt, "target": s.target.tolist()} for s in all_scenes},
        "quality": {"reach_tolerance": REACH_TOLERANCE,
                    "runs": [{"scene": r.scene, "controller": r.controller, **r.metrics} for r in runs],
                    "summary": _quality_summary(runs, families)},
        "scene_groups": groups,
        "same_ticks": same,
        "scaling": scaling_res,
        "harvest": harvest_res,
        "tsid_reference": {"tick_us": report.TSID_US, "credit": report.TSID_CREDIT},
    }
    res["targets"] = _targets(res)
    res = _finite_or_none(res)  # strict JSON: a statistic with no value (the floor's stages) is null
    if same:
        report.write_plots(res, tick_times, out)
    res["duration_s"] = time.time() - started  # `make bench`'s wall time (this run, plots included)
    (out / "results.json").write_text(json.dumps(res, indent=2, default=_json_default, allow_nan=False) + "\n")
    (out / "results.md").write_text(report.markdown(res))
    return res


def _finite_or_none(x: Any) -> Any:
    """``x`` with every NaN or infinite float (nested in dicts and lists) replaced by None."""
    if isinstance(x, dict):
        return {k: _finite_or_none(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite_or_none(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return float(x) if np.isfinite(x) else None
    return x


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
