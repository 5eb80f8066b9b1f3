"""Stop before contact on a fresh seeded set of scenes (issue 22's Targets; ``make soak-brake``): the
soak's generators (``tests/test_soak.py``) on a stream of their own (seed [SEED, 22]), every planar
scene given a torque-rate limit of 1–5 kN·m/s (the heavy planar arm: τ_max 500–1500 N·m), the Panda
with Franka's limits; static and moving obstacles as the generator draws them. Each scene runs behind
the verified backup (``controller.backup = true``, every tick checked) with the oracle on every 10th
visited state (:func:`test_soak_brake.guarded_run`).

    python -m benchmarks.soak_brake --scenes 200 --jobs 2 --out results/soak

writes ``summary_brake.json`` (the summary of :func:`test_soak_brake.summarise` and one row per
scene) after every finished scene, so a run cut short still reports the scenes it finished.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import sys
import time
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import test_soak as soak  # the soak's generator is the scenes' definition
import test_soak_brake as brake

STREAM = 22  # issue 22's scenes: a stream of their own


def rate_limited(raw: dict[str, Any], k: int) -> None:
    """Every planar scene with a torque-rate limit of 1–5 kN·m/s (its own draw per scene)."""
    if raw["robot"]["kind"] == "planar3":
        raw["robot"]["tau_rate_max"] = float(np.random.default_rng([soak.SEED, STREAM, k]).uniform(1000.0, 5000.0))


def fresh_scenes(count: int) -> Iterator[dict[str, Any]]:
    drawn = soak.valid_scenes(np.random.default_rng([soak.SEED, STREAM]), Counter(), rate_limited)
    for _ in range(count):
        yield next(drawn)[2]


def _run(raw: dict[str, Any], oracle_every: int = brake.ORACLE_EVERY) -> dict[str, Any]:
    try:
        return brake.guarded_run(raw, oracle_every)
    except Exception as exc:  # noqa: BLE001 — reported with the scene, the run goes on
        return {"name": raw["name"], "error": f"{type(exc).__name__}: {exc}"}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=200)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--oracle-every", type=int, default=brake.ORACLE_EVERY, help="0: no oracle")
    ap.add_argument("--out", type=Path, default=soak.OUT)
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    rows: list[dict[str, Any]] = []
    errors: list[dict[str, Any]] = []
    start = time.time()
    with mp.get_context("spawn").Pool(args.jobs) as pool:
        for row in pool.imap(_run, fresh_scenes(args.scenes), chunksize=1):
            (errors if "error" in row else rows).append(row)
            summary = {"seed": [soak.SEED, STREAM], "scenes_requested": args.scenes, "elapsed_s": time.time() - start,
                       "jobs": args.jobs, "errors": errors, **brake.summarise(rows)}
            (args.out / "summary_brake.json").write_text(
                json.dumps({"summary": summary, "runs": brake.public(rows)}, indent=1, default=float) + "\n")
            print(row["name"], {k: row.get(k) for k in ("min_clearance", "backup_ticks", "unverified",
                                                        "oracle_uncertified", "wall_s", "error")}, flush=True)
    print(json.dumps(summary, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
