"""The benchmark suites: closed-loop quality, same-tick timing, and scaling with the scene.

* :func:`closed_loop` — one controller on one scene in the built-in simulator (RK4, the scene's dt):
  success (reached the target, no collision), tracking error, peak torque and torque rate, least
  clearance, compute time per tick by stage.
* :func:`same_ticks` — every controller, and the floor (``pin.computeAllTerms`` alone), timed on the
  states of one closed-loop run (:mod:`qpctl.bench.timing`).
* :func:`scaling` — the canopy scene tiled to more obstacles (the uniform-grid broad phase on), timed
  on the same states.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from qpctl.bench.scenes import BenchScene, orchard_scene
from qpctl.bench.timing import (
    FLOOR,
    STAGES,
    PinocchioFloor,
    StateSequence,
    Steppable,
    TickTimes,
    time_on_states,
)
from qpctl.errors import QpctlError
from qpctl.scenario import Scenario
from qpctl.simulation.metrics import compute_metrics
from qpctl.simulation.simulator import Simulator

#: Reached: the task point ends within this distance of the path's last point [m].
REACH_TOLERANCE = 0.01


@dataclass(frozen=True)
class ControllerSpec:
    """A controller to benchmark: ``kind`` (paper, hsu, qp) and, for the QP, its solver."""

    kind: str
    solver: str | None = None

    @property
    def label(self) -> str:
        return self.kind if self.solver is None else f"{self.kind}-{self.solver}"


def controller_specs(solvers: Sequence[str]) -> list[ControllerSpec]:
    """The two closed forms, then the QP with each solver."""
    return [ControllerSpec("paper"), ControllerSpec("hsu")] + [ControllerSpec("qp", s) for s in solvers]


@dataclass
class ClosedLoop:
    """One closed-loop run: its metrics, and its states for the same-tick suites (None if it failed)."""

    scene: str
    controller: str
    metrics: dict[str, Any]
    states: StateSequence | None


def _stage_medians(infos: list[dict[str, Any]]) -> dict[str, float]:
    out = {}
    for stage in STAGES:
        vals = [float(i[stage]) for i in infos if stage in i]
        if vals:
            out[f"{stage[:-3]}_us_median"] = float(np.median(vals))
    return out


def closed_loop(scene: BenchScene, spec: ControllerSpec, *, max_ticks: int | None = None) -> ClosedLoop:
    """Run ``spec`` on ``scene`` (at most ``max_ticks`` ticks) and measure it."""
    duration = scene.duration if max_ticks is None else min(scene.duration, (max_ticks - 1) * scene.dt)
    controller = scene.controller(spec.kind, spec.solver)
    try:
        controller.warmup()  # as before a control loop: the first tick's workspace and compiled code ready
        traj = Simulator(controller, dt=scene.dt, duration=duration).run(scene.q0)
    except QpctlError as exc:  # diverged, or a controller error: a failed run, reported as such
        return ClosedLoop(scene.name, spec.label, {"success": False, "reached": False, "collided": None,
                                                   "error": f"{type(exc).__name__}: {exc}"}, None)
    m = compute_metrics(traj, d_safe=scene.gains.d_safe)
    final_to_target = float(np.linalg.norm(traj.x[-1] - scene.target))
    reached = final_to_target <= REACH_TOLERANCE
    metrics: dict[str, Any] = {
        "success": bool(reached and not m["collided"]),
        "reached": bool(reached),
        "collided": m["collided"],
        "final_distance_to_target": final_to_target,
        "rms_tracking_error": m["rms_tracking_error"],
        "max_tracking_error": m["max_tracking_error"],
        "max_abs_torque": m["max_abs_torque"],
        "max_abs_torque_rate": m["max_abs_torque_rate"],
        "min_clearance": m["min_clearance"],
        "tick_us_median": m["tick_us_median"],
        "tick_us_p99": m["tick_us_p99"],
        "tick_us_max": m["tick_us_max"],
        "ticks": m["ticks"],
    }
    metrics.update(_stage_medians(traj.infos))
    for key in ("qp_status_counts", "qp_iterations_max", "qp_fallbacks"):
        if key in m:
            metrics[key] = m[key]
    return ClosedLoop(scene.name, spec.label, metrics, StateSequence(traj.t, traj.q, traj.v))


def same_ticks(scene: BenchScene, specs: Sequence[ControllerSpec], states: StateSequence, *,
               floor: bool = True, progress: bool = False) -> dict[str, TickTimes]:
    """Every controller of ``specs`` timed on ``states`` of ``scene`` (interleaved), and with ``floor``
    the floor (label ``"floor"``: ``pin.computeAllTerms`` alone, interleaved like a controller)."""
    controllers: dict[str, Steppable] = {FLOOR: PinocchioFloor(scene.robot)} if floor else {}
    controllers.update({s.label: scene.controller(s.kind, s.solver) for s in specs})
    return time_on_states(controllers, states, progress=progress, desc=f"same ticks {scene.name}")


def scaling(scene: BenchScene, counts: Sequence[int], specs: Sequence[ControllerSpec], states: StateSequence, *,
            seed: int = 0, progress: bool = False) -> dict[int, dict[str, TickTimes]]:
    """Tick times against the number of obstacles: ``scene`` tiled to each count (the uniform-grid broad
    phase on at every count, 10 included), every (count, controller) timed on the same ``states``, all
    interleaved."""
    controllers: dict[tuple[int, str], Steppable] = {}
    for count in counts:
        tiled = orchard_scene(scene, count, seed=seed)
        for s in specs:
            controllers[(count, s.label)] = tiled.controller(s.kind, s.solver, broadphase=True)
    flat = time_on_states({f"{c}|{lb}": ctrl for (c, lb), ctrl in controllers.items()}, states,
                          progress=progress, desc=f"scaling {scene.name}")
    out: dict[int, dict[str, TickTimes]] = {c: {} for c in counts}
    for (count, label) in controllers:
        out[count][label] = flat[f"{count}|{label}"]
    return out


#: The harvesting scenario whose tick :func:`harvest_tick_cost` measures.
HARVEST_SCENARIO = "panda_harvest"


def harvest_tick_cost(run: Any, stride: int = 2) -> dict[str, float]:
    """``panda_harvest``'s approach task with self-collision rows against the position task without
    them (issue 11's tick target; ``make harvest`` and ``qpctl bench``): both QP controllers stepped on the same recorded states of ``run`` (every ``stride``-th tick, in order,
    alternating which goes first), medians of their own compute times [µs] and the ratio."""
    raw = Scenario.load(HARVEST_SCENARIO).data
    position = {**raw, "path": {k: v for k, v in raw["path"].items() if k != "approach"},
                "controller": {**raw["controller"], "task": "position", "self_collision": False}}
    ctrl_a = Scenario.load(HARVEST_SCENARIO).build_controller("qp")
    ctrl_p = Scenario.from_dict(position, source="position task").build_controller("qp")
    traj = run.trajectory
    times: dict[str, list[float]] = {"approach": [], "position": []}
    for c in (ctrl_a, ctrl_p):
        c.warmup()
    for i, k in enumerate(range(0, len(traj.t), stride)):
        pair = [("approach", ctrl_a), ("position", ctrl_p)]
        for name, c in pair if i % 2 == 0 else pair[::-1]:
            times[name].append(c.step(traj.q[k], traj.v[k], float(traj.t[k])).compute_us)
    a, p = float(np.median(times["approach"])), float(np.median(times["position"]))
    return {"approach_us": a, "position_us": p, "ratio": a / p, "ticks": len(times["approach"])}
