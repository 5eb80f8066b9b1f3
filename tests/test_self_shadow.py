"""The robot's shadow (qpctl.kernels.self_shadow): a return whose ray from the sensor passes through one
of the robot's inflated capsules is not an obstacle.

Independent references: python-fcl (a zero-radius capsule along the ray against each capsule:
``qpctl.perception.reference.in_shadow``, and a thin capsule's distance here), the cloud path for the
image path's rectangles (the same points, no culling), and the simulated camera's truth (which pixels
are flying pixels at the robot's silhouette).
"""

from __future__ import annotations

import dataclasses

import fcl
import numpy as np
import pytest
from solid_reference import fcl_segment

from qpctl import Scenario
from qpctl.kernels import depth as KD
from qpctl.kernels import self_shadow as SS
from qpctl.perception import SOFT, DepthFrame, PointCloud
from qpctl.perception.config import PerceptionConfig
from qpctl.perception.depth_map import DepthMap
from qpctl.perception.reference import classify_points
from qpctl.simulation.camera import DepthCamera


def test_a_ray_meets_a_capsule_where_fcl_says(rng: np.random.Generator) -> None:
    """The kernel's segment–capsule test against python-fcl's distance from a thin capsule along the ray
    (pairs within 1e-6 m of grazing are left out: there the two may round either way)."""
    checked = hits = 0
    for _ in range(3000):
        o, p = rng.uniform(-1, 1, 3), rng.uniform(-1, 1, 3)
        a = rng.uniform(-0.5, 0.5, 3)
        b = a if rng.random() < 0.1 else a + rng.normal(size=3) * 0.3  # a sphere now and then
        r = float(rng.uniform(0.02, 0.3))
        thin = fcl.distance(fcl_segment(o, p, 1e-9), fcl_segment(a, b, r), fcl.DistanceRequest(), fcl.DistanceResult())
        meets = fcl.collide(fcl_segment(o, p, 1e-9), fcl_segment(a, b, r), fcl.CollisionRequest(),
                            fcl.CollisionResult()) > 0
        if not meets and thin < 1e-6:
            continue
        got = SS.ray_meets_capsule(*o, *p, np.array([[a, b]]), np.array([r]), 0)
        assert got == meets, (o, p, a, b, r, thin)
        checked += 1
        hits += meets
    assert checked > 2900 and 200 < hits < checked - 200


def _capsules(robot, q, margin: float):
    m = DepthMap(PerceptionConfig(self_margin=margin), robot)
    m.record(0.0, q)
    return m, *m.capsules_at(0.0)


def test_cloud_statuses_with_a_sensor_match_the_reference(panda_robot, rng: np.random.Generator) -> None:
    """A cloud with a sensor origin: every point's status, shadow included, as the numpy/python-fcl
    reference gives it; soft points are never shadowed (a leaf is not the robot)."""
    m, segs, radii = _capsules(panda_robot, panda_robot.q_home, 0.03)
    sensor = np.array([0.9, -0.6, 0.8])
    pts = rng.uniform([-0.4, -0.3, -0.05], [0.7, 0.6, 0.95], (3000, 3))
    labels = rng.integers(0, 3, len(pts)).astype(np.uint8)
    rep = m.integrate(PointCloud(pts, 0.0, labels=labels, origin=sensor))
    ref = classify_points(pts, segs, radii, None, 0.0, m.grid, soft=labels == SOFT, sensor=sensor)
    assert np.array_equal(rep.status, ref)
    assert rep.counts["shadow"] > 50 and not np.any((rep.status == KD.SHADOW) & (labels == SOFT))
    # without an origin, or with the key off, no point is shadowed
    m2, *_ = _capsules(panda_robot, panda_robot.q_home, 0.03)
    assert m2.integrate(PointCloud(pts, 0.0, labels=labels)).counts["shadow"] == 0
    off = DepthMap(PerceptionConfig(self_shadow=False), panda_robot)
    off.record(0.0, panda_robot.q_home)
    assert off.integrate(PointCloud(pts, 0.0, labels=labels, origin=sensor)).counts["shadow"] == 0


def test_a_capsule_that_holds_the_sensor_casts_no_shadow(rng: np.random.Generator) -> None:
    """A wrist camera sits inside its own link's inflated capsule: that capsule's spans are empty and the
    points behind it are kept; another capsule still shadows what lies behind it, and its spans hold
    its image (the pinhole projection of points on its surface)."""
    segs = np.array([[[0.0, 0.0, 0.0], [0.0, 0.0, 0.2]], [[0.5, -0.05, 0.1], [0.5, 0.05, 0.1]]])
    radii = np.array([0.08, 0.05])
    sensor = np.array([0.0, 0.0, 0.1])  # inside capsule 0
    pose = np.eye(4)
    pose[:3, :3] = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # optical z along +x
    pose[:3, 3] = sensor
    boxes = np.empty((2, 6))
    KD.capsule_boxes(segs, radii, boxes)
    spans, reach = np.zeros((2, 240, 2), np.int32), np.zeros(2)
    union = SS.shadow_spans(segs, radii, pose, 300.0, 300.0, 160.0, 120.0, 320, 240, spans, reach)
    assert reach[1] == pytest.approx((0.5 - 0.05) ** 2)  # capsule 1's surface is 0.45 m from the camera
    assert np.all(spans[0, :, 0] > spans[0, :, 1])  # empty
    # capsule 1's surface, projected, lies in its spans; rows it does not reach have none
    a, b = segs[1]
    d = rng.normal(size=(4000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    surface = a + rng.uniform(0, 1, (4000, 1)) * (b - a) + radii[1] * d
    cam = (surface - sensor) @ pose[:3, :3]
    u = np.round(300.0 * cam[:, 0] / cam[:, 2] + 160.0).astype(int)
    v = np.round(300.0 * cam[:, 1] / cam[:, 2] + 120.0).astype(int)
    assert np.all((spans[1, v, 0] <= u) & (u <= spans[1, v, 1]))
    rows = np.nonzero(spans[1, :, 0] <= spans[1, :, 1])[0]
    assert 0 < len(rows) < 240 and union[1] == rows[0] and union[3] == rows[-1]
    assert spans[1, rows, 1].max() - spans[1, rows, 0].min() < 0.5 * 320  # far tighter than the image
    casts = SS.casting(segs, radii, *sensor)
    assert list(casts) == [False, True]
    behind_1 = np.array([1.0, 0.0, 0.1])  # straight ahead, behind capsule 1
    beside = np.array([1.0, 0.5, 0.1])
    assert SS.in_shadow_point(*sensor, *behind_1, segs, radii, boxes, casts)
    assert not SS.in_shadow_point(*sensor, *beside, segs, radii, boxes, casts)


def _canopy_camera(flying: float = 1.0):
    scen = Scenario.load("panda_canopy_depth", [f"camera.flying_pixels={flying}"])
    robot = scen.build_robot()
    return scen, robot, DepthCamera.from_scenario(scen, robot)


def test_the_image_path_shadows_what_the_cloud_path_shadows() -> None:
    """The image kernel's per-capsule rectangles cull nothing that matters: its statuses equal the cloud
    kernel's (no culling) on the same frame's back-projected points, with the camera's centre as the
    cloud's sensor, at configurations that put the arm near the camera and across the image."""
    scen, robot, cam = _canopy_camera()
    cfg = scen.perception_config()
    rng = np.random.default_rng(11)
    shadowed = 0
    for _ in range(4):
        q = robot.q_home + rng.uniform(-0.7, 0.7, robot.nq)
        img = DepthMap(cfg, robot)
        img.record(0.0, q)
        frame = cam.capture(q, 0.0)
        st = img.integrate(DepthFrame(frame.depth, frame.intrinsics, frame.pose, 0.0, None, frame.depth_scale)).status
        test = (st == KD.KEPT) | (st == KD.SHADOW) | (st == KD.OUTSIDE)
        v, u = np.nonzero(test)
        z = frame.depth[v, u].astype(float) * frame.depth_scale
        k, R, t = frame.intrinsics, frame.pose[:3, :3], frame.pose[:3, 3]
        xc, yc = (u - k.cx) * (1.0 / k.fx) * z, (v - k.cy) * (1.0 / k.fy) * z  # as the kernel rounds them
        pts = np.column_stack([R[a, 0] * xc + R[a, 1] * yc + R[a, 2] * z + t[a] for a in range(3)])
        cloud = DepthMap(cfg, robot)
        cloud.record(0.0, q)
        ref = cloud.integrate(PointCloud(pts, 0.0, origin=frame.pose[:3, 3])).status
        assert np.array_equal(st[v, u] == KD.SHADOW, ref == KD.SHADOW)
        shadowed += int((ref == KD.SHADOW).sum())
    assert shadowed > 100


@pytest.mark.parametrize("labels", [False, True])
def test_flying_pixels_at_the_robots_silhouette_never_become_rigid_points(labels: bool) -> None:
    """On the canopy with every depth edge a flying pixel (probability 1): without the shadow test some
    rigid or unlabelled flying returns beside the robot's silhouette are kept (the flying-pixel filter
    misses them), with it none is; the scenery it loses (hidden in the band around the silhouette) is
    under 3 % of what the camera keeps of it."""
    scen, robot, cam = _canopy_camera()
    if not labels:
        cam.config = dataclasses.replace(cam.config, labels=False)
    cfg0 = scen.perception_config()
    kept_near: dict[bool, int] = {}
    scenery: dict[bool, tuple[int, int]] = {}
    for shadow in (False, True):
        cfg = dataclasses.replace(cfg0, self_shadow=shadow)
        rng = np.random.default_rng(3)
        near_total, lost, kept = 0, 0, 0
        for _ in range(10):
            q = robot.q_home + rng.uniform(-0.6, 0.6, robot.nq)
            m = DepthMap(cfg, robot)
            m.record(0.0, q)
            frame = cam.capture(q, 0.0)
            st = m.integrate(frame).status
            truth = frame.truth
            rigid = np.ones(st.shape, bool) if frame.labels is None else frame.labels != SOFT
            beside = truth.robot.copy()  # within two pixels of the robot's silhouette
            for _ in range(2):
                grown = beside.copy()
                grown[1:] |= beside[:-1]
                grown[:-1] |= beside[1:]
                grown[:, 1:] |= beside[:, :-1]
                grown[:, :-1] |= beside[:, 1:]
                beside = grown
            near_total += int(((st == KD.KEPT) & rigid & truth.flying & beside).sum())
            surface = truth.scenery & ~truth.flying
            lost += int(((st == KD.SHADOW) & surface).sum())
            kept += int(((st == KD.KEPT) & surface).sum())
        kept_near[shadow] = near_total
        scenery[shadow] = (lost, kept)
    assert kept_near[False] > 0
    assert kept_near[True] == 0
    lost, kept = scenery[True]
    assert scenery[False][0] == 0 and lost < 0.03 * (lost + kept)
