"""The depth map's costs on the same recorded frames (issue 21's targets; docs/perception.md).

    python -m benchmarks.perception [--quick] [--out results/perception]
    python -m benchmarks.perception --canopies 20 [--duration S] [--out results/perception-canopies]

1. **Frame to field**: 640×480 frames of a seeded canopy (300 soft leaves, 12 rigid branches, depth
   noise σ = 1 mm·z²), recorded once into ``frames.npz``; each goes through the whole pipeline
   (filtering, back-projection, the Panda's self-filter and its shadow, voxels, clearing, decay, the EDT and its
   gradient for both channels) at 2 cm over a 1.6 × 1.2 × 1.0 m box — labelled (leaves soft), and
   the same frames without labels, as a camera without a segmenter gives them (every return rigid:
   each goes through the self-filter and the shadow test) — and at 1 cm over a 0.4 m box around the
   hand. Stage times from the pipeline's own clocks; one thread.
2. **Distance transforms** on the same occupancy: qpctl's numba EDT, scipy's ``distance_transform_edt``
   and the ``edt`` package (where installed), interleaved.
3. **Field queries**: the tick's lookups in the field for the Panda's capsules — both channels' pairs and
   the soft speed points — by :func:`qpctl.kernels.field_samples.field_samples` (one pass, as the tick
   makes them) and by the separate :func:`qpctl.kernels.field.field_pairs` (per channel) and
   :func:`qpctl.kernels.field.speed_points`, interleaved on the same states.
4. **The tick with the field**: the Panda's compiled QP tick on a ``panda_spheres`` run's states (10
   sphere primitives), without and with the canopy map's field rows, interleaved.
5. **The tick beside the worker**: the Panda's QP tick on a closed-loop run of ``panda_spheres``,
   in alternating stretches with the map worker idle and with it fed frames at 30 Hz; p99 ratio.

6. With ``--canopies N``: the closed loop on ``panda_canopy_depth`` under canopy seeds 1..N (the
   camera's noise on): collisions, true rigid and soft clearances, soft contact speeds, fruits
   reached, map costs and latency, phantom rows (``canopies.json``, ``canopies.md``).

Writes ``perception.json`` and ``perception.md`` (the tables of docs/perception.md) in --out.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
from numba import njit
from scipy import ndimage

from qpctl.bench.timing import PinocchioFloor
from qpctl.kernels import edt as KE
from qpctl.kernels import field as KF
from qpctl.kernels import field_samples as KS
from qpctl.perception import DepthFrame, DepthMap, Intrinsics, MapWorker, PerceptionConfig
from qpctl.perception.synthetic import canopy, look_at, render
from qpctl.robot.model import panda
from qpctl.sweep.backends import LocalBackend
from qpctl.sweep.engine import map_ordered

K640 = Intrinsics.from_fov(640, 480, 58.0)  # a RealSense D435-like depth stream
EYE = look_at([-0.35, 0.05, 0.75], [0.55, 0.0, 0.45])
BOX_2CM = PerceptionConfig(voxel=0.02, bounds_min=[-0.3, -0.6, 0.0], bounds_max=[1.3, 0.6, 1.0], truncation=0.3)


def hand_box(robot: Any) -> PerceptionConfig:
    """1 cm voxels in a 0.4 m cube about the hand at the home pose."""
    import pinocchio as pin

    data = robot.model.createData()
    pin.framesForwardKinematics(robot.model, data, robot.q_home)
    p = data.oMf[robot.ee_frame_id].translation
    return PerceptionConfig(voxel=0.01, bounds_min=list(p - 0.2), bounds_max=list(p + 0.2), truncation=0.15)


def record_frames(path: Path, n: int, seed: int = 7) -> list[DepthFrame]:
    """``n`` noisy frames of one canopy, 1/30 s apart (made once, then read back)."""
    if path.exists():
        z = np.load(path)
        if z["depth"].shape[0] >= n:
            return [DepthFrame(z["depth"][i], K640, z["pose"], float(z["stamp"][i]), labels=z["labels"][i])
                    for i in range(n)]
    scene = canopy(seed)
    rng = np.random.default_rng(seed)
    frames = [render(EYE, scene, K640, stamp=i / 30.0, labelled=True, noise=0.001, rng=rng) for i in range(n)]
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, depth=np.stack([f.depth.astype(np.float32) for f in frames]),
                        labels=np.stack([f.labels for f in frames]), pose=EYE,
                        stamp=np.array([f.stamp for f in frames]))
    return record_frames(path, n, seed)


def floor_us(robot: Any, calls: int = 3000) -> float:
    """The machine's speed now: ``qpctl bench``'s floor (:class:`~qpctl.bench.timing.PinocchioFloor`,
    ``pin.computeAllTerms``) on the Panda at rest at its home pose, median of ``calls`` calls [µs]
    (this machine runs at two speeds)."""
    floor = PinocchioFloor(robot)
    q, v = robot.q_home, np.zeros(robot.nv)
    return float(np.median([floor.step(q, v, 0.0).compute_us for _ in range(calls)]))


def _stats(v: list[float] | np.ndarray) -> dict[str, float]:
    a = np.asarray(v, float)
    return {"median": float(np.median(a)), "p99": float(np.percentile(a, 99)), "max": float(a.max())}


def frame_to_field(frames: list[DepthFrame], cfg: PerceptionConfig, robot: Any) -> dict[str, Any]:
    m = DepthMap(cfg, robot)
    m.record(0.0, robot.q_home)
    m.update(frames[0])  # compile / load the kernels
    total, integrate, field, cpu = [], [], [], []
    for f in frames[1:]:
        c0 = time.thread_time()
        t0 = time.perf_counter()
        rep = m.integrate(f)
        t1 = time.perf_counter()
        snap = m.snapshot(started=t0)
        t2 = time.perf_counter()
        cpu.append((time.thread_time() - c0) * 1e3)
        total.append((t2 - t0) * 1e3)
        integrate.append((t1 - t0) * 1e3)
        field.append((t2 - t1) * 1e3)
    return {"grid": list(m.grid.shape), "voxel_m": cfg.voxel, "total_ms": _stats(total), "cpu_ms": _stats(cpu),
            "integrate_ms": _stats(integrate), "field_ms": _stats(field), "occupied": list(snap.occupied),
            "counts": rep.counts, "build_ms_reported": snap.build_ms}


def transforms(m: DepthMap, reps: int) -> dict[str, Any]:
    occ = m._occupied[1] | m._occupied[0]
    work = np.empty((2, *occ.shape), np.float32)
    dist = np.empty(occ.shape, np.float32)
    fns = {"qpctl numba (windowed)": lambda: KE.distance_field(occ, m.grid.voxel, m.config.truncation, work, dist),
           "scipy distance_transform_edt": lambda: ndimage.distance_transform_edt(~occ)}
    try:
        import edt  # type: ignore[import-not-found]

        fns["edt package"] = lambda: edt.edt(~occ, parallel=1)
    except ImportError:
        pass
    for f in fns.values():
        f()
    times: dict[str, list[float]] = {k: [] for k in fns}
    cpu: dict[str, list[float]] = {k: [] for k in fns}
    for r in range(reps):
        order = list(fns)[r % len(fns):] + list(fns)[:r % len(fns)]
        for k in order:
            c0 = time.thread_time()
            t0 = time.perf_counter()
            fns[k]()
            times[k].append((time.perf_counter() - t0) * 1e3)
            cpu[k].append((time.thread_time() - c0) * 1e3)
    return {"grid": list(occ.shape), "occupied": int(occ.sum()), "ms": {k: _stats(v) for k, v in times.items()},
            "cpu_ms": {k: _stats(v) for k, v in cpu.items()}}


@njit(cache=True)
def _repeat_separate(reps: int, states: np.ndarray, vels: np.ndarray, radii: np.ndarray, dist: np.ndarray,
                     grad: np.ndarray, origin: np.ndarray, voxel: float, trunc: float, samples: int, rows: int,
                     vs: float, gain: float, vmargin: float, cutoff: float, ds: np.ndarray, out_d: np.ndarray,
                     out_n: np.ndarray, out_p: np.ndarray, out_s: np.ndarray, vp: np.ndarray, vu: np.ndarray,
                     vb: np.ndarray, vd: np.ndarray) -> None:
    """The tick's field lookups the separate way (the tick's before the one-pass kernel), ``reps`` times
    over the ``states`` (K, L, 2, 3) with body velocities ``vels`` (K, L, 6): both channels' field_pairs,
    then the soft channel's speed_points, inside compiled code."""
    k = out_d.shape[0] // 2
    for i in range(reps * states.shape[0]):
        segs, vel = states[i % states.shape[0]], vels[i % states.shape[0]]
        for ch in range(2):
            KF.field_pairs(segs, radii, dist[ch], grad[ch], origin, voxel, trunc, samples, rows, True, ds,
                           out_d[ch * k:(ch + 1) * k], out_n[ch * k:(ch + 1) * k], out_p[ch * k:(ch + 1) * k],
                           out_s[ch * k:(ch + 1) * k])
        KF.speed_points(segs, radii, dist[1], origin, voxel, trunc, samples, vel, vs, gain, vmargin, cutoff, ds,
                        vp, vu, vb, vd)


@njit(cache=True)
def _repeat_one_pass(reps: int, states: np.ndarray, vels: np.ndarray, radii: np.ndarray, dist: np.ndarray,
                     pairs: np.ndarray, grad: np.ndarray, origin: np.ndarray, voxel: float, trunc: float, samples: int, rows: int,
                     vs: float, gain: float, vmargin: float, cutoff: float, ds2: np.ndarray, out_d: np.ndarray,
                     out_n: np.ndarray, out_p: np.ndarray, out_s: np.ndarray, vp: np.ndarray, vu: np.ndarray,
                     vb: np.ndarray, vd: np.ndarray) -> None:
    """The same lookups as the tick makes them: field_samples (one pass, both channels)."""
    for i in range(reps * states.shape[0]):
        segs, vel = states[i % states.shape[0]], vels[i % states.shape[0]]
        KS.field_samples(segs, radii, dist, pairs, grad, origin, voxel, trunc, samples, rows, True, vel, vs, gain, vmargin,
                         cutoff, ds2, out_d, out_n, out_p, out_s, vp, vu, vb, vd)


def field_queries(m: DepthMap, robot: Any, reps: int, states: int = 16) -> dict[str, Any]:
    """The tick's field lookups (both channels' pairs and the soft speed points) on the canopy's map for
    ``states`` seeded states about the home pose (q ± 0.08 rad, q̇ in ±0.6 rad/s): the one-pass kernel
    (what the tick calls) and the separate kernels (what it called before), in alternating blocks of
    about 100 calls inside compiled code (each block cycling through the states; which way goes first
    alternating), wall and thread CPU time per call; the two ways' outputs checked equal first."""
    from qpctl.law import LawGains
    from qpctl.perception.rows import FieldBarrier

    snap = m.snapshot()
    cfg = m.config
    gains = LawGains()
    bar = FieldBarrier(_Snapshot(snap), robot, cfg, d_safe=gains.d_safe, cutoff=gains.d_influence)
    rng = np.random.default_rng(21)
    qs = [robot.q_home] + [robot.q_home + rng.normal(0.0, 0.08, robot.nv) for _ in range(states - 1)]
    segs = np.array([bar.segments(q) for q in qs])
    vels = np.array([bar.body_velocities(q, rng.uniform(-0.6, 0.6, robot.nv)) for q in qs])
    radii = bar.radii
    L, S, R = len(radii), cfg.samples, cfg.rows_per_link
    grid = (snap.grid.origin, snap.grid.voxel, snap.truncation, S, R)
    speed = (cfg.soft_speed, bar.funnel, bar.speed_margin, bar.cutoff)

    def outs() -> tuple[np.ndarray, ...]:
        return (np.empty(2 * L * R), np.empty((2 * L * R, 3)), np.empty((2 * L * R, 3)), np.empty(2 * L * R),
                np.empty((2 * L, 3)), np.empty((2 * L, 3)), np.empty(2 * L), np.empty(2 * L))

    o_sep, o_one = outs(), outs()
    ways = {"one pass (the tick)": (_repeat_one_pass, (snap.dist, snap.pairs, snap.grad), (np.empty((2, S)), *o_one)),
            "separate kernels": (_repeat_separate, (snap.dist, snap.grad), (np.empty(S), *o_sep))}
    active = speed_rows = 0
    for i in range(states):
        for rep, grids, extra in ways.values():
            rep(1, segs[i:i + 1], vels[i:i + 1], radii, *grids, *grid, *speed, *extra)
        for a, b in zip(o_sep, o_one, strict=True):
            if not np.array_equal(a, b):
                raise AssertionError("the one-pass field lookups differ from the separate kernels'")
        active += int(np.sum((o_one[0] < bar.cutoff) & np.any(o_one[1] != 0.0, axis=1)))
        speed_rows += int(np.sum(np.isfinite(o_one[6])))
    per = max(100 // states, 1)  # calls per block: per × states
    wall: dict[str, list[float]] = {k: [] for k in ways}
    cpu: dict[str, list[float]] = {k: [] for k in ways}
    for r in range(max(reps // (per * states), 5)):
        for k in list(ways)[:: 1 if r % 2 else -1]:
            rep, grids, extra = ways[k]
            c0 = time.thread_time()
            t0 = time.perf_counter()
            rep(per, segs, vels, radii, *grids, *grid, *speed, *extra)
            wall[k].append((time.perf_counter() - t0) * 1e6 / (per * states))
            cpu[k].append((time.thread_time() - c0) * 1e6 / (per * states))
    one = (snap.dist, snap.pairs, snap.grad, *grid, True, vels[0], *speed, *ways["one pass (the tick)"][2])
    KS.field_samples(segs[0], radii, *one)
    us = []
    for i in range(reps):  # called from Python, the dispatch included
        sg = segs[i % states]
        t0 = time.perf_counter()
        KS.field_samples(sg, radii, *one)
        us.append((time.perf_counter() - t0) * 1e6)
    st = {k: _stats(v) for k, v in wall.items()}
    return {"links": L, "samples": S, "rows_per_link": R, "channels": 2, "states": states, "block": per * states,
            "blocks": len(wall["separate kernels"]),
            "us": st["one pass (the tick)"], "cpu_us": _stats(cpu["one pass (the tick)"]),
            "us_separate": st["separate kernels"], "cpu_us_separate": _stats(cpu["separate kernels"]),
            "median_ratio": st["separate kernels"]["median"] / st["one pass (the tick)"]["median"],
            "us_from_python": _stats(us), "active_pairs_per_state": active / states,
            "speed_rows_per_state": speed_rows / states}


def tick_beside_worker(frames: list[DepthFrame], robot: Any, stretches: int, seconds: float) -> dict[str, Any]:
    """The QP tick's wall time, alternating stretches with the worker idle and fed at 30 Hz."""
    from qpctl import Scenario, simulate

    scen = Scenario.load("panda_spheres")
    run = simulate(scen, kind="qp")
    traj = run.trajectory
    ctrl = scen.build_controller("qp")
    ctrl.warmup()
    m = DepthMap(BOX_2CM, robot)
    m.record(0.0, robot.q_home)
    worker = MapWorker(m).start()
    feeding = threading.Event()
    stop = threading.Event()

    def feed() -> None:
        k = 0
        next_t = time.perf_counter()
        while not stop.is_set():
            if feeding.is_set():
                f = frames[k % len(frames)]
                worker.submit(DepthFrame(f.depth, f.intrinsics, f.pose, 1000.0 + k / 30.0, labels=f.labels))
                k += 1
            next_t += 1 / 30.0
            time.sleep(max(0.0, next_t - time.perf_counter()))

    feeder = threading.Thread(target=feed, daemon=True)
    feeder.start()
    times: dict[str, list[float]] = {"worker idle": [], "worker at 30 Hz": []}
    T = len(traj.t)
    k = 0
    try:
        for s in range(2 * stretches):
            on = s % 2 == 1
            (feeding.set if on else feeding.clear)()
            if not on:
                worker.wait_idle()
            end = time.perf_counter() + seconds
            label = "worker at 30 Hz" if on else "worker idle"
            while time.perf_counter() < end:
                i = k % T
                t0 = time.perf_counter()
                ctrl.torque(traj.q[i], traj.v[i], float(traj.t[i]))
                times[label].append((time.perf_counter() - t0) * 1e6)
                k += 1
                if i == T - 1:
                    ctrl.reset()
    finally:
        stop.set()
        feeder.join()
        worker.stop()
    out = {k: _stats(v) for k, v in times.items()}
    return {"ticks": {k: len(v) for k, v in times.items()}, "us": out, "frames_built": worker.built,
            "frames_dropped": worker.dropped,
            "p99_ratio": out["worker at 30 Hz"]["p99"] / out["worker idle"]["p99"],
            "median_ratio": out["worker at 30 Hz"]["median"] / out["worker idle"]["median"]}


class _Snapshot:
    """A fixed map for a controller's field rows (what a Perception hands it)."""

    def __init__(self, snapshot: Any) -> None:
        self.snapshot = snapshot


def tick_with_field(reps: int) -> dict[str, Any]:
    """The Panda's compiled QP tick on the states of a ``panda_spheres`` run (its 10 sphere primitives),
    without and with the field's rows, interleaved state by state (the order alternating): the map is
    a cloud of 2,000 points on each of the scene's spheres (2 cm voxels over the box the run reaches,
    so that the rows are active where the primitives' are), the states those of the closed loop with
    both (so that the QP stays feasible for both); wall time of
    ``step`` [µs] and the field rows active per tick."""
    from qpctl import Scenario
    from qpctl.perception import PointCloud
    from qpctl.perception.rows import FieldBarrier
    from qpctl.perception.synthetic import sphere_surface_points
    from qpctl.simulation.simulator import Simulator

    scen = Scenario.load("panda_spheres")
    cfg = PerceptionConfig(voxel=0.02, bounds_min=[-0.8, -0.8, -0.1], bounds_max=[0.8, 0.8, 1.2], truncation=0.3,
                           depth_noise=0.0)
    m = DepthMap(cfg)
    m.integrate(PointCloud(sphere_surface_points(scen.build_obstacles()), 0.0))
    plain, field = scen.build_controller("qp"), scen.build_controller("qp")
    bar = FieldBarrier(_Snapshot(m.snapshot()), field.robot, cfg, d_safe=field.gains.d_safe, cutoff=field.cutoff,
                       k0=field.config.barrier_k0, k1=field.config.barrier_k1)
    field.add_constraint(bar)
    assert field.workspace().spec is not None and field.workspace().spec.field is not None  # compiled
    # the states: the closed loop with both the primitives' and the field's rows (feasible for both)
    traj = Simulator(field, dt=1e-3, duration=float(scen.data["sim"]["duration"]), obstacles=scen.build_obstacles()
                     ).run(scen.q0(field.robot))
    plain.warmup()
    field.warmup()
    times: dict[str, list[float]] = {"primitives only": [], "primitives + field": []}
    active: list[int] = []
    fallbacks = 0
    T = len(traj.t)
    for k in range(reps):
        i = k % T
        q, v, t = traj.q[i], traj.v[i], float(traj.t[i])
        if i == 0:
            plain.reset()
            field.reset()
        for ctrl, label in ((plain, "primitives only"), (field, "primitives + field"))[:: 1 if k % 2 else -1]:
            t0 = time.perf_counter()
            out = ctrl.step(q, v, t)
            times[label].append((time.perf_counter() - t0) * 1e6)
            if ctrl is field:
                active.append(int(bar.last.active.sum()) if bar.last is not None else 0)
                fallbacks += "fallback" in out.info
    st = {k: _stats(v) for k, v in times.items()}
    return {"ticks": reps, "us": st, "field_rows": bar.rows, "active_rows_median": float(np.median(active)),
            "ticks_with_field_rows": float(np.mean(np.asarray(active) > 0)), "fallbacks": fallbacks,
            "median_ratio": st["primitives + field"]["median"] / st["primitives only"]["median"]}


def tau_dot(duration: float, out: Path) -> dict[str, Any]:
    """|τ̇| on ``panda_canopy_depth`` (seed 1, noise on) over ``duration`` [s] with the smooth rows (the
    parabola-refined witness point, the interpolated gradient grid) and with the raw ones (the best
    sample's point, the trilinear interpolant's own gradient, which jumps at every voxel face), both on
    the Python path; |τ̇| = max over joints of |Δτ|/dt [N·m/s], its median, p99 and max over the run,
    the ticks at the drives' rate limit, and a figure (``tau_dot.png``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    import qpctl.perception.rows as rows_module
    from qpctl import Scenario
    from qpctl.run import simulate

    original = rows_module.FieldBarrier
    res: dict[str, Any] = {}
    fig, ax = plt.subplots(figsize=(9, 3.6))
    try:
        for smooth in (True, False):
            class Rows(original):  # type: ignore[misc, valid-type]
                field_spec = None  # the Python path for both

                def __init__(self, *a: Any, smooth: bool = smooth, **k: Any) -> None:
                    super().__init__(*a, smooth=smooth, **k)

            rows_module.FieldBarrier = Rows  # type: ignore[misc]
            scen = Scenario.load("panda_canopy_depth", overrides=[f"sim.duration={duration}"])
            run = simulate(scen)
            tr = run.trajectory
            rate = np.abs(np.diff(tr.tau, axis=0)).max(axis=1) / np.diff(tr.t)
            lim = float(np.min(run.controller.robot.tau_rate_max))
            name = "smooth" if smooth else "raw"
            res[name] = {"median": float(np.median(rate)), "p99": float(np.percentile(rate, 99)),
                         "max": float(rate.max()), "at_rate_limit": int(np.sum(rate >= 0.999 * lim)),
                         "ticks": int(rate.size), "min_clearance": float(run.metrics["min_clearance"]),
                         "fallbacks": int(sum(v for k, v in run.metrics.get("qp_status_counts", {}).items()
                                              if k != "solved"))}
            ax.plot(tr.t[1:], rate, lw=0.7, label=f"{name} rows (p99 {res[name]['p99']:.0f} N·m/s)", alpha=0.8)
    finally:
        rows_module.FieldBarrier = original  # type: ignore[misc]
    ax.axhline(lim, color="k", ls="--", lw=0.8, label="the drives' rate limit")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("max over joints |τ̇| [N·m/s]")
    ax.set_yscale("log")
    ax.legend(loc="lower right", fontsize=8)
    ax.set_title(f"panda_canopy_depth, seed 1, {duration:g} s: the field's rows smooth and raw")
    fig.tight_layout()
    out.mkdir(parents=True, exist_ok=True)
    fig.savefig(out / "tau_dot.png", dpi=110)
    plt.close(fig)
    res["rate_limit"] = lim
    return res


CLOSED_LOOP_KEYS = ("collided", "min_clearance", "min_soft_clearance", "soft_contact_max_speed",
                    "soft_contact_max_approach_speed", "map_min_clearance", "map_age_ms_max", "map_update_cpu_ms_median",
                    "map_update_cpu_ms_p99", "map_latency_ms_p99", "phantom_rows", "phantom_rows_checked",
                    "stale_stop_ticks", "tick_us_median", "fruit_errors_mm", "lag_ticks", "lag_max_m", "path_end_s",
                    "path_extra_s", "fruits_picked", "fruit_misses")


def closed_loop(seed: int, duration: float | None = None, overrides: tuple[str, ...] = ()) -> dict[str, Any]:
    """``panda_canopy_depth`` under one canopy seed (seed 1 is the packaged scenario), noise on, with the
    scenario ``overrides`` (``--set``'s KEY=VALUE): the closed-loop metrics of issue 21's targets, and the
    canopy's unreachable fruits with their reasons."""
    from qpctl import Scenario
    from qpctl.run import simulate

    extra = [f"sim.duration={duration}"] if duration else []
    scen = Scenario.load("panda_canopy_depth", overrides=[f"canopy.seed={seed}", *extra, *overrides])
    t0 = time.perf_counter()
    m = simulate(scen).metrics
    row = {"seed": seed, "wall_s": time.perf_counter() - t0, "d_safe": float(scen.data["controller"]["d_safe"]),
           "voxel": scen.perception_config().voxel, "soft_speed": scen.perception_config().soft_speed,
           "duration_s": float(scen.data["sim"]["duration"]), "overrides": list(overrides)}
    row.update({k: m.get(k) for k in CLOSED_LOOP_KEYS})
    canopy = m.get("canopy", {})
    row["unreachable"] = [f.get("reason", "") for f in canopy.get("fruits", []) if not f.get("reachable", True)]
    print(json.dumps(row, default=str), flush=True)
    return row


def closed_loops(seeds: list[int], duration: float | None = None, jobs: int = 1,
                 overrides: tuple[str, ...] = ()) -> list[dict[str, Any]]:
    """:func:`closed_loop` on each seed, in seed order, on the sweep engine's local backend (``jobs``
    processes; 1: one after another in this process). A map's costs then share the cores; its latency
    is fixed."""
    return map_ordered(closed_loop, [(seed, duration, tuple(overrides)) for seed in seeds], LocalBackend(jobs),
                       desc="canopies")


def closed_loop_markdown(rows: list[dict[str, Any]]) -> str:
    lines = [("| seed | collided | min clearance [m] | ≥ d_safe − voxel | min soft clearance [m] | soft contact speed "
             "[m/s] (into the leaf) | fruits within 5 mm | path end [s] (extra) | map p99 [ms CPU] | stamp → rows p99 [ms] | "
             "phantom rows |"),
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        errs = r["fruit_errors_mm"] or []
        ok = r["min_clearance"] >= r["d_safe"] - r["voxel"]
        end = r.get("path_end_s")
        ends = "not reached" if end is None or not math.isfinite(end) else f"{end:.1f} (+{r['path_extra_s']:.1f})"
        lines.append(f"| {r['seed']} | {r['collided']} | {r['min_clearance']:.3f} | {'yes' if ok else 'NO'} | "
                     f"{r['min_soft_clearance']:.3f} | {r['soft_contact_max_speed']:.2f} "
                     f"({r['soft_contact_max_approach_speed']:.2f}) | {sum(e <= 5.0 for e in errs)} of {len(errs)} | {ends} | "
                     f"{r['map_update_cpu_ms_p99']:.1f} | {r['map_latency_ms_p99']:.1f} | "
                     f"{r['phantom_rows']} of {r['phantom_rows_checked']} |")
    misses = [(r["seed"], f) for r in rows for f in (r.get("fruit_misses") or [])]
    if misses:
        causes = Counter(f["cause"] for _, f in misses)
        lines += ["", f"The {len(misses)} fruits missed by more than 5 mm, by cause: "
                  + ", ".join(f"{c} {n}" for c, n in causes.most_common()) + " (qpctl.perception.misses):", ""]
        lines += [f"* seed {seed}, fruit {f['fruit'] + 1} ({f['error_mm']:.0f} mm at {f['t_s']:.1f} s): {f['reason']}"
                  for seed, f in misses]
    return "\n".join(lines) + "\n"


def markdown(res: dict[str, Any]) -> str:
    lines = [(f"Machine: {res['machine']}; load before: {res['load_before']}, after: {res['load_after']}; "
              f"its speed, `pin.computeAllTerms` on the Panda (`qpctl bench`'s floor): {res['floor_us_before']:.2f} µs "
              f"before, {res['floor_us_after']:.2f} µs after."), ""]
    lines += [("| frame → field (640×480) | grid | wall median [ms] | wall p99 [ms] | CPU median [ms] | CPU p99 [ms] "
              "| integrate median [ms] | field median [ms] |"), "|---|---|---|---|---|---|---|---|"]
    for name, r in res["frame_to_field"].items():
        lines.append(f"| {name} | {'×'.join(map(str, r['grid']))} | {r['total_ms']['median']:.1f} | "
                     f"{r['total_ms']['p99']:.1f} | {r['cpu_ms']['median']:.1f} | {r['cpu_ms']['p99']:.1f} | "
                     f"{r['integrate_ms']['median']:.1f} | {r['field_ms']['median']:.1f} |")
    tr = res["transforms"]
    lines += ["", (f"| distance transform ({'×'.join(map(str, tr['grid']))}, {tr['occupied']} occupied) | wall median [ms] "
              "| wall p99 [ms] | CPU median [ms] |"), "|---|---|---|---|"]
    lines += [f"| {k} | {v['median']:.2f} | {v['p99']:.2f} | {tr['cpu_ms'][k]['median']:.2f} |"
              for k, v in tr["ms"].items()]
    fq = res["field_queries"]
    lines += ["", (f"Field queries: {fq['links']} links × {fq['samples']} samples × {fq['channels']} channels, "
              f"{fq['rows_per_link']} rows per link, and the soft speed points, inside compiled code as the tick "
              f"calls them, {fq['states']} states, blocks of {fq['block']} calls alternating: one pass median "
              f"{fq['us']['median']:.2f} µs wall (CPU {fq['cpu_us']['median']:.2f} µs), p99 {fq['us']['p99']:.2f} µs; "
              f"the separate kernels median {fq['us_separate']['median']:.2f} µs (CPU "
              f"{fq['cpu_us_separate']['median']:.2f} µs), p99 {fq['us_separate']['p99']:.2f} µs; ratio "
              f"{fq['median_ratio']:.2f} (called from Python: median {fq['us_from_python']['median']:.2f} µs, the "
              f"call's dispatch included).")]
    if "tick_with_field" in res:
        tf = res["tick_with_field"]
        lines += ["", f"| Panda compiled QP tick, {tf['ticks']} panda_spheres states, interleaved | median [µs] | p99 [µs] |",
                  "|---|---|---|"]
        lines += [f"| {k} | {v['median']:.1f} | {v['p99']:.1f} |" for k, v in tf["us"].items()]
        lines += ["", (f"Median ratio {tf['median_ratio']:.2f}; {tf['field_rows']} field rows, a median of "
                  f"{tf['active_rows_median']:.0f} active ({100 * tf['ticks_with_field_rows']:.0f} % of ticks with one); "
                  f"{tf['fallbacks']} fallbacks.")]
    if "tick_beside_worker" in res:
        tb = res["tick_beside_worker"]
        lines += ["", "| Panda QP tick (panda_spheres run) | ticks | median [µs] | p99 [µs] |", "|---|---|---|---|"]
        lines += [f"| {k} | {tb['ticks'][k]} | {v['median']:.1f} | {v['p99']:.1f} |" for k, v in tb["us"].items()]
        lines += ["", (f"p99 ratio {tb['p99_ratio']:.2f}, median ratio {tb['median_ratio']:.2f}; "
                  f"{tb['frames_built']} frames built, {tb['frames_dropped']} dropped.")]
    return "\n".join(lines) + "\n"


def markdown_tick(res: dict[str, Any]) -> str:
    tf = res["tick_with_field"]
    return json.dumps(tf, indent=1)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer frames and shorter stretches")
    ap.add_argument("--out", default="results/perception")
    ap.add_argument("--canopies", type=int, default=0,
                    help="instead: closed loops on panda_canopy_depth under canopy seeds 1..N")
    ap.add_argument("--tau-dot", type=float, default=0.0, help="instead: |τ̇| with smooth and raw rows over S seconds")
    ap.add_argument("--only-tick", action="store_true", help="only the frames' map and the tick with the field")
    ap.add_argument("--duration", type=float, default=None, help="with --canopies: simulated seconds")
    ap.add_argument("--jobs", type=int, default=1, help="with --canopies: runs at once (processes)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="with --canopies: a scenario override for every canopy (repeatable, as qpctl simulate --set)")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.canopies:
        load = " ".join(f"{x:.2f}" for x in os.getloadavg())
        rows = closed_loops(list(range(1, args.canopies + 1)), args.duration, args.jobs, tuple(args.set))
        (out / "canopies.json").write_text(json.dumps(rows, indent=2, default=str))
        md = (f"Load before: {load}, after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}; {args.jobs} job(s); "
              f"{rows[0]['duration_s']:g} s each"
              + (f"; overrides {' '.join(args.set)}" if args.set else "") + ".\n\n" + closed_loop_markdown(rows))
        (out / "canopies.md").write_text(md)
        print(md)
        return {"canopies": rows}
    robot = panda()
    n = 12 if args.quick else 61
    res: dict[str, Any] = {"machine": f"{os.cpu_count()} cores, {os.uname().machine}",
                           "load_before": " ".join(f"{x:.2f}" for x in os.getloadavg()),
                           "floor_us_before": floor_us(robot)}
    if args.tau_dot:
        res["tau_dot"] = tau_dot(args.tau_dot, out)
        (out / "tau_dot.json").write_text(json.dumps(res["tau_dot"], indent=1))
        print(json.dumps(res["tau_dot"], indent=1))
        return res
    if args.only_tick:
        res["tick_with_field"] = tick_with_field(20000)
        print(markdown_tick(res))
        return res
    frames = record_frames(out / "frames.npz", n)
    unlabelled = [DepthFrame(f.depth, f.intrinsics, f.pose, f.stamp) for f in frames]  # a camera without a segmenter
    res["frame_to_field"] = {"2 cm, 1.6×1.2×1.0 m": frame_to_field(frames, BOX_2CM, robot),
                             "2 cm, unlabelled (no segmenter)": frame_to_field(unlabelled, BOX_2CM, robot),
                             "1 cm, 0.4 m about the hand": frame_to_field(frames, hand_box(robot), robot)}
    m = DepthMap(BOX_2CM, robot)
    m.record(0.0, robot.q_home)
    for f in frames[:3]:
        m.update(f)
    res["transforms"] = transforms(m, 5 if args.quick else 21)
    res["field_queries"] = field_queries(m, robot, 2000 if args.quick else 20000)
    res["tick_with_field"] = tick_with_field(2000 if args.quick else 20000)
    res["tick_beside_worker"] = tick_beside_worker(frames, robot, 2 if args.quick else 4, 1.0 if args.quick else 3.0)
    res["load_after"] = " ".join(f"{x:.2f}" for x in os.getloadavg())
    res["floor_us_after"] = floor_us(robot)
    (out / "perception.json").write_text(json.dumps(res, indent=2))
    md = markdown(res)
    (out / "perception.md").write_text(md)
    print(md)
    return res


if __name__ == "__main__":
    main()
