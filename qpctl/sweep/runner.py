"""One run of a sweep: :class:`~qpctl.sweep.spec.RunParams` in, one result row out.

:func:`execute_run` builds the run's scenario (its family's scene, then the overrides), simulates it
with :func:`qpctl.run.simulate` and returns a flat row (:data:`METRIC_COLUMNS`, the tick-time
percentiles, status and error). A run that raises gives a row with ``status = "failed"`` and the
error's message: a run never takes the sweep down. The row depends on the parameters only, except
the timing columns (:data:`TIMING_COLUMNS`).
"""

from __future__ import annotations

import os
import socket
import time
from typing import Any

import numpy as np

from qpctl.sweep.spec import CLOSED_FORM, RunParams

#: Reached: the task point ends within this distance of the path's last point [m] (as the bench's).
REACH_TOLERANCE = 0.01

#: Per-run metrics [m, N·m, N·m/s, rad/s], from :func:`qpctl.simulation.metrics.compute_metrics`.
METRIC_COLUMNS: dict[str, str] = {
    "success": "bool", "reached": "bool", "collided": "bool", "safety_violated": "bool",
    "min_clearance": "float64", "rms_tracking_error": "float64", "max_tracking_error": "float64",
    "final_tracking_error": "float64", "max_abs_torque": "float64", "max_abs_torque_rate": "float64",
    "final_null_space_error": "float64", "singular_ticks": "int64", "ticks": "int64", "duration_s": "float64",
    "qp_iterations_max": "float64", "qp_slack_max": "float64", "qp_fallbacks": "int64",
}
#: Wall-clock columns: the only ones that differ between two runs of the same parameters.
TIMING_COLUMNS: dict[str, str] = {
    "tick_us_p50": "float64", "tick_us_p90": "float64", "tick_us_p99": "float64", "tick_us_max": "float64",
    "wall_s": "float64", "cpu_s": "float64", "worker": "string", "finished_at": "float64",
}


def build_scenario(params: RunParams) -> Any:
    """The run's validated :class:`~qpctl.scenario.Scenario`."""
    from qpctl.scenario import Scenario
    from qpctl.sweep.families import scene_dict

    name, raw, base = scene_dict(params.kind, seed=params.scene_seed or 0, obstacles=params.obstacles,
                                 duration=params.duration, scenario=params.scenario)
    return Scenario.from_dict(raw, source=f"{params.family}/{name}", overrides=params.override_strings(),
                              base_dir=base)


def scene_name(params: RunParams) -> str:
    if params.kind == "scenario":
        return params.scenario
    return f"{params.kind}-{params.scene_seed}"


def _qp_fallbacks(metrics: dict[str, Any]) -> int | None:
    v = metrics.get("qp_fallbacks")
    if isinstance(v, dict):
        return int(sum(v.values()))
    return None if v is None else int(v)


def execute_run(params: RunParams) -> dict[str, Any]:
    """Simulate one run and return its row (never raises for the run's own errors)."""
    from qpctl.run import simulate

    t0, c0 = time.perf_counter(), time.process_time()
    row: dict[str, Any] = {"status": "ok", "error": ""}
    try:
        scen = build_scenario(params)
        result = simulate(scen, kind=params.controller, solver=None if params.solver == CLOSED_FORM else params.solver)
        m, traj = result.metrics, result.trajectory
        final = float(np.linalg.norm(traj.x_ref[-1] - traj.x[-1])) if traj.t.size else float("inf")
        reached = final <= REACH_TOLERANCE
        row.update({k: m.get(k) for k in METRIC_COLUMNS})
        row.update(reached=reached, success=bool(reached and not m["collided"]), qp_fallbacks=_qp_fallbacks(m))
        tick = np.asarray(traj.tick_us, float)
        row.update(tick_us_p50=float(np.percentile(tick, 50)), tick_us_p90=float(np.percentile(tick, 90)),
                   tick_us_p99=float(np.percentile(tick, 99)), tick_us_max=float(np.max(tick)))
    except Exception as exc:  # noqa: BLE001 — the run failed: recorded with its message, the sweep goes on
        row.update(status="failed", error=f"{type(exc).__name__}: " + " ".join(str(exc).split()))
    row.update(wall_s=time.perf_counter() - t0, cpu_s=time.process_time() - c0, worker=f"{socket.gethostname()}:{os.getpid()}",
               finished_at=time.time())
    return row
