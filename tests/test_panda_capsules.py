"""The Panda's collision capsules cover its collision meshes.

Each link's collision mesh (example-robot-data's panda_description/meshes/collision/*.stl, binary
STL read here with numpy) is expressed in its joint's frame — for link 7 together with the hand
(hand.stl, 0.107 m along z and −45° about z) and the two closed fingers (finger.stl, 0.0584 m along
the hand's z, the right one turned 180°), which the locked-finger model carries rigidly on joint 7 —
and every vertex must lie inside its capsule. Measured (see the table's comment in
qpctl/robot/model.py): 100 % of the vertices of every link, largest vertex distance 0.069–0.088 m
against radii 0.07–0.09 m. The radii must stay modest (≤ 0.09 m; the meshes are unions of
0.055 m cylinders).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from qpctl.robot.model import example_robot_data_path


def read_binary_stl(path: Path) -> np.ndarray:
    """Unique vertices (k, 3) [m] of a binary STL file."""
    raw = path.read_bytes()
    count = int(np.frombuffer(raw[80:84], "<u4")[0])
    dtype = np.dtype([("normal", "<f4", 3), ("vertices", "<f4", (3, 3)), ("attr", "<u2")])
    assert len(raw) == 84 + dtype.itemsize * count, f"{path.name} is not a binary STL"
    tris = np.frombuffer(raw[84:], dtype=dtype, count=count)
    return np.unique(tris["vertices"].reshape(-1, 3).astype(float), axis=0)


def rot_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def segment_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    s = np.clip((points - a) @ ab / max(float(ab @ ab), 1e-12), 0.0, 1.0)
    return np.linalg.norm(points - (a + s[:, None] * ab), axis=1)


def link_vertices(i: int) -> np.ndarray:
    def mesh(name: str) -> np.ndarray:
        return read_binary_stl(example_robot_data_path(f"panda_description/meshes/collision/{name}.stl"))

    verts = mesh(f"link{i}")
    if i == 7:
        finger = mesh("finger")
        hand = np.vstack([mesh("hand"), finger + [0, 0, 0.0584], finger @ rot_z(np.pi).T + [0, 0, 0.0584]])
        verts = np.vstack([verts, hand @ rot_z(-np.pi / 4).T + [0, 0, 0.107]])
    return verts


@pytest.mark.parametrize("link", range(1, 8))
def test_capsule_holds_every_mesh_vertex(panda_robot, link):
    joint_id = panda_robot.model.getJointId(f"panda_joint{link}")
    caps = [c for c in panda_robot.capsules if c.joint_id == joint_id]
    assert len(caps) == 1
    cap = caps[0]
    d = segment_distance(link_vertices(link), cap.p0, cap.p1)
    assert np.mean(d <= cap.radius) == 1.0, f"{np.mean(d <= cap.radius):.1%} inside, worst {d.max():.4f} m"
    assert cap.radius <= 0.09
    # and not grossly oversized: the farthest vertex is within 1 cm of the surface
    assert cap.radius - d.max() < 0.01
