"""Slow, obviously-correct references for the depth map's compiled kernels (the tests compare).

* :func:`classify_points` — :func:`qpctl.kernels.depth.integrate_points`' statuses, in numpy, the
  robot's shadow by python-fcl (the ray from the sensor to a point, a capsule of radius 0, against the
  inflated capsules);
* :func:`distance_field` — scipy's ``distance_transform_edt`` for :func:`qpctl.kernels.edt.distance_field`;
* :func:`field_at` — scipy's ``map_coordinates`` (order 1, the trilinear interpolation) of the
  distance and gradient grids for :func:`qpctl.kernels.field.trilinear`;
* :func:`field_pairs` — per link, a dense search along the axis for :func:`qpctl.kernels.field.field_pairs`'
  nearest row.
"""

from __future__ import annotations

import fcl
import numpy as np
from scipy import ndimage

from qpctl.geometry.self_collision import capsule_object
from qpctl.kernels.depth import KEPT, OUTSIDE, SELF, SHADOW, TARGET
from qpctl.perception.snapshot import VoxelGrid


def in_shadow(points: np.ndarray, sensor: np.ndarray, segments: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """(N,) bool: the segment from ``sensor`` to the point meets a capsule that does not hold the sensor
    (python-fcl's collision of a zero-radius capsule along the ray with each capsule)."""
    sensor = np.asarray(sensor, float)
    caps = []
    for (a, b), r in zip(segments, radii, strict=True):
        u = b - a
        s = np.clip((sensor - a) @ u / (u @ u), 0.0, 1.0) if u @ u > 0 else 0.0
        if np.linalg.norm(sensor - (a + s * u)) >= r:  # one that holds the sensor casts no shadow
            caps.append(capsule_object(a, b, r))
    out = np.zeros(len(points), bool)
    req = fcl.CollisionRequest()
    for i, p in enumerate(np.asarray(points, float)):
        ray = capsule_object(sensor, p, 0.0)
        out[i] = any(fcl.collide(ray, c, req, fcl.CollisionResult()) > 0 for c in caps)
    return out


def classify_points(points: np.ndarray, segments: np.ndarray, radii: np.ndarray, target: np.ndarray | None,
                    target_radius: float, grid: VoxelGrid, soft: np.ndarray | None = None,
                    sensor: np.ndarray | None = None) -> np.ndarray:
    """(N,) statuses of finite base-frame points: inside a capsule or near the target (unless ``soft``,
    (N,) bool), in the capsules' shadow from ``sensor`` (unless soft; None: no shadow test), outside, kept."""
    pts = np.asarray(points, float)
    status = np.full(len(pts), KEPT, np.uint8)
    inside = np.zeros(len(pts), bool)
    for (a, b), r in zip(segments, radii, strict=True):
        u = b - a
        s = np.clip(((pts - a) @ u) / max(u @ u, 1e-300), 0.0, 1.0) if u @ u > 0 else np.zeros(len(pts))
        inside |= np.linalg.norm(pts - (a + s[:, None] * u), axis=1) < r
    near = (np.linalg.norm(pts - target, axis=1) < target_radius) if target is not None else np.zeros(len(pts), bool)
    if soft is not None:
        near &= ~soft
        inside &= ~soft  # a leaf is not the robot
    idx = np.floor((pts - grid.origin) / grid.voxel)
    out = np.any((idx < 0) | (idx >= np.asarray(grid.shape)), axis=1)
    status[out] = OUTSIDE
    if sensor is not None:
        rest = ~inside & ~near & (np.ones(len(pts), bool) if soft is None else ~soft)
        shadow = np.zeros(len(pts), bool)
        shadow[rest] = in_shadow(pts[rest], sensor, segments, radii)
        status[shadow] = SHADOW
    status[near] = TARGET
    status[inside] = SELF
    return status


def distance_field(occupied: np.ndarray, voxel: float, truncation: float) -> np.ndarray:
    """scipy's exact EDT of the free voxels [m], capped at ``truncation`` (everywhere when none is occupied)."""
    if not occupied.any():
        return np.full(occupied.shape, truncation)
    return np.minimum(ndimage.distance_transform_edt(~occupied) * voxel, truncation)


def field_at(dist: np.ndarray, grad: np.ndarray, grid: VoxelGrid, truncation: float, points: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """Trilinear distance (k,) and interpolated gradient (k, 3) at points (k, 3) [m] by scipy."""
    pts = np.asarray(points, float).reshape(-1, 3)
    f = (pts - grid.origin) / grid.voxel
    outside = np.any((f < 0) | (f > np.asarray(grid.shape)), axis=1)
    idx = np.clip(f - 0.5, 0.0, np.asarray(grid.shape) - 1.0).T
    d = ndimage.map_coordinates(dist.astype(float), idx, order=1, mode="nearest")
    g = np.stack([ndimage.map_coordinates(grad[..., a].astype(float), idx, order=1, mode="nearest")
                  for a in range(3)], axis=1)
    d[outside] = truncation
    g[outside] = 0.0
    return d, g


def field_pairs(segments: np.ndarray, radii: np.ndarray, dist: np.ndarray, grad: np.ndarray, grid: VoxelGrid,
                truncation: float, dense: int = 2001) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per link, the point of least field distance along its axis (``dense`` samples): distance − r
    (L,) [m], unit normal (L, 3) and witness point on the surface (L, 3) [m]."""
    L = len(segments)
    out_d, out_n, out_p = np.empty(L), np.zeros((L, 3)), np.empty((L, 3))
    s = np.linspace(0.0, 1.0, dense)
    for i, ((a, b), r) in enumerate(zip(segments, radii, strict=True)):
        pts = a + s[:, None] * (b - a)
        d, g = field_at(dist, grad, grid, truncation, pts)
        j = int(np.argmin(d))
        n = g[j] / np.linalg.norm(g[j]) if np.linalg.norm(g[j]) > 1e-9 else np.zeros(3)
        out_d[i], out_n[i], out_p[i] = d[j] - r, n, pts[j] - r * n
    return out_d, out_n, out_p
