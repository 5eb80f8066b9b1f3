"""Synthetic depth frames for the perception tests: spheres and walls ray-cast in closed form.

Written from first principles (ray–sphere and ray–plane intersections), not from the library, so
that a depth image and its true points are an independent reference for the pipeline.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from qpctl.perception import DepthFrame, Intrinsics

K = Intrinsics(fx=300.0, fy=300.0, cx=159.5, cy=119.5, width=320, height=240)


@dataclass
class Sphere:
    centre: tuple[float, float, float]
    radius: float
    label: int = 0


def look_at(eye: np.ndarray | list[float], target: np.ndarray | list[float]) -> np.ndarray:
    """4×4 pose of an optical camera frame (z forward, x right, y down) at ``eye`` facing ``target``."""
    eye_a, target_a = np.asarray(eye, float), np.asarray(target, float)
    z = target_a - eye_a
    z /= np.linalg.norm(z)
    up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.99 else np.array([0.0, 1.0, 0.0])
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, y, z])
    T[:3, 3] = eye_a
    return T


def rays(pose: np.ndarray, k: Intrinsics = K) -> np.ndarray:
    """(H, W, 3) world directions of the pixels' rays, scaled so that their optical z is 1."""
    u, v = np.meshgrid(np.arange(k.width, dtype=float), np.arange(k.height, dtype=float))
    d = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones_like(u)], axis=-1)
    return d @ pose[:3, :3].T


def render(pose: np.ndarray, spheres: list[Sphere], wall_x: float | None = None, stamp: float = 0.0,
           k: Intrinsics = K, labelled: bool = False) -> DepthFrame:
    """A depth frame (optical z [m], NaN where nothing is hit) of spheres and an optional wall x = wall_x."""
    d = rays(pose, k)
    o = pose[:3, 3]
    depth = np.full(d.shape[:2], np.inf)
    label = np.zeros(d.shape[:2], np.uint8)
    for s in spheres:
        c = np.asarray(s.centre) - o
        a = (d * d).sum(-1)
        b = -2.0 * (d @ c)
        disc = b * b - 4 * a * (c @ c - s.radius ** 2)
        t = np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0.0))) / (2 * a), np.inf)
        t = np.where(t > 0, t, np.inf)
        closer = t < depth
        depth[closer] = t[closer]
        label[closer] = s.label
    if wall_x is not None:
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (wall_x - o[0]) / d[..., 0]
        t = np.where(t > 0, t, np.inf)
        closer = t < depth
        depth[closer] = t[closer]
        label[closer] = 0
    depth[~np.isfinite(depth)] = np.nan
    return DepthFrame(depth, k, pose, stamp, labels=label if labelled else None)


def true_points(frame: DepthFrame) -> np.ndarray:
    """(k, 3) the base-frame points of a frame's valid pixels (independent back-projection)."""
    d = rays(frame.pose, frame.intrinsics)
    z = frame.metres()
    ok = np.isfinite(z) & (z > 0)
    return frame.pose[:3, 3] + d[ok] * z[ok][:, None]
