"""The harvesting scenario under every law: each fruit reached, held and left along its approach line?

    python -m benchmarks.harvest [--out results/harvest] [--quick]        (make harvest)

Runs ``panda_harvest`` (the Panda, three fruits each with its own approach direction, a canopy) with
``paper``, ``hsu`` and ``qp`` on two tasks: the scenario's own ``approach`` task (position and the
approach axis, 5 rows: 2 degrees of redundancy left) and a ``pose`` task (the whole orientation
along the same rotations, 6 rows: 1 left). Writes ``harvest.md`` (the table of docs/harvesting.md),
``harvest.json`` and ``harvest.png`` (the approach-axis angle and the clearances over time).

Measured per run, from ``trajectory.npz``'s arrays, at each fruit: the largest position error [mm]
and approach-axis angle [deg] while grasping (the path's zero-length segments) and the largest
distance [mm] of the task point from the approach line over the approach and the retreat (the
segments before and after the grasp); over the run: the least clearance to the canopy and between
the arm's own links [m], and the largest fraction of each drive limit used (|τ|/τ_max, |q̇|/q̇_max,
|τ̇|/τ̇_max, and joint position: > 1 means the limit was exceeded).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from qpctl import Scenario
from qpctl.bench.suites import HARVEST_SCENARIO, harvest_tick_cost
from qpctl.run import simulate

SCENARIO = HARVEST_SCENARIO
LAWS = ("paper", "hsu", "qp")
TARGET_MM, TARGET_DEG, LINE_MM = 5.0, 3.0, 10.0  # issue 11: at the grasp; the approach line
_RUNS: dict[str, Any] = {}


def scenario(task: str) -> Scenario:
    """The packaged scenario with its own approach task, or as a pose task along the same rotations
    (each waypoint's whole orientation, from the approach path's)."""
    from importlib import resources

    import pinocchio as pin
    import tomllib

    base = Scenario.load(SCENARIO)
    if task == "approach":
        return base
    robot = base.build_robot()
    path = base.build_path(robot, base.q0(robot))
    raw = tomllib.loads((resources.files("qpctl") / "scenarios" / f"{SCENARIO}.toml").read_text())
    del raw["path"]["approach"]
    raw["path"]["orientations"] = [pin.Quaternion(R).coeffs().tolist() for R in path.rotations[1:]]  # type: ignore[attr-defined]
    raw["controller"]["task"] = "pose"
    return Scenario.from_dict(raw, source=f"{SCENARIO} (pose task)")


def fruit_legs(path: Any) -> list[tuple[int, int, int]]:
    """(approach, grasp, retreat) segment indices of each fruit: a grasp is a zero-length segment."""
    lengths = np.linalg.norm(np.diff(path.points, axis=0), axis=1)
    return [(k - 1, k, k + 1) for k in range(1, len(lengths) - 1) if lengths[k] == 0.0]


def _line_distance(x: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    u = (b - a) / np.linalg.norm(b - a)
    w = x - a
    return np.linalg.norm(w - np.outer(w @ u, u), axis=1)


def measure(run: Any, scen: Scenario) -> dict[str, Any]:
    """The table's numbers for one run (module docstring)."""
    traj, ctrl = run.trajectory, run.controller
    robot, path = ctrl.robot, ctrl.path
    t = traj.t
    fruits = []
    for a, g, r in fruit_legs(path):
        def window(seg: int) -> np.ndarray:
            return (t >= path.starts[seg]) & (t <= path.starts[seg] + path.durations[seg])

        grasp = window(g)
        pos = np.linalg.norm(traj.x[grasp] - path.points[g], axis=1)
        near = window(a) | window(r)
        line = _line_distance(traj.x[near], path.points[a], path.points[g])
        fruits.append({"position_mm": 1e3 * float(pos.max()), "angle_deg": float(traj.orientation_error_deg[grasp].max()),
                       "line_mm": 1e3 * float(line.max())})
    dt = float(np.median(np.diff(t)))
    rate = np.abs(np.diff(traj.tau, axis=0)) / dt
    limits = {
        "torque": float(np.max(np.abs(traj.tau) / robot.tau_max)),
        "speed": float(np.max(np.abs(traj.v) / robot.v_max)),
        "torque_rate": float(np.max(rate / robot.tau_rate_max)),
        "position": float(np.max(np.maximum((traj.q - robot.q_max) / (robot.q_max - robot.q_min),
                                            (robot.q_min - traj.q) / (robot.q_max - robot.q_min))) + 1.0),
    }
    m = run.metrics
    g = ctrl.gains
    self_ds = float(scen.data["controller"]["self_d_safe"])
    out = {"fruits": fruits, "min_clearance": m["min_clearance"], "min_self_clearance": m.get("min_self_clearance"),
           "limits": limits, "tick_us_median": m["tick_us_median"], "fallbacks": sum(m.get("qp_fallbacks", {}).values()),
           "max_tracking_error_mm": 1e3 * m["max_tracking_error"]}
    out["targets_met"] = bool(
        all(f["position_mm"] <= TARGET_MM and f["angle_deg"] <= TARGET_DEG and f["line_mm"] <= LINE_MM for f in fruits)
        and m["min_clearance"] >= g.d_safe - 1e-3 and (out["min_self_clearance"] or np.inf) >= self_ds - 1e-3
        and limits["torque"] <= 1 + 1e-9 and limits["speed"] <= 1 + 1e-9 and limits["position"] <= 1 + 1e-9
        and limits["torque_rate"] <= 1 + 1e-6)
    out["_series"] = {"t": t, "angle": traj.orientation_error_deg, "clearance": traj.clearance,
                      "self_clearance": traj.self_clearance}
    return out


def table(results: dict[str, dict[str, Any]]) -> str:
    head = ("| task (redundancy) | law | fruit 1, 2, 3 at the grasp: position [mm] / axis angle [°] | off the approach "
            "line [mm] | min clearance [m] | min self clearance [m] | max \\|τ\\|, \\|q̇\\|, \\|τ̇\\| / limit | joint limits | "
            "tick median [µs] | targets |\n|---|---|---|---|---|---|---|---|---|---|")
    rows = [head]
    for key, r in results.items():
        task, law = key.split("/")
        red = "approach (2)" if task == "approach" else "pose (1)"
        grasp = ", ".join(f"{f['position_mm']:.2f} / {f['angle_deg']:.2f}" for f in r["fruits"])
        line = ", ".join(f"{f['line_mm']:.2f}" for f in r["fruits"])
        lim = r["limits"]
        joint = "held" if lim["position"] <= 1 + 1e-9 else f"exceeded ({lim['position']:.2f})"
        rows.append(f"| {red} | {law} | {grasp} | {line} | {r['min_clearance']:+.4f} | {r['min_self_clearance']:+.4f} | "
                    f"{lim['torque']:.2f}, {lim['speed']:.2f}, {lim['torque_rate']:.2f} | {joint} | "
                    f"{r['tick_us_median']:.0f} | {'met' if r['targets_met'] else 'missed'} |")
    return "\n".join(rows) + "\n"


def figure(results: dict[str, dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 1, figsize=(9, 8), sharex=True)
    for key, r in results.items():
        if not key.startswith("approach/"):
            continue
        s, law = r["_series"], key.split("/")[1]
        axes[0].plot(s["t"], s["angle"], label=law)
        axes[1].plot(s["t"], s["clearance"], label=law)
        axes[2].plot(s["t"], s["self_clearance"], label=law)
    axes[0].set_ylabel("approach axis\nangle error [°]")
    axes[0].set_yscale("log")
    axes[1].set_ylabel("clearance to\nthe canopy [m]")
    axes[2].set_ylabel("clearance between\nthe links [m]")
    for ax, level in ((axes[1], 0.03), (axes[2], 0.02)):
        ax.axhline(level, color="k", lw=0.8, ls="--", label="d_safe")
        ax.axhline(0.0, color="r", lw=0.8)
        ax.set_ylim(-0.06, 0.25)
    axes[2].set_xlabel("t [s]")
    axes[0].legend(loc="upper right")
    axes[1].legend(loc="upper right")
    fig.suptitle("panda_harvest, approach task: three fruits, each along its own line")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="results/harvest", help="output folder")
    ap.add_argument("--quick", action="store_true", help="the approach task only")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    tasks = ("approach",) if args.quick else ("approach", "pose")
    results: dict[str, dict[str, Any]] = {}
    from tqdm import tqdm

    runs = [(task, law) for task in tasks for law in LAWS]
    for task, law in tqdm(runs, desc="harvest", unit="run"):
        scen = scenario(task)
        _RUNS[f"{task}/{law}"] = run = simulate(scen, kind=law)
        results[f"{task}/{law}"] = measure(run, scen)
    cost = harvest_tick_cost(_RUNS["approach/qp"])
    md = table(results) + (
        f"\nThe tick of the QP with the 5-row approach task and the self-collision rows, against the same QP with the "
        f"position task alone, on the same {cost['ticks']} recorded states (interleaved): median "
        f"{cost['approach_us']:.1f} µs against {cost['position_us']:.1f} µs, {100 * (cost['ratio'] - 1):+.0f} %.\n")
    (out / "harvest.md").write_text(md)
    summary = {k: {kk: vv for kk, vv in v.items() if kk != "_series"} for k, v in results.items()}
    summary["tick_cost"] = cost  # type: ignore[assignment]
    (out / "harvest.json").write_text(json.dumps(summary, indent=2))
    figure(results, out / "harvest.png")
    sys.stdout.write(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
