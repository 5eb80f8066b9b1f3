"""The compiled tick's Python shell, measured: what a QP tick costs around its kernel.

    python -m benchmarks.shell [--scenario panda_spheres] [--ticks 2500] [--runs 2]

Records the closed-loop states of the scenario's QP (daqp), then replays every other state through,
interleaved in blocks of 25 ticks (the order rotating from block to block):

* ``floor``: ``pin.computeAllTerms`` alone (the figure ``qpctl bench`` divides by);
* ``qp``, ``paper``: the controllers' whole ``step``;
* ``rigid``: ``qpctl.tick.rigid_pass`` alone (crba and nonLinearEffects through the bindings);
* ``kernel``: the QP's one-call kernel through its compiled entry point alone, on the same workspace:
  what numba's call and the compiled tick cost — Pinocchio's pass included where the kernel runs it
  (the native library, ``qpctl.kernels.pin_native``), else after ``rigid_pass`` outside the timer.

``shell = qp − kernel`` (less ``rigid`` where Python runs the pass) is the Python around the kernel:
the type guard, the skip rule's memory, the output, the timers. Prints one JSON line per run: medians [µs], the shell, and the QP's
and the paper law's ratios to the floor. To compare two commits on the same machine, run it
alternately with ``PYTHONPATH=<a worktree of the other commit>`` (that commit's benchmarks/shell.py
if it has one; its kernel's signature must be this one's).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import pinocchio as pin

from qpctl import Scenario
from qpctl.run import simulate
from qpctl.tick import rigid_pass

BLOCK = 25
NAMES = ("floor", "qp", "paper", "rigid", "kernel")


def measure(scenario: str = "panda_spheres", ticks: int = 2500) -> dict[str, float]:
    """One run: the medians [µs] of :data:`NAMES` over ``ticks`` recorded states, the shell and the
    ratios to the floor."""
    scen = Scenario.load(scenario)
    traj = simulate(scen, kind="qp", solver="daqp").trajectory
    idx = np.arange(0, len(traj.t), 2)[:ticks]
    Q = [np.ascontiguousarray(traj.q[k], dtype=float) for k in idx]
    V = [np.ascontiguousarray(traj.v[k], dtype=float) for k in idx]
    T = [float(traj.t[k]) for k in idx]
    qp, paper = scen.build_controller("qp", "daqp"), scen.build_controller("paper")
    for c in (qp, paper):
        c.warmup()
        for i in range(50):
            c.step(Q[i], V[i], T[i])
        c.reset()
    path = qp.qp_path()
    ws = path.ws
    model, data = qp.robot.model, qp.robot.model.createData()
    entry, ty, addr = path._entry, path._ty, path._addr
    if entry is None:
        raise RuntimeError("the QP's one-call kernel has no entry point here (DAQP's C API missing?)")
    out = np.empty(ws.rec.shape[0])
    relax = path.relax
    now = time.perf_counter
    times: dict[str, list[float]] = {n: [] for n in NAMES}
    for b, start in enumerate(range(0, len(idx), BLOCK)):
        order = NAMES[b % len(NAMES):] + NAMES[:b % len(NAMES)]
        for name in order:
            for i in range(start, min(start + BLOCK, len(idx))):
                q, v, t = Q[i], V[i], T[i]
                if name == "floor":
                    s = now()
                    pin.computeAllTerms(model, data, q, v)
                    e = now()
                elif name == "qp":
                    s = now()
                    qp.step(q, v, t)
                    e = now()
                elif name == "paper":
                    s = now()
                    paper.step(q, v, t)
                    e = now()
                elif name == "rigid":
                    s = now()
                    rigid_pass(ws.model, ws.data, q, v)
                    e = now()
                else:
                    if ws.py_rigid:
                        rigid_pass(ws.model, ws.data, q, v)
                    try_hard = relax.always_hard or (relax.skip_rule and relax._try_hard)
                    s = now()
                    entry(ty, addr, q, v, t, try_hard, out)
                    e = now()
                times[name].append((e - s) * 1e6)
    med = {n: float(np.median(v)) for n, v in times.items()}
    med["shell"] = med["qp"] - med["kernel"] - (med["rigid"] if ws.py_rigid else 0.0)
    med["qp_ratio"] = med["qp"] / med["floor"]
    med["paper_ratio"] = med["paper"] / med["floor"]
    return med


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenario", default="panda_spheres")
    ap.add_argument("--ticks", type=int, default=2500)
    ap.add_argument("--runs", type=int, default=2)
    args = ap.parse_args()
    for _ in range(args.runs):
        print(json.dumps({k: round(v, 3) for k, v in measure(args.scenario, args.ticks).items()}), flush=True)


if __name__ == "__main__":
    main()
