"""Capsules fitted to a robot's meshes (qpctl.robot.capsules, ``qpctl fit-capsules``).

Checked against independent computations: python-fcl's signed distance from every mesh vertex (the
meshes read here with trimesh straight from example-robot-data's files) to the fitted capsules,
scipy's convex hull volume, a capsule's volume from its formula (one capsule) or a voxel count (two),
and known shapes (points on a capsule's own surface, on a sphere) whose least capsule is known.
"""

from __future__ import annotations

import math
from pathlib import Path

import fcl
import numpy as np
import pinocchio as pin
import pytest
import trimesh
from scipy.spatial import ConvexHull

from qpctl.errors import ConfigError
from qpctl.robot.capsules import (
    Capsule,
    file_geometry,
    fit_capsule,
    fit_link,
    fit_links,
    read_capsules,
    write_capsules,
)
from qpctl.robot.model import example_robot_data_path

TOL = 1e-3  # [m] the target: every vertex inside to 1 mm
FCL_TOL = 2e-4  # [m] python-fcl's signed distance (GJK/EPA) is off by up to ~1e-4 m on a surface point


def fcl_signed_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray, radius: float) -> np.ndarray:
    """python-fcl's signed distance [m] of each point to the capsule a–b of ``radius`` (negative inside)."""
    axis = np.asarray(b, float) - np.asarray(a, float)
    length = float(np.linalg.norm(axis))
    z = axis / length if length > 1e-12 else np.array([0.0, 0.0, 1.0])
    R = pin.Quaternion.FromTwoVectors(np.array([0.0, 0.0, 1.0]), z).matrix()
    cap = fcl.CollisionObject(fcl.Capsule(radius, length), fcl.Transform(R, 0.5 * (np.asarray(a) + np.asarray(b))))
    req = fcl.DistanceRequest(enable_signed_distance=True)
    out = np.empty(len(points))
    for i, p in enumerate(points):
        out[i] = fcl.distance(fcl.CollisionObject(fcl.Sphere(1e-9), fcl.Transform(np.asarray(p, float))), cap, req,
                              fcl.DistanceResult())
    return out


def capsule_surface(a: np.ndarray, b: np.ndarray, r: float, n: int, rng: np.random.Generator) -> np.ndarray:
    """Points on the capsule's surface: its cylinder and both hemispherical caps."""
    axis = b - a
    d = axis / np.linalg.norm(axis)
    e1 = np.cross(d, [1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(d, e1)
    th = rng.uniform(0, 2 * np.pi, n)
    side = a + rng.uniform(0, 1, n)[:, None] * axis + r * (np.cos(th)[:, None] * e1 + np.sin(th)[:, None] * e2)
    u = rng.normal(size=(2 * n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    caps = np.vstack([a + r * u[:n] * np.where(u[:n] @ d > 0, -1, 1)[:, None],
                      b + r * u[n:] * np.where(u[n:] @ d < 0, -1, 1)[:, None]])
    return np.vstack([side, caps])


def voxel_union_volume(capsules: list[Capsule], h: float = 2e-3) -> float:
    """Volume [m³] of a union of capsules by counting the centres of h-sized voxels inside one."""
    lo = np.min([np.minimum(c.a, c.b) - c.radius for c in capsules], axis=0)
    hi = np.max([np.maximum(c.a, c.b) + c.radius for c in capsules], axis=0)
    axes = [np.arange(lo[k] + h / 2, hi[k], h) for k in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    inside = np.zeros(len(grid), bool)
    for c in capsules:
        ab = c.b - c.a
        s = np.clip((grid - c.a) @ ab / max(float(ab @ ab), 1e-18), 0, 1)
        inside |= np.linalg.norm(grid - (c.a + s[:, None] * ab), axis=1) <= c.radius
    return float(inside.sum() * h**3)


def test_fit_recovers_a_capsule_from_points_on_its_surface(rng):
    a, b, r = np.array([0.1, -0.2, 0.3]), np.array([0.25, 0.05, 0.1]), 0.06
    pts = capsule_surface(a, b, r, 600, rng)
    fit = fit_capsule(pts)
    true_volume = math.pi * r * r * np.linalg.norm(b - a) + 4 / 3 * math.pi * r**3
    assert fcl_signed_distance(pts, fit.a, fit.b, fit.radius).max() <= FCL_TOL
    assert fit.volume <= 1.01 * true_volume  # no larger than the capsule the points came from
    assert abs(fit.radius - r) < 2e-3
    ends = sorted([fit.a, fit.b], key=lambda p: np.linalg.norm(p - a))
    assert np.linalg.norm(ends[0] - a) < 5e-3 and np.linalg.norm(ends[1] - b) < 5e-3


def test_fit_of_a_sphere_is_the_sphere(rng):
    u = rng.normal(size=(400, 3))
    pts = 0.08 * u / np.linalg.norm(u, axis=1, keepdims=True) + [0.3, 0.1, -0.2]
    fit = fit_capsule(pts)
    assert fit.radius <= 0.0805 and np.linalg.norm(fit.b - fit.a) < 0.01
    assert fcl_signed_distance(pts, fit.a, fit.b, fit.radius).max() <= FCL_TOL


def test_fit_holds_every_point_of_random_clouds(rng):
    for _ in range(5):
        pts = rng.normal(size=(200, 3)) * rng.uniform(0.01, 0.2, 3) + rng.uniform(-1, 1, 3)
        fit = fit_capsule(pts)
        assert fcl_signed_distance(pts, fit.a, fit.b, fit.radius).max() <= FCL_TOL
        # and it is tighter than the bounding sphere about the centroid (a crude upper bound)
        assert fit.volume <= 4 / 3 * math.pi * np.linalg.norm(pts - pts.mean(0), axis=1).max() ** 3 + 1e-12


PANDA_LINKS = [f"panda_link{i}" for i in range(8)] + ["panda_hand", "panda_leftfinger", "panda_rightfinger"]


@pytest.fixture(scope="module")
def panda_fits():
    geometry = [g for g in file_geometry(example_robot_data_path("panda_description/urdf/panda.urdf"))
                if g.link in PANDA_LINKS]
    return {f.link: f for f in fit_links(geometry)}


def panda_finger_corners(link: str) -> np.ndarray:
    """The corners (k, 3) [m] of a finger's collision boxes, read from the URDF's XML (origin xyz, rpy
    and size of each <box>) in the finger's frame."""
    import xml.etree.ElementTree as ET

    root = ET.parse(example_robot_data_path("panda_description/urdf/panda.urdf")).getroot()
    node = next(n for n in root.iter("link") if n.get("name") == link)
    out = []
    for col in node.iter("collision"):
        origin, box = col.find("origin"), col.find("geometry/box")
        xyz = np.array([float(x) for x in origin.get("xyz").split()])
        R = pin.rpy.rpyToMatrix(*[float(x) for x in origin.get("rpy").split()])
        half = 0.5 * np.array([float(x) for x in box.get("size").split()])
        signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T
        out.append(xyz + (signs * half) @ R.T)
    return np.vstack(out)


def panda_mesh_vertices(link: str) -> np.ndarray:
    """The link's collision mesh as trimesh reads it from the package (link frame: the Panda's URDF
    places every collision mesh at its link's origin); a finger's box corners."""
    if link.endswith("finger"):
        return panda_finger_corners(link)
    name = link.removeprefix("panda_")
    path = example_robot_data_path(f"panda_description/meshes/collision/{name}.stl")
    return np.asarray(trimesh.load(path, force="mesh").vertices, float)


@pytest.mark.parametrize("link", PANDA_LINKS)
def test_panda_link_capsules_hold_every_mesh_vertex(panda_fits, link):
    fit = panda_fits[link]
    verts = panda_mesh_vertices(link)
    d = np.min([fcl_signed_distance(verts, c.a, c.b, c.radius) for c in fit.capsules], axis=0)
    assert d.max() <= TOL, f"{link}: a vertex {d.max() * 1e3:.2f} mm outside"
    assert fit.max_outside <= TOL


@pytest.mark.parametrize("link", PANDA_LINKS)
def test_panda_link_capsules_within_twice_the_hull(panda_fits, link):
    fit = panda_fits[link]
    hull = ConvexHull(panda_mesh_vertices(link)).volume
    assert fit.hull_volume == pytest.approx(hull, rel=1e-6)
    volume = voxel_union_volume(list(fit.capsules))
    assert fit.volume == pytest.approx(volume, rel=0.03)
    assert volume <= 2.0 * hull, f"{link}: {volume / hull:.2f} × the hull"
    if len(fit.capsules) == 1:  # one capsule: the formula
        c = fit.capsules[0]
        assert fit.volume == pytest.approx(math.pi * c.radius**2 * np.linalg.norm(c.b - c.a)
                                           + 4 / 3 * math.pi * c.radius**3, rel=1e-12)


def test_panda_l_shaped_links_get_two_capsules(panda_fits):
    # link 6, the hand and the fingers are where one capsule is poor (2.0, 2.2 and 2.3 × their hulls)
    assert len(panda_fits["panda_link6"].capsules) == 2
    assert len(panda_fits["panda_hand"].capsules) == 2
    assert len(panda_fits["panda_leftfinger"].capsules) == 2
    assert len(panda_fits["panda_link4"].capsules) == 1


def test_a_third_capsule_only_where_two_exceed_twice_the_hull(panda_fits):
    """The base (a squat block: one capsule 2.36 ×, the best two 2.11 × its hull) gets three; no
    other Panda link needs them."""
    assert len(panda_fits["panda_link0"].capsules) == 3
    assert all(len(f.capsules) <= 2 for link, f in panda_fits.items() if link != "panda_link0")
    verts = panda_mesh_vertices("panda_link0")
    two, v_two, hull = fit_link(verts, max_capsules=2)
    assert len(two) == 2 and v_two > 2.0 * hull  # what two can do on it: not enough


def test_capsules_file_round_trip(panda_fits, tmp_path):
    fits = list(panda_fits.values())
    path = write_capsules(fits, tmp_path / "caps.toml", robot="panda", source="panda.urdf", command="test")
    entries = read_capsules(path)
    assert [e.link for e in entries] == [f.link for f in fits for _ in f.capsules]
    for e, c in zip(entries, [c for f in fits for c in f.capsules]):
        assert np.allclose(e.capsule.a, c.a, atol=1e-9) and e.capsule.radius == pytest.approx(c.radius, abs=1e-12)
    # rounding to 10 µm kept every vertex inside
    for f in fits:
        verts = panda_mesh_vertices(f.link)
        mine = [e.capsule for e in entries if e.link == f.link]
        assert np.min([fcl_signed_distance(verts, c.a, c.b, c.radius) for c in mine], axis=0).max() <= FCL_TOL


def test_robot_reads_capsules_in_link_frames(panda_robot, panda_fits, tmp_path, rng):
    path = write_capsules(list(panda_fits.values()), tmp_path / "caps.toml", robot="panda", source="-",
                          command="test")
    robot = panda_robot.with_capsules(path)
    assert len(robot.capsules) == sum(len(f.capsules) for f in panda_fits.values())
    assert robot.capsules[0].name == "panda_link0:0" and {c.links for c in robot.capsules} >= {("panda_hand",)}
    data = robot.model.createData()
    q = rng.uniform(robot.q_min, robot.q_max)
    pin.framesForwardKinematics(robot.model, data, q)
    for cap in robot.capsules:
        link = cap.links[0]
        fit = panda_fits[link]
        k = int(cap.name.split(":")[1]) if ":" in cap.name else 0
        world = data.oMi[cap.joint_id].act(cap.p0)
        expected = data.oMf[robot.model.getFrameId(link)].act(fit.capsules[k].a)
        assert np.allclose(world, expected, atol=2e-5)


def test_capsules_file_errors(panda_robot, tmp_path):
    with pytest.raises(ConfigError, match=r"robot\.capsules: capsules file not found"):
        panda_robot.with_capsules(tmp_path / "none.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[[capsule]\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        panda_robot.with_capsules(bad)
    bad.write_text('[[capsule]]\nlink = "panda_link9"\na = [0, 0, 0]\nb = [0, 0, 0.1]\nradius = 0.05\n')
    with pytest.raises(ConfigError, match="names link 'panda_link9', which panda lacks; its links: panda_link0"):
        panda_robot.with_capsules(bad)
    bad.write_text('[[capsule]]\nlink = "panda_link1"\na = [0, 0]\nb = [0, 0, 0.1]\nradius = 0.05\n')
    with pytest.raises(ConfigError, match=r"capsule\[0\]: link must be a name, a and b 3 finite"):
        panda_robot.with_capsules(bad)
    bad.write_text('[[capsule]]\nlink = "panda_link1"\na = [0, 0, 0]\nb = [0, 0, 0.1]\nradius = -1\n')
    with pytest.raises(ConfigError, match="radius must be a positive number"):
        panda_robot.with_capsules(bad)


def two_link_urdf(folder: Path, mesh: str) -> Path:
    urdf = folder / "arm.urdf"
    urdf.write_text(f"""<robot name="arm">
  <link name="base"/>
  <link name="l1">
    <inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial>
    <collision><origin xyz="0 0 0.2" rpy="0 0 0"/><geometry><cylinder radius="0.05" length="0.4"/></geometry></collision>
  </link>
  <link name="l2">
    <inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial>
    <visual><origin xyz="0.1 0 0" rpy="0 1.5707963 0"/><geometry><mesh filename="{mesh}" scale="2 2 2"/></geometry></visual>
  </link>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/><axis xyz="0 0 1"/>
    <limit lower="-3" upper="3" effort="10" velocity="2"/></joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/><origin xyz="0 0 0.4"/><axis xyz="0 1 0"/>
    <limit lower="-3" upper="3" effort="10" velocity="2"/></joint>
</robot>""")
    return urdf


def test_primitives_and_visual_meshes_are_fitted(tmp_path):
    box = trimesh.creation.box(extents=[0.02, 0.03, 0.1])  # scaled by 2 in the URDF, turned about y, shifted
    box.export(tmp_path / "part.stl")
    urdf = two_link_urdf(tmp_path, "part.stl")
    geometry = {g.link: g for g in file_geometry(urdf)}
    assert geometry["l1"].source == "collision" and geometry["l2"].source == "visual"
    fits = {f.link: f for f in fit_links(geometry.values())}
    # l1: a cylinder r 0.05, length 0.4 along z from 0 to 0.4: its surface points must be inside
    th = np.linspace(0, 2 * np.pi, 360, endpoint=False)
    rim = np.array([[0.05 * np.cos(t), 0.05 * np.sin(t), z] for t in th for z in (0.0, 0.4)])
    c = fits["l1"].capsules[0]
    assert fcl_signed_distance(rim, c.a, c.b, c.radius).max() <= FCL_TOL
    assert c.radius < 0.06
    # l2: the box's corners, scaled, turned 90° about y and moved 0.1 m along x
    corners = np.asarray(box.vertices) * 2 @ pin.rpy.rpyToMatrix(0, 1.5707963, 0).T + [0.1, 0, 0]
    d = np.min([fcl_signed_distance(corners, c.a, c.b, c.radius) for c in fits["l2"].capsules], axis=0)
    assert d.max() <= FCL_TOL
    for c in fits["l2"].capsules:  # along the turned box: x
        assert abs((c.b - c.a)[0]) > 0.1 and abs((c.b - c.a)[2]) < 0.01


def test_a_mesh_that_does_not_load_names_the_key(tmp_path):
    urdf = two_link_urdf(tmp_path, "missing.stl")
    with pytest.raises(ConfigError, match=r"^ROBOT: arm\.urdf: .*missing\.stl"):
        file_geometry(urdf, key="ROBOT")
    (tmp_path / "broken.urdf").write_text("<robot name='x'><link name='a'>")
    with pytest.raises(ConfigError, match=r"^robot: cannot parse broken\.urdf"):
        file_geometry(tmp_path / "broken.urdf")


def test_a_robot_file_that_does_not_parse_names_the_key(tmp_path):
    from qpctl import Scenario

    (tmp_path / "broken.urdf").write_text("<robot name='x'><link name='a'>")
    raw = {"robot": {"kind": "urdf", "urdf": "broken.urdf", "ee_frame": "a"},
           "path": {"waypoints": [[0.4, 0.0, 0.3]], "duration": 1.0}}
    with pytest.raises(ConfigError, match=r"^<dict>: robot\.urdf: cannot parse broken\.urdf"):
        Scenario.from_dict(raw, base_dir=tmp_path)
    raw["robot"]["capsules"] = "none.toml"
    raw["robot"]["urdf"] = "package://example-robot-data/robots/ur_description/urdf/ur5_robot.urdf"
    raw["robot"]["ee_frame"] = "tool0"
    with pytest.raises(ConfigError, match=r"^<dict>: robot\.capsules: capsules file not found"):
        Scenario.from_dict(raw, base_dir=tmp_path)
