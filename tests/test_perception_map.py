"""The perception pipeline (qpctl.perception.DepthMap): filtering, self-filter, voxel map, clearing,
decay, the distance field against brute force, and bad input (issue 21, items 1, 2 and 9)."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from depth_scenes import K, Sphere, look_at, render, true_points
from scipy.spatial import cKDTree

from qpctl.dynamics import Dynamics
from qpctl.errors import ConfigError, PerceptionError
from qpctl.kernels.depth import FLYING, KEPT, NO_RETURN, SELF
from qpctl.perception import RIGID, SOFT, DepthFrame, PointCloud
from qpctl.perception.config import PerceptionConfig
from qpctl.perception.depth_map import DepthMap
from qpctl.perception.reference import classify_points
from qpctl.perception.self_filter import JointHistory

CFG = PerceptionConfig(voxel=0.02, bounds_min=[-0.2, -0.4, 0.0], bounds_max=[0.6, 0.4, 0.8], truncation=0.2,
                       decay=1.0, depth_noise=0.002)
EYE = look_at([-0.6, 0.0, 0.4], [0.3, 0.0, 0.4])  # looks along +x
BALL = Sphere((0.25, 0.05, 0.4), 0.08)


def _mapped(frames: list[DepthFrame], cfg: PerceptionConfig = CFG) -> DepthMap:
    m = DepthMap(cfg)
    for f in frames:
        m.integrate(f)
    return m


def test_field_matches_brute_force_nearest_point_within_one_voxel(rng: np.random.Generator) -> None:
    frame = render(EYE, [BALL, Sphere((0.1, -0.2, 0.5), 0.05)])
    m = DepthMap(CFG)
    snap = m.update(frame)
    pts = true_points(frame)
    inside = np.all((pts >= m.grid.origin) & (pts < m.grid.upper), axis=1)
    q = rng.uniform(m.grid.origin, m.grid.upper, (3000, 3))
    d, _ = snap.distance(q)
    # against the occupied voxels' centres: exact at the centres, trilinear in between
    centres = cKDTree(m.occupied_centres(0)).query(q)[0]
    near = centres < CFG.truncation - CFG.voxel
    assert near.sum() > 500
    assert np.max(np.abs(d[near] - centres[near])) <= CFG.voxel
    # against the true surface points (cKDTree on the frame's own points): within one voxel
    true = cKDTree(pts[inside]).query(q)[0]
    near = true < CFG.truncation - 2 * CFG.voxel
    assert np.max(np.abs(d[near] - true[near])) <= CFG.voxel
    # and the truncation holds far away
    far = true > CFG.truncation + 2 * CFG.voxel
    assert far.any() and np.all(d[far] == pytest.approx(CFG.truncation))


def test_field_gradient_matches_finite_differences(rng: np.random.Generator) -> None:
    snap = DepthMap(CFG).update(render(EYE, [BALL]))
    h = 1e-5
    checked = 0
    for p in rng.uniform([0.0, -0.2, 0.2], [0.5, 0.3, 0.6], (400, 3)):
        d, g = snap.distance(p[None], smooth=False)
        if not 2 * CFG.voxel < d[0] < CFG.truncation - 2 * CFG.voxel:
            continue
        fd = np.array([(snap.distance((p + h * e)[None], smooth=False)[0][0]
                        - snap.distance((p - h * e)[None], smooth=False)[0][0]) / (2 * h) for e in np.eye(3)])
        # the trilinear interpolant's gradient is its derivative (off a voxel face: rounding of float32)
        assert g[0] == pytest.approx(fd, abs=2e-3)
        # the smooth (interpolated central-difference) gradient is close to unit length and to it
        gs = snap.distance(p[None])[1][0]
        assert 0.8 < np.linalg.norm(gs) < 1.05
        assert gs @ fd / (np.linalg.norm(gs) * np.linalg.norm(fd)) > 0.9
        checked += 1
    assert checked > 50


def test_soft_labels_fill_the_soft_channel_only() -> None:
    leaf = Sphere((0.25, -0.2, 0.4), 0.06, SOFT)
    m = DepthMap(CFG)
    snap = m.update(render(EYE, [BALL, leaf], labelled=True))
    ball, lf = np.array(BALL.centre), np.array(leaf.centre)
    rigid, soft = m.occupied_centres(0), m.occupied_centres(1)
    assert len(rigid) and len(soft)
    assert np.all(np.linalg.norm(rigid - ball, axis=1) < BALL.radius + CFG.voxel)
    assert np.all(np.linalg.norm(soft - lf, axis=1) < leaf.radius + CFG.voxel)
    d_soft = snap.distance(lf[None] - [leaf.radius + 0.05, 0, 0], channel=1)[0][0]
    d_rigid = snap.distance(lf[None] - [leaf.radius + 0.05, 0, 0], channel=0)[0][0]
    assert d_soft == pytest.approx(0.05, abs=CFG.voxel) and d_rigid > 0.1


def test_uint16_with_a_depth_scale_gives_the_metric_map() -> None:
    f = render(EYE, [BALL])
    raw = np.nan_to_num(f.depth / 0.001, nan=0.0).round().astype(np.uint16)
    a, b = DepthMap(CFG), DepthMap(CFG)
    a.update(f)
    b.update(DepthFrame(raw, K, f.pose, 0.0, depth_scale=0.001))
    ca, cb = np.isfinite(a.last), np.isfinite(b.last)
    assert ca.sum() > 20
    assert np.sum(ca != cb) <= 0.1 * ca.sum()  # millimetre rounding moves a few points across a voxel face


def test_invalid_pixels_are_dropped_and_counted_not_errors() -> None:
    f = render(EYE, [BALL])
    depth = f.depth.copy()
    bad = {(10, 10): np.nan, (10, 11): np.inf, (10, 12): -np.inf, (10, 13): 0.0, (10, 14): -1.0}
    for (v, u), val in bad.items():
        depth[v, u] = val
    rep = DepthMap(CFG).integrate(DepthFrame(depth, K, f.pose, 0.0))
    assert rep.counts["no_return"] == int(np.sum(~np.isfinite(f.depth))) + 5 - int(
        sum(not math.isfinite(f.depth[v, u]) for v, u in bad))
    assert all(rep.status[v, u] == NO_RETURN for v, u in bad)
    assert sum(rep.counts.values()) == K.width * K.height


def test_flying_pixels_at_a_depth_edge_are_dropped_and_the_surfaces_kept() -> None:
    # a near plane (0.6 m) on the left half, a far one (1.2 m) on the right, one column of mixed
    # pixels between them (the average, as a real sensor's footprint straddling the edge reports):
    # every pixel with a neighbour nearer by more than 2 % of its depth is behind an edge
    depth = np.full((K.height, K.width), 1.2)
    depth[:, :160] = 0.6
    depth[:, 160] = 0.9
    rep = DepthMap(CFG).integrate(DepthFrame(depth, K, EYE, 0.0))
    assert np.all(rep.status[:, 160] == FLYING)
    assert np.all(rep.status[:, 159] == KEPT)  # the edge's near side is kept
    assert np.all(rep.status[:, 161] == FLYING)  # its far side's first pixel goes (seen beside it)
    assert np.all(rep.status[:, 162] != FLYING)
    assert rep.counts["flying"] == 2 * K.height
    # a steep but smooth ramp is not a depth edge
    ramp = np.tile(np.linspace(0.6, 1.2, K.width), (K.height, 1))
    assert DepthMap(CFG).integrate(DepthFrame(ramp, K, EYE, 0.0)).counts["flying"] == 0


def test_a_flying_pixel_beside_a_dropout_has_no_nearer_neighbour_but_no_support_either() -> None:
    # near plane | a column lost to grazing dropouts | mixed returns alternating 0.8 / 1.0 m | far
    # plane: the 0.8 m pixels have no neighbour nearer than them (the near side returned nothing), so
    # only the support test (fewer than two of the 8 neighbours within 2 % of the depth) drops them
    depth = np.full((K.height, K.width), 1.2)
    depth[:, :160] = 0.6
    depth[:, 160] = 0.0
    depth[:, 161] = np.where(np.arange(K.height) % 2 == 0, 0.8, 1.0)
    rep = DepthMap(CFG).integrate(DepthFrame(depth, K, EYE, 0.0))
    assert CFG.flying_support == 2
    assert np.all(rep.status[:, 161] == FLYING)
    assert np.all(rep.status[:, 159] == KEPT) and np.all(rep.status[:, 163] != FLYING)
    assert rep.counts["flying"] == 2 * K.height  # the mixed column and the far side's first pixel
    old = PerceptionConfig(**{**CFG.__dict__, "flying_support": 0})  # the 4-neighbour test alone
    status = DepthMap(old).integrate(DepthFrame(depth, K, EYE, 0.0)).status
    assert np.all(status[0::2, 161] != FLYING) and np.all(status[1::2, 161] == FLYING)


@pytest.mark.parametrize("support", [0, 2, 5])
def test_the_flying_test_on_a_noisy_image_is_numpys_neighbour_test(support: int, rng: np.random.Generator) -> None:
    """The kernel's row-wise (vectorised) flying test marks exactly the pixels that numpy's neighbour
    comparisons, written here on shifted copies of the image, mark: on an image of random depth steps,
    noise, and NaN, inf, 0 and negative dropouts at image borders and inside."""
    H, W = K.height, K.width
    depth = rng.choice([0.6, 0.9, 1.2], size=(H // 8, W // 8)).repeat(8, 0).repeat(8, 1)
    depth = depth + rng.normal(0.0, 0.004, (H, W)) * (rng.random((H, W)) < 0.5)
    for bad in (np.nan, np.inf, 0.0, -1.0):
        depth[rng.random((H, W)) < 0.03] = bad
    cfg = PerceptionConfig(**{**CFG.__dict__, "flying_support": support, "min_range": 0.0, "max_range": 10.0})
    status = DepthMap(cfg).integrate(DepthFrame(depth, K, EYE, 0.0)).status
    z = np.zeros((H + 2, W + 2))
    with np.errstate(invalid="ignore"):
        z[1:-1, 1:-1] = np.where((depth > 0) & np.isfinite(depth), depth, 0.0)
    zc = z[1:-1, 1:-1]
    thr = cfg.flying_pixel * zc
    shifts = [(0, -1), (0, 1), (-1, 0), (1, 0), (-1, -1), (-1, 1), (1, -1), (1, 1)]
    nb = [z[1 + a:H + 1 + a, 1 + b:W + 1 + b] for a, b in shifts]
    edge = np.any([(n > 0) & (n < zc - thr) for n in nb[:4]], axis=0)
    support_n = np.sum([(n > 0) & (np.abs(n - zc) <= thr) for n in nb], axis=0)
    expected = (zc > 0) & (edge | ((support > 0) & (support_n < support)))
    assert np.array_equal(status == FLYING, expected)
    assert 1000 < expected.sum() < 0.5 * H * W  # edges, dropouts' rims and noise: a test that can fail


def test_range_limits_drop_returns() -> None:
    cfg = PerceptionConfig(**{**CFG.__dict__, "min_range": 0.7, "max_range": 0.95})
    rep = DepthMap(cfg).integrate(render(EYE, [BALL]))
    d = render(EYE, [BALL]).depth
    valid = np.isfinite(d)
    assert rep.counts["out_of_range"] == int(np.sum(valid & ((d < 0.7) | (d > 0.95))))
    in_range = int(np.sum(valid & (d >= 0.7) & (d <= 0.95)))
    assert rep.counts["kept"] + rep.counts["outside"] + rep.counts["flying"] == in_range
    assert rep.counts["flying"] < 0.05 * in_range  # the ball's steep rim only


def test_statuses_match_the_numpy_reference_for_a_cloud(panda_robot, rng: np.random.Generator) -> None:
    m = DepthMap(CFG, panda_robot)
    q = panda_robot.q_home
    m.record(0.0, q)
    m.set_target([0.3, 0.0, 0.4])
    segs, radii = m.capsules_at(0.0)
    pts = rng.uniform([-0.3, -0.5, -0.1], [0.7, 0.5, 0.9], (20000, 3))
    labels = rng.integers(0, 3, len(pts)).astype(np.uint8)
    rep = m.integrate(PointCloud(pts, 0.0, labels=labels))
    ref = classify_points(pts, segs, radii, m.target, CFG.target_radius, m.grid, soft=labels == SOFT)
    assert np.array_equal(rep.status, ref)
    assert rep.counts["self"] > 100 and rep.counts["target"] > 10 and rep.counts["outside"] > 100


def test_self_filter_uses_the_robot_at_the_frame_stamp(panda_robot, rng: np.random.Generator) -> None:
    """Points on the Panda's capsule surfaces (from the tick's own link segments, a different code
    path) inflated by half the margin are dropped at the stamp the arm was there, kept after it moved."""
    dyn = Dynamics(panda_robot)
    q0 = panda_robot.q_home
    q1 = q0 + np.array([0.8, 0.3, 0.0, 0.4, 0.0, -0.3, 0.0])
    segs = dyn.compute(q0, np.zeros(7)).segments
    pts = []
    for (a, b), cap in zip(segs, panda_robot.capsules, strict=True):
        s = rng.uniform(0, 1, 200)
        dirs = rng.normal(size=(200, 3))
        dirs -= np.outer(dirs @ (b - a), b - a) / max((b - a) @ (b - a), 1e-12)
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        pts.append(a + s[:, None] * (b - a) + (cap.radius + 0.5 * CFG.self_margin) * dirs)
    cloud = np.concatenate(pts)
    history = JointHistory(7)
    m = DepthMap(CFG, panda_robot, history)
    history.record(0.0, q0)
    history.record(1.0, q1)
    at0 = m.integrate(PointCloud(cloud, 0.0))
    inside = at0.counts["kept"] + at0.counts["outside"]
    assert at0.counts["self"] == len(cloud) and inside == 0
    at1 = m.integrate(PointCloud(cloud, 1.0))
    assert at1.counts["self"] < 0.5 * len(cloud)
    # halfway in time, halfway in joint space (linear interpolation of the history)
    assert np.allclose(history.at(0.5), 0.5 * (q0 + q1))


def test_grasp_target_zone_is_not_an_obstacle() -> None:
    fruit = Sphere((0.25, 0.05, 0.4), 0.04)
    m = DepthMap(CFG)
    m.set_target(fruit.centre)
    rep = m.integrate(render(EYE, [fruit]))
    assert CFG.target_radius > fruit.radius
    assert rep.counts["target"] > 100 and rep.counts["kept"] == 0
    # the leaves in front of a fruit stay: a soft point in the zone is a soft obstacle
    leafy = DepthMap(CFG)
    leafy.set_target(fruit.centre)
    rep = leafy.integrate(render(EYE, [Sphere(fruit.centre, fruit.radius, SOFT)], labelled=True))
    assert rep.counts["target"] == 0 and rep.counts["kept"] > 100
    with pytest.raises(PerceptionError, match="target"):
        m.set_target([0.0, math.nan, 0.0])


def test_what_was_mapped_before_a_fruit_became_the_target_is_forgotten() -> None:
    """A fruit mapped while it was not the target (rigid) stops being an obstacle once it is: the next
    snapshot has no rigid voxel whose centre lies within target_radius of it (centres and distances
    computed here), keeps the rigid voxels of a ball beyond the zone and the soft voxels inside it."""
    fruit = Sphere((0.25, 0.05, 0.4), 0.04)
    far = Sphere((0.25, -0.2, 0.4), 0.05)  # 0.25 m from the fruit: beyond the zone
    m = DepthMap(CFG)
    m.integrate(render(EYE, [fruit, far], stamp=0.0))
    m.integrate(PointCloud(np.array(fruit.centre)[None] + [[0.0, 0.0, 0.06]], 0.0, labels=np.array([SOFT])))
    centre, zone = np.array(fruit.centre), CFG.target_radius

    def occupied(snap, channel):
        return m.grid.centres(np.argwhere(snap.dist[channel] <= 0.0))

    before = occupied(m.snapshot(), 0)
    assert np.sum(np.linalg.norm(before - centre, axis=1) <= zone) > 10  # the fruit is a rigid obstacle
    m.set_target(fruit.centre)
    snap = m.snapshot()
    rigid, soft = occupied(snap, 0), occupied(snap, 1)
    assert not np.any(np.linalg.norm(rigid - centre, axis=1) <= zone)
    kept_far = np.linalg.norm(rigid - np.array(far.centre), axis=1) <= far.radius + CFG.voxel
    assert kept_far.sum() == np.sum(np.linalg.norm(before - np.array(far.centre), axis=1) <= far.radius + CFG.voxel) > 10
    assert np.any(np.linalg.norm(soft - centre, axis=1) <= zone)  # the leaf's voxel stays
    m.set_target(None)  # forgotten, not hidden: no target, and the fruit is still gone
    assert not np.any(np.linalg.norm(occupied(m.snapshot(), 0) - centre, axis=1) <= fruit.radius)


def test_free_space_is_cleared_along_the_rays() -> None:
    # the ball is seen, then it is gone and the wall behind it is seen through where it was
    m = _mapped([render(EYE, [BALL], wall_x=0.55, stamp=0.0)])
    m.snapshot()
    ball = np.array(BALL.centre)
    near = lambda c: np.sum(np.linalg.norm(c - ball, axis=1) < BALL.radius + 2 * CFG.voxel)
    assert near(m.occupied_centres()) > 20
    rep = m.integrate(render(EYE, [], wall_x=0.55, stamp=0.1))
    m.snapshot()
    assert rep.cleared >= 20 and near(m.occupied_centres()) == 0
    assert len(m.occupied_centres()) > 100  # the wall stays


def test_occluded_voxels_are_not_cleared() -> None:
    far_ball = Sphere((0.45, 0.0, 0.4), 0.06)
    m = _mapped([render(EYE, [far_ball], stamp=0.0)])
    m.snapshot()
    n_far = len(m.occupied_centres())
    # a ball in front hides it: nothing behind the near ball may be cleared
    m.integrate(render(EYE, [Sphere((0.1, 0.0, 0.4), 0.12)], stamp=0.1))
    m.snapshot()
    c = m.occupied_centres()
    assert np.sum(np.linalg.norm(c - far_ball.centre, axis=1) < far_ball.radius + 2 * CFG.voxel) == n_far


def test_clearing_along_the_rays_of_a_cloud_with_a_sensor_origin() -> None:
    m = DepthMap(CFG)
    m.integrate(PointCloud([[0.3, 0.0, 0.4]], 0.0))
    m.snapshot()
    assert len(m.occupied_centres()) == 1
    # a later ray from (−0.1, 0, 0.4) to a point beyond it passes through that voxel
    m.integrate(PointCloud([[0.5, 0.0, 0.4]], 0.1, origin=[-0.1, 0.0, 0.4]))
    m.snapshot()
    assert np.allclose(m.occupied_centres(), [[0.51, 0.01, 0.41]])


def test_what_is_no_longer_seen_decays() -> None:
    m = DepthMap(CFG)
    m.integrate(PointCloud([[0.3, 0.0, 0.4]], 0.0))
    assert m.snapshot().occupied == (1, 0)
    m.integrate(PointCloud(np.zeros((0, 3)), 0.9))
    assert m.snapshot().occupied == (1, 0)
    m.integrate(PointCloud(np.zeros((0, 3)), 1.1))
    snap = m.snapshot()
    assert snap.occupied == (0, 0) and np.all(snap.dist == CFG.truncation)


def test_an_empty_cloud_is_a_valid_empty_map() -> None:
    snap = DepthMap(CFG).update(PointCloud(np.zeros((0, 3)), 0.0))
    assert snap.occupied == (0, 0) and np.all(snap.dist == CFG.truncation) and not snap.grad.any()


def test_stamps_going_backwards_raise() -> None:
    m = DepthMap(CFG)
    m.integrate(PointCloud([[0.3, 0.0, 0.4]], 1.0))
    m.integrate(PointCloud([[0.3, 0.0, 0.4]], 1.0))  # equal is fine
    with pytest.raises(PerceptionError, match="backwards"):
        m.integrate(PointCloud([[0.3, 0.0, 0.4]], 0.5))
    with pytest.raises(PerceptionError, match="DepthFrame or a PointCloud"):
        m.integrate(np.zeros((4, 3)))  # type: ignore[arg-type]


def test_snapshots_are_immutable_and_independent() -> None:
    m = DepthMap(CFG)
    frame = render(EYE, [BALL], stamp=0.0)
    t0 = time.perf_counter()
    first = m.update(frame)
    wall_ms = (time.perf_counter() - t0) * 1e3
    assert 0.0 < first.build_ms <= wall_ms  # from the frame's arrival to the snapshot's completion
    before = first.dist.copy()
    with pytest.raises(ValueError):
        first.dist[0, 0, 0, 0] = 0.0
    with pytest.raises(ValueError):
        first.grad[...] = 0.0
    with pytest.raises(ValueError):
        first.pairs[...] = 0.0
    m.update(render(EYE, [], wall_x=0.3, stamp=0.1))
    assert np.array_equal(first.dist, before) and first.stamp == 0.0
    # the tick's side-by-side grid: voxel (i, j, k)'s channel c is dist[c, i, j, k]
    assert np.any(first.dist[0] < CFG.truncation)
    for c in range(2):
        assert np.array_equal(first.pairs[:, :, :, c], first.dist[c])


@pytest.mark.parametrize("key,value,match", [
    ("voxel", 0.0, "voxel"), ("bounds_min", [0.0, 0.0], "bounds_min"), ("bounds_max", [0.0, 0.0, 0.0], "bounds_max"),
    ("max_range", 0.05, "max_range"), ("stale_stop", 0.1, "stale_stop"), ("samples", 1, "samples"),
    ("rows_per_link", 3, "rows_per_link"), ("truncation", 0.01, "truncation"), ("decay", -1.0, "decay"),
    ("lag_stop", 0.005, "lag_stop"), ("lag_slow", -0.01, "lag_slow"), ("lag_rate", 0.0, "lag_rate")])
def test_bad_settings_name_the_key(key: str, value: object, match: str) -> None:
    with pytest.raises(ConfigError, match=f"perception.{match}"):
        PerceptionConfig(**{key: value})


def test_kept_points_stamp_their_voxel() -> None:
    m = DepthMap(CFG)
    rep = m.integrate(PointCloud([[0.301, 0.001, 0.401], [5.0, 0.0, 0.0]], 0.25))
    assert list(rep.status) == [KEPT, 6] and rep.dropped == 1
    assert m.last[0, 25, 20, 20] == 0.25 and np.sum(np.isfinite(m.last)) == 1
    assert SELF == 4  # the statuses' codes are part of the figures' legend


def test_a_voxel_within_the_noise_margin_of_the_return_is_not_cleared() -> None:
    """A wall seen at x = 0.395 m, then 1 cm farther (within √3/2 voxel + depth noise): the depth
    noise must not erase the first sighting; 5 cm farther it is free space and is cleared."""
    m = _mapped([render(EYE, [], wall_x=0.395, stamp=0.0)])
    m.snapshot()
    first = {tuple(c) for c in np.round(m.occupied_centres(), 4)}
    m.integrate(render(EYE, [], wall_x=0.405, stamp=0.1))
    m.snapshot()
    assert first <= {tuple(c) for c in np.round(m.occupied_centres(), 4)}
    m.integrate(render(EYE, [], wall_x=0.445, stamp=0.2))
    m.snapshot()
    assert not first & {tuple(c) for c in np.round(m.occupied_centres(), 4)}


def test_a_lone_return_does_not_occupy_a_voxel() -> None:
    depth = np.full((K.height, K.width), np.nan)
    depth[100, 100] = 0.9  # one pixel in free space: the noise's tail
    m = DepthMap(CFG)
    m.integrate(DepthFrame(depth, K, EYE, 0.0))
    assert CFG.min_points == 2 and m.snapshot().occupied == (0, 0)
    depth[100:102, 100:102] = 0.9  # its neighbours fall in the same voxel: a surface (each pixel with
    m.integrate(DepthFrame(depth, K, EYE, 0.1))  # the flying test's two supporting neighbours)
    assert m.snapshot().occupied == (1, 0)


@pytest.mark.parametrize("label", [SOFT, RIGID])
@pytest.mark.parametrize("robot_there", [True, False])
def test_what_the_robot_hides_is_held_not_forgotten(panda_robot, robot_there: bool, label: int) -> None:
    """A leaf (soft) or a branch (rigid) seen once, then hidden for longer than the decay behind a shape
    on one of the Panda's link capsules: while that shape is the robot (its pixels self-filtered) the
    voxels are held (the arm waiting in a leaf hides it from the camera: canopy seed 16's leaf decayed
    3 s after the hand came in front of it, and the hand then crossed it at 0.15 m/s; canopy seed
    20's branch10, hidden by the forearm for the last 3.5 s of the run, decayed and was touched);
    in a map without the robot the same shape is an obstacle and they decay as before."""
    q0 = panda_robot.q_home
    a, b = Dynamics(panda_robot).compute(q0, np.zeros(7)).segments[1]
    eye = np.array([-0.6, 0.0, 0.4])
    mid = 0.5 * (a + b)
    ray = (mid - eye) / np.linalg.norm(mid - eye)
    leaf = Sphere(tuple(eye + (np.linalg.norm(mid - eye) + 0.25) * ray), 0.03, label)
    ch = 1 if label == SOFT else 0
    hider = Sphere(tuple(mid), 0.07)  # inside the capsule (radius 0.08)
    pose = look_at(eye, leaf.centre)
    history = JointHistory(7)  # empty at the first frame: the map saw it before the arm was there
    m = DepthMap(CFG, panda_robot, history) if robot_there else DepthMap(CFG)
    near = lambda: np.sum(np.linalg.norm(m.grid.centres(np.argwhere(m._occupied[ch])) - leaf.centre, axis=1)
                          < leaf.radius + 2 * CFG.voxel)
    m.integrate(render(pose, [leaf], labelled=True, stamp=0.0))
    m.snapshot()
    seen = near()
    assert seen > 5
    history.record(0.3, q0)
    for t in (0.4, 0.8, 1.2, 1.6):  # the decay is 1 s
        rep = m.integrate(render(pose, [leaf, hider], labelled=True, stamp=t))
        assert (rep.counts["self"] > 1000) == robot_there and (rep.counts["kept"] > 1000) != robot_there
        m.snapshot()
    assert near() == (seen if robot_there else 0)
