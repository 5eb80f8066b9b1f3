"""Soak (issue 6, ``make soak``): a seeded run of more than 100,000 QP control ticks over randomised
scenes — the planar 3-link arm at dt = 2 ms and some Panda scenes, random obstacles (static, drifting,
swaying), gains, torque limits, solvers, fallback chains and tick budgets — through the real
scenario validation and simulator. The closed forms run on every fourth scene.

It asserts: no unhandled exception; no non-finite torque; no torque beyond its limit; and on every
tick the QP itself solved, no obstacle-barrier row violated beyond the solver tolerance the controller
accepts (SOLUTION_RTOL, relative to 1 + |bound|) — checked on every tick against the tick's own QP
rows and, every 10th tick, against rows recomputed from a fresh state (its own Pinocchio data and
python-fcl queries). It writes ``results/soak/summary.json`` (the README's "Reliability" numbers).

``test_soak_with_faults`` (issue 12) runs as many QP ticks again on scenes from the same generators
(a stream of their own) with random faults on (:func:`random_faults`: sensing noise and encoder
steps, delays, lost commands, torque lag and saturation, mass errors, payloads, map noise and drift)
and asserts the same, the applied torques within the limits too; it counts the collisions and
explains each: whether the same scene collides without faults too, and whether the controller saw
it coming (its own clearance, on its map and measured state, went below d_safe) or not (its view
kept d_safe while the truth did not). It writes
``results/soak/summary_faults.json``.
"""

from __future__ import annotations

import faulthandler
import itertools
import json
import os
import sys
import time
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from qpctl import ConfigError, InvalidStateError, Scenario, SimulationError, panda, planar_arm
from qpctl.constraints import ObstacleBarrier
from qpctl.controllers.qp import (
    BUILT_IN_FALLBACKS,
    FALLBACK_BRAKE,
    FALLBACK_CLOSED_FORM,
    FALLBACK_SAFE_STOP,
    SOLUTION_RTOL,
)
from qpctl.dynamics import Dynamics
from qpctl.scenario import arm_reach
from qpctl.simulation import Simulator
from qpctl.solvers import available_solvers

SEED = 20240611
TARGET_QP_TICKS = int(os.environ.get("QPCTL_SOAK_TICKS", "100000"))  # a shorter trial: QPCTL_SOAK_TICKS=5000
DT = 0.002
OUT = Path(__file__).resolve().parents[1] / "results" / "soak"
SCENE_WATCHDOG_S = 600  # a scene that runs longer than this dumps every thread's stack and ends the run

SOLVER_WEIGHTS = {"proxqp": 0.45, "osqp": 0.25, "daqp": 0.2, "quadprog": 0.1}
CHAINS = [[FALLBACK_CLOSED_FORM], ["daqp", FALLBACK_CLOSED_FORM], [FALLBACK_BRAKE], ["osqp", FALLBACK_CLOSED_FORM],
          [FALLBACK_CLOSED_FORM, FALLBACK_SAFE_STOP], ["daqp", FALLBACK_CLOSED_FORM, FALLBACK_SAFE_STOP]]


def _obstacle(rng: np.random.Generator, centre: np.ndarray, spread: float, planar: bool) -> dict[str, Any]:
    shape = str(rng.choice(["sphere", "sphere", "box", "capsule", "cylinder"]))
    pos = centre + rng.uniform(-spread, spread, 3)
    if planar:
        pos[2] = 0.0
    ob: dict[str, Any] = {"shape": shape, "position": pos.tolist()}
    if shape == "box":
        ob["size"] = rng.uniform(0.05, 0.35, 3).tolist()
    else:
        ob["radius"] = float(rng.uniform(0.04, 0.15 if not planar else 0.2))
    if shape in ("capsule", "cylinder"):
        ob["length"] = float(rng.uniform(0.1, 0.5))
        axis = rng.normal(size=3)
        ob["axis"] = (axis if not planar else np.array([0.0, 0.0, 1.0])).tolist()
    motion = rng.uniform()
    if motion < 0.2:
        vel = rng.uniform(-0.3, 0.3, 3)
        if planar:
            vel[2] = 0.0
        ob["velocity"] = vel.tolist()
    elif motion < 0.4:
        amp = rng.uniform(-0.25, 0.25, 3)
        if planar:
            amp[2] = 0.0
        ob["amplitude"], ob["frequency"] = amp.tolist(), float(rng.uniform(0.2, 1.0))
    return ob


def _controller(rng: np.random.Generator) -> dict[str, Any]:
    names = [s for s in SOLVER_WEIGHTS if s in available_solvers()]
    weights = np.array([SOLVER_WEIGHTS[s] for s in names])
    solver = str(rng.choice(names, p=weights / weights.sum()))
    kp = float(rng.uniform(50.0, 300.0))
    d_safe = float(rng.uniform(0.02, 0.08))
    k1 = float(rng.choice([20.0, 40.0, 60.0]))
    # proxsuite can spend seconds on an infeasible tick, so its scenes always have a budget;
    # the other solvers detect infeasibility themselves and sometimes run without one.
    budgets = [5000.0, 10000.0, 20000.0] + ([0.0] if solver != "proxqp" else [])
    chain = [c for c in CHAINS[int(rng.integers(len(CHAINS)))] if c in BUILT_IN_FALLBACKS or c in available_solvers()]
    return {"kind": "qp", "solver": solver, "kp": kp, "kv": float(2 * np.sqrt(kp) * rng.uniform(0.8, 1.5)),
            "kn": float(rng.uniform(0.0, 20.0)), "v_ref": float(rng.uniform(0.0, 2.0)), "d_safe": d_safe,
            "d_influence": d_safe + float(rng.uniform(0.1, 0.4)),
            # k₁² ≥ 4k₀: a critically or over-damped barrier (an under-damped one overshoots into d_safe
            # by design, and was seen to reach the obstacle: −1.2 cm with k₀ = 400, k₁ = 20)
            "barrier_k1": k1, "barrier_k0": float(k1 * k1 / 4 * rng.uniform(0.25, 1.0)),
            "fallback": chain, "tick_budget_us": float(rng.choice(budgets))}


def near_the_arm(rng: np.random.Generator, robot: Any, q0: np.ndarray, route: list[np.ndarray]) -> np.ndarray:
    """A point on the route of the task point or on a link at the start, where obstacles matter."""
    if rng.uniform() < 0.5:
        i = int(rng.integers(len(route) - 1))
        return route[i] + rng.uniform() * (route[i + 1] - route[i])
    import pinocchio as pin

    data = robot.model.createData()
    pin.forwardKinematics(robot.model, data, q0)
    cap = robot.capsules[int(rng.integers(len(robot.capsules)))]
    return data.oMi[cap.joint_id].act(cap.p0 + rng.uniform() * (cap.p1 - cap.p0))


def _ee(robot: Any, q0: np.ndarray) -> np.ndarray:
    import pinocchio as pin

    data = robot.model.createData()
    pin.framesForwardKinematics(robot.model, data, q0)
    return data.oMf[robot.ee_frame_id].translation.copy()


PLANAR = planar_arm()


def planar_scene(rng: np.random.Generator, k: int) -> dict[str, Any]:
    q0 = rng.uniform(-np.pi, np.pi, 3)
    duration = float(rng.uniform(1.0, 3.0))
    waypoints = []
    for _ in range(int(rng.integers(1, 4))):
        r, a = rng.uniform(0.4, 2.8), rng.uniform(-np.pi, np.pi)
        waypoints.append([r * np.cos(a), r * np.sin(a)])
    # A robot has limits: torque always (gravity alone needs up to ~440 N·m), joint speed in half the
    # scenes. (Without limits a fast path can drive the arm to ~100 rad/s and the RK4 simulation at
    # 2 ms diverges, with the closed forms as with the QP: a property of the scene, not tested here.)
    robot: dict[str, Any] = {"kind": "planar3", "q0": q0.tolist(), "tau_max": float(rng.uniform(500.0, 1500.0))}
    if rng.uniform() < 0.5:
        robot["v_max"] = float(rng.uniform(3.0, 8.0))
    drives = np.random.default_rng([SEED, k])  # its own stream: the scenes above stay as they were
    if drives.uniform() < 0.5:  # a torque-rate limit in half the scenes (the Panda has Franka's always)
        robot["tau_rate_max"] = float(drives.uniform(1000.0, 5000.0))
    route = [_ee(PLANAR, q0)] + [np.array([*w, 0.0]) for w in waypoints]
    length = sum(float(np.linalg.norm(b[:2] - a[:2])) for a, b in itertools.pairwise(route))
    duration = max(duration, length / 1.5)  # at most 1.5 m/s on average (peaks 1.9× that)
    obstacles = [_obstacle(rng, near_the_arm(rng, PLANAR, q0, route), 0.35, planar=True)
                 for _ in range(int(rng.integers(1, 5)))]
    return {"name": f"soak-planar-{k}", "robot": robot, "path": {"waypoints": waypoints, "duration": duration},
            "obstacles": obstacles, "controller": _controller(rng),
            "sim": {"dt": DT, "duration": duration + 0.5}}


PANDA = panda()
PANDA_CENTRE, PANDA_REACH = arm_reach(PANDA)  # type: ignore[misc]


def panda_scene(rng: np.random.Generator, k: int) -> dict[str, Any]:
    lo, hi = PANDA.q_min, PANDA.q_max
    q0 = np.clip(PANDA.q_home + rng.normal(0.0, 0.3, PANDA.nv), lo + 0.05, hi - 0.05)
    import pinocchio as pin

    data = PANDA.model.createData()
    pin.framesForwardKinematics(PANDA.model, data, q0)
    start = data.oMf[PANDA.ee_frame_id].translation.copy()
    waypoints = [(start + rng.uniform(-0.25, 0.25, 3)).tolist() for _ in range(int(rng.integers(1, 3)))]
    duration = float(rng.uniform(1.0, 2.0))
    route = [start] + [np.array(w) for w in waypoints]
    obstacles = [_obstacle(rng, near_the_arm(rng, PANDA, q0, route), 0.2, planar=False)
                 for _ in range(int(rng.integers(1, 4)))]
    ctrl = _controller(rng)
    ctrl["d_safe"] = min(ctrl["d_safe"], 0.04)
    ctrl["d_influence"] = ctrl["d_safe"] + float(rng.uniform(0.08, 0.2))
    return {"name": f"soak-panda-{k}", "robot": {"kind": "panda", "q0": q0.tolist()},
            "path": {"waypoints": waypoints, "duration": duration}, "obstacles": obstacles, "controller": ctrl,
            "sim": {"dt": DT, "duration": duration + 0.3}}


class Checker:
    """Wraps a controller's ``step``: per-tick checks and counters."""

    def __init__(self, ctrl: Any, stats: dict[str, Any], independent_every: int = 10) -> None:
        self.ctrl, self.stats, self.every = ctrl, stats, independent_every
        self.inner = ctrl.step
        self.fresh = Dynamics(ctrl.robot, ctrl.obstacles, cutoff=ctrl.gains.d_influence) if ctrl.obstacles else None
        self.barrier = next((c for c in getattr(ctrl, "constraints", []) if isinstance(c, ObstacleBarrier)), None)
        budget = getattr(getattr(ctrl, "config", None), "tick_budget_us", 0.0)
        self.budget = budget
        self.k = 0
        self.previous: tuple[np.ndarray, float] | None = None  # (τ, t) of the last tick
        self.seen_clearance: list[float] = []  # the controller's own least distance, each tick
        ctrl.step = self.step

    def step(self, q: np.ndarray, v: np.ndarray, t: float) -> Any:
        out = self.inner(q, v, t)
        s, ctrl = self.stats, self.ctrl
        self.k += 1
        self.seen_clearance.append(out.clearance)
        s["ticks"] += 1
        if not np.all(np.isfinite(out.tau)):
            s["nonfinite_torques"] += 1
            return out
        if np.any(np.abs(out.tau) > ctrl.robot.tau_max + 1e-9):
            s["torque_limit_exceeded"] += 1
        if ctrl.kind == "qp" and self.previous is not None and t > self.previous[1]:  # the drives' rate limit
            allowed = ctrl.robot.tau_rate_max * (t - self.previous[1])
            if np.any(np.abs(out.tau - self.previous[0]) > allowed * (1 + 1e-6) + 1e-9):
                s["rate_limit_exceeded"] += 1
            s["rate_limited_ticks"] += bool(out.info.get("rate_limited"))
        self.previous = (out.tau.copy(), t)
        s["singular_ticks"] += int(out.singular)
        if ctrl.kind != "qp":
            return out
        info = out.info
        s["status"][info["status"]] += 1
        if self.budget > 0:
            s["budget_ticks"] += 1
            over = out.compute_us - self.budget
            s["budget_overrun_max_us"] = max(s["budget_overrun_max_us"], over)
            if over > 1000.0:
                s["budget_overrun_gt_1ms"] += 1
                s["overruns"].append({k: (round(v) if isinstance(v, float) else v) for k, v in info.items()
                                      if k in ("solver", "status", "fallback", "state_us", "build_us", "solve_us",
                                               "fallback_us", "fallback_tried")} | {"tick_us": round(out.compute_us)})
        s["tick_us"].append(out.compute_us)
        if "fallback" in info:
            s["fallbacks"][info["fallback"]] += 1
            return out
        s["qp_solved_ticks"] += 1
        s["torque_clip_max_Nm"] = max(s["torque_clip_max_Nm"], float(info.get("clipped", 0.0)))
        problem = ctrl.last_problem
        x = ctrl.last_solution.x[: ctrl.n]  # the solver's q̈ (the command differs by the torque clip above)
        rows = [i for i, name in enumerate(problem.row_names) if name == ObstacleBarrier.name]
        if rows:
            lo = problem.l[rows]
            finite = np.isfinite(lo)
            if np.any(finite):
                viol = (lo[finite] - problem.C[rows][finite, : ctrl.n] @ x) / (1.0 + np.abs(lo[finite]))
                worst = float(np.max(viol))
                s["barrier_rel_violation_max"] = max(s["barrier_rel_violation_max"], worst)
                if worst > SOLUTION_RTOL:
                    s["barrier_violations"] += 1
        if self.fresh is not None and self.barrier is not None and self.k % self.every == 0:
            state = self.fresh.compute(q, v, t)
            pairs = state.pairs
            drift = state.barrier_drift() if len(pairs) else np.zeros(0)
            for r in np.argsort(pairs.distance, kind="stable")[: self.barrier.rows]:
                n, Jp = pairs.normal[r], state.pair_jac[r]
                h = pairs.distance[r] - ctrl.gains.d_safe
                hdot = n @ (Jp @ v) - n @ pairs.v_obstacle[r]
                bound = self.barrier.k1 * hdot + self.barrier.k0 * h + drift[r]
                lhs = n @ (Jp @ out.qdd) + bound
                # Exact only where python-fcl's distance is closed-form (a separated sphere or capsule);
                # elsewhere GJK's ~1e-4 m and ~1e-3 rad noise enters h, ḣ and the drift: reported only.
                exact = pairs.distance[r] > 0 and ctrl.obstacles[pairs.obstacle[r]].shape in ("sphere", "capsule")
                key = "exact" if exact else "gjk"
                s[f"independent_rows_{key}"] += 1
                rel = float(-lhs / (1.0 + abs(bound)))
                s[f"independent_rel_violation_max_{key}"] = max(s[f"independent_rel_violation_max_{key}"], rel)
                if exact and rel > 2 * SOLUTION_RTOL:
                    s["independent_violations"] += 1
                    s["independent_cases"].append({"t": t, "distance": float(pairs.distance[r]), "lhs": float(lhs),
                                                   "bound": float(bound), "solver": info["solver"]})
        return out


def new_stats() -> dict[str, Any]:
    return {"ticks": 0, "qp_solved_ticks": 0, "nonfinite_torques": 0, "torque_limit_exceeded": 0,
            "rate_limit_exceeded": 0, "rate_limited_ticks": 0,
            "singular_ticks": 0, "status": Counter(), "fallbacks": Counter(), "barrier_violations": 0,
            "barrier_rel_violation_max": -np.inf, "torque_clip_max_Nm": 0.0, "independent_rows_exact": 0, "independent_rows_gjk": 0,
            "independent_violations": 0, "independent_rel_violation_max_exact": -np.inf,
            "independent_rel_violation_max_gjk": -np.inf, "budget_ticks": 0, "budget_overrun_max_us": -np.inf,
            "budget_overrun_gt_1ms": 0, "tick_us": [], "overruns": [], "independent_cases": []}


def valid_scenes(rng: np.random.Generator, rejected: Counter[str],
                 decorate: Callable[[dict[str, Any], int], None] | None = None
                 ) -> Iterator[tuple[int, str, dict[str, Any]]]:
    """The soak's scenes in draw order — scene k a Panda when k % 4 == 0, else planar — as (k, which,
    raw) for those the scenario validation accepts (an obstacle drawn on top of the start pose is a
    valid refusal) and whose start is clear of d_safe (valid, but then d_safe cannot be promised); the
    others counted in ``rejected`` by key. ``decorate(raw, k)`` adds to a scene before validation."""
    k = 0
    while True:
        k += 1
        which = "panda" if k % 4 == 0 else "planar"
        raw = panda_scene(rng, k) if which == "panda" else planar_scene(rng, k)
        if decorate is not None:
            decorate(raw, k)
        try:
            scen = Scenario.from_dict(raw, source=raw["name"])
        except ConfigError as exc:
            rejected[str(exc.key)] += 1
            continue
        robot = scen.build_robot()
        start_clearance = Dynamics(robot, scen.build_obstacles()).compute(scen.q0(robot), np.zeros(robot.nv)).clearance
        if start_clearance < raw["controller"]["d_safe"]:
            rejected["start within d_safe"] += 1
            continue
        yield k, which, raw


def run_scene(raw: dict[str, Any], kind: str, stats: dict[str, Any], exceptions: list[str],
              diverged: list[str]) -> dict[str, Any] | None:
    """Run one scene; a run whose state diverges (the simulator's SimulationError, or the controller's
    InvalidStateError on an overflowing state) goes to ``diverged``; any other exception to
    ``exceptions``. With a ``[faults]`` table the controller is built on its map of the obstacles and
    the simulator applies the faults."""
    scen = Scenario.from_dict(raw, source=raw["name"])
    faults = scen.faults()
    try:
        robot = scen.build_robot()
        truth = scen.build_obstacles()
        ctrl = scen.build_controller(kind, robot=robot, obstacles=faults.perceived(truth, robot.task_axes))
        ctrl.warmup()  # before the Checker: its two ticks are not the run's
        checker = Checker(ctrl, stats)
        sim = Simulator(ctrl, dt=DT, duration=raw["sim"]["duration"], faults=faults, obstacles=truth)
        traj = sim.run(scen.q0(ctrl.robot))
    except (SimulationError, InvalidStateError) as exc:  # the simulated state blew up (named errors)
        diverged.append(f"{raw['name']} ({kind}): {type(exc).__name__}: {exc}")
        return None
    except Exception as exc:  # noqa: BLE001 — counted and reported: the soak's first claim is "none"
        exceptions.append(f"{raw['name']} ({kind}): {type(exc).__name__}: {exc}")
        return None
    d_safe = float(raw["controller"].get("d_safe", 0.05))  # the scenario's: a margin does not move the goal
    fallback_ticks = sum("fallback" in i for i in traj.infos)
    config = getattr(ctrl, "config", None)  # the QP's (the closed forms have none)
    worst = int(np.argmin(traj.clearance))
    out = {"name": raw["name"], "solver": ctrl.solver, "chain": list(getattr(config, "fallback", [])),
           "min_clearance": float(np.min(traj.clearance)),
           "min_clearance_minus_d_safe": float(np.min(traj.clearance) - d_safe), "fallback_ticks": fallback_ticks,
           "pairs_dropped_ticks": sum("pairs_dropped" in i for i in traj.infos),
           "shapes": sorted({o.shape for o in ctrl.obstacles}),
           "collided": bool(np.min(traj.clearance) < 0.0),
           "rate_limited": bool(np.isfinite(ctrl.robot.tau_rate_max).any()),
           "moving": any(o.moving for o in ctrl.obstacles)}
    if faults.active:
        applied = np.abs(traj.tau) > ctrl.robot.tau_max + 1e-9
        stats["applied_torque_limit_exceeded"] = stats.get("applied_torque_limit_exceeded", 0) + int(applied.any())
        stats["applied_torque_nonfinite"] = stats.get("applied_torque_nonfinite", 0) + int(
            not np.all(np.isfinite(traj.tau)))
        seen = np.array(checker.seen_clearance)
        out.update(faults=faults.kinds(), **sim.fault_counts,
                   # the controller's own least distance (its map, its measured state) up to the true worst tick
                   seen_min_clearance_to_worst=float(np.min(seen[: worst + 1])),
                   seen_below_d_safe=bool(np.min(seen[: worst + 1]) < ctrl.gains.d_safe - 1e-3),
                   d_safe_margin=float(ctrl.gains.d_safe - d_safe))
    return out


@pytest.mark.slow
def test_soak():
    rng = np.random.default_rng(SEED)
    qp, closed = new_stats(), new_stats()
    exceptions: list[str] = []
    diverged: list[str] = []  # closed-form runs whose state diverged (reported: a property of the laws)
    qp_diverged: list[str] = []
    rejected: Counter[str] = Counter()
    scenes = {"planar": 0, "panda": 0}
    clearance: list[dict[str, Any]] = []
    start = time.time()
    closed_runs = 0
    drawn = valid_scenes(rng, rejected)
    while qp["ticks"] < TARGET_QP_TICKS:
        k, which, raw = next(drawn)
        scenes[which] += 1
        faulthandler.dump_traceback_later(SCENE_WATCHDOG_S, exit=True, file=sys.stderr)
        try:
            res = run_scene(raw, "qp", qp, exceptions, qp_diverged)
            if res is not None:
                clearance.append({**res, "robot": which})
            if k % 4 == 0:
                closed_runs += 2
                for kind in ("paper", "hsu"):
                    run_scene(raw, kind, closed, exceptions, diverged)
        finally:
            faulthandler.cancel_dump_traceback_later()
    elapsed = time.time() - start
    tick_us = np.array(qp.pop("tick_us"))
    closed.pop("tick_us")
    static = [c for c in clearance if not c["moving"]]
    summary = {
        "seed": SEED, "elapsed_s": round(elapsed, 1), "scenes": scenes, "scenes_rejected_by_validation": dict(rejected),
        "unhandled_exceptions": exceptions, "qp_runs_diverged": qp_diverged, "closed_form_runs_diverged": diverged,
        "qp": {**{k: (dict(v) if isinstance(v, Counter) else v) for k, v in qp.items()},
               "tick_us_median": float(np.median(tick_us)), "tick_us_p99": float(np.percentile(tick_us, 99)),
               "tick_us_max": float(np.max(tick_us))},
        "closed_forms": {**{k: v for k, v in closed.items() if k in ("ticks", "nonfinite_torques", "singular_ticks")},
                         "runs": closed_runs},
        "clearance": {"scenes": len(clearance), "collided_scenes": sum(c["collided"] for c in clearance),
                      "collided_static_scenes": sum(c["collided"] for c in static),
                      "collided_scenes_without_fallback": sum(c["collided"] and not c["fallback_ticks"]
                                                              for c in clearance),
                      "below_d_safe_scenes_without_fallback": sum(c["min_clearance_minus_d_safe"] < -1e-3
                                                                  and not c["fallback_ticks"] for c in clearance),
                      "below_d_safe_scenes": sum(c["min_clearance_minus_d_safe"] < -1e-3 for c in clearance),
                      "below_d_safe_static_scenes": sum(c["min_clearance_minus_d_safe"] < -1e-3 for c in static),
                      "static_scenes": len(static),
                      "worst_min_clearance_minus_d_safe": min(c["min_clearance_minus_d_safe"] for c in clearance),
                      "collisions": [c for c in clearance if c["collided"]],
                      # the fallback chains with and without the safe stop, compared
                      "scenes_with_safe_stop": sum(FALLBACK_SAFE_STOP in c["chain"] for c in clearance),
                      "collided_with_safe_stop": sum(c["collided"] and FALLBACK_SAFE_STOP in c["chain"]
                                                     for c in clearance),
                      "collided_without_safe_stop": sum(c["collided"] and FALLBACK_SAFE_STOP not in c["chain"]
                                                        for c in clearance),
                      # with and without a torque-rate limit on the drives
                      "scenes_with_rate_limit": sum(c["rate_limited"] for c in clearance),
                      "collided_with_rate_limit": sum(c["collided"] and c["rate_limited"] for c in clearance),
                      "collided_without_rate_limit": sum(c["collided"] and not c["rate_limited"]
                                                         for c in clearance)},
    }
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "summary.json").write_text(json.dumps(summary, indent=2, default=float) + "\n")
    print(json.dumps(summary, indent=2, default=float))
    assert not exceptions, exceptions
    assert not qp_diverged, qp_diverged
    assert qp["ticks"] >= TARGET_QP_TICKS
    assert qp["nonfinite_torques"] == 0 and closed["nonfinite_torques"] == 0
    assert qp["torque_limit_exceeded"] == 0
    assert qp["rate_limit_exceeded"] == 0
    assert qp["barrier_violations"] == 0, qp["barrier_rel_violation_max"]
    assert qp["independent_violations"] == 0, qp["independent_cases"][:5]


def random_faults(rng: np.random.Generator, raw: dict[str, Any], k: int) -> dict[str, Any]:
    """A ``[faults]`` table: each fault on with probability 0.4, at a level up to the robustness study's
    highest (README, Faults and robustness); the payload arrives at a random time of the run."""
    duration = raw["sim"]["duration"]
    planar = raw["robot"]["kind"] == "planar3"
    draws: dict[str, Any] = {
        "q_noise": lambda: float(rng.uniform(0.0, 1e-3)),
        "q_quantum": lambda: float(rng.choice([1e-4, 1e-3, 5e-3])),
        "v_noise": lambda: float(rng.uniform(0.0, 5e-2)),
        "delay_ticks": lambda: int(rng.integers(1, 6)),
        "miss_rate": lambda: float(rng.uniform(0.0, 0.3)),
        "torque_lag": lambda: float(rng.uniform(0.0, 0.02)),
        # drives weaker than the limits the controller knows (the planar arm's: 500–1500 N·m; the Panda's URDF's)
        "torque_saturation": lambda: float(rng.uniform(0.5, 1.0)) * (raw["robot"]["tau_max"] if planar else 87.0),
        "mass_error": lambda: float(rng.uniform(0.0, 0.2)),
        "payload_mass": lambda: float(rng.uniform(0.0, 2.0 if planar else 1.0)),
        "obstacle_noise": lambda: float(rng.uniform(0.0, 0.03)),
        "obstacle_velocity": lambda: float(rng.uniform(0.0, 0.05)),
    }
    table: dict[str, Any] = {key: draw() for key, draw in draws.items() if rng.uniform() < 0.4}
    if "payload_mass" in table:
        table["payload_time"] = float(rng.uniform(0.0, duration))
    if not table:  # every scene has at least one fault
        table["q_noise"] = 1e-4
    table["seed"] = k
    return table


@pytest.mark.slow
def test_soak_with_faults():
    scene_rng = np.random.default_rng([SEED, 12])  # issue 12's scenes: a stream of their own
    qp, closed = new_stats(), new_stats()
    exceptions: list[str] = []
    diverged: list[str] = []
    qp_diverged: list[str] = []
    rejected: Counter[str] = Counter()
    runs: list[dict[str, Any]] = []
    scenes = {"planar": 0, "panda": 0}
    start = time.time()
    closed_runs = 0

    def with_faults(raw: dict[str, Any], k: int) -> None:
        raw["faults"] = random_faults(np.random.default_rng([SEED, 12, k]), raw, k)

    drawn = valid_scenes(scene_rng, rejected, with_faults)
    while qp["ticks"] < TARGET_QP_TICKS:
        k, which, raw = next(drawn)
        scenes[which] += 1
        faulthandler.dump_traceback_later(SCENE_WATCHDOG_S, exit=True, file=sys.stderr)
        try:
            res = run_scene(raw, "qp", qp, exceptions, qp_diverged)
            if res is not None and res["collided"]:  # the same scene without faults: does it collide anyway?
                ideal = run_scene({key: val for key, val in raw.items() if key != "faults"}, "qp", new_stats(),
                                  exceptions, qp_diverged)
                res["collided_without_faults"] = ideal is not None and ideal["collided"]
            if res is not None:
                runs.append({**res, "robot": which})
            if k % 4 == 0:
                closed_runs += 2
                for kind in ("paper", "hsu"):
                    run_scene(raw, kind, closed, exceptions, diverged)
        finally:
            faulthandler.cancel_dump_traceback_later()
    elapsed = time.time() - start
    tick_us = np.array(qp.pop("tick_us"))
    closed.pop("tick_us")
    collided = [r for r in runs if r["collided"]]
    kinds = sorted({f for r in runs for f in r["faults"]})
    summary = {
        "seed": [SEED, 12], "elapsed_s": round(elapsed, 1), "scenes": scenes,
        "scenes_rejected_by_validation": dict(rejected), "unhandled_exceptions": exceptions,
        "qp_runs_diverged": qp_diverged, "closed_form_runs_diverged": diverged,
        "qp": {**{k: (dict(v) if isinstance(v, Counter) else v) for k, v in qp.items()},
               "tick_us_median": float(np.median(tick_us)), "tick_us_p99": float(np.percentile(tick_us, 99))},
        "closed_forms": {**{k: v for k, v in closed.items() if k in ("ticks", "nonfinite_torques", "singular_ticks")},
                         "runs": closed_runs},
        "commands_lost": sum(r.get("missed_commands", 0) for r in runs),
        "saturated_ticks": sum(r.get("saturated_ticks", 0) for r in runs),
        "clearance": {
            "scenes": len(runs), "collided_scenes": len(collided),
            # explained: did the controller's own view (its map, its measured state) go below d_safe first?
            "collided_seen_below_d_safe": sum(r["seen_below_d_safe"] for r in collided),
            "collided_unseen": sum(not r["seen_below_d_safe"] for r in collided),
            "collided_without_faults_too": sum(r["collided_without_faults"] for r in collided),
            "collided_with_fallback_ticks": sum(r["fallback_ticks"] > 0 for r in collided),
            "collided_with_rate_limit": sum(r["rate_limited"] for r in collided),
            "scenes_with_rate_limit": sum(r["rate_limited"] for r in runs),
            "collided_with_map_error": sum(bool({"obstacle_noise", "obstacle_velocity"} & set(r["faults"]))
                                           for r in collided),
            "scenes_with_map_error": sum(bool({"obstacle_noise", "obstacle_velocity"} & set(r["faults"]))
                                         for r in runs),
            "by_fault": {f: {"scenes": sum(f in r["faults"] for r in runs),
                             "collided": sum(f in r["faults"] for r in collided)} for f in kinds},
            "below_d_safe_scenes": sum(r["min_clearance_minus_d_safe"] < -1e-3 for r in runs),
            "collisions": collided,
        },
    }
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "summary_faults.json").write_text(json.dumps(summary, indent=2, default=float) + "\n")
    print(json.dumps({k: v for k, v in summary.items() if k != "clearance"} | {
        "clearance": {k: v for k, v in summary["clearance"].items() if k != "collisions"}}, indent=2, default=float))
    assert not exceptions, exceptions
    assert not qp_diverged, qp_diverged
    assert qp["ticks"] >= TARGET_QP_TICKS
    assert qp["nonfinite_torques"] == 0 and closed["nonfinite_torques"] == 0
    assert qp.get("applied_torque_nonfinite", 0) == 0
    assert qp["torque_limit_exceeded"] == 0 and qp.get("applied_torque_limit_exceeded", 0) == 0
    assert qp["rate_limit_exceeded"] == 0  # the commands; lost ones make the applied torque jump further
    assert qp["barrier_violations"] == 0, qp["barrier_rel_violation_max"]
    assert qp["independent_violations"] == 0, qp["independent_cases"][:5]


@pytest.mark.slow
def test_soak_barrier_design():
    """Issue 16's "feasibility by design" on the soak's own scenes: every scene of the first 120 drawn
    (the stream of test_soak) that has a torque-rate limit and a valid start, run with the scene's
    hand-drawn barrier and with ``barrier_design = "drives"``. Written to
    ``results/soak/summary_design.json`` (the README's "Reliability" numbers); the claims: no commanded
    torque change beyond the limit in either mode, and the designed barrier holds d_safe − 1 mm on at
    least as many scenes as the hand-drawn one."""
    rows: list[dict[str, Any]] = []
    start = time.time()
    for k, _, raw in valid_scenes(np.random.default_rng(SEED), Counter()):
        if k > 120:
            break
        robot = Scenario.from_dict(raw, source=raw["name"]).build_robot()
        if not np.isfinite(robot.tau_rate_max).any():
            continue
        row: dict[str, Any] = {"name": raw["name"], "d_safe": raw["controller"]["d_safe"]}
        for mode in ("manual", "drives"):
            scen = Scenario.from_dict({**raw, "controller": {**raw["controller"], "barrier_design": mode}},
                                      source=raw["name"])
            ctrl = scen.build_controller()
            traj = Simulator(ctrl, dt=DT, duration=raw["sim"]["duration"]).run(scen.q0(ctrl.robot))
            step = np.abs(np.diff(traj.tau, axis=0)).max(axis=0) / (np.diff(traj.t).min())
            row[mode] = {"min_clearance_minus_d_safe": float(traj.clearance.min() - raw["controller"]["d_safe"]),
                         "rms_tracking_error": float(np.sqrt(np.mean(np.sum((traj.x - traj.x_ref) ** 2, axis=1)))),
                         "rate_over_limit": float(np.max(step / robot.tau_rate_max)),
                         "fallback_ticks": sum("fallback" in i for i in traj.infos),
                         "k0_k1_d_influence": [ctrl.config.barrier_k0, ctrl.config.barrier_k1, ctrl.gains.d_influence]}
        rows.append(row)
    held = {m: sum(r[m]["min_clearance_minus_d_safe"] >= -1e-3 for r in rows) for m in ("manual", "drives")}
    collided = {m: sum(r[m]["min_clearance_minus_d_safe"] < -r["d_safe"] for r in rows) for m in ("manual", "drives")}
    summary = {"scenes": len(rows), "held_d_safe": held, "wall_s": time.time() - start, "runs": rows,
               "collided": collided}
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "summary_design.json").write_text(json.dumps(summary, indent=2, default=float) + "\n")
    assert len(rows) >= 15
    assert all(r[m]["rate_over_limit"] <= 1 + 1e-6 for r in rows for m in ("manual", "drives"))
    assert held["drives"] >= held["manual"], held
