"""Robustness (issue 12, ``make robust``): every fault kind at three levels, ``paper``, ``hsu`` and
``qp``, on seeded paper-arm and Panda-canopy scenes.

    python -m benchmarks.robustness --out results/robust        (what ``make robust`` runs)

Scenes: the packaged ``paper`` and ``panda_canopy`` scenarios, ``planar_scene(seed)`` (the paper's
arm past 2–4 random discs, 3 s) and ``canopy_scene(seed)`` (the Panda reaching into a random canopy
of 10 branches and leaves, 2.5 s) from :mod:`qpctl.bench.scenes`; every run in the built-in
simulator at 1 ms, the QP with daqp (the default solver). Faults of scene i are seeded
``FAULT_SEED + i``: the three controllers meet the same realisation.

Phases, each spread over ``--jobs`` processes by the sweep engine with a progress bar:

1. every controller on every scene without faults (the baseline, and each scene's peak torques,
   from which the torque-saturation levels are taken);
2. every fault kind alone at three levels (:data:`KINDS`), and the issue's moderate faults together
   (:data:`MODERATE`), every controller; ``qp`` also with ``controller.d_safe_margin = "auto"``
   where that margin is not zero;
3. for each fault kind, at the first level at which ``qp`` loses d_safe (on any scene, by more
   than :data:`D_SAFE_TOLERANCE`), ``qp`` with the margins of :data:`MARGINS` [m] in increasing order
   until one restores d_safe on every scene (the smallest that does is reported).

Writes ``results.json`` (every run) and ``robust.md`` (the tables of docs/reliability.md) to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from qpctl.sweep.backends import LocalBackend
from qpctl.sweep.engine import map_ordered

FAULT_SEED = 1200
D_SAFE_TOLERANCE = 1e-3  # [m] a run "keeps d_safe" when its least clearance ≥ d_safe − this
MARGINS = (0.005, 0.01, 0.02, 0.04)  # [m] tried in phase 3
CONTROLLERS = ("paper", "hsu", "qp")
PLANAR_SEEDS = tuple(range(10))
CANOPY_SEEDS = tuple(range(100, 110))


@dataclass(frozen=True)
class Kind:
    """A fault kind: its key, unit, three levels and how a level becomes ``Faults`` fields on a scene."""

    name: str
    unit: str
    levels: tuple[float, float, float]
    fields: Callable[[float, dict[str, Any]], dict[str, Any]]  # (level, scene info) → Faults fields


def _key(name: str) -> Callable[[float, dict[str, Any]], dict[str, Any]]:
    return lambda level, _info: {name: level}


KINDS: tuple[Kind, ...] = (
    Kind("q_noise", "rad", (3e-5, 1e-4, 1e-3), _key("q_noise")),
    Kind("q_quantum", "rad", (1e-4, 1e-3, 5e-3), _key("q_quantum")),
    Kind("v_noise", "rad/s", (3e-3, 1e-2, 5e-2), _key("v_noise")),
    Kind("delay_ticks", "ticks", (1, 3, 10), lambda lv, _i: {"delay_ticks": int(lv)}),
    Kind("miss_rate", "", (0.01, 0.1, 0.3), _key("miss_rate")),
    Kind("torque_lag", "s", (0.002, 0.005, 0.02), _key("torque_lag")),
    # the drives keep this fraction of the headroom each joint used above holding the arm in the scene's
    # ideal qp run: τ_sat = G + f·(τ_peak − G), G the largest gravity torque along that run (a drive
    # weaker than G cannot hold the arm up at all: every controller drops it)
    Kind("torque_saturation", "of the headroom", (0.75, 0.5, 0.25),
         lambda lv, info: {"torque_saturation": [g + lv * max(p - g, 0.0) for p, g in
                                                 zip(info["peak_torque"], info["peak_gravity"], strict=True)]}),
    Kind("mass_error", "±", (0.05, 0.1, 0.2), _key("mass_error")),
    Kind("payload_mass", "kg", (0.2, 0.5, 1.0),
         lambda lv, info: {"payload_mass": lv, "payload_time": 0.5 * info["duration"]}),
    Kind("obstacle_noise", "m", (0.003, 0.01, 0.03), _key("obstacle_noise")),
    Kind("obstacle_velocity", "m/s", (0.005, 0.02, 0.05), _key("obstacle_velocity")),
)

#: The issue's moderate faults, together (the payload from half the run on).
MODERATE = {"q_noise": 1e-4, "v_noise": 1e-2, "delay_ticks": 1, "mass_error": 0.1, "payload_mass": 0.5,
            "obstacle_noise": 0.01}


@dataclass(frozen=True)
class Run:
    """One simulation: a scene, a controller, a fault kind and level (None: ideal), a d_safe margin."""

    scene: str
    controller: str
    kind: str | None = None
    level: int = -1  # index into the kind's levels
    margin: float | str = 0.0  # [m] or "auto"
    faults: tuple[tuple[str, Any], ...] = ()
    declared: bool = False  # the controller's robot.tau_max lowered to the drives' saturation

    @property
    def label(self) -> str:
        return (f"{self.scene}/{self.controller}/{self.kind or 'ideal'}[{self.level}]/m={self.margin}"
                + ("/declared" if self.declared else ""))


# -- scenes (built once per process) -----------------------------------------------------------------
_SCENES: dict[str, Any] = {}


def scene_names(planar: int, canopy: int) -> list[str]:
    return (["paper", "panda_canopy"] + [f"planar-{s}" for s in PLANAR_SEEDS[:planar]]
            + [f"canopy-{s}" for s in CANOPY_SEEDS[:canopy]])


def get_scene(name: str) -> Any:
    from qpctl.bench.scenes import canopy_scene, planar_scene, scenario_scene

    if name not in _SCENES:
        if name in ("paper", "panda_canopy"):
            _SCENES[name] = scenario_scene(name, "paper" if name == "paper" else "canopy")
        elif name.startswith("planar-"):
            _SCENES[name] = planar_scene(int(name.split("-")[1]))
        else:
            _SCENES[name] = canopy_scene(int(name.split("-")[1]))
    return _SCENES[name]


def scene_info(name: str) -> dict[str, Any]:
    scene = get_scene(name)
    return {"duration": scene.duration, "family": "planar" if scene.robot.m == 2 else "panda",
            "d_safe": scene.gains.d_safe}


# -- one run -----------------------------------------------------------------------------------------
def run_one(run: Run) -> dict[str, Any]:
    """Simulate ``run``; a small record of what happened (true clearance, tracking, torque-limit ticks)."""
    from qpctl.controllers.factory import make_controller
    from qpctl.errors import QpctlError
    from qpctl.simulation import Faults, Simulator

    scene = get_scene(run.scene)
    robot = scene.robot
    faults = Faults(**dict(run.faults)) if run.faults else None
    truth = list(scene.obstacles)
    seen = faults.perceived(truth, robot.task_axes) if faults is not None else truth
    margin = run.margin
    if margin == "auto":
        margin = faults.margin(robot) if faults is not None else 0.0
    gains = replace(scene.gains, d_safe=scene.gains.d_safe + float(margin))
    cfg = dict(scene.controller_cfg, kind=run.controller, solver="daqp")
    record: dict[str, Any] = {"run": run.label, "scene": run.scene, "controller": run.controller, "kind": run.kind,
                              "level": run.level, "margin": float(margin), "margin_setting": run.margin,
                              "d_safe": scene.gains.d_safe, "declared": run.declared}
    start = time.perf_counter()
    try:
        model = robot
        if run.declared and faults is not None and faults.torque_saturation is not None:
            model = robot.with_limits(tau_max=np.minimum(robot.tau_max, faults.torque_saturation))
        ctrl = make_controller(cfg, model, scene.path, seen, gains)
        sim = Simulator(ctrl, dt=scene.dt, duration=scene.duration, faults=faults, obstacles=truth)
        traj = sim.run(scene.q0)
    except QpctlError as exc:  # a diverged state (SimulationError, InvalidStateError): counted, not hidden
        record.update(error=f"{type(exc).__name__}: {' '.join(str(exc).splitlines())}"[:300])
        return record
    err = np.linalg.norm(traj.x_ref - traj.x, axis=1)
    cmd = traj.tau if traj.tau_command is None else traj.tau_command
    limit = robot.tau_max
    finite = np.isfinite(limit)
    at_limit = np.any(np.abs(cmd[:, finite]) >= limit[finite] * (1 - 1e-6), axis=1) if finite.any() else \
        np.zeros(len(cmd), bool)
    record.update(
        min_clearance=float(np.min(traj.clearance)), max_tracking_error=float(np.max(err)),
        rms_tracking_error=float(np.sqrt(np.mean(err**2))), torque_limit_ticks=int(np.count_nonzero(at_limit)),
        ticks=len(traj.t), peak_torque=np.max(np.abs(cmd), axis=0).tolist(),
        fallback_ticks=sum(1 for i in traj.infos if i.get("fallback")), seconds=time.perf_counter() - start,
        **sim.fault_counts)
    if faults is None:  # the largest gravity torque along the run [N·m], per joint (Pinocchio's G(q))
        import pinocchio as pin

        data = robot.model.createData()
        record["peak_gravity"] = np.max([np.abs(pin.computeGeneralizedGravity(robot.model, data, q))
                                         for q in traj.q[::5]], axis=0).tolist()
    return record


def run_all(runs: Sequence[Run], jobs: int, desc: str) -> list[dict[str, Any]]:
    """Every run, ``jobs`` at a time through the sweep engine (local processes), in the runs' order."""
    return map_ordered(run_one, [(r,) for r in runs], LocalBackend(jobs), desc=desc)


# -- the study ---------------------------------------------------------------------------------------
def fault_fields(kind: Kind | None, level: int, scene: str, index: int, peaks: dict[str, dict[str, Any]]) -> tuple:
    info = scene_info(scene) | {"peak_torque": peaks.get(scene, {}).get("peak_torque", []),
                                "peak_gravity": peaks.get(scene, {}).get("peak_gravity", [])}
    if kind is None:  # the moderate faults together
        fields = dict(MODERATE, payload_time=0.5 * info["duration"])
    else:
        fields = kind.fields(kind.levels[level], info)
    fields["seed"] = FAULT_SEED + index
    return tuple(sorted((k, tuple(v) if isinstance(v, list) else v) for k, v in fields.items()))


def keeps(rec: dict[str, Any]) -> bool:
    """Whether a run kept d_safe (within :data:`D_SAFE_TOLERANCE`); a run that errored did not."""
    return "error" not in rec and rec["min_clearance"] >= rec["d_safe"] - D_SAFE_TOLERANCE


def study(scenes: list[str], jobs: int, kinds: Sequence[Kind] = KINDS) -> dict[str, Any]:
    t0 = time.time()
    ideal = run_all([Run(s, c) for s in scenes for c in CONTROLLERS], jobs, "robustness 1/3: ideal")
    peaks = {r["scene"]: r for r in ideal if r["controller"] == "qp" and "error" not in r}
    runs: list[Run] = []
    auto_kinds = []
    for kind in (*kinds, None):
        levels = range(3) if kind is not None else [0]
        for level in levels:
            fields = {s: fault_fields(kind, level, s, i, peaks) for i, s in enumerate(scenes)}
            name = kind.name if kind is not None else "moderate"
            runs += [Run(s, c, name, level, 0.0, fields[s]) for s in scenes for c in CONTROLLERS]
            from qpctl.simulation import Faults

            probe = Faults(**dict(fields[scenes[0]]))
            if probe.q_noise or probe.q_quantum or probe.obstacle_noise:  # the auto margin is not zero
                auto_kinds.append(name)
                runs += [Run(s, "qp", name, level, "auto", fields[s]) for s in scenes]
            if probe.torque_saturation is not None:  # the QP told the drives' real limit
                runs += [Run(s, "qp", name, level, 0.0, fields[s], declared=True) for s in scenes]
    faulty = run_all(runs, jobs, "robustness 2/3: faults")
    # phase 3: the first level at which qp loses d_safe, and the margins that may restore it
    first_loss: dict[str, int] = {}
    for kind in (*kinds, None):
        name = kind.name if kind is not None else "moderate"
        for level in range(3 if kind is not None else 1):
            recs = [r for r in faulty if r["kind"] == name and r["level"] == level and r["controller"] == "qp"
                    and r["margin_setting"] == 0.0 and not r["declared"]]
            if not all(keeps(r) for r in recs):
                first_loss[name] = level
                break
    margins: list[dict[str, Any]] = []
    pending = dict(first_loss)
    for k, margin in enumerate(MARGINS):  # smallest first; a kind leaves once a margin restores d_safe
        if not pending:
            break
        batch = [Run(s, "qp", name, level, margin,
                     fault_fields(next((kd for kd in KINDS if kd.name == name), None), level, s, i, peaks))
                 for name, level in pending.items() for i, s in enumerate(scenes)]
        done = run_all(batch, jobs, f"robustness 3/3: margin {1e3 * margin:g} mm ({k + 1}/{len(MARGINS)})")
        margins += done
        pending = {name: lv for name, lv in pending.items()
                   if not all(keeps(r) for r in done if r["kind"] == name)}
    import platform

    return {"scenes": scenes, "fault_seed": FAULT_SEED, "d_safe_tolerance": D_SAFE_TOLERANCE,
            "kinds": {k.name: {"unit": k.unit, "levels": list(k.levels)} for k in kinds}, "moderate": MODERATE,
            "margins": list(MARGINS), "first_loss": first_loss, "ideal": ideal, "faulty": faulty,
            "margin_runs": margins, "elapsed_s": round(time.time() - t0, 1), "jobs": jobs,
            "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, Python "
                       f"{platform.python_version()}"}


# -- the report ----------------------------------------------------------------------------------------
def _mm(x: float) -> str:
    return f"{1e3 * x:+.1f}"


def _g(x: float) -> str:
    """A length [m] in mm, two significant digits (thousands separated)."""
    mm = 1e3 * x
    return f"{mm:,.0f}" if abs(mm) >= 100 else f"{mm:.2g}"


def _cell(recs: list[dict[str, Any]], ideal: dict[tuple[str, str], float]) -> list[str]:
    """collided / below d_safe (+ diverged); clearance − d_safe min, p10, median [mm]; max tracking error
    median and largest increase over the same controller's ideal run [mm]; scenes with τ-limit ticks."""
    ok = [r for r in recs if "error" not in r]
    bad = len(recs) - len(ok)
    coll = sum(r["min_clearance"] < 0 for r in ok)
    below = sum(not keeps(r) for r in ok)
    margin = np.array([r["min_clearance"] - r["d_safe"] for r in ok]) if ok else np.array([np.nan])
    track = np.array([r["max_tracking_error"] for r in ok]) if ok else np.array([np.nan])
    rise = max((r["max_tracking_error"] - ideal[(r["scene"], r["controller"])] for r in ok
                if (r["scene"], r["controller"]) in ideal), default=float("nan"))
    hits = sum(r["torque_limit_ticks"] > 0 for r in ok)
    first = f"{coll} / {below}" + (f" (+{bad} diverged)" if bad else "")
    clr = f"{_mm(np.min(margin))} / {_mm(np.percentile(margin, 10))} / {_mm(np.median(margin))}"
    return [first, clr, f"{_g(float(np.median(track)))} / {'+' if rise >= 0 else ''}{_g(rise)}", str(hits)]


def _level(kind: str, level: int, data: dict[str, Any]) -> str:
    if kind == "moderate":
        return "σ_q 1e-4, σ_v 1e-2, 1 tick, ±10 %, 0.5 kg, 1 cm"
    unit = data["kinds"][kind]["unit"]
    val = data["kinds"][kind]["levels"][level]
    return f"{val:g} {unit}".strip()


def report(data: dict[str, Any]) -> str:
    n = len(data["scenes"])
    planar = sum(not s.startswith(("canopy", "panda")) for s in data["scenes"])
    seeds = {f: ", ".join(s.split("-")[1] for s in data["scenes"] if s.startswith(f)) for f in ("planar-", "canopy-")}
    intro = (f"{n} scenes ({planar} paper-arm: the packaged `paper` and `planar_scene` seeds {seeds['planar-']}; "
             f"{n - planar} Panda: `panda_canopy` and `canopy_scene` seeds {seeds['canopy-']}), 1 ms, fault seed "
             f"{data['fault_seed']} + scene index; `make robust` took {data['elapsed_s'] / 60:.1f} min on "
             f"{data['machine']} ({data['jobs']} processes).")
    legend = (f"Per controller: **collided / below d_safe** (scenes of {n}; below: least clearance < d_safe − "
              f"{1e3 * data['d_safe_tolerance']:.0f} mm); **clearance − d_safe [mm]**, the least over each run: "
              "min / 10th percentile / median over the scenes; **tracking [mm]**: the run's largest tracking error, "
              "median over the scenes / the largest increase over the same controller's ideal run on the same "
              "scene; **τ-limit**: scenes with a commanded torque at or beyond τ_max (Panda only: the planar "
              "arm has no torque limits). No margin (`controller.d_safe_margin = 0`).")
    lines = [intro, "", legend, ""]
    head = "| fault | level |" + "".join(f" {c}: collided / below | {c}: clearance − d_safe | {c}: tracking | "
                                         f"{c}: τ-limit |" for c in CONTROLLERS)
    lines += [head, "|" + "---|" * (2 + 4 * len(CONTROLLERS))]

    ideal = {(r["scene"], r["controller"]): r["max_tracking_error"] for r in data["ideal"] if "error" not in r}

    def group(kind: str | None, level: int, margin: Any = 0.0, controllers: Sequence[str] = CONTROLLERS,
              declared: bool = False) -> dict[str, list[dict[str, Any]]]:
        recs = data["ideal"] if kind is None else data["faulty"]
        return {c: [r for r in recs if r["controller"] == c and (kind is None or (
            r["kind"] == kind and r["level"] == level and r["margin_setting"] == margin
            and r["declared"] == declared))] for c in controllers}

    rows = [("none", None, 0)] + [(k, k, lv) for k in data["kinds"] for lv in range(3)] + [("moderate", "moderate", 0)]
    for label, kind, level in rows:
        g = group(kind, level)
        cells = [cell for c in CONTROLLERS for cell in _cell(g[c], ideal)]
        lv = "–" if kind is None else _level(kind, level, data)
        lines.append(f"| {label} | {lv} | " + " | ".join(cells) + " |")
    # qp and its margins
    auto = ("`qp` with the automatic margin (`controller.d_safe_margin = \"auto\"`: 3σ of the map noise + the "
            "joint noise through the reach), where it is not zero:")
    lines += ["", auto, "",
              "| fault | level | margin [mm] | collided / below | clearance − d_safe [mm] | tracking [mm] | τ-limit |",
              "|---|---|---|---|---|---|---|"]
    for kind in [*data["kinds"], "moderate"]:
        for level in range(3 if kind != "moderate" else 1):
            recs = group(kind, level, "auto", ("qp",))["qp"]
            if recs:
                ms = sorted({r["margin"] for r in recs})
                mtxt = f"{1e3 * ms[0]:.1f}" if len(ms) == 1 else f"{1e3 * ms[0]:.1f}–{1e3 * ms[-1]:.1f}"
                lines.append(f"| {kind} | {_level(kind, level, data)} | {mtxt} | " + " | ".join(_cell(recs, ideal)) + " |")
    known = ("`qp` told the drives' real limit (`robot.tau_max` lowered to the saturation, the same faults): "
             "its torque rows then hold what the drives can deliver:")
    lines += ["", known, "", "| fault | level | collided / below | clearance − d_safe [mm] | tracking [mm] | τ-limit |",
              "|---|---|---|---|---|---|"]
    for kind in data["kinds"]:
        for level in range(3):
            recs = group(kind, level, 0.0, ("qp",), declared=True)["qp"]
            if recs:
                lines.append(f"| {kind} | {_level(kind, level, data)} | " + " | ".join(_cell(recs, ideal)) + " |")
    first = (f"Where `qp` first loses d_safe (any scene below d_safe − {1e3 * data['d_safe_tolerance']:.0f} mm, no "
             f"margin) and the smallest margin of {', '.join(f'{1e3 * m:g}' for m in data['margins'])} mm that "
             "restores it on every scene:")
    head3 = ("| fault | first level losing d_safe | scenes below / worst [mm] | margin that restores d_safe | "
             "with it: collided / below, worst [mm], tracking median [mm] |")
    lines += ["", first, "", head3, "|---|---|---|---|---|"]
    for kind in [*data["kinds"], "moderate"]:
        level = data["first_loss"].get(kind)
        if level is None:
            lines.append(f"| {kind} | none of the three | – | – | – |")
            continue
        recs = group(kind, level, 0.0, ("qp",))["qp"]
        ok = [r for r in recs if "error" not in r]
        worst = min(r["min_clearance"] - r["d_safe"] for r in ok) if ok else float("nan")
        below = sum(not keeps(r) for r in recs)
        found = "none up to " + f"{1e3 * data['margins'][-1]:g} mm"
        detail = "–"
        for m in data["margins"]:
            mr = [r for r in data["margin_runs"] if r["kind"] == kind and r["margin_setting"] == m]
            if mr and all(keeps(r) for r in mr):
                c = _cell(mr, ideal)
                found, detail = f"{1e3 * m:g} mm", f"{c[0]}, {c[1].split(' / ')[0]}, {c[2].split(' / ')[0]}"
                break
        lines.append(f"| {kind} | {_level(kind, level, data)} | {below} / {_mm(worst)} | {found} | {detail} |")
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.robustness", description=__doc__.splitlines()[0])
    p.add_argument("--out", default="results/robust", help="output folder")
    p.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="processes")
    p.add_argument("--planar", type=int, default=len(PLANAR_SEEDS), help="planar_scene seeds (0–10)")
    p.add_argument("--canopy", type=int, default=len(CANOPY_SEEDS), help="canopy_scene seeds (0–10)")
    p.add_argument("--kinds", help="a comma-separated subset of the fault kinds (a shorter trial)")
    p.add_argument("--report-only", action="store_true", help="rewrite robust.md from results.json")
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.report_only:
        data = json.loads((out / "results.json").read_text())
    else:
        from qpctl.warmup import warmup

        warmup()  # compile or load the kernels once here, before the workers load them from the cache
        kinds = KINDS if not args.kinds else tuple(k for k in KINDS if k.name in args.kinds.split(","))
        data = study(scene_names(args.planar, args.canopy), args.jobs, kinds)
        (out / "results.json").write_text(json.dumps(data, indent=1, default=float) + "\n")
    text = report(data)
    (out / "robust.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
