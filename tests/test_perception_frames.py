"""The sensor inputs' checks (qpctl.perception.frames) and the obstacles' material keys."""

from __future__ import annotations

import math

import numpy as np
import pytest

from qpctl.errors import ConfigError, PerceptionError, QpctlError
from qpctl.geometry.obstacles import Obstacle
from qpctl.perception import RIGID, SOFT, DepthFrame, Intrinsics, PointCloud
from qpctl.perception.frames import check_pose

K = Intrinsics(fx=600.0, fy=600.0, cx=319.5, cy=239.5, width=640, height=480)


def _rot(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues' formula, written out (an independent rotation)."""
    a = axis / np.linalg.norm(axis)
    A = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * A + (1 - math.cos(angle)) * A @ A


def _pose(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, p
    return T


def test_intrinsics_from_fov_matches_the_pinhole_formula() -> None:
    k = Intrinsics.from_fov(640, 480, 58.0)
    # the top image row's ray leaves the axis at half the vertical field of view
    assert math.degrees(math.atan((0 - k.cy - 0.5) / k.fy)) == pytest.approx(-29.0, abs=1e-9)
    assert k.matrix()[0, 0] == k.fx and k.matrix()[1, 2] == k.cy


@pytest.mark.parametrize("field,value", [("fx", 0.0), ("fy", -1.0), ("cx", math.nan), ("width", 0),
                                         ("height", 2.5)])
def test_bad_intrinsics_are_named(field: str, value: float) -> None:
    args = dict(fx=600.0, fy=600.0, cx=319.5, cy=239.5, width=640, height=480)
    args[field] = value
    with pytest.raises(PerceptionError, match=f"intrinsics.{field}"):
        Intrinsics(**args)  # type: ignore[arg-type]


def test_depth_frame_in_millimetres_scales_to_metres() -> None:
    raw = np.full((480, 640), 1234, np.uint16)
    raw[0, 0] = 0  # no return
    f = DepthFrame(raw, K, np.eye(4), 0.5, depth_scale=0.001)
    d = f.metres()
    assert d.dtype == np.float64 and d[1, 1] == pytest.approx(1.234) and d[0, 0] == 0.0


def test_depth_frame_rejects_wrong_shape_missing_intrinsics_and_bad_labels() -> None:
    with pytest.raises(PerceptionError, match="480 x 640"):
        DepthFrame(np.ones((480, 641)), K, np.eye(4), 0.0)
    with pytest.raises(PerceptionError, match="intrinsics"):
        DepthFrame(np.ones((480, 640)), None, np.eye(4), 0.0)  # type: ignore[arg-type]
    with pytest.raises(PerceptionError, match="labels"):
        DepthFrame(np.ones((480, 640)), K, np.eye(4), 0.0, labels=np.zeros((480, 640), np.uint8) + 3)
    with pytest.raises(PerceptionError, match="stamp"):
        DepthFrame(np.ones((480, 640)), K, np.eye(4), math.inf)
    assert issubclass(PerceptionError, QpctlError)


def test_rigid_poses_pass_and_others_are_refused() -> None:
    rng = np.random.default_rng(3)
    for _ in range(20):
        T = _pose(_rot(rng.normal(size=3), rng.uniform(-3, 3)), rng.normal(size=3))
        assert np.array_equal(check_pose(T), T)
    R = _rot(np.array([0.0, 0.0, 1.0]), 0.3)
    for bad in (_pose(1.01 * R, np.zeros(3)),  # scaled
                _pose(R @ np.diag([1.0, 1.0, -1.0]), np.zeros(3)),  # a reflection (det −1)
                _pose(R + 1e-3, np.zeros(3))):  # not orthonormal
        with pytest.raises(PerceptionError, match="rigid"):
            check_pose(bad)
    skew = np.eye(4)
    skew[3, 0] = 0.1
    with pytest.raises(PerceptionError, match="rigid"):
        check_pose(skew)
    with pytest.raises(PerceptionError, match="4x4"):
        check_pose(np.eye(3))


def test_point_clouds_empty_labelled_and_wrong() -> None:
    empty = PointCloud(np.zeros((0, 3)), 1.0)
    assert empty.points.shape == (0, 3)
    assert PointCloud([], 1.0).points.shape == (0, 3)
    pc = PointCloud(np.ones((4, 3)), 1.0, labels=np.array([RIGID, SOFT, 0, SOFT]), origin=[0, 0, 1])
    assert pc.labels is not None and pc.labels.dtype == np.uint8 and pc.origin is not None
    with pytest.raises(PerceptionError, match="N x 3"):
        PointCloud(np.ones((4, 2)), 0.0)
    with pytest.raises(PerceptionError, match="labels"):
        PointCloud(np.ones((4, 3)), 0.0, labels=np.zeros(3, int))


def test_obstacle_material_is_checked_and_defaults_rigid() -> None:
    o = Obstacle("sphere", np.zeros(3), radius=0.1)
    assert o.material == "rigid" and o.perceived is False
    assert Obstacle("sphere", np.zeros(3), radius=0.1, material="soft", perceived=True).material == "soft"
    with pytest.raises(ConfigError, match="material"):
        Obstacle("sphere", np.zeros(3), radius=0.1, material="leafy", name="l1")
