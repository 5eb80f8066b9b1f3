"""Stop before contact on a fresh seeded set of scenes (issue 22's Targets; ``make soak-brake``): the
soak's generators (``tests/test_soak.py``) on a stream of their own (seed [SEED, 22]), every planar
scene given a torque-rate limit of 1–5 kN·m/s (the heavy planar arm: τ_max 500–1500 N·m), the Panda
with Franka's limits; static and moving obstacles as the generator draws them. Each scene runs behind
the verified backup (``controller.backup = true``, every tick checked) with the oracle on every 10th
visited state (:func:`test_soak_brake.guarded_run`).

    python -m benchmarks.soak_brake --scenes 200 --jobs 2 --out results/soak

writes ``summary_brake.json`` (the summary of :func:`test_soak_brake.summarise` and one row per
scene) after every finished scene, so a run cut short still reports the scenes it finished.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import sys
import time
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import test_soak as soak  # the soak's generator is the scenes' definition
import test_soak_brake as brake

STREAM = 22  # issue 22's scenes: a stream of their own


def rate_limited(raw: dict[str, Any], k: int) -> None:
    """Every planar scene with a torque-rate limit of 1–5 kN·m/s (its own draw per scene)."""
    if raw["robot"]["kind"] == "planar3":
        raw["robot"]["tau_rate_max"] = float(np.random.default_rng([soak.SEED, STREAM, k]).uniform(1000.0, 5000.0))


def fresh_scenes(count: int) -> Iterator[dict[str, Any]]:
    drawn = soak.valid_scenes(np.random.default_rng([soak.SEED, STREAM]), Counter(), rate_limited)
    for _ in range(count):
        yield next(drawn)[2]


def soak_scenes(count: int) -> Iterator[dict[str, Any]]:
    """The soak's own scenes (``make soak``'s stream, tests/test_soak_brake.py), in draw order."""
    drawn = soak.valid_scenes(np.random.default_rng(soak.SEED), Counter())
    for _ in range(count):
        yield next(drawn)[2]


def unbudgeted(raw: dict[str, Any]) -> dict[str, Any]:
    """The scene with ``tick_budget_us = 0`` (its run does not depend on the machine's load) — except a
    proxqp scene, which keeps its budget: proxsuite without one spends tens of milliseconds to seconds
    on an infeasible tick (41 ms a tick over 969 ticks of the faults soak's soak-planar-47 on
    2026-12-07, 5.4 s of simulated time taking over 15 min), which is why the soak's generator
    (``test_soak._controller``) never draws one without a budget."""
    if raw["controller"].get("solver") == "proxqp":
        return raw
    return {**raw, "controller": {**raw["controller"], "tick_budget_us": 0.0}}


def _run(job: tuple[dict[str, Any], int, bool]) -> dict[str, Any]:
    raw, oracle_every, backup = job
    try:
        return brake.guarded_run(raw, oracle_every, backup=backup)
    except Exception as exc:  # noqa: BLE001 — reported with the scene, the run goes on
        return {"name": raw["name"], "error": f"{type(exc).__name__}: {exc}"}


def compare(guarded: list[dict[str, Any]], bare: list[dict[str, Any]]) -> dict[str, Any]:
    """Issue 22 item 6 on the scenes both runs finished: median RMS tracking [m] with the guard vs
    without over the scenes that were collision-free without it (and over those free in both), the
    collisions each way, and the per-tick cost of the guard (every tick, and the checked ones) [µs]."""
    by = {r["name"]: r for r in bare}
    pairs = [(g, by[g["name"]]) for g in guarded if g["name"] in by]
    free = [(g, b) for g, b in pairs if not b["collided"]]
    both = [(g, b) for g, b in free if not g["collided"]]
    ticks = np.concatenate([np.asarray(g["tick_us"], float) for g, _ in pairs]) if pairs else np.zeros(0)
    checked = np.concatenate([np.asarray(g["check_us"], float) for g, _ in pairs]) if pairs else np.zeros(0)

    def med(rows: list[dict[str, Any]]) -> float | None:
        return float(np.median([r["rms_tracking_error"] for r in rows])) if rows else None

    out: dict[str, Any] = {
        "scenes": len(pairs), "collided_without": sum(b["collided"] for _, b in pairs),
        "collided_with": sum(g["collided"] for g, _ in pairs),
        "static_collided_without": sum(b["collided"] and not b["moving"] for _, b in pairs),
        "static_collided_with": sum(g["collided"] and not g["moving"] for g, _ in pairs),
        "free_without": len(free), "rms_median_without": med([b for _, b in free]),
        "rms_median_with": med([g for g, _ in free]),
        "free_both": len(both), "rms_median_without_free_both": med([b for _, b in both]),
        "rms_median_with_free_both": med([g for g, _ in both]),
        "rms_ratio_per_scene_median": float(np.median([g["rms_tracking_error"] / max(b["rms_tracking_error"], 1e-12)
                                                      for g, b in free])) if free else None,
        "tick_us_median": float(np.median(ticks)) if ticks.size else None,
        "tick_us_p99": float(np.percentile(ticks, 99)) if ticks.size else None,
        "checked_us_median": float(np.median(checked)) if checked.size else None,
        "checked_us_p99": float(np.percentile(checked, 99)) if checked.size else None,
        "intervention_share": sum(g["backup_ticks"] for g, _ in pairs) / max(sum(g["ticks"] for g, _ in pairs), 1),
    }
    if out["rms_median_with"] is not None and out["rms_median_without"]:
        out["rms_change"] = out["rms_median_with"] / out["rms_median_without"] - 1
    return out


def check_cost(scenes: int, every: int = 3, passes: int = 1) -> dict[str, Any]:
    """The guard's check, replayed (``--cost``): each of the first ``scenes`` soak scenes runs behind
    the guard and every ``every``-th tick's check inputs are recorded (state, proposal, stored gain,
    torque applied last); each recorded check is then replayed, in turn, by the guard as configured
    (``guard``) and by the reference (``exact``: every step's clearance evaluated, no early end, every
    gain tried; the previous code's verdict). It reports per mode the CPU time of a check (``time.thread_time``: independent of the
    other processes' load on a shared machine; the wall time too) as median / p99 [µs], and counts the
    checks whose outcome (the torque applied, the gain stored) differs from the reference's."""
    from qpctl import Scenario
    from qpctl.simulation import Simulator

    modes = {"guard": False, "exact": True}
    cpu: dict[str, list[float]] = {m: [] for m in modes}
    wall: dict[str, list[float]] = {m: [] for m in modes}
    differ = dict.fromkeys(modes, 0)
    replayed = 0
    for raw in soak_scenes(scenes):
        sc = Scenario.from_dict(brake.guarded(raw), source=raw["name"])
        guard = sc.build_controller()
        guard.warmup()
        rec: list[tuple[Any, ...]] = []
        check = guard.check
        tick = [0]

        def recording(q: np.ndarray, v: np.ndarray, tau: np.ndarray, t: float, info: dict[str, Any],
                      check: Any = check, guard: Any = guard, rec: list[tuple[Any, ...]] = rec,
                      tick: list[int] = tick) -> np.ndarray:
            tick[0] += 1
            if tick[0] % every == 0:
                rec.append((q.copy(), v.copy(), tau.copy(), t, guard._gain, guard._tau_prev.copy()))
            return check(q, v, tau, t, info)

        guard.check = recording
        Simulator(guard, dt=raw["sim"]["dt"], duration=raw["sim"]["duration"]).run(sc.q0(guard.robot))
        del guard.check
        guard._limit = None  # no side effect on the controller's rate window in the replay
        for q, v, tau, t, gain, prev in rec:
            outcome = {}
            for _ in range(passes):
                for m, exact in modes.items():
                    guard.exact = exact
                    guard._gain, guard._tau_prev = gain, prev
                    c0, w0 = time.thread_time(), time.perf_counter()
                    applied = guard.check(q, v, tau, t, {})
                    cpu[m].append((time.thread_time() - c0) * 1e6)
                    wall[m].append((time.perf_counter() - w0) * 1e6)
                    outcome[m] = (applied.copy(), guard._gain)
            ref_tau, ref_gain = outcome["exact"]
            for m, (got_tau, got_gain) in outcome.items():
                differ[m] += bool(got_gain != ref_gain or not np.allclose(got_tau, ref_tau, rtol=1e-9, atol=1e-9))
            replayed += 1
        guard.exact = False
        print(raw["name"], len(rec), {m: round(float(np.median(cpu[m][-len(rec):])), 1) for m in modes}, flush=True)
    return {"scenes": scenes, "every": every, "checks_replayed": replayed,
            **{m: {"cpu_us_median": float(np.median(cpu[m])), "cpu_us_p99": float(np.percentile(cpu[m], 99)),
                   "wall_us_median": float(np.median(wall[m])), "wall_us_p99": float(np.percentile(wall[m], 99)),
                   "outcomes_differing_from_exact": differ[m]} for m in modes}}


def panda_khz(raws: list[dict[str, Any]]) -> dict[str, Any]:
    """The set's Panda scenes at 1 kHz (``--panda-1khz``): each scene's ``sim.dt`` set to 1 ms, behind the
    guard, no oracle, one process (the timings are the point): every checked tick's check [µs wall] —
    median, p99, p99.9, max over all ticks, and the scenes whose p99 is within 1 ms — next to the QP's
    tick, and the interventions, unverified ticks (of them on the way to a carried search's anchor),
    collisions and tracking."""
    rows: list[dict[str, Any]] = []
    for raw in raws:
        if raw["robot"]["kind"] != "panda":
            continue
        raw = {**raw, "sim": {**raw["sim"], "dt": 1e-3}}
        row = brake.guarded_run(raw, 0)
        rows.append(row)
        print(raw["name"], {k: row[k] for k in ("collided", "backup_ticks", "unverified", "min_clearance")},
              f"check median {np.median(row['tick_us']):.0f} µs, p99 {np.percentile(row['tick_us'], 99):.0f} µs",
              flush=True)
    us = np.concatenate([r["tick_us"] for r in rows])
    return {"scenes": [r["name"] for r in rows], "ticks": int(us.size),
            "check_us_median": float(np.median(us)), "check_us_p99": float(np.percentile(us, 99)),
            "check_us_p999": float(np.percentile(us, 99.9)), "check_us_max": float(us.max()),
            "ticks_over_1ms": int(np.sum(us > 1000.0)),
            "scenes_p99_within_1ms": int(sum(np.percentile(r["tick_us"], 99) <= 1000.0 for r in rows)),
            "backup_ticks": int(sum(r["backup_ticks"] for r in rows)),
            "carried_ticks": int(sum(r["carried_ticks"] for r in rows)),
            "carried_adopted": int(sum(r["carried_adopted"] for r in rows)),
            "worst_rms_tracking_error": float(max(r["rms_tracking_error"] for r in rows)),
            "unverified_ticks": int(sum(r["unverified"] for r in rows)),
            "collided": [r["name"] for r in rows if r["collided"]],
            "median_rms_tracking_error": float(np.median([r["rms_tracking_error"] for r in rows])),
            "per_scene": [{"name": r["name"], "moving": r["moving"], "ticks": r["ticks"],
                           "check_us_median": float(np.median(r["tick_us"])),
                           "check_us_p99": float(np.percentile(r["tick_us"], 99)),
                           "ticks_over_1ms": int(np.sum(np.asarray(r["tick_us"]) > 1000.0)),
                           "check_us_max": float(np.max(r["tick_us"])),
                           "backup_ticks": r["backup_ticks"], "retreat_ticks": r["retreat_ticks"],
                           "unverified": r["unverified"], "carried_ticks": r["carried_ticks"],
                           "carried_adopted": r["carried_adopted"], "collided": r["collided"],
                           "rms_tracking_error": r["rms_tracking_error"]} for r in rows]}


def faults_run(raw: dict[str, Any], backup: bool) -> dict[str, Any]:
    """One faults-soak scene (its ``[faults]`` table: the simulator applies them, the controller runs
    on its perceived map and measured state) with or without the guard; tick budgets off (:func:`unbudgeted`:
    proxqp scenes keep theirs)."""
    from qpctl import Scenario
    from qpctl.simulation import Simulator
    from qpctl.simulation.metrics import compute_metrics

    raw = unbudgeted(raw)
    scen = Scenario.from_dict(brake.guarded(raw, backup=backup), source=raw["name"])
    faults = scen.faults()
    robot = scen.build_robot()
    truth = scen.build_obstacles()
    ctrl = scen.build_controller(robot=robot, obstacles=faults.perceived(truth, robot.task_axes))
    ctrl.warmup()
    try:
        tr = Simulator(ctrl, dt=raw["sim"]["dt"], duration=raw["sim"]["duration"], faults=faults,
                       obstacles=truth).run(scen.q0(robot))
    except Exception as exc:  # noqa: BLE001 — a diverged run is reported with its scene
        return {"name": raw["name"], "backup": backup, "error": f"{type(exc).__name__}: {exc}"}
    m = compute_metrics(tr)
    return {"name": raw["name"], "backup": backup, "faults": faults.kinds(),
            "moving": any(o.moving for o in truth), "collided": bool(tr.clearance.min() < 0),
            "min_clearance": float(tr.clearance.min()), "collisions_at_rest": m["collisions_at_rest"],
            "backup_ticks": m.get("backup_ticks", 0), "unverified": m.get("backup_unverified_ticks", 0),
            "rms_tracking_error": m["rms_tracking_error"]}


def _faults_run(job: tuple[dict[str, Any], bool]) -> dict[str, Any]:
    return faults_run(*job)


def faults_compare(count: int, jobs: int = 1, path: Path | None = None) -> dict[str, Any]:
    """The faults soak's scenes (``test_soak.test_soak_with_faults``: stream [SEED, 12], its random
    faults), the first ``count``, each without and with the guard (``--faults``), on ``jobs`` processes;
    the summary is written to ``path`` after every finished run, so a run cut short reports the runs it
    finished."""
    def with_faults(raw: dict[str, Any], k: int) -> None:
        raw["faults"] = soak.random_faults(np.random.default_rng([soak.SEED, 12, k]), raw, k)

    drawn = soak.valid_scenes(np.random.default_rng([soak.SEED, 12]), Counter(), with_faults)
    work = [(raw, backup) for raw in (next(drawn)[2] for _ in range(count)) for backup in (False, True)]
    rows: dict[bool, list[dict[str, Any]]] = {False: [], True: []}
    start = time.time()
    out = faults_summary(rows, count, 0.0)
    with mp.get_context("spawn").Pool(jobs) as pool:
        for (_, backup), row in zip(work, pool.imap(_faults_run, work, chunksize=1), strict=True):
            rows[backup].append(row)
            print(row["name"], "guard" if backup else "bare",
                  {k: row.get(k) for k in ("min_clearance", "collided", "backup_ticks", "unverified", "error")}, flush=True)
            out = faults_summary(rows, count, time.time() - start)
            if path is not None:
                path.write_text(json.dumps(out, indent=1, default=float) + "\n")
    return out


def faults_summary(rows: dict[bool, list[dict[str, Any]]], count: int, elapsed: float) -> dict[str, Any]:
    """:func:`faults_compare`'s summary of the runs finished so far."""
    def count_of(rs: list[dict[str, Any]], pred: Any) -> int:
        return sum(1 for r in rs if "error" not in r and pred(r))

    out: dict[str, Any] = {"seed": [soak.SEED, 12], "scenes": count, "elapsed_s": elapsed}
    for backup, rs in rows.items():
        out["with_guard" if backup else "without_guard"] = {
            "errors": [r["name"] for r in rs if "error" in r],
            "collided": count_of(rs, lambda r: r["collided"]),
            "static_scenes": count_of(rs, lambda r: not r["moving"]),
            "static_collided": count_of(rs, lambda r: r["collided"] and not r["moving"]),
            "collided_names": [r["name"] for r in rs if r.get("collided")],
            "unverified_ticks": sum(r.get("unverified", 0) for r in rs),
            "scenes_with_unverified": count_of(rs, lambda r: r["unverified"] > 0),
            "backup_ticks": sum(r.get("backup_ticks", 0) for r in rs)}
    out["runs"] = rows[False] + rows[True]
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=200)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--oracle-every", type=int, default=brake.ORACLE_EVERY, help="0: no oracle")
    ap.add_argument("--out", type=Path, default=soak.OUT)
    ap.add_argument("--scene-set", choices=("fresh", "soak"), default="fresh",
                    help="fresh: issue 22's seeded set (summary_brake.json); soak: make soak's own scenes")
    ap.add_argument("--compare", action="store_true",
                    help="each scene with and without the guard (no oracle): item 6's tracking, collisions "
                         "both ways, the per-tick cost (summary_brake_compare_<set>.json)")
    ap.add_argument("--cost", action="store_true",
                    help="replay every 3rd tick's check of the first --scenes soak scenes: the guard's vs the "
                         "exact reference, CPU µs per check and the outcomes that differ")
    ap.add_argument("--no-budget", action="store_true",
                    help="tick_budget_us = 0 in every scene but the proxqp ones: the runs do not depend on the machine's load")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a controller key for every scene, e.g. backup_check_steps=400 (the output file gets "
                         "the settings in its name)")
    ap.add_argument("--panda-1khz", action="store_true",
                    help="the set's Panda scenes among its first --scenes at dt = 1 ms, one process, no oracle: the "
                         "check's cost a tick at 1 kHz (summary_brake_panda_1khz_<set>.json)")
    ap.add_argument("--faults", action="store_true",
                    help="the faults soak's first --scenes scenes without and with the guard (summary_brake_faults.json)")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    if args.faults:
        out = faults_compare(args.scenes, args.jobs, args.out / "summary_brake_faults.json")
        print(json.dumps({k: v for k, v in out.items() if k != "runs"}, indent=1, default=float))
        return 0
    if args.cost:
        out = check_cost(args.scenes)
        (args.out / "brake_check_cost.json").write_text(json.dumps(out, indent=1) + "\n")
        print(json.dumps(out, indent=1))
        return 0
    scenes = list((fresh_scenes if args.scene_set == "fresh" else soak_scenes)(args.scenes))
    if args.no_budget:
        scenes = [unbudgeted(raw) for raw in scenes]
    settings = {k.strip(): json.loads(v) for k, v in (kv.split("=", 1) for kv in args.set)}
    scenes = [{**raw, "controller": {**raw["controller"], **settings}} for raw in scenes]
    tag = "".join(f"_{k}={v}" for k, v in settings.items())
    if args.panda_1khz:
        out = panda_khz(scenes)
        (args.out / f"summary_brake_panda_1khz_{args.scene_set}{tag}.json").write_text(json.dumps(out, indent=1) + "\n")
        print(json.dumps({k: v for k, v in out.items() if k != "per_scene"}, indent=1))
        return 0
    if args.compare:
        jobs = [(raw, 0, b) for raw in scenes for b in (True, False)]
        path = args.out / f"summary_brake_compare_{args.scene_set}.json"
    else:
        jobs = [(raw, args.oracle_every, True) for raw in scenes]
        path = args.out / ("summary_brake.json" if args.scene_set == "fresh" else "summary_brake_soakset.json")
    if settings:
        path = path.with_name(path.stem + tag + ".json")
    rows: list[dict[str, Any]] = []
    bare: list[dict[str, Any]] = []
    errors: list[dict[str, Any]] = []
    start = time.time()
    with mp.get_context("spawn").Pool(args.jobs) as pool:
        for (_, _, backup), row in zip(jobs, pool.imap(_run, jobs, chunksize=1), strict=True):
            (errors if "error" in row else rows if backup else bare).append(row)
            summary = {"seed": [soak.SEED, STREAM] if args.scene_set == "fresh" else soak.SEED,
                       "scene_set": args.scene_set, "scenes_requested": args.scenes, "no_budget": args.no_budget,
                       "elapsed_s": time.time() - start, "jobs": args.jobs, "errors": errors, **brake.summarise(rows)}
            if args.compare:
                summary["compare"] = compare(rows, bare)
            path.write_text(json.dumps({"summary": summary, "runs": brake.public(rows), "runs_without": brake.public(bare)},
                                       indent=1, default=float) + "\n")
            print(row["name"], "guard" if backup else "bare",
                  {k: row.get(k) for k in ("min_clearance", "collided", "rms_tracking_error", "backup_ticks",
                                           "unverified", "oracle_uncertified", "wall_s", "error")}, flush=True)
    print(json.dumps(summary, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
