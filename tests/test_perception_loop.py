"""The field's rows and the closed loop: point Jacobians and drifts against finite differences, the
rows against their definition, and a short Panda run that sees its obstacles only through a simulated
depth camera (qpctl.perception.rows, .closed_loop; issue 21, items 3, 4 and 7)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pinocchio as pin
import pytest

from qpctl import Scenario
from qpctl.dynamics import Dynamics
from qpctl.perception import Perception, PerceptionConfig, PointCloud
from qpctl.perception.closed_loop import attach
from qpctl.perception.rows import FieldBarrier, field_pairs
from qpctl.perception.stale import OK, SLOW, StalePolicy
from qpctl.simulation.camera import CameraConfig, DepthCamera
from qpctl.simulation.simulator import Simulator

CFG = PerceptionConfig(voxel=0.02, bounds_min=[-0.3, -0.6, 0.0], bounds_max=[1.1, 0.6, 1.1], truncation=0.3,
                       depth_noise=0.025)  # 3σ of the camera at 1.3 m (σ = 0.5 mm + 4.2 mm·z²)


def _sphere_cloud(centre: list[float], radius: float, n: int = 4000, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    return np.asarray(centre) + radius * d / np.linalg.norm(d, axis=1, keepdims=True)


def test_witness_point_jacobian_and_drift_match_finite_differences(panda_robot, rng: np.random.Generator) -> None:
    p = Perception(CFG)
    bar = FieldBarrier(p, panda_robot, CFG, d_safe=0.05, cutoff=0.3)
    model = panda_robot.model
    data = model.createData()
    h = 1e-6
    for _ in range(5):
        q = rng.uniform(panda_robot.q_min, panda_robot.q_max)
        v = rng.uniform(-1, 1, 7)
        links = np.arange(len(panda_robot.capsules))
        pin.forwardKinematics(model, data, q)
        # a point fixed on each link's body (its capsule's p1 shifted off the axis)
        local = [np.asarray(c.p1) + [0.01, -0.02, 0.03] for c in panda_robot.capsules]
        pts = np.array([data.oMi[c.joint_id].act(x) for c, x in zip(panda_robot.capsules, local, strict=True)])
        J, a = bar.jacobians(q, v, links, pts)

        def points(qq: np.ndarray, local: list[np.ndarray] = local) -> np.ndarray:
            pin.forwardKinematics(model, data, qq)
            return np.array([data.oMi[c.joint_id].act(x) for c, x in zip(panda_robot.capsules, local, strict=True)])

        # ṗ = J_p q̇ and p̈ at q̈ = 0 = J̇_p q̇, by central differences along q(t) = q + v t
        p_plus, p_minus, p_0 = points(q + h * v), points(q - h * v), points(q)
        assert np.einsum("kin,n->ki", J, v) == pytest.approx((p_plus - p_minus) / (2 * h), abs=1e-6)
        hh = 1e-4
        acc = (points(q + hh * v) - 2 * p_0 + points(q - hh * v)) / hh ** 2
        assert a == pytest.approx(acc, abs=1e-4)


def test_rows_are_the_barrier_of_the_field_distance(panda_robot) -> None:
    """A static map of a sphere beside the forearm: each active rigid row is n^T J_p (J_p the witness
    point's Jacobian) and its bound −k1 ḣ − k0 (d − margin) − n^T J̇_p q̇ (inside the margin
    −k_r (ḣ − min(k0/k1 (margin − d), soft_speed)) − n^T J̇_p q̇, k_r = recovery_gain); ḣ = row·q̇ matches the rate
    of change of the pair's distance along the motion."""
    robot = panda_robot
    q = robot.q_home.copy()
    seg = Dynamics(robot).compute(q, np.zeros(7)).segments
    mid = 0.5 * (seg[3, 0] + seg[3, 1])
    centre = mid + [0.0, 0.18, 0.0]
    p = Perception(CFG)
    p.submit(PointCloud(_sphere_cloud(list(centre), 0.05), 0.0))
    bar = FieldBarrier(p, robot, CFG, d_safe=0.05, cutoff=0.3, k0=400.0, k1=40.0)
    dyn = Dynamics(robot)
    v = np.array([0.1, -0.2, 0.3, 0.2, -0.1, 0.2, 0.1])
    st = dyn.compute(q, v, 0.0)
    ineq = bar.compute(st, None)  # type: ignore[arg-type]
    pairs = bar.last
    assert pairs is not None
    rigid = np.flatnonzero(pairs.active & ~pairs.soft)
    assert rigid.size >= 2 and not (pairs.active & pairs.soft).any()
    J, a = bar.jacobians(q, v, pairs.link[rigid], pairs.point[rigid])
    rows = np.einsum("ri,rin->rn", pairs.normal[rigid], J)
    hdot = rows @ v
    m, d = CFG.rigid_margin(0.05), pairs.distance[rigid]
    # inside the margin (d < m) away at min(k0/k1 (m − d), soft_speed) with the recovery gain; no torque
    # window given: no cap
    expect = np.where(d < m, -CFG.recovery_gain * (hdot - np.minimum(10.0 * (m - d), CFG.soft_speed)),
                      -40.0 * hdot - 400.0 * (d - m)) - np.einsum("ri,ri->r", pairs.normal[rigid], a)
    assert (d < m).any() and (d >= m).any()  # both kinds of row
    assert ineq.C[rigid] == pytest.approx(rows) and ineq.lower[rigid] == pytest.approx(expect)
    P = bar.pairs
    assert np.all(np.isinf(ineq.lower[:P][~pairs.active])) and not ineq.C[:P][~pairs.active].any()
    assert np.all(np.isinf(ineq.lower[P:])) and not ineq.C[P:].any()  # no leaf: no speed rows
    # ḣ: the rate of change of the pairs' distances along q + v t (pairs clear of the voxels, where
    # the field is a distance; a link inside the map's occupied voxels has no gradient to speak of)
    clear = pairs.distance[rigid] > 2 * CFG.voxel
    assert clear.sum() >= 2
    h = 1e-4
    d = [field_pairs(p.snapshot, dyn.compute(q + s * v, v).segments, bar.radii, CFG, 0.3).distance[rigid]
         for s in (-h, h)]
    assert ((d[1] - d[0]) / (2 * h))[clear] == pytest.approx(hdot[clear], rel=0.05, abs=2e-3)


def test_soft_rows_cap_the_approach_speed_not_the_distance(panda_robot) -> None:
    robot = panda_robot
    q = robot.q_home.copy()
    seg = Dynamics(robot).compute(q, np.zeros(7)).segments
    tip = seg[-1, 1]
    p = Perception(CFG)
    p.submit(PointCloud(_sphere_cloud(list(tip + [0.0, 0.0, -0.1]), 0.04), 0.0,
                        labels=np.full(4000, 2, np.uint8)))
    cfg = PerceptionConfig(**{**CFG.__dict__, "soft_margin": 0.03})
    bar = FieldBarrier(p, robot, cfg, d_safe=0.05, cutoff=0.3)
    st = Dynamics(robot).compute(q, np.zeros(7), 0.0)
    ineq = bar.compute(st, None)  # type: ignore[arg-type]
    pairs = bar.last
    assert pairs is not None
    soft = np.flatnonzero(pairs.active & pairs.soft)
    assert soft.size and not (pairs.active & ~pairs.soft).any()
    # at rest: −k1 v_s − k0 max(d − m_s, 0) (no d_safe: contact is allowed at v_s)
    expect = -40.0 * cfg.soft_speed - 400.0 * np.maximum(pairs.distance[soft] - 0.03, 0.0)
    assert (pairs.distance[soft] < 0.03).any() and (pairs.distance[soft] > 0.03).any()
    assert ineq.lower[soft] == pytest.approx(expect, abs=1e-9)


def _camera_scene() -> tuple[Scenario, list, DepthCamera]:
    scen = Scenario.load("panda_spheres", overrides=["sim.duration=0.8"])
    robot = scen.build_robot()
    world = scen.build_obstacles()
    cam = DepthCamera(CameraConfig(mount="world", position=[1.6, 0.0, 0.9], look_at=[0.45, 0.0, 0.5], width=320,
                                   height=240, fov_y=70.0), robot, world)
    return scen, world, cam


def test_a_short_run_sees_its_obstacles_only_through_the_camera(tmp_path) -> None:
    scen, world, cam = _camera_scene()
    robot = cam.robot
    ctrl = scen.build_controller("qp", robot=robot, obstacles=[])  # no primitive: the map only
    sim = Simulator(ctrl, dt=1e-3, duration=0.8, obstacles=world)
    loop = attach(ctrl, sim, CFG, camera=cam, world=world)
    traj = sim.run(scen.q0(robot))
    m = loop.metrics()
    assert m["map_frames"] == 25  # 30 Hz from 0 to 0.8 s
    assert math.isfinite(m["map_min_clearance"]) and m["map_update_ms_p99"] > 0
    assert m["map_latency_ms_p99"] >= CFG.latency * 1e3 - 1e-6  # no map before its declared latency
    assert m["map_updates_over_latency"] == sum(c > CFG.latency * 1e3 for c in loop.build_cpu_ms)
    # the first frames' map arrives after its build time: the policy held the arm until then
    assert loop.stop_ticks >= 1
    d_safe = float(scen.data["controller"]["d_safe"])
    assert traj.clearance.min() >= d_safe - CFG.voxel
    assert m["phantom_rows_checked"] > 0
    # the maps the replay draws (every MAP_RECORD_EVERY s): voxel centres on the true spheres
    pts, stamps = loop.map_points()
    assert len(np.unique(stamps)) >= 2 and stamps.min() >= 0.0 and stamps.max() <= 0.8
    gap = np.min([np.abs(np.linalg.norm(pts - o.position, axis=1) - o.radius) for o in world], axis=0)
    assert np.mean(gap <= 2 * CFG.voxel + CFG.depth_noise) >= 0.95
    # 0.8 s into a path whose first fruit is at 1.5 s: every fruit missed, the reference not there yet
    misses = loop.explain_misses(traj, ctrl.path.points[1:])
    assert [f["fruit"] for f in misses] == list(range(len(ctrl.path.points) - 1))
    assert {f["cause"] for f in misses} == {"reference"}
    files = loop.write_figures(tmp_path, traj.t, traj.clearance, d_safe)  # the run's three figures
    assert [f.name for f in files] == ["depth_frame.png", "field_slice.png", "clearance_true_vs_map.png"]
    assert all(f.stat().st_size > 10_000 for f in files)


def test_the_closed_loop_is_the_same_run_however_long_the_map_takes() -> None:
    """The map reaches the rows at its stamp + the declared latency, whatever the build cost: a run
    made while another thread keeps a core busy (the build then takes longer on the wall clock and
    in CPU time as caches are shared) is the same run, torque for torque; and a longer declared
    latency delays the first rows by exactly the difference."""
    import threading

    def run(latency: float, busy: bool) -> tuple[np.ndarray, list[float], dict]:
        scen, world, cam = _camera_scene()
        ctrl = scen.build_controller("qp", robot=cam.robot, obstacles=[])
        sim = Simulator(ctrl, dt=1e-3, duration=0.3, obstacles=world)
        cfg = dataclasses.replace(CFG, latency=latency)
        loop = attach(ctrl, sim, cfg, camera=cam, world=world)
        stop = threading.Event()
        spin = threading.Thread(target=lambda: [sum(range(1000)) for _ in iter(stop.is_set, True)])
        if busy:
            spin.start()
        try:
            traj = sim.run(scen.q0(cam.robot))
        finally:
            stop.set()
            if busy:
                spin.join()
        return traj.tau, loop.series["age_ms"], loop.metrics()

    tau_a, age_a, _ = run(0.03, busy=False)
    tau_b, _, _ = run(0.03, busy=True)
    assert np.array_equal(tau_a, tau_b)
    _, age_c, m_c = run(0.06, busy=False)
    _, _, m_0 = run(0.0, busy=False)  # no build takes no time: every frame is over a zero latency
    assert m_0["map_updates_over_latency"] == m_0["map_frames"] == 10 and m_c["map_frames"] == 10
    first = [next(i for i, a in enumerate(ages) if np.isfinite(a)) for ages in (age_a, age_c)]
    assert first[1] - first[0] == 30  # ticks of 1 ms


def test_few_rows_come_from_what_is_not_there() -> None:
    """Rows from what is not there: flying pixels at the robot's and the spheres' silhouettes whose
    neighbours across the edge are flying too or lost to grazing dropouts pass the 4-neighbour test
    (6 of 364 checked rows with it alone, 19-28 % before the map's latency was fixed); the 8-neighbour
    support test removes them."""
    scen, world, cam = _camera_scene()
    ctrl = scen.build_controller("qp", robot=cam.robot, obstacles=[])
    sim = Simulator(ctrl, dt=1e-3, duration=0.8, obstacles=world)
    loop = attach(ctrl, sim, CFG, camera=cam, world=world)
    sim.run(scen.q0(cam.robot))
    m = loop.metrics()
    assert m["phantom_rows_checked"] >= 200
    assert m["phantom_rows"] <= 0.01 * m["phantom_rows_checked"]


FRUIT1 = np.array([0.55, 0.25, 0.45])  # panda_spheres' first waypoint, reached at t = 1.5 s on its nominal clock


def _hand_through_a_leaf(duration: float, cfg: PerceptionConfig, *, time_scaled: bool = False
                         ) -> tuple[dict, np.ndarray, np.ndarray]:
    """panda_spheres without its spheres; a filled soft ball (r = 6 cm) on the hand's way to the first
    fruit, known to the map as a cloud of soft points and to the metrics as a soft sphere. The
    metrics (with ``solved``), the times [s] and the hand's distances to the first fruit [m]."""
    from qpctl.geometry.obstacles import Obstacle

    scen = Scenario.load("panda_spheres")
    robot = scen.build_robot()
    q0 = scen.q0(robot)
    ctrl = scen.build_controller("qp", robot=robot, obstacles=[])
    start = ctrl.dynamics.compute(q0, np.zeros(robot.nv)).segments[-1, 1]
    centre = start + 0.4 * (FRUIT1 - start)
    rng = np.random.default_rng(0)
    d = rng.normal(size=(6000, 3))
    pts = centre + 0.06 * d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(0, 1, (6000, 1)) ** (1 / 3)
    leaf = Obstacle("sphere", centre, radius=0.06, material="soft", name="leaf")
    sim = Simulator(ctrl, dt=1e-3, duration=duration, obstacles=[leaf])
    p = Perception(cfg, robot)
    p.submit(PointCloud(pts, 0.0, labels=np.full(len(pts), 2, np.uint8)))
    loop = attach(ctrl, sim, cfg, world=[leaf], perception=p, time_scaled=time_scaled)
    traj = sim.run(q0)
    m = {**loop.metrics(), "solved": bool(np.all(traj.qp_status == "solved"))}
    return m, traj.t, np.linalg.norm(traj.x[:, :3] - FRUIT1, axis=1)


def test_the_hand_passes_through_a_leaf_no_faster_than_soft_speed() -> None:
    """The soft speed rows hold the fastest point of a link inside the true leaf (the metric, from
    python-fcl's witness points) to soft_speed: 0.0536 m/s measured against 0.05 (the tangent rows'
    second-order error, the points between the axis samples and the slack where the drives' rate limit
    binds), against 0.078 m/s with the rows bounding each sample's own speed in 14 fixed directions."""
    m, _, _ = _hand_through_a_leaf(0.7, CFG)
    assert m["solved"] and m["min_soft_clearance"] < -0.03  # the hand went well into the leaf
    assert m["soft_contact_max_speed"] <= 1.1 * CFG.soft_speed


def test_the_path_waits_for_the_hand_in_a_leaf() -> None:
    """The waiting reference (qpctl.perception.stale, the lag): the soft speed rows hold the arm to
    soft_speed while its links pass through the ball, and the path slows with the tracking error
    instead of running on. The hand reaches the first fruit within 5 mm (1.0 mm measured, at t = 7.1 s
    against the nominal 1.5 s: the forearm is in the ball most of the way), never faster than
    soft_speed (+20 %: 0.058 m/s measured) inside; with the path's waiting off (lag_stop = 0) the
    reference runs on to the second fruit and the hand passes the first no nearer than 5 mm
    (0.24 m at t = 4 s). A static map: the stale policy's thresholds out of the way."""
    cfg = dataclasses.replace(CFG, stale_slow=100.0, stale_stop=200.0)
    m, t, err = _hand_through_a_leaf(7.5, cfg, time_scaled=True)
    assert m["solved"] and m["min_soft_clearance"] < -0.03 and m["lag_ticks"] > 1000
    reached = np.flatnonzero(err <= 0.005)
    assert reached.size and t[reached[0]] > 1.5 + 2.0  # reached, seconds later than the nominal path
    assert m["soft_contact_max_speed"] <= 1.2 * cfg.soft_speed
    assert m["lag_max_m"] <= cfg.lag_stop + 0.01  # the path waited: it never ran away from the hand
    m0, _, err0 = _hand_through_a_leaf(7.5, dataclasses.replace(cfg, lag_stop=0.0), time_scaled=True)
    assert m0["lag_ticks"] == 0 and err0.min() > 0.005


def test_lag_policy_slows_the_path_with_the_tracking_error() -> None:
    """κ_lag against its definition: 1 up to lag_slow, linear to 0 at lag_stop, rate-limited at
    lag_rate both ways; κ is the lesser of the age's and the lag's; the map's mode is the age's."""
    p = StalePolicy(0.1, 0.3, lag_slow=0.01, lag_stop=0.05, lag_rate=5.0)
    assert p.lag_target(0.005) == 1.0 and p.lag_target(0.03) == pytest.approx(0.5) and p.lag_target(0.06) == 0.0
    dt = 0.001
    kap, lagk = [], []
    for k in range(1000):
        t = k * dt
        lag = 0.08 if 0.1 <= t < 0.5 else 0.0  # the arm held back from 0.1 s to 0.5 s; the map always fresh
        v = p(t, 0.0, lag)
        assert v.mode == OK
        kap.append(v.kappa)
        lagk.append(v.lag_kappa)
    kap = np.array(kap)
    assert np.all(np.abs(np.diff(kap)) <= 5.0 * dt + 1e-12)
    # κ falls from the first tick of the lag (t = 0.1 s) by lag_rate·dt a tick, and climbs back likewise
    assert kap[99] == 1.0 and kap[200] == pytest.approx(1.0 - 5.0 * 0.101, abs=1e-9) and kap[400] == 0.0
    assert kap[600] == pytest.approx(5.0 * 0.101, abs=1e-9) and kap[900] == 1.0 and np.array_equal(kap, lagk)
    # an old map and a lag together: the lesser factor
    q = StalePolicy(0.1, 0.3, lag_slow=0.01, lag_stop=0.05, lag_rate=5.0)
    v = q(0.0, 0.2, 0.02)
    assert v.kappa == pytest.approx(min(0.5, 0.75)) and v.mode == SLOW and v.lag_kappa == pytest.approx(0.75)
    assert StalePolicy(0.1, 0.3)(0.0, 0.0, 1.0).kappa == 1.0  # without lag thresholds the lag is ignored
    with pytest.raises(ValueError):
        StalePolicy(0.1, 0.3, lag_slow=0.05, lag_stop=0.01)


def test_a_fruit_is_picked_when_the_hand_reaches_it_and_the_camera_no_longer_sees_it() -> None:
    """panda_spheres' first two waypoints as fruits only the camera sees (scenery, unlabelled: rigid in
    the map): the hand reaches the first within its radius, and from then on the camera's frames
    have no pixel on it (it is harvested, not a rigid obstacle at the hand when the target moves on);
    the second, not reached in the run, is still seen."""
    from qpctl.geometry.obstacles import Obstacle

    scen = Scenario.load("panda_spheres")
    robot = scen.build_robot()
    ctrl = scen.build_controller("qp", robot=robot, obstacles=[])
    path = ctrl.path
    fruits = [Obstacle("sphere", np.asarray(p, float), radius=0.035, name=f"fruit{i}")
              for i, p in enumerate(path.points[1:3])]
    cam = DepthCamera(CameraConfig(mount="world", position=[1.6, 0.0, 0.9], look_at=[0.45, 0.0, 0.5], width=160,
                                   height=120, fov_y=70.0), robot, [], scenery=fruits)
    duration = 2.0
    sim = Simulator(ctrl, dt=1e-3, duration=duration, obstacles=[])
    targets = (np.asarray(path.points[1:], float), np.asarray(path.starts, float))
    loop = attach(ctrl, sim, CFG, camera=cam, world=[], targets=targets)
    q0 = scen.q0(robot)
    first, second = 0, 1  # their shapes' indices in the camera (no obstacles before them)
    assert np.any(cam.capture(q0, 0.0).truth.hit == first)  # seen on its tree before the run
    traj = sim.run(q0)
    err = np.linalg.norm(traj.x[:, :3] - fruits[0].position, axis=1)
    assert err.min() <= fruits[0].radius and loop.metrics()["fruits_picked"] == 1
    assert not cam.visible[first] and cam.visible[second]
    frame = cam.capture(traj.q[-1], duration)
    assert not np.any(frame.truth.hit == first) and np.any(frame.truth.hit == second)
    loop.reset()  # a new run: back on its tree
    assert cam.visible[first]
