"""The mobile harvester's (or the dual-arm Baxter's) QP tick against the single-arm Panda's,
interleaved in one process.

    python -m benchmarks.mobile_tick [--ticks 3000] [--case mobile|dual]

Runs examples/mobile_harvester.toml (10 joints: x–y–θ cart + Panda, 8 capsules, 9 obstacles) — or,
with ``--case dual``, examples/baxter_two_fruits.toml (14 joints, two task frames: 6 task rows, 14
capsules, 4 obstacles) — and panda_canopy (the Panda alone, 7 capsules, 6 obstacles) once each under
the QP to record their closed-loop states, then replays both controllers' ``torque(q, v, t)`` on those states in blocks of 25
ticks, alternating which goes first, and prints the medians [µs], the 99th percentiles and the ratio
(the load of the machine moves both alike). Results are printed as JSON.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from qpctl import Scenario
from qpctl.run import simulate

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--ticks", type=int, default=3000, help="states replayed per controller")
    ap.add_argument("--case", choices=("mobile", "dual"), default="mobile",
                    help="mobile_harvester (default) or baxter_two_fruits against panda_canopy")
    args = ap.parse_args(argv)
    other = "mobile_harvester" if args.case == "mobile" else "baxter_two_fruits"
    cases = {other: Scenario.load(EXAMPLES / f"{other}.toml"),
             "panda_canopy": Scenario.load("panda_canopy", ["controller.kind=qp"])}
    states, ctrls = {}, {}
    for name, sc in cases.items():
        traj = simulate(sc, progress=False).trajectory
        idx = np.linspace(0, len(traj.t) - 1, args.ticks).astype(int)
        states[name] = (traj.t[idx], traj.q[idx], traj.v[idx])
        ctrls[name] = sc.build_controller()
        ctrls[name].warmup()
    times: dict[str, list[float]] = {n: [] for n in cases}
    names = list(cases)
    for b, start in enumerate(range(0, args.ticks, 25)):
        for name in names[b % 2:] + names[:b % 2]:
            t, q, v = states[name]
            c = ctrls[name]
            if start == 0:
                c.reset()
            for k in range(start, min(start + 25, args.ticks)):
                s = time.perf_counter()
                c.torque(q[k], v[k], t[k])
                times[name].append((time.perf_counter() - s) * 1e6)
    med = {n: float(np.median(v)) for n, v in times.items()}
    p99 = {n: float(np.percentile(v, 99)) for n, v in times.items()}
    print(json.dumps({"median_us": med, "p99_us": p99, f"ratio_{args.case}_to_panda": med[other] / med["panda_canopy"]}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
