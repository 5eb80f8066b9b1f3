"""The two ray casters of the simulated depth camera, against each other and an independent reference.

* qpctl's kernel (:mod:`qpctl.kernels.raycast`): its z-buffered image (each shape's rays only, inside
  the shape's screen bound) against its own brute force (every ray against every shape), so the
  culling is exact; and sampled rays against :func:`~qpctl.simulation.raycast_reference.reference_depth`, which
  sphere-traces python-fcl's distance and knows no intersection formula.
* The hit normals: a point backed off the surface along the normal by h is python-fcl's h away,
  with the hit point its nearest.
* ``mujoco.mj_multiRay`` in a MuJoCo model of the same scene (built by ``qpctl.adapters.mujoco``)
  against the kernel, pixel for pixel: the shape seen, the depth, the incidence; with a moving
  obstacle, rotated boxes and cylinders, and a wrist camera inside its own link's capsule.
"""

from __future__ import annotations

import math

import fcl
import numpy as np
import pytest

from qpctl import ConfigError, Scenario
from qpctl.geometry.obstacles import Obstacle
from qpctl.kernels import raycast as K
from qpctl.simulation.camera import CameraConfig, DepthCamera, NumbaCaster
from qpctl.simulation.raycast_reference import reference_depth


def random_obstacles(rng: np.random.Generator, count: int, lo: tuple[float, ...], hi: tuple[float, ...]) -> list[Obstacle]:
    """Spheres, capsules, boxes and cylinders at random places, sizes and (rotated) axes."""
    out = []
    for i in range(count):
        kind = ("sphere", "capsule", "box", "cylinder")[i % 4]
        c, axis = rng.uniform(lo, hi), rng.normal(size=3)
        if kind == "sphere":
            out.append(Obstacle(kind, c, radius=rng.uniform(0.03, 0.2), name=f"s{i}"))
        elif kind == "box":
            out.append(Obstacle(kind, c, size=rng.uniform(0.03, 0.3, 3), axis=axis, name=f"b{i}"))
        else:
            out.append(Obstacle(kind, c, radius=rng.uniform(0.02, 0.12), length=rng.uniform(0.05, 0.6), axis=axis,
                                name=f"c{i}"))
    return out


def primitives(obstacles: list[Obstacle], t: float = 0.0) -> K.Primitives:
    scene = K.Primitives.empty(len(obstacles))
    for i, o in enumerate(obstacles):
        K.obstacle_primitive(o, t, scene, i)
    return scene


def image_rays(W: int, H: int, f: float, R: np.ndarray) -> np.ndarray:
    u, v = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    cam = np.column_stack([((u - (W - 1) / 2) / f).ravel(), ((v - (H - 1) / 2) / f).ravel(), np.ones(W * H)])
    return cam @ R.T


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    Q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    Q = Q * np.sign(np.diag(r))
    return Q if np.linalg.det(Q) > 0 else -Q


@pytest.mark.parametrize("seed", range(4))
def test_image_equals_brute_force(seed):
    """The screen bounds drop no ray a shape covers: same shape and depth at every pixel, shapes in
    front, beside, behind, straddling the camera's plane and beyond its range included."""
    rng = np.random.default_rng(seed)
    obstacles = random_obstacles(rng, 40, (-1.5, -1.5, -1.5), (1.5, 1.5, 1.5))  # all around the camera
    origin, R = rng.uniform(-0.1, 0.1, 3), random_rotation(rng) if seed else np.eye(3)
    obstacles += [Obstacle("capsule", origin + R @ [0.3, 0.1, 0.0], radius=0.05, length=1.0, axis=R[:, 2]),  # across
                  Obstacle("box", origin + R @ [-0.2, 0.0, 0.1], size=[0.1, 0.1, 0.4], axis=R[:, 2]),  # the plane
                  Obstacle("sphere", origin + R @ [0.0, 0.0, -0.5], radius=0.3),  # behind
                  Obstacle("sphere", origin + R @ [0.0, 0.25, 0.05], radius=0.2),  # beside, across the plane
                  Obstacle("cylinder", origin + R @ [-0.1, -0.1, 0.3], radius=0.03, length=1.2, axis=R @ [1, 1, 0.2]),
                  Obstacle("capsule", origin + R @ [0.0, 0.06, 0.03], radius=0.05, length=1.0, axis=R[:, 0]),
                  Obstacle("capsule", origin + R @ [0.05, 0.0, -0.01], radius=0.049, length=1.0, axis=R[:, 1])]
    # two bars just before and beside the camera, across its whole view: on one plane each one's shadow
    # holds the camera, the second's axis behind it
    scene = primitives(obstacles)
    W, H, f = 96, 72, 60.0
    depth, hit, cos = np.empty((H, W)), np.empty((H, W), np.int32), np.empty((H, W))
    tests = K.cast_image(origin, R, f, f, (W - 1) / 2, (H - 1) / 2, *scene, np.ones(len(obstacles), bool), 2.0,
                         depth, hit, cos)
    dirs = image_rays(W, H, f, R)
    t, who = np.empty(len(dirs)), np.empty(len(dirs), np.int32)
    K.cast_rays(origin, dirs, *scene, 2.0, t, who)
    assert (hit.ravel() == who).all()
    seen = who >= 0
    assert np.isinf(depth.ravel()[~seen]).all()
    assert np.abs(depth.ravel()[seen] - t[seen]).max() < 1e-12  # the rays' directions round differently
    assert 0.02 < (who >= 0).mean() < 0.98  # a scene with hits and misses
    n = len(obstacles)
    seen_ids = set(who.tolist())
    assert {n - 7, n - 6, n - 2, n - 1} <= seen_ids and seen_ids & {n - 4, n - 3}  # seen across the camera's plane
    assert tests < W * H * len(obstacles) / 2  # the bounds cull


@pytest.mark.parametrize("seed", range(3))
def test_rays_against_fcl_sphere_tracing(seed):
    """Sampled rays: the shape hit and its depth (to 1e-7 m) as python-fcl's sphere tracing finds them."""
    rng = np.random.default_rng(100 + seed)
    obstacles = random_obstacles(rng, 12, (-0.5, -0.4, 0.6), (0.5, 0.4, 2.0))
    scene = primitives(obstacles)
    origin = np.zeros(3)
    dirs = image_rays(80, 60, 60.0, np.eye(3))
    t, who = np.empty(len(dirs)), np.empty(len(dirs), np.int32)
    K.cast_rays(origin, dirs, *scene, 5.0, t, who)
    pick = np.concatenate([rng.choice(np.flatnonzero(who >= 0), 150, replace=False),  # hits and misses alike
                           rng.choice(np.flatnonzero(who < 0), 100, replace=False)])
    dirs, t, who = dirs[pick], t[pick], who[pick]
    grazing = 0
    for k, d in enumerate(dirs):
        t_ref, j_ref = reference_depth(origin, d, obstacles, t_max=5.0)
        if math.isnan(t_ref):
            grazing += 1
            continue
        assert j_ref == who[k], f"ray {k}: fcl sees {j_ref}, the kernel {who[k]}"
        if j_ref >= 0:
            assert abs(t_ref - t[k]) < 1e-7
    assert grazing <= 2


def test_origin_inside_a_shape_is_not_seen():
    """A camera inside a shape sees out of it, as the reference (which skips it) does."""
    obstacles = [Obstacle("capsule", [0.0, 0.0, 0.05], radius=0.1, length=0.3, axis=[0, 1, 1]),
                 Obstacle("box", [0.02, 0.0, 0.0], size=[0.2, 0.2, 0.2], axis=[1, 0, 1]),
                 Obstacle("cylinder", [0.0, 0.03, 0.0], radius=0.1, length=0.1),
                 Obstacle("sphere", [0.0, 0.0, 1.0], radius=0.2)]
    scene = primitives(obstacles)
    inside = np.zeros(4, bool)
    K.contains_point(*scene, np.zeros(3), inside)
    assert inside.tolist() == [True, True, True, False]
    t, who = np.empty(1), np.empty(1, np.int32)
    K.cast_rays(np.zeros(3), np.array([[0.0, 0.0, 1.0]]), *scene, 5.0, t, who)
    assert who[0] == 3 and abs(t[0] - 0.8) < 1e-12
    assert reference_depth(np.zeros(3), np.array([0.0, 0.0, 1.0]), obstacles)[1] == 3


def test_contains_against_fcl(rng):
    """Inside/outside of random points as python-fcl's collision test says (points off the surface)."""
    obstacles = random_obstacles(rng, 8, (-0.1, -0.1, -0.1), (0.1, 0.1, 0.1))
    scene = primitives(obstacles)
    point = fcl.CollisionObject(fcl.Sphere(0.0), fcl.Transform(np.zeros(3)))
    inside = np.zeros(len(obstacles), bool)
    counts = [0, 0]
    for p in rng.uniform(-0.3, 0.3, (300, 3)):
        K.contains_point(*scene, p, inside)
        point.setTranslation(p)
        for j, o in enumerate(obstacles):
            shape = fcl.CollisionObject(o.geometry(), o.transform(0.0))
            gap = fcl.distance(point, shape, fcl.DistanceRequest(), fcl.DistanceResult())
            if abs(gap) < 1e-9:
                continue
            assert inside[j] == (gap < 0), (j, p)
            counts[int(inside[j])] += 1
    assert min(counts) > 50


def test_hit_normals_against_fcl(rng):
    """At a hit point p with normal n, p + h n is h from the shape and p its nearest point (python-fcl)."""
    obstacles = random_obstacles(rng, 8, (-0.4, -0.3, 0.8), (0.4, 0.3, 1.6))
    scene = primitives(obstacles)
    dirs = image_rays(64, 48, 45.0, np.eye(3))
    t, who = np.empty(len(dirs)), np.empty(len(dirs), np.int32)
    K.cast_rays(np.zeros(3), dirs, *scene, 5.0, t, who)
    hits = np.flatnonzero(who >= 0)
    assert len(hits) > 100
    n = np.zeros(3)
    probe = fcl.CollisionObject(fcl.Sphere(0.0), fcl.Transform(np.zeros(3)))
    request = fcl.DistanceRequest(enable_nearest_points=True)
    h = 1e-3  # along a valid outward normal of a convex shape the nearest point stays p, edges included
    for k in rng.choice(hits, 150, replace=False):
        i = int(who[k])
        p = t[k] * dirs[k]
        K.surface_normal(i, *scene, p[0], p[1], p[2], n)
        assert abs(np.linalg.norm(n) - 1) < 1e-12 and n @ dirs[k] <= 0  # outward, facing the camera
        o = obstacles[i]
        probe.setTranslation(p + h * n)
        result = fcl.DistanceResult()
        gap = fcl.distance(probe, fcl.CollisionObject(o.geometry(), o.transform(0.0)), request, result)
        assert abs(gap - h) < 1e-9, (o.shape, gap)
        assert np.linalg.norm(np.asarray(result.nearest_points[1]) - p) < 1e-6


# -- mj_multiRay in a MuJoCo model of the same scene ---------------------------------------------------
mujoco = pytest.importorskip("mujoco")


def _pair(robot, obstacles, cfg):
    from qpctl.adapters.mujoco import scene_caster

    numba_cam, mujoco_cam = DepthCamera(cfg, robot, obstacles), DepthCamera(cfg, robot, obstacles)
    mujoco_cam.caster = scene_caster(mujoco_cam)
    return numba_cam, mujoco_cam


def _agree(a, b, min_hits: int) -> None:
    assert (a.hit == b.hit).mean() > 0.9995
    same = (a.hit == b.hit) & (a.hit >= 0)
    assert same.sum() > min_hits
    assert np.abs(a.depth[same] - b.depth[same]).max() < 1e-9
    assert np.abs(a.cos_incidence - b.cos_incidence)[same].max() < 1e-6


def test_mujoco_multiray_matches_the_kernel(panda_robot, rng):
    """A world camera on the Panda at two configurations among rotated shapes, one moving: the same
    shape, depth (1e-9 m) and incidence at (nearly) every pixel."""
    obstacles = random_obstacles(rng, 16, (0.3, -0.5, 0.1), (0.9, 0.5, 0.9))
    obstacles.append(Obstacle("sphere", [-0.13, -0.49, 0.89], radius=0.05, velocity=[0.0, 0.4, 0.0],
                              name="moving"))
    cfg = CameraConfig(mount="world", position=[-0.4, -0.5, 1.1], look_at=[0.5, 0.0, 0.4], width=160, height=120)
    a_cam, b_cam = _pair(panda_robot, obstacles, cfg)
    for q, t in ((panda_robot.q_home, 0.0), (panda_robot.q_home + rng.uniform(-0.4, 0.4, 7), 0.7)):
        _, a = a_cam.render(q, t)
        _, b = b_cam.render(q, t)
        _agree(a, b, 3000)
        assert (a.hit == len(obstacles) - 1).any()  # the moving sphere, where it is at t
        assert (a_cam.source[a.hit[a.hit >= 0]] == 3).any()  # and the robot's own links


def test_wrist_camera_inside_its_link_capsule(panda_robot):
    """A camera on the hand, inside link 7's capsule: both casters look out of it, see the fingers'
    neighbours and the scene, never the capsule that holds them."""
    obstacles = [Obstacle("box", [0.45, 0.0, 0.05], size=[0.6, 0.8, 0.1], name="table"),
                 Obstacle("sphere", [0.35, 0.05, 0.2], radius=0.04, name="fruit")]
    cfg = CameraConfig(mount="panda_hand", position=[0.05, 0.0, 0.02], quaternion=[0.0, 0.0, 0.0, 1.0],
                       width=120, height=90, range_min=0.0)
    a_cam, b_cam = _pair(panda_robot, obstacles, cfg)
    _, a = a_cam.render(panda_robot.q_home, 0.0)
    _, b = b_cam.render(panda_robot.q_home, 0.0)
    _agree(a, b, 5000)
    link7 = a_cam.names.index("panda_joint7")
    assert not (a.hit == link7).any()
    assert (a.hit == 0).mean() > 0.5 and (a.hit == 1).any()


def test_camera_in_the_mujoco_simulators_live_model(panda_robot):
    """In the MuJoCo simulator (caster "auto") the camera casts in the simulator's own model, which
    holds the scenario's obstacles and the arm; it sees what the kernel sees."""
    from qpctl.adapters.mujoco import MujocoSimulator

    scen_keys = ["camera.mount=world", "camera.position=[-0.3, -0.6, 1.0]", "camera.look_at=[0.6, 0.0, 0.4]",
                 "camera.width=160", "camera.height=120"]
    scen = Scenario.load("panda_canopy", overrides=[*scen_keys, "sim.simulator=mujoco"])
    sim = MujocoSimulator.from_scenario(scen.build_controller(robot=panda_robot), scen)
    live = DepthCamera.from_scenario(scen, panda_robot, simulator=sim)
    from qpctl.adapters.mujoco_camera import MujocoCaster

    assert isinstance(live.caster, MujocoCaster) and live.caster.model is sim.model
    with pytest.raises(ConfigError) as err:  # MuJoCo's casting outside the MuJoCo simulator
        DepthCamera.from_scenario(Scenario.load("panda_canopy", overrides=[*scen_keys, "camera.caster=mujoco"]))
    assert err.value.key == "camera.caster"
    assert isinstance(DepthCamera.from_scenario(Scenario.load("panda_canopy", overrides=[
        *scen_keys, "camera.caster=numba"]), panda_robot, simulator=sim).caster, NumbaCaster)
    ours = DepthCamera.from_scenario(scen, panda_robot)
    q = panda_robot.q_home + 0.2
    _agree(ours.render(q, 0.0)[1], live.render(q, 0.0)[1], 2000)


def test_a_users_own_model_is_seen_as_the_robot():
    """examples/my_arm.xml (the user's MJCF, its own link geoms): MuJoCo sees the user's geoms and
    names them "robot"; where they are, the kernel sees qpctl's link capsules of the same size."""
    from pathlib import Path

    from qpctl.adapters.mujoco import MujocoSimulator

    toml = Path(__file__).resolve().parents[1] / "examples" / "my_arm.toml"
    scen = Scenario.load(toml, overrides=["camera.mount=world", "camera.position=[0.0, -1.0, 2.5]",
                                          "camera.look_at=[0.0, -1.0, 0.0]", "camera.up=[0, 1, 0]",
                                          "camera.width=240", "camera.height=180"])
    robot = scen.build_robot()
    sim = MujocoSimulator.from_scenario(scen.build_controller(robot=robot), scen)
    live = DepthCamera.from_scenario(scen, robot, simulator=sim)
    ours = DepthCamera.from_scenario(scen, robot)
    q = scen.q0(robot)
    a, b = ours.render(q, 0.0)[1], live.render(q, 0.0)[1]
    robot_a = a.hit >= len(ours.obstacles)
    assert (b.hit[robot_a] == live.id_robot).all() and robot_a.sum() > 200
    assert ((b.hit == live.id_robot) == robot_a).mean() > 0.995
    assert (a.hit[~robot_a] == b.hit[~robot_a]).all() and (b.hit == 0).sum() > 30  # obstacle A
    both = np.isfinite(a.depth) & np.isfinite(b.depth)
    assert np.abs(a.depth[both] - b.depth[both]).max() < 1e-9
