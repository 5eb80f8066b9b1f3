"""A sensor's inputs: depth images (with pinhole intrinsics and the camera's pose) and point clouds.

Every frame is timestamped (``stamp`` [s], on the controller's clock) and may carry class labels per
pixel or per point: :data:`RIGID` (stems, branches, trunk, wires: hard barrier rows), :data:`SOFT`
(leaves: slack-penalised rows) or :data:`UNLABELED` (treated as rigid: the safe reading).

Conventions: the camera frame is the optical one (x right, y down, z forward along the view); a
pixel (u, v) at depth z [m] is the point ((u − c_x) z / f_x, (v − c_y) z / f_y, z) in it; ``pose`` is
the 4×4 homogeneous transform of the camera frame in the robot's base frame. A depth image is H×W,
in metres (float) or as raw integers (uint16) that ``depth_scale`` [m per unit] turns into metres
(RealSense: 0.001). NaN, ±inf, zero and negative depths mean "no return": they are dropped and
counted downstream, never an error. What *is* an error (:class:`~qpctl.errors.PerceptionError`): a
wrongly shaped image or label array, missing or non-positive intrinsics, a pose that is not a rigid
transform, a non-finite stamp.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from qpctl.errors import PerceptionError

UNLABELED, RIGID, SOFT = 0, 1, 2  # class labels (uint8); UNLABELED counts as RIGID

RIGID_TOL = 1e-6  # how far RᵀR may be from I, and det R from 1, for a pose to count as rigid


def check_pose(pose: np.ndarray, what: str = "pose") -> np.ndarray:
    """``pose`` as a float 4×4 rigid transform (rotation orthonormal with det +1 to 1e-6, last row
    0 0 0 1, finite), or :class:`PerceptionError` naming what is wrong."""
    T = np.asarray(pose, dtype=float)
    if T.shape != (4, 4):
        raise PerceptionError(f"{what} must be a 4x4 homogeneous transform, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise PerceptionError(f"{what} has non-finite entries")
    R = T[:3, :3]
    if (not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=RIGID_TOL, rtol=0.0)
            or not np.allclose(R.T @ R, np.eye(3), atol=RIGID_TOL, rtol=0.0)
            or abs(np.linalg.det(R) - 1.0) > RIGID_TOL):
        raise PerceptionError(f"{what} is not a rigid transform (its rotation must be orthonormal with "
                              "determinant +1 and its last row 0 0 0 1)")
    return T


def _stamp(stamp: float) -> float:
    if isinstance(stamp, bool) or not isinstance(stamp, (int, float, np.floating, np.integer)):
        raise PerceptionError(f"stamp must be a number of seconds, got {stamp!r}")
    s = float(stamp)
    if not math.isfinite(s):
        raise PerceptionError(f"stamp must be finite, got {s}")
    return s


def _labels(labels: np.ndarray | None, shape: tuple[int, ...], what: str) -> np.ndarray | None:
    if labels is None:
        return None
    lab = np.asarray(labels)
    if lab.shape != shape:
        raise PerceptionError(f"labels must have the {what}'s shape {shape}, got {lab.shape}")
    if lab.size and (not np.issubdtype(lab.dtype, np.integer) or lab.min() < 0 or lab.max() > SOFT):
        raise PerceptionError(f"labels must be integers {UNLABELED} (unlabeled), {RIGID} (rigid) or {SOFT} (soft)")
    return lab.astype(np.uint8, copy=False)


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of a depth camera: focal lengths f_x, f_y and principal point c_x, c_y
    [pixels], image width × height [pixels]."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        for name in ("fx", "fy"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise PerceptionError(f"intrinsics.{name} must be a positive number of pixels, got {v!r}")
        for name in ("cx", "cy"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v)):
                raise PerceptionError(f"intrinsics.{name} must be a finite number of pixels, got {v!r}")
        for name in ("width", "height"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v <= 0:
                raise PerceptionError(f"intrinsics.{name} must be a positive integer, got {v!r}")

    @classmethod
    def from_fov(cls, width: int, height: int, fov_y_deg: float) -> Intrinsics:
        """Square pixels, the principal point at the image centre, vertical field of view [deg]."""
        f = 0.5 * height / math.tan(math.radians(fov_y_deg) / 2.0)
        return cls(f, f, (width - 1) / 2.0, (height - 1) / 2.0, int(width), int(height))

    def matrix(self) -> np.ndarray:
        """The 3×3 camera matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class DepthFrame:
    """One depth image: ``depth`` (H×W, [m] as float, or integers × ``depth_scale`` [m/unit]), its
    ``intrinsics`` (None is an error: a depth image cannot be placed without them), the camera's
    ``pose`` in the robot's base frame (4×4), its ``stamp`` [s] and optional per-pixel ``labels``."""

    depth: np.ndarray
    intrinsics: Intrinsics
    pose: np.ndarray
    stamp: float
    labels: np.ndarray | None = None
    depth_scale: float = 1.0
    meta: dict[str, float] = field(default_factory=dict, compare=False)  # e.g. the simulated noise's σ

    def __post_init__(self) -> None:
        if not isinstance(self.intrinsics, Intrinsics):
            raise PerceptionError("a depth frame needs its camera intrinsics (qpctl.perception.Intrinsics), "
                                  f"got {self.intrinsics!r}")
        depth = np.asarray(self.depth)
        shape = (self.intrinsics.height, self.intrinsics.width)
        if depth.ndim != 2 or depth.shape != shape:
            raise PerceptionError(f"depth image must be H x W = {shape[0]} x {shape[1]} (the intrinsics'), "
                                  f"got shape {depth.shape}")
        if not (np.issubdtype(depth.dtype, np.floating) or np.issubdtype(depth.dtype, np.integer)):
            raise PerceptionError(f"depth image must be float metres or integer units, got dtype {depth.dtype}")
        if not (math.isfinite(self.depth_scale) and self.depth_scale > 0):
            raise PerceptionError(f"depth_scale must be a positive number of metres per unit, got {self.depth_scale}")
        object.__setattr__(self, "depth", depth)
        object.__setattr__(self, "pose", check_pose(self.pose, "camera pose"))
        object.__setattr__(self, "stamp", _stamp(self.stamp))
        object.__setattr__(self, "labels", _labels(self.labels, shape, "depth image"))

    def metres(self) -> np.ndarray:
        """The depth image in metres (float64; no-return pixels keep their NaN, inf, 0 or negative)."""
        if np.issubdtype(self.depth.dtype, np.integer):
            return self.depth.astype(np.float64) * self.depth_scale
        d = self.depth.astype(np.float64, copy=False)
        return d * self.depth_scale if self.depth_scale != 1.0 else d


@dataclass(frozen=True)
class PointCloud:
    """N points (N×3, [m]) in the robot's base frame at ``stamp`` [s], optional per-point ``labels``,
    and optionally the sensor's ``origin`` [m] (base frame) from which free space along the rays can
    be cleared (None: no clearing from this cloud). An empty cloud (0×3) is a valid, empty view."""

    points: np.ndarray
    stamp: float
    labels: np.ndarray | None = None
    origin: np.ndarray | None = None

    def __post_init__(self) -> None:
        pts = np.asarray(self.points, dtype=float)
        if pts.size == 0:
            pts = pts.reshape(0, 3)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise PerceptionError(f"a point cloud must be N x 3 [m], got shape {pts.shape}")
        object.__setattr__(self, "points", pts)
        object.__setattr__(self, "stamp", _stamp(self.stamp))
        object.__setattr__(self, "labels", _labels(self.labels, (pts.shape[0],), "point cloud"))
        if self.origin is not None:
            o = np.asarray(self.origin, dtype=float).reshape(-1)
            if o.shape != (3,) or not np.all(np.isfinite(o)):
                raise PerceptionError(f"origin must be 3 finite numbers [m], got {self.origin!r}")
            object.__setattr__(self, "origin", o)
