"""Braking-aware rows (issue 22) on the soak's scenes that start at rest among static obstacles with a
torque-rate limit: collisions, worst clearance and median RMS tracking per setting.

    python -m benchmarks.braking --modes off,0.5,0.5r1.5 --scenes 12

A mode is ``off`` (``controller.braking = "off"``), ``SHARE[rREACH]`` (braking on with that
``braking_share`` and, if given, ``braking_reach`` [m]), or ``backup`` (braking off, the controller
behind :class:`qpctl.safety.BackupGuard`: its check's cost per checked tick and how often it
intervenes are reported too). Scenes come from the soak's own generator
(``tests/test_soak.py``: its seed, its validation, each scene's solver and fallback chain), in draw
order, the first ``--scenes`` with a torque-rate limit and no moving obstacle. Prints one line per
scene and a summary per mode; ``--out`` writes them as JSON too.

    python -m benchmarks.braking --cost panda_spheres [--set controller.braking_reach=0.0]

    python -m benchmarks.braking --oracle --scenes 12

runs each scene with braking off and asks the oracle (:func:`qpctl.safety.certify`) about every 10th
visited state (the torque applied before it as τ_prev): how many it certifies viable, and in the scenes
that collide when the first uncertified state came before the contact.

    python -m benchmarks.braking --rollout

times one brake's rollout per step [µs] from a moving state near obstacles (the states of
``tests/test_rollout.py``: the planar arm with a rate limit, the Panda): the Simulator-based
:func:`qpctl.safety.oracle.rollout` against :class:`qpctl.safety.rollout.BrakeRollout`'s Python loop
and its native one (:mod:`qpctl.native`), exact and with the lazy clearance, interleaved, 11 passes
(medians; state the load beside them).

``--cost`` times ``ctrl.step`` with braking off and on alternately on every 5th state of one run of the scenario
(braking off), three passes: medians and p99 [µs] (state the machine's load beside them).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import test_soak as soak  # the soak's generator is the scenes' definition

from qpctl import Scenario
from qpctl.run import simulate
from qpctl.safety import BackupGuard, certify
from qpctl.simulation import Simulator

NO_BUDGET = False  # --no-budget: tick_budget_us = 0 (a wall-clock budget makes runs depend on the load)


def controller_table(raw: dict[str, Any], mode: str) -> dict[str, Any]:
    c = dict(raw["controller"])
    if NO_BUDGET:
        c["tick_budget_us"] = 0.0
    if mode in ("off", "backup"):
        c["braking"] = "off"
        return c
    share, _, reach = mode.partition("r")
    c.update(braking="on", braking_share=float(share))
    if reach:
        c["braking_reach"] = float(reach)
    return c


def tick_cost(name: str, overrides: list[str], solver: str = "daqp") -> dict[str, Any]:
    """Interleaved QP tick times [µs], braking off and on, on the states of one run (module docstring),
    both with ``solver`` (daqp: the compiled one-call tick)."""
    sc_off = Scenario.load(name, overrides=['controller.braking="off"'])
    sc_on = Scenario.load(name, overrides=['controller.braking="on"', *overrides])
    tr = simulate(sc_off, kind="qp", solver=solver).trajectory
    off, on = sc_off.build_controller("qp", solver), sc_on.build_controller("qp", solver)
    off.warmup()
    on.warmup()
    t_off, t_on = [], []
    for _ in range(3):
        off.reset()
        on.reset()
        for k in range(0, len(tr.t), 5):
            q, v, t = np.ascontiguousarray(tr.q[k]), np.ascontiguousarray(tr.v[k]), float(tr.t[k])
            a = time.perf_counter()
            off.step(q, v, t)
            b = time.perf_counter()
            on.step(q, v, t)
            t_off.append((b - a) * 1e6)
            t_on.append((time.perf_counter() - b) * 1e6)
    return {"solver": solver, "ticks": len(t_off), "off_median": float(np.median(t_off)), "off_p99": float(np.percentile(t_off, 99)),
            "on_median": float(np.median(t_on)), "on_p99": float(np.percentile(t_on, 99))}


def rollout_cost(passes: int = 11) -> dict[str, dict[str, float]]:
    """µs (CPU) per step of the oracle's rollout and the lean one's (module docstring), medians."""
    import test_rollout as cases

    from qpctl.safety.oracle import rollout
    from qpctl.safety.rollout import BrakeRollout

    out = {}
    for name, make in (("planar", cases.planar_case), ("panda", cases.panda_case)):
        ctrl, q, v = make()
        sim = Simulator(ctrl, dt=cases.DT, duration=cases.DT)
        lean = BrakeRollout(ctrl.robot, sim.world, cases.DT)
        tau = cases.gravity(ctrl.robot, q)
        handle = lean.native  # the native loop (qpctl.native), or None where it is not built
        keys = ["oracle", "lean", "lean_lazy", "lean_lazy_unfused"] + (["native", "native_lazy"] if handle else [])
        times: dict[str, list[float]] = {k: [] for k in keys}
        for _ in range(passes + 1):  # the first pass compiles and is dropped
            for key, got in times.items():
                lean.fused = key != "lean_lazy_unfused"  # the RK4 stages in two kernel calls, or one per operation
                lean.native = handle if key.startswith("native") else None
                a = time.thread_time()  # CPU time: the machine is shared
                c = (rollout(sim, q, v, tau, 0.0, 25.0) if key == "oracle"
                     else lean.run(q, v, tau, 0.0, 25.0, exact=key in ("lean", "native")))
                got.append((time.thread_time() - a) * 1e6 / max(c.steps, 1))
        out[name] = {k: float(np.median(t[1:])) for k, t in times.items()} | {"steps": c.steps}
    return out


def oracle_sample(scenes: int, every: int = 10) -> int:
    """Every ``every``-th visited state of the braking-off runs, certified or not (module docstring)."""
    rng = np.random.default_rng(soak.SEED)
    total = certified = count = 0
    for _, which, raw in soak.valid_scenes(rng, Counter()):
        if count >= scenes:
            break
        if any("velocity" in o or "amplitude" in o for o in raw["obstacles"]) or not (
                which == "panda" or "tau_rate_max" in raw["robot"]):
            continue
        count += 1
        sc = Scenario.from_dict({**raw, "controller": controller_table(raw, "off")}, source=raw["name"])
        run = simulate(sc)
        tr, ctrl, dt = run.trajectory, run.controller, raw["sim"]["dt"]
        ks = list(range(every, len(tr.t), every))
        ok = [certify(ctrl, tr.q[k], tr.v[k], tr.tau[k - 1], float(tr.t[k]), dt).viable for k in ks]
        total, certified = total + len(ks), certified + sum(ok)
        contact = np.flatnonzero(tr.clearance < 0)
        first_bad = next((tr.t[k] for k, good in zip(ks, ok, strict=True) if not good), None)
        print(raw["name"], f"certified {sum(ok)}/{len(ks)}", "first uncertified t", first_bad,
              "first contact t", tr.t[contact[0]] if contact.size else None, flush=True)
    print(f"certified {certified} of {total} sampled states")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--modes", default="off,0.5")
    ap.add_argument("--scenes", type=int, default=12)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--cost", default=None, help="a scenario: time its QP ticks with braking off and on")
    ap.add_argument("--set", action="append", default=[], help="KEY=VALUE for the braking run of --cost")
    ap.add_argument("--solver", default="daqp", help="the QP's solver for --cost (daqp: the compiled one-call tick)")
    ap.add_argument("--oracle", action="store_true", help="certify every 10th visited state (braking off)")
    ap.add_argument("--rollout", action="store_true", help="time a brake rollout per step: oracle vs lean")
    ap.add_argument("--no-budget", action="store_true", help="tick_budget_us = 0: runs independent of the load")
    ap.add_argument("--only", action="append", default=[], help="run only this scene (repeatable), e.g. soak-planar-238")
    args = ap.parse_args(argv)
    global NO_BUDGET
    NO_BUDGET = args.no_budget
    if args.oracle:
        return oracle_sample(args.scenes)
    if args.rollout:
        print(rollout_cost())
        return 0
    if args.cost is not None:
        print(args.cost, tick_cost(args.cost, args.set, args.solver))
        return 0
    modes, only = args.modes.split(","), set(args.only)
    rng = np.random.default_rng(soak.SEED)
    rows: dict[str, list[dict[str, Any]]] = {m: [] for m in modes}
    t0, count = time.time(), 0
    for _, which, raw in soak.valid_scenes(rng, Counter()):
        if count >= args.scenes:
            break
        moving = any("velocity" in o or "amplitude" in o for o in raw["obstacles"])
        if moving or not (which == "panda" or "tau_rate_max" in raw["robot"]):
            continue
        count += 1
        if only and raw["name"] not in only:
            continue
        for m in modes:
            sc = Scenario.from_dict({**raw, "controller": controller_table(raw, m)}, source=raw["name"])
            extra: dict[str, Any] = {}
            if m == "backup":
                guard = BackupGuard(sc.build_controller(), dt=raw["sim"]["dt"])
                tr = Simulator(guard, dt=raw["sim"]["dt"], duration=raw["sim"]["duration"]).run(sc.q0(guard.robot))
                us = np.array(guard.stats["check_us"]) if guard.stats["check_us"] else np.zeros(1)
                extra = {"checked": guard.stats["checked"], "backup_ticks": guard.stats["backup"], "ticks": len(tr.t),
                         "check_us_median": float(np.median(us)), "check_us_p99": float(np.percentile(us, 99))}
            else:
                tr = simulate(sc).trajectory
            rms = float(np.sqrt(np.mean(np.sum((tr.x - tr.x_ref) ** 2, axis=1))))
            rows[m].append({"scene": raw["name"], "min_clearance": float(tr.clearance.min()), "rms_tracking": rms,
                            **extra})
        print(raw["name"], [(m, round(rows[m][-1]["min_clearance"], 4)) for m in modes], flush=True)
    summary = {}
    for m in modes:
        cl = np.array([r["min_clearance"] for r in rows[m]])
        if not cl.size:
            continue
        summary[m] = {"scenes": int(cl.size), "collide": int(np.sum(cl < 0)), "worst_clearance": float(cl.min()),
                      "median_rms_tracking": float(np.median([r["rms_tracking"] for r in rows[m]]))}
        if m == "backup":
            ticks = sum(r["ticks"] for r in rows[m])
            summary[m].update(intervention_rate=sum(r["backup_ticks"] for r in rows[m]) / ticks,
                              checked_rate=sum(r["checked"] for r in rows[m]) / ticks,
                              check_us_median=float(np.median([r["check_us_median"] for r in rows[m]])),
                              check_us_p99=float(max(r["check_us_p99"] for r in rows[m])))
        print(m, summary[m])
    print(f"{time.time() - t0:.0f} s")
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "braking.json").write_text(json.dumps({"summary": summary, "runs": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
