"""``qpctl sweep``: expand a spec, skip the runs already in the folder, run the rest, store each row.

The driver writes every finished run's row at once (:class:`~qpctl.sweep.store.RunStore`), so an
interrupted sweep resumes where it stopped when the same command is run again.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from qpctl.sweep.engine import Outcome, execute
from qpctl.sweep.runner import execute_run
from qpctl.sweep.spec import SweepSpec
from qpctl.sweep.store import RunStore


@dataclass(frozen=True)
class SweepReport:
    """What one ``qpctl sweep`` did: runs planned, skipped (already done), run now, failed among them."""

    out: Path
    total: int
    skipped: int
    ran: int
    failed: int
    wall_s: float
    backend: str
    workers: int

    def line(self) -> str:
        rate = 60.0 * self.ran / self.wall_s if self.wall_s > 0 and self.ran else 0.0
        return (f"{self.ran} runs in {self.wall_s:.1f} s ({rate:.0f} runs/min, {self.backend} backend, "
                f"{self.workers} workers), {self.failed} failed, {self.skipped} already done; "
                f"{self.total} in the sweep -> {self.out}")


def run_sweep(spec: SweepSpec | str | Path, out: str | Path, *, backend: str = "local", jobs: int | None = None,
              address: str | None = None, progress: bool = True, limit: int | None = None) -> SweepReport:
    """Run every run of ``spec`` not yet in ``out`` (at most ``limit`` of them) through ``backend``."""
    from qpctl.sweep.backends import make_backend

    spec = spec if isinstance(spec, SweepSpec) else SweepSpec.load(spec)
    out = Path(out)
    runs = spec.runs()
    store = RunStore(out, spec)
    store.open(len(runs))
    done = store.done_ids()
    pending = [p for p in runs if p.run_id not in done]
    todo = pending if limit is None else pending[: max(limit, 0)]
    t0 = time.perf_counter()
    engine = make_backend(backend, jobs=jobs, address=address) if todo else None
    failed = 0
    try:
        if engine is not None:
            def row_failed(o: Outcome) -> bool:
                return o.ok and o.value.get("status") != "ok"

            for outcome in execute(execute_run, [(p,) for p in todo], engine, progress=progress,
                                   desc=f"sweep {spec.name}", failed=row_failed):
                params = todo[outcome.index]
                if outcome.ok:
                    result = outcome.value
                else:  # the worker died under it: recorded as failed like a run that raised
                    result = {"status": "failed", "error": outcome.message}
                failed += result.get("status") != "ok"
                store.write(store.row(params, result))
    finally:
        if engine is not None:
            engine.close()
    if len(todo) == len(pending):
        store.compact()  # every run is done: its one-row files (10^5 of them, maybe) become one part file
    return SweepReport(out, len(runs), len(runs) - len(pending), len(todo), failed, time.perf_counter() - t0,
                       engine.name if engine else backend, engine.workers if engine else 0)
