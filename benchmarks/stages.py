"""The QP's and the paper law's ticks stage by stage, with the floor, on the same recorded states.

    python -m benchmarks.stages [--scenario panda_spheres] [--passes 3]

Records the scenario's QP (daqp) closed loop, then steps the floor (``pin.computeAllTerms``), the QP
and the paper law through every other state, interleaved in blocks of 25 ticks, ``--passes`` times.
Prints one JSON line: the medians [µs] of each controller's tick (``compute_us``) and stages
(``out.info``: rigid, state, build, solve), the floor, and the ticks' ratios to it. To compare two
commits on this machine, run it alternately with ``PYTHONPATH=<a worktree of the other commit>``
(the stages come from ``out.info``, which every commit since the stage timers has).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import pinocchio as pin

from qpctl import Scenario
from qpctl.run import simulate

BLOCK = 25


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenario", default="panda_spheres")
    ap.add_argument("--passes", type=int, default=3)
    args = ap.parse_args()
    scen = Scenario.load(args.scenario)
    traj = simulate(scen, kind="qp", solver="daqp").trajectory
    states = [(np.ascontiguousarray(traj.q[k]), np.ascontiguousarray(traj.v[k]), float(traj.t[k]))
              for k in range(0, min(5000, len(traj.t)), 2)]
    qp, paper = scen.build_controller("qp", "daqp"), scen.build_controller("paper")
    for c in (qp, paper):
        c.warmup()
    model = qp.robot.model
    data = model.createData()
    res: dict[str, list[float]] = {k: [] for k in ("floor", "qp", "qp_rigid", "qp_state", "qp_build", "qp_solve",
                                                  "paper", "paper_rigid", "paper_state", "paper_build")}
    now = time.perf_counter
    for _ in range(args.passes):
        for start in range(0, len(states), BLOCK):
            block = states[start:start + BLOCK]
            for q, v, _t in block:
                s = now()
                pin.computeAllTerms(model, data, q, v)
                res["floor"].append((now() - s) * 1e6)
            for name, c in (("qp", qp), ("paper", paper)):
                for q, v, t in block:
                    out = c.step(q, v, t)
                    info = out.info
                    res[name].append(out.compute_us)
                    res[f"{name}_rigid"].append(info["rigid_us"])
                    res[f"{name}_state"].append(info["state_us"] - info["rigid_us"])
                    res[f"{name}_build"].append(info["build_us"])
                    if name == "qp":
                        res["qp_solve"].append(info["solve_us"])
    med = {k: round(float(np.median(v)), 3) for k, v in res.items()}
    med["qp_ratio"] = round(med["qp"] / med["floor"], 3)
    med["paper_ratio"] = round(med["paper"] / med["floor"], 3)
    print(json.dumps(med), flush=True)


if __name__ == "__main__":
    main()
