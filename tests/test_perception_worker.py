"""Off the loop: the map worker's thread, its snapshots, the stale-map policy and the time-scaled
reference (qpctl.perception.worker, .stale, .perception; issue 21, item 3)."""

from __future__ import annotations

import itertools
import threading

import numpy as np
import pytest
from depth_scenes import Sphere, look_at, render

from qpctl.errors import PerceptionError
from qpctl.paths import WaypointPath
from qpctl.perception import MapWorker, Perception, PerceptionConfig, PointCloud, StalePolicy, TimeScaledPath
from qpctl.perception.depth_map import DepthMap
from qpctl.perception.stale import OK, SLOW, STOP

CFG = PerceptionConfig(voxel=0.02, bounds_min=[-0.2, -0.4, 0.0], bounds_max=[0.6, 0.4, 0.8], truncation=0.2,
                       decay=0.01)


def _point(k: int) -> np.ndarray:
    return np.array([0.0 + 0.02 * (k % 25), 0.0, 0.4])


def test_the_reader_only_ever_sees_whole_snapshots() -> None:
    """Frame k holds one point p_k, and the decay forgets the previous ones: every snapshot the
    reader thread catches must have its field's zero at the p_k of its own stamp."""
    worker = MapWorker(DepthMap(CFG)).start()
    seen: list[tuple[float, int]] = []
    stop = threading.Event()
    bad: list[str] = []

    def read() -> None:
        last = None
        while not stop.is_set():
            snap = worker.latest
            if snap is last or snap.frames == 0:
                continue
            last = snap
            k = round(snap.stamp / 0.05)
            i = np.unravel_index(int(np.argmin(snap.dist[0])), snap.dist[0].shape)
            centre = snap.grid.centres(np.array([i]))[0]
            if snap.occupied != (1, 0) or np.linalg.norm(centre - _point(k)) > 0.02 or snap.dist.flags.writeable:
                bad.append(f"stamp {snap.stamp}: {snap.occupied}, zero at {centre}")
            seen.append((snap.stamp, snap.frames))

    reader = threading.Thread(target=read)
    reader.start()
    try:
        for k in range(60):
            worker.submit(PointCloud([_point(k)], 0.05 * k))
            if k % 3 == 0:
                worker.wait_idle()
        assert worker.wait_idle()
    finally:
        stop.set()
        reader.join()
        worker.stop()
    assert not bad
    assert len(seen) >= 10
    assert all(b[0] >= a[0] and b[1] > a[1] for a, b in itertools.pairwise(seen))
    assert worker.built + worker.dropped == 60
    assert worker.latest.stamp == pytest.approx(0.05 * 59)


def test_a_frame_waiting_in_the_mailbox_is_replaced_and_counted() -> None:
    worker = MapWorker(DepthMap(CFG))
    with worker:
        frames = [render(look_at([-0.6, 0, 0.4], [0.3, 0, 0.4]), [Sphere((0.25, 0.0, 0.4), 0.08)], stamp=0.01 * k)
                  for k in range(8)]
        for f in frames:
            worker.submit(f)  # faster than it builds
        assert worker.wait_idle()
    assert worker.dropped > 0 and worker.built + worker.dropped == 8
    assert worker.latest.stamp == frames[-1].stamp


def test_an_error_in_the_worker_reaches_the_submitter() -> None:
    worker = MapWorker(DepthMap(CFG)).start()
    try:
        worker.submit(PointCloud([_point(0)], 1.0))
        worker.wait_idle()
        worker.submit(PointCloud([_point(0)], 0.5))  # backwards
        worker.wait_idle()
        with pytest.raises(PerceptionError, match="backwards"):
            worker.submit(PointCloud([_point(0)], 2.0))
    finally:
        worker.stop()
    with pytest.raises(PerceptionError, match="not running"):
        MapWorker(DepthMap(CFG)).submit(PointCloud([_point(0)], 0.0))


def test_perception_threaded_and_inline_build_the_same_map() -> None:
    pose = look_at([-0.6, 0, 0.4], [0.3, 0, 0.4])
    frame = render(pose, [Sphere((0.25, 0.0, 0.4), 0.08)], stamp=0.2)
    inline = Perception(CFG)
    assert inline.snapshot.stamp == -np.inf and Perception(CFG).staleness(0.0).mode == STOP  # no map yet
    inline.update_map(frame.depth, frame.intrinsics, frame.pose, frame.stamp)
    with Perception(CFG, threaded=True) as threaded:
        threaded.update_map(frame.depth, frame.intrinsics, frame.pose, frame.stamp)
        assert threaded.worker is not None and threaded.worker.wait_idle()
        assert np.array_equal(threaded.snapshot.dist, inline.snapshot.dist)
        assert len(threaded.build_ms) == len(inline.build_ms) == 1
    assert inline.staleness(0.25).mode == OK


def test_stale_policy_slows_then_stops_and_resumes_smoothly() -> None:
    p = StalePolicy(0.1, 0.3)
    assert p.target(0.05) == 1.0 and p.target(0.2) == pytest.approx(0.5) and p.target(0.4) == 0.0
    dt = 0.001
    kappas, modes = [], []
    for k in range(600):
        t = k * dt
        age = t if t < 0.45 else t - 0.45  # the map stops at t = 0, a fresh one arrives at t = 0.45
        v = p(t, age)
        kappas.append(v.kappa)
        modes.append(v.mode)
    kap = np.array(kappas)
    assert np.all(np.abs(np.diff(kap)) <= p.rate * dt + 1e-12)  # never jumps
    assert kap[50] == 1.0 and kap[200] == pytest.approx(0.5, abs=1e-9) and kap[350] == 0.0
    assert modes[50] == OK and modes[200] == SLOW and modes[350] == STOP
    # after the fresh map, κ climbs back at the rate limit, SLOW until it reaches 1
    assert modes[460] == SLOW and kap[460] == pytest.approx(11 * dt * p.rate, abs=1e-9)
    with pytest.raises(ValueError):
        StalePolicy(0.3, 0.1)


def test_time_scaled_reference_is_the_path_at_the_scaled_clock() -> None:
    path = WaypointPath([[0.0, 0.0, 0.0], [0.3, 0.1, -0.2]], duration=1.0)
    ts = TimeScaledPath(path)
    dt = 1e-4
    t = 0.0
    xs, xds, refs = [], [], []
    for k in range(8000):
        t = k * dt
        kappa = 1.0 if t < 0.2 else max(0.0, 1.0 - (t - 0.2) / 0.4)  # slows to a halt by t = 0.6
        ts.advance(t, kappa)
        r = ts(t)
        xs.append(r.x)
        xds.append(r.xd)
        refs.append(r)
    xs, xds = np.array(xs), np.array(xds)
    # ẋ_d and ẍ_d are the derivatives of what it returns (finite differences over the scaled clock)
    assert np.allclose(np.gradient(xs, dt, axis=0)[1:-1], xds[1:-1], atol=1e-3)
    xdd = np.array([r.xdd for r in refs])
    fd = np.gradient(xds, dt, axis=0)
    smooth = np.ones(len(xdd), bool)  # but where κ̇ itself jumps (t = 0.2 s, 0.6 s) and the ends
    for k in (0, 2000, 6000, len(xdd) - 1):
        smooth[max(k - 3, 0):k + 4] = False
    assert np.abs(fd[smooth] - xdd[smooth]).max() < 1e-2 * np.abs(xdd).max()
    # it halts part-way along: s = 0.2 + ∫ κ = 0.2 + 0.2 = 0.4, and the reference then holds still
    assert ts.s == pytest.approx(0.4, abs=1e-3)
    assert np.allclose(xs[-1], path(ts.s).x, atol=1e-12) and not np.any(xds[-1])
    assert ts.dim == path.dim


def test_time_scaled_position_and_orientation_drop_a_non_finite_rate_alike() -> None:
    """Where κ̇ is not finite (a jump of κ over a vanishing step) the acceleration is κ² x'' alone —
    for the position and the orientation alike, as the compiled tick's reference does — compared with
    the wrapped pose path read directly at the scaled clock."""
    from qpctl.paths import PosePath

    Rz = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    path = PosePath([[0.0, 0.0, 0.0], [0.3, 0.1, -0.2]], [np.eye(3), Rz], duration=1.0)
    ts = TimeScaledPath(path)
    ts.advance(0.4, 0.5)
    ts.kappa_rate = float("inf")
    t = 0.45
    s = ts.time_at(t)
    ref, (R, w, wd) = path(s), path.orientation(s)
    got, (gR, gw, gwd) = ts(t), ts.orientation(t)
    assert np.all(np.isfinite(got.xdd)) and np.all(np.isfinite(gwd))
    assert np.allclose(got.xdd, 0.25 * ref.xdd, atol=1e-15) and np.allclose(got.xd, 0.5 * ref.xd, atol=1e-15)
    assert np.allclose(gwd, 0.25 * wd, atol=1e-15) and np.allclose(gw, 0.5 * w, atol=1e-15)
    assert np.array_equal(gR, R) and np.any(wd != 0.0)


def test_the_compiled_tick_evaluates_a_time_scaled_waypoint_path() -> None:
    """A TimeScaledPath over a WaypointPath stays in the one-call kernel (the clock bound to the
    workspace, written by every advance): the record's x_d, ẋ_d, ẍ_d at each tick equal the path's own
    Python evaluation at that tick (1e-12), while κ slows, halts and resumes; and the torques equal those
    of the same controller whose path is evaluated in Python each tick (the same clock through a wrapper
    the kernel cannot read), to 1e-9."""
    from qpctl import Scenario

    scen = Scenario.load("panda_spheres", ["sim.duration=1.0"])

    def build(wrap):
        ctrl = scen.build_controller("qp", "daqp")
        scaled = TimeScaledPath(wrap(ctrl.path))
        ctrl.path = scaled
        ctrl._ws = None  # rebuilt on the next tick with the new path (as perception.attach does)
        return ctrl, scaled

    compiled, ts_c = build(lambda p: p)
    python, ts_p = build(lambda p: (lambda t: p(t)))
    assert ts_c.compiled and not ts_p.compiled
    q, v = scen.q0(compiled.robot), np.zeros(compiled.robot.nv)
    dt = 1e-3
    for k in range(600):
        t = k * dt
        kappa = 1.0 if t < 0.1 else (0.0 if t < 0.25 else min(1.0, 0.5 + (t - 0.25)))  # slows, halts, resumes
        for ts in (ts_c, ts_p):
            ts.advance(t, kappa)
        out_c, out_p = compiled.step(q, v, t), python.step(q, v, t)
        ref = ts_p(t)
        np.testing.assert_allclose(out_c.ref.x, ref.x, rtol=0, atol=1e-12)
        np.testing.assert_allclose(out_c.ref.xd, ref.xd, rtol=0, atol=1e-12)
        np.testing.assert_allclose(out_c.ref.xdd, ref.xdd, rtol=0, atol=1e-12 * max(1.0, np.abs(ref.xdd).max()))
        np.testing.assert_allclose(out_c.tau, out_p.tau, rtol=0, atol=1e-9 * max(1.0, np.abs(out_p.tau).max()))
        q = q + dt * v
        v = v + dt * out_c.qdd
    ws = compiled.workspace()
    assert ws.path_in_kernel and ws.fast  # the one-call tick
    assert not python.workspace().path_in_kernel
