"""Synthetic depth frames of spheres and a wall, ray-cast in closed form (numpy).

For the examples, the perception benchmark and the tests: a stand-in for a camera where none is
attached (the simulated camera of :mod:`qpctl.simulation.camera` renders whole scenes in the
simulator). Each sphere is intersected only over the pixels of its image-space bounding box.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from qpctl.geometry.obstacles import Obstacle
from qpctl.perception.frames import RIGID, SOFT, DepthFrame, Intrinsics


@dataclass(frozen=True)
class Sphere:
    """A sphere of ``radius`` [m] at ``centre`` [m] (base frame), labelled rigid or soft."""

    centre: tuple[float, float, float]
    radius: float
    label: int = RIGID


def sphere_surface_points(obstacles: Sequence[Obstacle], per: int = 2000, seed: int = 0) -> np.ndarray:
    """(spheres·per, 3) points [m] uniform on the surface of each sphere among ``obstacles`` (the
    other shapes skipped) at its position at t = 0, seeded: a cloud that sees every sphere all round,
    for a map whose rows stand where the spheres' primitive rows do (the field's tick in
    ``benchmarks/perception.py``, ``tests/test_equality_qp.py``)."""
    rng = np.random.default_rng(seed)
    pts = []
    for o in obstacles:
        if o.shape != "sphere":
            continue
        d = rng.normal(size=(per, 3))
        pts.append(np.asarray(o.position) + o.radius * d / np.linalg.norm(d, axis=1, keepdims=True))
    return np.concatenate(pts) if pts else np.empty((0, 3))


def look_at(eye: np.ndarray | list[float], target: np.ndarray | list[float]) -> np.ndarray:
    """4×4 pose of an optical camera frame (z forward, x right, y down) at ``eye`` [m] facing ``target``."""
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


def rays(pose: np.ndarray, k: Intrinsics) -> np.ndarray:
    """(H, W, 3) base-frame directions of the pixels' rays, scaled so that their optical z is 1."""
    u, v = np.meshgrid(np.arange(k.width, dtype=float), np.arange(k.height, dtype=float))
    d = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones_like(u)], axis=-1)
    return np.asarray(d @ pose[:3, :3].T)


def _window(s: Sphere, pose: np.ndarray, k: Intrinsics) -> tuple[slice, slice] | None:
    """The pixels a sphere can cover (None: behind the camera); the whole image when it is near."""
    c = pose[:3, :3].T @ (np.asarray(s.centre, float) - pose[:3, 3])
    if c[2] + s.radius <= 0:
        return None
    if c[2] - s.radius < 0.05:
        return slice(0, k.height), slice(0, k.width)
    half = 1.5 * s.radius / (c[2] - s.radius)
    u0, u1 = k.cx + k.fx * (c[0] / c[2] - half), k.cx + k.fx * (c[0] / c[2] + half)
    v0, v1 = k.cy + k.fy * (c[1] / c[2] - half), k.cy + k.fy * (c[1] / c[2] + half)
    if u1 < 0 or v1 < 0 or u0 >= k.width or v0 >= k.height:
        return None
    return (slice(max(math.floor(v0) - 1, 0), min(math.ceil(v1) + 2, k.height)),
            slice(max(math.floor(u0) - 1, 0), min(math.ceil(u1) + 2, k.width)))


def render(pose: np.ndarray, spheres: list[Sphere], k: Intrinsics, *, wall_x: float | None = None,
           stamp: float = 0.0, labelled: bool = False, noise: float = 0.0,
           rng: np.random.Generator | None = None) -> DepthFrame:
    """A depth frame (optical z [m], NaN where nothing is hit) of the spheres and an optional wall
    x = ``wall_x`` [m]; ``labelled``: per-pixel labels (the wall is rigid); ``noise``: Gaussian depth
    noise of σ = noise · z² [m] (z in metres)."""
    d = rays(pose, k)
    o = pose[:3, 3]
    depth = np.full(d.shape[:2], np.inf)
    label = np.zeros(d.shape[:2], np.uint8)
    if wall_x is not None:
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (wall_x - o[0]) / d[..., 0]
        depth = np.where(t > 0, t, np.inf)
        label[np.isfinite(depth)] = RIGID
    for s in spheres:
        win = _window(s, pose, k)
        if win is None:
            continue
        dw = d[win]
        c = np.asarray(s.centre, float) - o
        a = (dw * dw).sum(-1)
        b = -2.0 * (dw @ c)
        disc = b * b - 4 * a * (c @ c - s.radius ** 2)
        with np.errstate(invalid="ignore"):
            t = np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0.0))) / (2 * a), np.inf)
        t = np.where(t > 0, t, np.inf)
        sub, lab = depth[win], label[win]
        closer = t < sub
        sub[closer] = t[closer]
        lab[closer] = s.label
    if noise > 0:
        gen = rng if rng is not None else np.random.default_rng(0)
        fin = np.isfinite(depth)
        depth[fin] += gen.normal(size=int(fin.sum())) * noise * depth[fin] ** 2
    depth[~np.isfinite(depth)] = np.nan
    return DepthFrame(depth, k, pose, stamp, labels=label if labelled else None)


def true_points(frame: DepthFrame) -> np.ndarray:
    """(k, 3) base-frame points [m] of a frame's valid pixels (a back-projection of its own)."""
    d = rays(frame.pose, frame.intrinsics)
    z = frame.metres()
    ok = np.isfinite(z) & (z > 0)
    return np.asarray(frame.pose[:3, 3] + d[ok] * z[ok][:, None])


def canopy(seed: int, *, leaves: int = 300, branches: int = 12, centre: tuple[float, float, float] = (0.5, 0.0, 0.5),
           extent: tuple[float, float, float] = (0.35, 0.6, 0.45)) -> list[Sphere]:
    """A seeded canopy of spheres: ``leaves`` soft ones (radius 2–4 cm) and ``branches`` rigid
    chains of 2 cm spheres along random segments, in a box of half-``extent`` [m] about ``centre``."""
    rng = np.random.default_rng(seed)
    c, e = np.asarray(centre, float), np.asarray(extent, float)
    out = [Sphere(tuple(p), float(r), SOFT)  # type: ignore[arg-type]
           for p, r in zip(rng.uniform(c - e, c + e, (leaves, 3)), rng.uniform(0.02, 0.04, leaves), strict=True)]
    for _ in range(branches):
        a, b = rng.uniform(c - e, c + e, (2, 3))
        n = max(int(np.linalg.norm(b - a) / 0.015), 2)
        out += [Sphere(tuple(a + f * (b - a)), 0.02, RIGID) for f in np.linspace(0, 1, n)]  # type: ignore[arg-type]
    return out
