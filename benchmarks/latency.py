"""Start-up costs of the compiled tick: import time and first-tick latency, cold and warm cache.

    python -m benchmarks.latency [--scenario panda_spheres] [--runs 3]

Each measurement is a fresh interpreter (``sys.executable``) with ``NUMBA_CACHE_DIR`` pointing at a
folder of its own: the first run in that folder compiles every kernel (a cold cache, as on a fresh
install before ``qpctl warmup``), the later ones load them from it (a warm cache). The package's own
cache (``qpctl/kernels/__pycache__``) is neither read nor written. Per run it reports, in seconds:
``import qpctl``, building the controllers, the first ``step`` of the paper law and of the QP (which
compiles or loads the kernels, and sets DAQP up), and the median of the next 200 ticks [µs].
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from typing import Any

CHILD = r"""
import json, sys, time
t0 = time.perf_counter()
import qpctl
t1 = time.perf_counter()
import numpy as np
scenario = qpctl.Scenario.load(sys.argv[1])
paper, qp = scenario.build_controller("paper"), scenario.build_controller("qp")
q0 = scenario.q0(paper.robot).astype(float)
v0 = np.zeros(paper.n)
t2 = time.perf_counter()
paper.step(q0, v0, 0.0)
t3 = time.perf_counter()
qp.step(q0, v0, 0.0)
t4 = time.perf_counter()
ticks = {}
for name, c in (("paper", paper), ("qp", qp)):
    us = []
    for k in range(1, 201):
        s = time.perf_counter(); c.step(q0, v0, k * 1e-3); us.append((time.perf_counter() - s) * 1e6)
    ticks[name] = float(np.median(us))
print(json.dumps({"import_s": t1 - t0, "build_s": t2 - t1, "first_paper_tick_s": t3 - t2,
                  "first_qp_tick_s": t4 - t3, "tick_us_median": ticks}))
"""


def measure(scenario: str = "panda_spheres", runs: int = 3) -> dict[str, Any]:
    """One cold run, then ``runs − 1`` warm ones, each in a fresh interpreter."""
    with tempfile.TemporaryDirectory(prefix="qpctl-numba-cache-") as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache}
        out = []
        for _ in range(runs):
            proc = subprocess.run([sys.executable, "-c", CHILD, scenario], env=env, capture_output=True, text=True,
                                  check=True, timeout=600)
            out.append(json.loads(proc.stdout.strip().splitlines()[-1]))
    return {"scenario": scenario, "cold": out[0], "warm": out[1:]}


def markdown(res: dict[str, Any]) -> str:
    rows = [("cold cache (compiles)", res["cold"])] + [(f"warm cache, run {i + 1}", r) for i, r in enumerate(res["warm"])]
    lines = [f"Scenario `{res['scenario']}`, each row a fresh interpreter (`python -m benchmarks.latency`):", "",
             ("| run | `import qpctl` [s] | build controllers [s] | first `paper` tick [s] | first `qp` tick [s] "
             "| then `paper` / `qp` median [µs] |"), "|---|---|---|---|---|---|"]
    for name, r in rows:
        lines.append(f"| {name} | {r['import_s']:.2f} | {r['build_s']:.2f} | {r['first_paper_tick_s']:.2f} | "
                     f"{r['first_qp_tick_s']:.2f} | {r['tick_us_median']['paper']:.1f} / {r['tick_us_median']['qp']:.1f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="panda_spheres")
    ap.add_argument("--runs", type=int, default=3, help="one cold run, then runs − 1 warm ones")
    args = ap.parse_args(argv)
    print(markdown(measure(args.scenario, max(args.runs, 2))))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
