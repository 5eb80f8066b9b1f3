"""The simulated depth camera: projection and mounts, the noise model's statistics, labels and truth,
encodings, the frame schedule, its scenario keys.

Independent references: python-fcl (a back-projected pixel lies on the surface it saw), Pinocchio's
frame placement (a wrist camera's pose), the noise formulas (σ = σ₀ + k z², binomial dropout counts),
the frames' own contract (:class:`~qpctl.perception.frames.DepthFrame` checks every frame).
"""

from __future__ import annotations

import math

import fcl
import numpy as np
import pinocchio as pin
import pytest

from qpctl import ConfigError, Obstacle, Scenario
from qpctl.perception import RIGID, SOFT, UNLABELED, DepthFrame
from qpctl.simulation.camera import EDGE_JUMP, CameraConfig, DepthCamera


def wall_camera(robot, distance=1.0, tilt_deg=0.0, **keys):
    """A world camera at (0, 0, 1) looking along +x at a 6 m wide, 1 cm thin wall whose face passes
    through the point ``distance`` ahead, its normal turned ``tilt_deg`` about z from the view (the
    incidence at the image's centre); the robot out of view behind the camera."""
    a = math.radians(tilt_deg)
    normal = np.array([-math.cos(a), -math.sin(a), 0.0])  # towards the camera
    wall = Obstacle("box", np.array([distance, 0.0, 1.0]) - 0.005 * normal, size=[6.0, 6.0, 0.01], axis=normal,
                    name="wall")
    cfg = CameraConfig(mount="world", position=[0.0, 0.0, 1.0], look_at=[1.0, 0.0, 1.0], **keys)
    return DepthCamera(cfg, robot, [wall])


def back_project(frame, depth):
    k = frame.intrinsics
    v, u = np.nonzero(np.isfinite(depth) & (depth > 0))
    z = depth[v, u]
    cam = np.column_stack([(u - k.cx) * z / k.fx, (v - k.cy) * z / k.fy, z])
    return cam @ frame.pose[:3, :3].T + frame.pose[:3, 3], v, u


def test_pixels_back_project_onto_the_surfaces_they_saw(panda_robot):
    """Every noise-free return, back-projected with the frame's intrinsics and pose (DESIGN §6's
    convention), lies on the obstacle the truth names (python-fcl distance ≈ 0)."""
    obstacles = [Obstacle("sphere", [0.6, 0.2, 0.5], radius=0.07, name="leaf", material="soft"),
                 Obstacle("capsule", [0.7, -0.1, 0.5], radius=0.03, length=0.5, axis=[0, 1, 0.3], name="branch"),
                 Obstacle("cylinder", [0.5, -0.3, 0.3], radius=0.05, length=0.2, axis=[1, 0, 1], name="stem")]
    cam = DepthCamera(CameraConfig(mount="world", position=[-0.2, -0.6, 1.0], look_at=[0.6, 0.0, 0.4],
                                   width=200, height=150, noise=False), panda_robot, obstacles)
    frame = cam.capture(panda_robot.q_home, 0.0)
    DepthFrame(frame.depth, frame.intrinsics, frame.pose, frame.stamp, frame.labels)  # the frames' contract
    assert np.abs(frame.metres() - np.nan_to_num(frame.truth.depth)).max() < 1e-6  # float32 of the truth
    pts, v, u = back_project(frame, frame.truth.depth)
    hit = frame.truth.hit[v, u]
    probe = fcl.CollisionObject(fcl.Sphere(0.0), fcl.Transform(np.zeros(3)))
    seen = set()
    for j, o in enumerate(obstacles):
        shape = fcl.CollisionObject(o.geometry(), o.transform(0.0))
        for p in pts[hit == j][::7]:
            back = p - frame.pose[:3, 3]
            probe.setTranslation(p - 1e-7 * back / np.linalg.norm(back))  # a step back along the ray: outside
            gap = fcl.distance(probe, shape, fcl.DistanceRequest(), fcl.DistanceResult())  # exact (unsigned)
            assert 0 <= gap < 2e-7
            seen.add(j)
    assert seen == {0, 1, 2}
    assert frame.truth.robot.any()  # the arm is in view too


def test_look_at_centres_the_target(panda_robot):
    """The principal point's ray passes through look_at; 'up' is up in the image (−y)."""
    cfg = CameraConfig(mount="world", position=[-0.3, 0.4, 1.2], look_at=[0.5, -0.1, 0.3], width=101, height=81)
    R = cfg.mount_pose()[:3, :3]
    view = np.array([0.8, -0.5, -0.9])
    assert np.allclose(R[:, 2], view / np.linalg.norm(view))
    assert np.allclose(R.T @ R, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)
    assert R[:, 1] @ [0.0, 0.0, 1.0] < 0  # image y (down) against the world's up
    ball = Obstacle("sphere", [0.5, -0.1, 0.3], radius=0.02, name="target")
    cam = DepthCamera(CameraConfig(**{**cfg.__dict__, "noise": False}), panda_robot, [ball])
    _, hits = cam.render(np.array([0.0, -1.5, 0.0, -2.9, 0.0, 1.5, 0.0]), 0.0)
    assert hits.hit[40, 50] == 0
    assert abs(hits.depth[40, 50] - (np.linalg.norm(view) - 0.02)) < 1e-9


def test_intrinsics_from_keys():
    k = CameraConfig(mount="world", position=[0, 0, 0], fx=600.0, cx=300.0).intrinsics()
    assert (k.fx, k.fy, k.cx, k.cy, k.width, k.height) == (600.0, 600.0, 300.0, 239.5, 640, 480)
    k = CameraConfig(mount="world", position=[0, 0, 0], width=320, height=240, fov_y=90.0).intrinsics()
    assert math.isclose(k.fy, 120.0) and math.isclose(k.cx, 159.5)


def test_wrist_camera_rides_its_frame(panda_robot, rng):
    """On panda_hand the pose is Pinocchio's oMf(q) times the mount; a ball fixed in the hand's frame
    stays at the same pixel and depth whatever q."""
    cfg = CameraConfig(mount="panda_hand", position=[0.06, 0.0, 0.03], look_at=[0.0, 0.0, 0.3],
                       up=[1.0, 0.0, 0.0], width=80, height=60, noise=False)
    cam = DepthCamera(cfg, panda_robot, [])
    data = panda_robot.model.createData()
    fid = panda_robot.model.getFrameId("panda_hand")
    pixels = []
    for _ in range(3):
        q = panda_robot.q_home + rng.uniform(-0.5, 0.5, 7)
        pin.framesForwardKinematics(panda_robot.model, data, q)
        oMf = data.oMf[fid].homogeneous
        assert np.allclose(cam.pose(q), oMf @ cfg.mount_pose())
        ball = Obstacle("sphere", (oMf @ [0.0, 0.01, 0.3, 1.0])[:3], radius=0.02, name="ball")
        other = DepthCamera(cfg, panda_robot, [ball])
        _, hits = other.render(q, 0.0)
        v, u = np.nonzero(hits.hit == 0)
        pixels.append((u.mean(), v.mean(), hits.depth[hits.hit == 0].min()))
    assert np.allclose(pixels, pixels[0], atol=1e-6)


def test_depth_noise_sigma_and_dropout(panda_robot):
    """Facing a wall at 1.5 m: the depth error's spread is σ₀ + k z² (±5 %), the lost returns a
    binomial(dropout) count (±4σ), no flying pixels inside a flat wall."""
    cam = wall_camera(panda_robot, 1.5, width=320, height=240, sigma_0=0.001, sigma_z2=0.004, dropout=0.02)
    frame = cam.capture(panda_robot.q_home, 0.5)
    truth = frame.truth
    wall = truth.hit == 0
    assert wall.all()
    z = frame.metres()
    ok = z > 0
    err = (z - truth.depth)[ok]
    sigma = 0.001 + 0.004 * truth.depth[ok] ** 2
    assert abs(np.std(err / sigma) - 1.0) < 0.05 and abs(np.mean(err / sigma)) < 0.02
    n, p = wall.sum(), 0.02
    assert abs((~ok).sum() - n * p) < 4 * math.sqrt(n * p * (1 - p))
    assert (truth.dropped == ~ok).all() and not truth.flying.any()


@pytest.mark.parametrize(("tilt", "lost"), [(70.0, False), (85.0, True)])
def test_grazing_returns_are_lost(panda_robot, tilt, lost):
    """A wall turned 85° from the view is lost past grazing_deg = 80; one at 70° is not."""
    cam = wall_camera(panda_robot, 1.0, tilt, width=64, height=48, dropout=0.0)
    frame = cam.capture(panda_robot.q_home, 0.0)
    centre = (slice(None), slice(30, 34))  # columns within ±2.5° of the optical axis
    assert (frame.truth.hit[centre] == 0).all()
    returned = frame.depth[centre] > 0
    assert (~returned).all() if lost else returned.all()


def test_flying_pixels_at_depth_edges_only(panda_robot):
    """A ball in front of a wall: flying pixels lie on the ball's silhouette (an edge of the true
    depth image), about flying_pixels of those edges, at a depth between ball and wall."""
    wall = Obstacle("box", [2.0, 0.0, 1.0], size=[0.02, 4.0, 3.0], name="wall")
    ball = Obstacle("sphere", [1.0, 0.0, 1.0], radius=0.15, name="ball")
    cfg = CameraConfig(mount="world", position=[0.0, 0.0, 1.0], look_at=[1.0, 0.0, 1.0], width=160, height=120,
                       flying_pixels=0.4, dropout=0.0, sigma_0=0.0, sigma_z2=0.0)
    frame = DepthCamera(cfg, panda_robot, [wall, ball]).capture(panda_robot.q_home, 0.0)
    z_true, fly = frame.truth.depth, frame.truth.flying
    pad = np.pad(z_true, 1, constant_values=np.nan)
    neighbours = np.stack([pad[:-2, 1:-1], pad[2:, 1:-1], pad[1:-1, :-2], pad[1:-1, 2:]])
    with np.errstate(invalid="ignore"):
        edge = (np.abs(neighbours - z_true) > EDGE_JUMP).any(axis=0)
    assert edge.sum() > 100
    assert not (fly & ~edge).any()
    assert abs(fly.sum() / edge.sum() - 0.4) < 0.1
    z = frame.metres()
    lo, hi = np.nanmin(neighbours, axis=0), np.nanmax(neighbours, axis=0)
    assert ((z[fly] >= np.minimum(lo, z_true)[fly]) & (z[fly] <= np.maximum(hi, z_true)[fly])).all()
    assert (z[~fly & (z > 0)] == z_true[~fly & (z > 0)].astype(np.float32)).all()  # no noise asked


def test_seeded_and_stamped(panda_robot):
    """The same (q, t, seed) gives the same frame; another stamp or seed other noise."""
    cam = wall_camera(panda_robot, 1.0, width=64, height=48)
    a, b = cam.capture(panda_robot.q_home, 0.2), cam.capture(panda_robot.q_home, 0.2)
    c = cam.capture(panda_robot.q_home, 0.2 + 1 / 30)
    d = wall_camera(panda_robot, 1.0, width=64, height=48, seed=3).capture(panda_robot.q_home, 0.2)
    assert np.array_equal(a.depth, b.depth) and a.stamp == 0.2
    assert not np.array_equal(a.depth, c.depth) and not np.array_equal(a.depth, d.depth)


def test_labels_and_truth(panda_robot):
    """Soft obstacles SOFT, rigid ones RIGID, the robot and the scenery UNLABELED with their truth
    masks; pixels without a return UNLABELED; labels = false gives none."""
    obstacles = [Obstacle("sphere", [0.75, -0.45, 0.55], radius=0.08, material="soft", name="leaf"),
                 Obstacle("capsule", [0.7, -0.2, 0.5], radius=0.04, length=0.4, name="branch")]
    fruit = Obstacle("sphere", [0.55, 0.0, 0.8], radius=0.04, name="fruit")
    cfg = CameraConfig(mount="world", position=[-0.3, -0.6, 1.0], look_at=[0.6, 0.0, 0.5], width=160, height=120)
    cam = DepthCamera(cfg, panda_robot, obstacles, scenery=[fruit])
    frame = cam.capture(panda_robot.q_home, 0.0)
    t, lab, ret = frame.truth, frame.labels, frame.depth > 0
    assert (lab[(t.hit == 0) & ret] == SOFT).all() and ((t.hit == 0) & ret).sum() > 50
    assert (lab[(t.hit == 1) & ret] == RIGID).all() and ((t.hit == 1) & ret).sum() > 50
    assert t.robot.sum() > 200 and (lab[t.robot] == UNLABELED).all()
    assert t.scenery.sum() > 10 and (t.hit[t.scenery] == 2).all() and t.names[2] == "fruit"
    assert (lab[~ret] == UNLABELED).all()
    assert set(np.unique(t.hit[t.robot])) <= {cam.names.index(c.name) for c in panda_robot.capsules}
    off = DepthCamera(CameraConfig(**{**cfg.__dict__, "labels": False}), panda_robot, obstacles)
    assert off.capture(panda_robot.q_home, 0.0).labels is None


def test_uint16_encoding_and_range(panda_robot):
    """uint16 in depth_scale units reads back to the metres image to half a unit; a surface nearer
    than range_min returns 0 and counts as dropped."""
    keys = {"width": 64, "height": 48, "noise": False}
    metres = wall_camera(panda_robot, 1.2, **keys).capture(panda_robot.q_home, 0.0)
    raw = wall_camera(panda_robot, 1.2, encoding="uint16", depth_scale=0.0005, **keys).capture(panda_robot.q_home, 0.0)
    assert raw.depth.dtype == np.uint16 and raw.depth_scale == 0.0005
    assert np.abs(raw.metres() - metres.metres()).max() <= 0.00025 + 1e-9
    near = wall_camera(panda_robot, 0.08, **keys).capture(panda_robot.q_home, 0.0)
    assert (near.depth == 0).all() and near.truth.dropped.all()
    far = wall_camera(panda_robot, 3.5, **keys).capture(panda_robot.q_home, 0.0)
    assert (far.depth == 0).all() and (far.truth.hit == -1).all() and not far.truth.dropped.any()


def test_frame_schedule(panda_robot):
    """due() marks exactly one tick per frame period: 30 frames in 1 s at 1 kHz, at k/30 s."""
    cam = wall_camera(panda_robot, rate=30.0)
    ticks = [k for k in range(1000) if cam.due(k * 1e-3, 1e-3)]
    assert len(ticks) == 30
    assert all(abs(k * 1e-3 - i / 30) < 1e-3 for i, k in enumerate(ticks))


# -- scenario keys ----------------------------------------------------------------------------------------
def _load(*overrides: str) -> Scenario:
    return Scenario.load("panda_canopy", overrides=list(overrides))


def test_camera_keys_in_a_scenario(panda_robot):
    scen = _load("camera.mount=world", "camera.position=[-0.3, -0.6, 1.0]", "camera.look_at=[0.6, 0.0, 0.4]",
                 "camera.rate=15", "camera.encoding=uint16")
    cam = DepthCamera.from_scenario(scen, panda_robot)
    assert cam.config.rate == 15.0 and len(cam.obstacles) == len(scen.build_obstacles())
    frame = cam.capture(panda_robot.q_home, 0.0)
    assert frame.depth.dtype == np.uint16 and frame.depth.shape == (480, 640)
    assert not _load().camera_config().enabled


@pytest.mark.parametrize(("overrides", "key"), [
    (["camera.rate=15"], "camera.mount"),  # a [camera] without its mount
    (["camera.mount=world"], "camera.position"),
    (["camera.mount=panda_nowhere"], "camera.mount"),
    (["camera.mount=panda_hand", "camera.look_at=[0, 0, 1]", "camera.quaternion=[0, 0, 0, 1]"], "camera.quaternion"),
    (["camera.mount=panda_hand", "camera.position=[0, 0, 0]", "camera.look_at=[0, 0, 0]"], "camera.look_at"),
    (["camera.mount=panda_hand", "camera.look_at=[0, 0, 1]", "camera.up=[0, 0, 2]"], "camera.up"),
    (["camera.mount=panda_hand", "camera.dropout=1.0"], "camera.dropout"),
    (["camera.mount=panda_hand", "camera.flying_pixels=-0.1"], "camera.flying_pixels"),
    (["camera.mount=panda_hand", "camera.range_min=3.0"], "camera.range_min"),
    (["camera.mount=panda_hand", "camera.fov_y=180"], "camera.fov_y"),
    (["camera.mount=panda_hand", "camera.fx=-5"], "camera.fx"),
    (["camera.mount=panda_hand", "camera.fy=500"], "camera.fy"),
    (["camera.mount=panda_hand", "camera.width=0"], "camera.width"),
    (["camera.mount=panda_hand", "camera.encoding=png"], "camera.encoding"),
    (["camera.mount=panda_hand", "camera.caster=opengl"], "camera.caster"),
    (["camera.mount=panda_hand", "camera.rate=0"], "camera.rate"),
    (["camera.mount=panda_hand", "camera.seed=-1"], "camera.seed"),
    (["camera.mount=panda_hand", "camera.position=[1, 2]"], "camera.position"),
    (["camera.mount=panda_hand", "camera.lens=wide"], "camera.lens"),
])
def test_bad_camera_keys_name_the_key(overrides, key):
    with pytest.raises(ConfigError) as err:
        _load(*overrides)
    assert err.value.key == key
    assert err.value.source == ("--set" if key == "camera.lens" else "panda_canopy (packaged)")
