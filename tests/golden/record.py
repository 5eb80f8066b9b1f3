"""Record the golden ticks: states of closed-loop runs, and every controller's output on them.

Run it from an UNTOUCHED checkout of the code whose ticks are to be kept, with that checkout first
on the path (the venv's editable install points elsewhere; PYTHONPATH wins, and this script checks):

    cd /work/golden-src && PYTHONPATH=/work/golden-src /work/main/.venv/bin/python \\
        /work/main/tests/golden/record.py --source /work/golden-src [--out DIR] [--case NAME ...]

For each case (a scene) it simulates the closed loop twice with the built-in RK4 simulator — the
QP with DAQP, and the paper law (whose states go elsewhere, e.g. into obstacles) — and keeps three
sequences of states (t, q, v):

* ``qp-daqp:start``  — the QP run's first START_TICKS ticks, consecutive (1 ms warm starts);
* ``qp-daqp:window`` — WINDOW ticks, every STRIDE-th, of the QP run around its least clearance;
* ``paper:window``   — WINDOW ticks, every STRIDE-th, of the paper-law run ending PEN_AFTER ticks
  after its first penetration (around its least clearance if it never penetrates).

Then, per sequence and per controller (paper, hsu, qp-daqp, qp-proxqp), it REPLAYS: a fresh
controller, ``reset()``, ``step(q, v, t)`` on the states in order; and keeps per tick ``tau``,
``qdd``, ``e_null``, ``clearance`` (the controller's), ``status`` and ``fallback`` (QP ``info``;
"" when absent), ``singular``, ``pairs`` (pairs within the cutoff) and the number of penetrating
pairs (``n_pen``) and of penetrating link-capsule/obstacle-capsule pairs (``n_pen_capcap``).
tests/test_golden.py replays the same way and compares. One ``<case>.npz`` per case, beside this file.

Each file also holds the scene's full definition (``meta["scene"]``: the validated scenario data, or
the benchmark scene's robot, path, obstacles, gains and controller settings), from which the replays
build their controllers — so later edits to the packaged scenarios or to benchmarks/scenes.py do not
move the golden ticks. This module is imported by tests/test_golden.py for CASES, CONTROLLERS and
build_controller(), so that recording and replay build controllers the same way; importing it does
nothing else.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent

#: Controllers replayed on every sequence: label -> (kind, solver).
CONTROLLERS: dict[str, tuple[str, str | None]] = {
    "paper": ("paper", None),
    "hsu": ("hsu", None),
    "qp-daqp": ("qp", "daqp"),
    "qp-proxqp": ("qp", "proxqp"),
}

#: Cases: how to rebuild the scene. ``scenario`` is a packaged name or a file beside this script.
CASES: dict[str, dict[str, Any]] = {
    "paper": {"source": "scenario", "scenario": "paper", "overrides": []},
    "panda_canopy": {"source": "scenario", "scenario": "panda_canopy", "overrides": []},
    # examples/moving_obstacle.py as a scenario file, plus a sphere drifting at constant velocity
    "moving_obstacle": {"source": "scenario", "scenario": "file:moving_obstacle.toml", "overrides": []},
    # copy of /work/shared/tools/panda_spheres.toml (Panda, 10 sphere obstacles)
    "panda_spheres": {"source": "scenario", "scenario": "file:panda_spheres.toml", "overrides": []},
    "planar-0": {"source": "bench", "builder": "planar_scene", "seed": 0, "kwargs": {}},
    "planar-1": {"source": "bench", "builder": "planar_scene", "seed": 1, "kwargs": {}},
    "canopy-0": {"source": "bench", "builder": "canopy_scene", "seed": 0, "kwargs": {}},
    "canopy-1": {"source": "bench", "builder": "canopy_scene", "seed": 1, "kwargs": {}},
}

START_TICKS = 40  # consecutive ticks from t = 0
STRIDE = 10  # every 10th tick in the windows
WINDOW = 110  # states per window
PEN_AFTER = 60  # a penetrating run's window ends this many states after its first penetration...
#: ...except here: on the Panda's penetrating ticks the QP is infeasible and proxqp runs to its
#: iteration cap before the fallback (~0.4 s a tick), so keep few of them (moving_obstacle and the
#: planar scenes have many penetrating ticks, cheap ones; moving_obstacle's are capsule-capsule).
PEN_AFTER_CASE = {"panda_canopy": 8, "panda_spheres": 8}
REPEATS = 2  # extra replays per (sequence, controller) to measure the replay's own repeatability

#: The runs whose states are kept: label -> (kind, solver); the first also gives the start sequence.
RUNS: dict[str, tuple[str, str | None]] = {"qp-daqp": ("qp", "daqp"), "paper": ("paper", None)}

OUT_KEYS = ("tau", "qdd", "e_null", "clearance", "status", "fallback", "singular", "pairs", "n_pen",
            "n_pen_capcap")


def scene_for(spec: dict[str, Any], golden_dir: Path = HERE) -> dict[str, Any]:
    """A case from its source (packaged scenario, scenario file, benchmark builder): ``make(kind,
    solver)`` -> fresh controller, ``q0``, ``dt``, ``duration``, and ``frozen``: the scene's full
    definition as JSON-able data, stored in the golden file so that replays do not depend on the source."""
    if spec["source"] == "scenario":
        from qpctl import Scenario

        name = spec["scenario"]
        where = str(golden_dir / name[5:]) if name.startswith("file:") else name
        scen = Scenario.load(where, spec.get("overrides", []))
        robot = scen.build_robot()
        return {"make": lambda kind, solver: scen.build_controller(kind, solver), "q0": scen.q0(robot),
                "dt": scen.data["sim"]["dt"], "duration": scen.data["sim"]["duration"],
                "frozen": {"type": "scenario", "source": scen.source, "data": scen.data}}
    if spec["source"] == "bench":
        import dataclasses

        from qpctl.bench import scenes

        bench = getattr(scenes, spec["builder"])(spec["seed"], **spec.get("kwargs", {}))
        path = bench.path
        assert len(path.durations) == 1, "benchmark scenes are one straight segment (no dwell to freeze)"
        obstacles = [{f.name: (v.tolist() if isinstance(v, np.ndarray) else v)
                      for f in dataclasses.fields(o) for v in [getattr(o, f.name)]} for o in bench.obstacles]
        gains = dataclasses.asdict(bench.gains)
        assert not gains.pop("obstacle_v_ref")
        frozen = {"type": "bench", "robot": bench.robot.name, "q0": bench.q0.tolist(), "dt": bench.dt,
                  "duration": bench.duration, "gains": gains, "controller_cfg": dict(bench.controller_cfg),
                  "obstacles": obstacles,
                  "path": {"points": path.points.tolist(), "durations": path.durations.tolist(),
                           "start_time": float(path.starts[0]), "dwell": 0.0}}
        return {"make": lambda kind, solver: bench.controller(kind, solver), "q0": bench.q0, "dt": bench.dt,
                "duration": bench.duration, "frozen": frozen}
    raise ValueError(f"unknown case source {spec['source']!r}")


# Added after the recording (issue #16), switched off in a replay: the golden ticks hold the law as
# it was. The drives' torque-rate and acceleration limits (on by default on the Panda), and the QP's
# damping of the self-motion (on by default), and the self-collision barrier (on by default).
LATER_LIMITS_OFF = {"tau_rate_max": float("inf"), "qdd_max": float("inf")}
LATER_COSTS_OFF = {"damping": 0.0, "self_collision": False}


def build_controller(frozen: dict[str, Any], label: str) -> Any:
    """A fresh controller ``label`` (a key of CONTROLLERS) for the scene ``frozen`` (scene_for()'s),
    without the limits and costs added after the recording (LATER_LIMITS_OFF, LATER_COSTS_OFF)."""
    kind, solver = CONTROLLERS[label]
    if frozen["type"] == "scenario":  # the validated scenario, re-read as it was recorded
        from qpctl import Scenario

        data = {**frozen["data"], "robot": {**frozen["data"]["robot"], **LATER_LIMITS_OFF},
                "controller": {**frozen["data"]["controller"], **LATER_COSTS_OFF}}
        return Scenario.from_dict(data, source=frozen["source"]).build_controller(kind, solver)
    if frozen["type"] == "bench":  # as qpctl.bench.scenes.BenchScene.controller() builds it
        from qpctl import LawGains, Obstacle, WaypointPath
        from qpctl.controllers.factory import make_controller
        from qpctl.robot.model import load_robot

        robot = load_robot(frozen["robot"]).with_limits(**LATER_LIMITS_OFF)
        p = frozen["path"]
        path = WaypointPath(p["points"], durations=p["durations"], start_time=p["start_time"], dwell=p["dwell"])
        obstacles = [Obstacle(**o) for o in frozen["obstacles"]]
        cfg = dict(frozen["controller_cfg"], kind=kind, **LATER_COSTS_OFF)
        if solver is not None:
            cfg["solver"] = solver
        return make_controller(cfg, robot, path, obstacles, LawGains(**frozen["gains"]))
    raise ValueError(f"unknown scene type {frozen['type']!r}")


def replay(controller: Any, t: np.ndarray, q: np.ndarray, v: np.ndarray, *, flags: bool = True) -> dict[str, np.ndarray]:
    """``reset()``, then ``step(q[k], v[k], t[k])`` in order; the per-tick outputs as arrays."""
    obstacles = controller.obstacles
    capsule_obstacle = np.array([o.shape == "capsule" for o in obstacles], bool)
    seen: list[Any] = []
    if flags:  # see each tick's TickState (transparently) to count penetrating pairs
        compute = controller.dynamics.compute

        def capture(*args: Any, **kwargs: Any) -> Any:
            state = compute(*args, **kwargs)
            seen.append(state)
            return state

        controller.dynamics.compute = capture
    controller.reset()
    rows: dict[str, list[Any]] = {k: [] for k in OUT_KEYS}
    for k in range(len(t)):
        seen.clear()
        out = controller.step(q[k].copy(), v[k].copy(), float(t[k]))
        rows["tau"].append(np.array(out.tau, float))
        rows["qdd"].append(np.array(out.qdd, float))
        rows["e_null"].append(np.array(out.e_null, float))
        rows["clearance"].append(float(out.clearance))
        rows["status"].append(str(out.info.get("status") or ""))
        rows["fallback"].append(str(out.info.get("fallback") or ""))
        rows["singular"].append(bool(out.singular))
        rows["pairs"].append(int(out.info.get("pairs", -1)))
        if flags:
            assert len(seen) == 1, f"expected one state computation per tick, saw {len(seen)}"
            pairs = seen[0].pairs
            pen = pairs.distance < 0
            rows["n_pen"].append(int(pen.sum()))
            rows["n_pen_capcap"].append(int((pen & capsule_obstacle[pairs.obstacle]).sum()))
        else:
            rows["n_pen"].append(-1)
            rows["n_pen_capcap"].append(-1)
    if flags:
        del controller.dynamics.compute
    return {
        "tau": np.array(rows["tau"]), "qdd": np.array(rows["qdd"]), "e_null": np.array(rows["e_null"]),
        "clearance": np.array(rows["clearance"], float), "status": np.array(rows["status"], dtype="U"),
        "fallback": np.array(rows["fallback"], dtype="U"), "singular": np.array(rows["singular"], bool),
        "pairs": np.array(rows["pairs"], np.int16), "n_pen": np.array(rows["n_pen"], np.int16),
        "n_pen_capcap": np.array(rows["n_pen_capcap"], np.int16),
    }


def _window(clearance: np.ndarray, pen_after: int = PEN_AFTER) -> tuple[np.ndarray, str]:
    """Tick indices of a window (WINDOW states, every STRIDE-th) and why it is there."""
    T = len(clearance)
    pen = np.flatnonzero(clearance < 0)
    if pen.size:
        start = int(pen[0]) - (WINDOW - pen_after) * STRIDE
        why = f"up to {pen_after} states past the first penetration (tick {int(pen[0])})"
    else:
        kmin = int(np.argmin(clearance))
        start, why = kmin - (WINDOW // 2) * STRIDE, f"around the least clearance (tick {kmin})"
    start = max(0, min(start, T - 1 - (WINDOW - 1) * STRIDE))
    return start + STRIDE * np.arange(WINDOW), why


def _counts(values: np.ndarray) -> dict[str, int]:
    keys, counts = np.unique(values, return_counts=True)
    return {str(k) or "-": int(c) for k, c in zip(keys, counts)}


def _git(source: Path, *args: str) -> str:
    return subprocess.run(["git", "-C", str(source), *args], capture_output=True, text=True, check=True).stdout.strip()


def _versions() -> dict[str, str]:
    import importlib.metadata as md

    out = {"python": sys.version.split()[0]}
    for dist in ("numpy", "pin", "python-fcl", "daqp", "proxsuite", "qpsolvers", "example-robot-data"):
        try:
            out[dist] = md.version(dist)
        except md.PackageNotFoundError:
            out[dist] = "?"
    return out


def record_case(name: str, spec: dict[str, Any], source_info: dict[str, Any]) -> dict[str, np.ndarray]:
    from qpctl.simulation.simulator import Simulator

    scene = scene_for(spec)
    frozen = json.loads(json.dumps(scene["frozen"]))  # exactly what the file will hold
    arrays: dict[str, np.ndarray] = {}
    sequences: dict[str, dict[str, Any]] = {}
    for run_label, (kind, solver) in RUNS.items():
        t0 = time.perf_counter()
        ctrl = scene["make"](kind, solver)
        traj = Simulator(ctrl, dt=scene["dt"], duration=scene["duration"]).run(scene["q0"])
        pen = int((traj.clearance < 0).sum())
        print(f"  run {run_label:8s} {len(traj.t)} ticks in {time.perf_counter() - t0:.1f} s; least clearance "
              f"{traj.clearance.min():+.4f} m, {pen} penetrating ticks", flush=True)
        picks = []
        if run_label == "qp-daqp":
            picks.append(("start", np.arange(START_TICKS), "the first ticks, consecutive"))
        idx, why = _window(traj.clearance, PEN_AFTER_CASE.get(name, PEN_AFTER))
        picks.append(("window", idx, why))
        for part, ticks, why in picks:
            seq = f"{run_label}:{part}"
            sequences[seq] = {"run": run_label, "ticks": [int(ticks[0]), int(ticks[-1])], "n": len(ticks),
                              "stride": int(ticks[1] - ticks[0]), "why": why,
                              "run_ticks": len(traj.t), "run_penetrating_ticks": pen}
            arrays[f"{seq}/tick"] = ticks.astype(np.int32)
            arrays[f"{seq}/t"], arrays[f"{seq}/q"], arrays[f"{seq}/v"] = traj.t[ticks], traj.q[ticks], traj.v[ticks]
    repeat: dict[str, float] = {}
    for seq in sequences:
        t, q, v = arrays[f"{seq}/t"], arrays[f"{seq}/q"], arrays[f"{seq}/v"]
        outs: dict[str, dict[str, np.ndarray]] = {}
        for label, (kind, solver) in CONTROLLERS.items():
            t0 = time.perf_counter()
            out = replay(build_controller(frozen, label), t, q, v)
            # More replays (without the penetration counting), the first with the controller built
            # from the case's source rather than from its frozen definition: the replay must repeat
            # itself well inside the test's 1e-8 (proxsuite's torques vary by up to ~1.4e-10 relative
            # from one replay to the next; the others repeat bit for bit).
            rel = 0.0
            for r in range(REPEATS):
                again = replay(scene["make"](kind, solver) if r == 0 else build_controller(frozen, label),
                               t, q, v, flags=False)
                rel = max(rel, float(np.max(np.linalg.norm(out["tau"] - again["tau"], axis=1)
                                            / np.maximum(np.linalg.norm(out["tau"], axis=1), 1.0))))
            assert rel <= 1e-9, f"{name} {seq} {label}: replays differ by {rel:.2e} relative"
            repeat[f"{seq} {label}"] = rel
            outs[label] = out
            npen = int((out["clearance"] < 0).sum())
            print(f"  {seq:16s} {label:9s} {len(t):4d} ticks {1e3 * (time.perf_counter() - t0) / ((1 + REPEATS) * len(t)):.2f} "
                  f"ms/tick; penetrating {npen} (capsule-capsule {int((out['n_pen_capcap'] > 0).sum())}); "
                  f"statuses {_counts(out['status'])}; "
                  f"fallbacks {int((out['fallback'] != '').sum())}; replay-to-replay {rel:.1e}", flush=True)
        # one array per quantity, controllers stacked along axis 0 (in CONTROLLERS' order): what the
        # controllers share (e_null of the weighted laws, clearance, pair counts) then compresses away
        for key in OUT_KEYS:
            arrays[f"{seq}/{key}"] = np.stack([outs[label][key] for label in CONTROLLERS])
    meta = {"case": name, "spec": spec, "scene": frozen, "controllers": {k: list(v) for k, v in CONTROLLERS.items()},
            "sequences": sequences, "repeat_rel": repeat, "dt": scene["dt"], "duration": scene["duration"], **source_info}
    arrays["meta"] = np.array(json.dumps(meta))
    return arrays


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--source", type=Path, default=Path.cwd(),
                    help="the checkout to record from; qpctl, baselines and benchmarks must import from it")
    ap.add_argument("--expect-commit", default=None, help="fail unless the source's HEAD starts with this")
    ap.add_argument("--out", type=Path, default=HERE, help="folder for the <case>.npz files (default: beside this)")
    ap.add_argument("--case", action="append", choices=sorted(CASES), help="record only these (repeatable)")
    args = ap.parse_args(argv)

    import baselines
    import benchmarks
    import qpctl

    source = args.source.resolve()
    for mod in (qpctl, baselines, benchmarks):
        where = Path(mod.__file__).resolve()
        print(f"{mod.__name__}.__file__ = {where}")
        assert where.is_relative_to(source), f"{mod.__name__} imports from {where}, not from {source}"
    commit = _git(source, "rev-parse", "HEAD")
    dirty = _git(source, "status", "--porcelain", "--", "qpctl", "baselines", "benchmarks")
    print(f"recording from {source} at commit {commit}")
    assert not dirty, f"the source checkout has changes:\n{dirty}"
    if args.expect_commit:
        assert commit.startswith(args.expect_commit), f"HEAD {commit} is not {args.expect_commit}"
    info = {"commit": commit, "source": str(source), "versions": _versions(),
            "recorded": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    args.out.mkdir(parents=True, exist_ok=True)
    for name in args.case or list(CASES):
        print(f"case {name}", flush=True)
        arrays = record_case(name, CASES[name], info)
        path = args.out / f"{name}.npz"
        np.savez_compressed(path, **arrays)
        print(f"  wrote {path} ({path.stat().st_size / 1024:.0f} KiB)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
