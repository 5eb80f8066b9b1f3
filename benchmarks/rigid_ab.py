"""The tick with Pinocchio's pass inside the kernel (the native library) against the same controller
with ``rigid_pass`` in Python, side by side in one process.

    python -m benchmarks.rigid_ab [--scenario panda_spheres] [--kind qp] [--ticks 2500] [--passes 3]

Records the scenario's QP (daqp) closed loop, builds the controller twice — with the native pass, and
with the library made unavailable (``qpctl.native.library`` returning None while it is built) — and
steps both through the same states, interleaved in blocks of 25 ticks (the order alternating), with
``pin.computeAllTerms`` (the floor) timed on the same states after each block. Prints one JSON line
per pass: the medians [µs] of each controller's stages (``out.info``) and whole tick
(``compute_us``), the floor, and each tick's ratio to it.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import pinocchio as pin

import qpctl.native
from qpctl import Scenario
from qpctl.run import simulate

BLOCK = 25
STAGES = ("rigid", "state", "build", "solve", "tick")


def _build(scen: Scenario, kind: str, native: bool):  # type: ignore[no-untyped-def]
    keep = qpctl.native.library
    if not native:
        qpctl.native.library = lambda: None  # type: ignore[assignment]
    try:
        c = scen.build_controller(kind, "daqp") if kind == "qp" else scen.build_controller(kind)
        c.warmup()
    finally:
        qpctl.native.library = keep  # type: ignore[assignment]
    ws = c.qp_path().ws if kind == "qp" else c.workspace()
    if ws.py_rigid == native:
        raise RuntimeError(f"the controller's pass is not the one asked for (native={native}): "
                           f"{qpctl.native.why_unavailable()}")
    return c


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenario", default="panda_spheres")
    ap.add_argument("--kind", default="qp", choices=("qp", "paper", "hsu"))
    ap.add_argument("--ticks", type=int, default=2500)
    ap.add_argument("--passes", type=int, default=3)
    args = ap.parse_args()
    scen = Scenario.load(args.scenario)
    traj = simulate(scen, kind="qp", solver="daqp").trajectory
    idx = np.arange(0, len(traj.t), 2)[:args.ticks]
    states = [(np.ascontiguousarray(traj.q[k]), np.ascontiguousarray(traj.v[k]), float(traj.t[k])) for k in idx]
    ctrl = {"native": _build(scen, args.kind, True), "python": _build(scen, args.kind, False)}
    model = ctrl["native"].robot.model
    data = model.createData()
    now = time.perf_counter
    for _ in range(args.passes):
        res = {name: {s: [] for s in STAGES} for name in ctrl}
        floor: list[float] = []
        for b, start in enumerate(range(0, len(states), BLOCK)):
            block = states[start:start + BLOCK]
            for name in (("native", "python") if b % 2 == 0 else ("python", "native")):
                c, r = ctrl[name], res[name]
                for q, v, t in block:
                    out = c.step(q, v, t)
                    info = out.info
                    r["rigid"].append(info["rigid_us"])
                    r["state"].append(info["state_us"] - info["rigid_us"])
                    r["build"].append(info["build_us"])
                    r["solve"].append(info.get("solve_us", 0.0))
                    r["tick"].append(out.compute_us)
            for q, v, _t in block:
                s = now()
                pin.computeAllTerms(model, data, q, v)
                floor.append((now() - s) * 1e6)
        fl = float(np.median(floor))
        line: dict[str, object] = {"floor": round(fl, 2)}
        for name, r in res.items():
            med = {s: round(float(np.median(x)), 2) for s, x in r.items()}
            line[name] = med
            line[f"{name}_ratio"] = round(med["tick"] / fl, 2)
        print(json.dumps(line), flush=True)


if __name__ == "__main__":
    main()
