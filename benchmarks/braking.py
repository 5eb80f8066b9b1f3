"""Braking-aware rows (issue 22) on the soak's scenes that start at rest among static obstacles with a
torque-rate limit: collisions, worst clearance and median RMS tracking per setting.

    python -m benchmarks.braking --modes off,0.5,0.5r1.5 --scenes 12

A mode is ``off`` (``controller.braking = "off"``) or ``SHARE[rREACH]`` (braking on with that
``braking_share`` and, if given, ``braking_reach`` [m]). Scenes come from the soak's own generator
(``tests/test_soak.py``: its seed, its validation, each scene's solver and fallback chain), in draw
order, the first ``--scenes`` with a torque-rate limit and no moving obstacle. Prints one line per
scene and a summary per mode; ``--out`` writes them as JSON too.
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


def controller_table(raw: dict[str, Any], mode: str) -> dict[str, Any]:
    c = dict(raw["controller"])
    if mode == "off":
        c["braking"] = "off"
        return c
    share, _, reach = mode.partition("r")
    c.update(braking="on", braking_share=float(share))
    if reach:
        c["braking_reach"] = float(reach)
    return c


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--modes", default="off,0.5")
    ap.add_argument("--scenes", type=int, default=12)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    modes = args.modes.split(",")
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
        for m in modes:
            tr = simulate(Scenario.from_dict({**raw, "controller": controller_table(raw, m)},
                                             source=raw["name"])).trajectory
            rms = float(np.sqrt(np.mean(np.sum((tr.x - tr.x_ref) ** 2, axis=1))))
            rows[m].append({"scene": raw["name"], "min_clearance": float(tr.clearance.min()), "rms_tracking": rms})
        print(raw["name"], [(m, round(rows[m][-1]["min_clearance"], 4)) for m in modes], flush=True)
    summary = {}
    for m in modes:
        cl = np.array([r["min_clearance"] for r in rows[m]])
        summary[m] = {"scenes": int(cl.size), "collide": int(np.sum(cl < 0)), "worst_clearance": float(cl.min()),
                      "median_rms_tracking": float(np.median([r["rms_tracking"] for r in rows[m]]))}
        print(m, summary[m])
    print(f"{time.time() - t0:.0f} s")
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "braking.json").write_text(json.dumps({"summary": summary, "runs": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
