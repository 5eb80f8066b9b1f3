"""Built-in, MuJoCo, PyBullet and Drake side by side: the same controller, scenario and step in each.

    python -m benchmarks.simulators [--out results/simulators] [--quick]

For each case (scenario, law) it runs the built-in simulator (RK4 and semi-implicit Euler), MuJoCo
(RK4), PyBullet (its own semi-implicit Euler) and Drake (a continuous plant under its fixed-step
semi-explicit Euler) through :func:`qpctl.run.simulate`, and reports per
simulator: the largest |Δq| [rad] and |Δx| [m] over the run against the built-in RK4 run and against
the built-in run with the simulator's own integrator, the closed-loop outcome (min clearance [m],
max and rms tracking error [m], collided), and the simulator's own cost per tick [µs]: read the
state, apply a torque, step — timed by replaying the run's recorded torques open-loop, so the
controller's time is not in it. Writes ``simulators.md`` (the table of docs/simulators.md) and ``simulators.json``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from qpctl import Scenario
from qpctl.adapters import simulator_class
from qpctl.run import simulate

CASES = [("paper", "qp"), ("paper", "paper"), ("panda_canopy", "qp"), ("panda_canopy", "hsu")]
SIMS = [("builtin", "rk4"), ("builtin", "euler"), ("mujoco", "rk4"), ("pybullet", "euler"), ("drake", "euler")]


def step_cost_us(which: str, integrator: str, scenario: Scenario, kind: str, tau: np.ndarray, q0: np.ndarray) -> float:
    """Median over 3 passes of the per-tick time [µs] of read + apply + step, replaying ``tau``."""
    sc = Scenario.from_dict(scenario.data, source=scenario.source, overrides=[f"sim.integrator={integrator}"])
    controller = sc.build_controller(kind)
    cls = simulator_class(which)
    sim = cls.from_scenario(controller, sc)
    passes = []
    for _ in range(3):
        sim.reset(q0)
        start = time.perf_counter()
        for k in range(len(tau) - 1):
            sim.read()
            sim.apply(tau[k])
            sim.step(k * sim.dt)
        passes.append((time.perf_counter() - start) / (len(tau) - 1) * 1e6)
    return float(np.median(passes))


def run(quick: bool = False) -> list[dict]:
    rows = []
    for name, kind in CASES:
        overrides = ["sim.duration=1.0"] if quick else []
        runs = {}
        for which, integrator in SIMS:
            scenario = Scenario.load(name, overrides + [f"sim.integrator={integrator}"])
            result = simulate(scenario, kind=kind, simulator=which)
            runs[which, integrator] = (scenario, result)
        ref = runs["builtin", "rk4"][1].trajectory
        for (which, integrator), (scenario, result) in runs.items():
            traj, m = result.trajectory, result.metrics
            same = runs["builtin", integrator][1].trajectory
            rows.append({
                "scenario": name, "controller": kind, "simulator": which, "integrator": integrator,
                "duration_s": float(traj.t[-1]),
                "dq_vs_rk4": float(np.max(np.abs(traj.q - ref.q))),
                "dx_vs_rk4": float(np.max(np.abs(traj.x - ref.x))),
                "dq_vs_same_integrator": float(np.max(np.abs(traj.q - same.q))),
                "min_clearance": m["min_clearance"], "d_safe": float(scenario.data["controller"]["d_safe"]),
                "max_tracking_error": m["max_tracking_error"], "rms_tracking_error": m["rms_tracking_error"],
                "collided": m["collided"],
                "step_us": step_cost_us(which, integrator, scenario, kind, traj.tau, traj.q[0]),
                "notes": m.get("simulator_notes", []),
            })
    return rows


def markdown(rows: list[dict]) -> str:
    lines = [("| scenario, law | simulator (integrator) | max \\|Δq\\| vs built-in RK4 [rad] | max \\|Δx\\| vs "
              "built-in RK4 [m] | max \\|Δq\\| vs built-in, same integrator [rad] | min clearance [m] (d_safe) | "
              "max / rms tracking error [mm] | collided | simulator step [µs/tick] |"),
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(
            f"| {r['scenario']}, `{r['controller']}` ({r['duration_s']:g} s) | {r['simulator']} ({r['integrator']}) | "
            f"{r['dq_vs_rk4']:.2g} | {r['dx_vs_rk4']:.2g} | {r['dq_vs_same_integrator']:.2g} | "
            f"{r['min_clearance']:+.4f} ({r['d_safe']:g}) | {1e3 * r['max_tracking_error']:.3f} / "
            f"{1e3 * r['rms_tracking_error']:.3f} | {'**yes**' if r['collided'] else 'no'} | {r['step_us']:.1f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="results/simulators")
    parser.add_argument("--quick", action="store_true", help="1 s of each run instead of the scenario's duration")
    args = parser.parse_args(argv)
    rows = run(quick=args.quick)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "simulators.json").write_text(json.dumps(rows, indent=2) + "\n")
    text = markdown(rows)
    (out / "simulators.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
