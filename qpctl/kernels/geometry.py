"""Closed-form distances between link capsules and sphere or capsule obstacles, compiled.

A capsule is a segment swept by a radius, so every pair here reduces to the closest points of two
segments (a sphere's segment has zero length): with P on the link's axis and Q on the obstacle's,
w = P − Q, the signed distance is d = |w| − r_link − r_obstacle, exact whether the shapes are apart
or penetrating (python-fcl's signed query runs GJK/EPA instead, off by up to ~1e-4 m when
penetrating, and stalls for a sphere centred on a capsule's axis end), the normal is n = w/|w|
(obstacle → link) and the witness points are P − r_link n and Q + r_obstacle n. When the axes meet
(w = 0) n is taken perpendicular to both (to the link's axis and the world axis least aligned with
it for a sphere), a choice, since every direction is then a closest one.

References (``tests/test_kernels.py``): python-fcl's distance and nearest points on the same shapes,
and :mod:`qpctl.geometry.distance` (the previous, per-pair implementation).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

# Segments with |u|²|s|² − (u·s)² ≤ eps·|u|²|s|² (sin²θ ≤ eps) take the "parallel" branch (the first
# segment's start). Near that limit the denominator is rounding noise, but any start parameter then
# leads Ericson's clamping to a closest pair to within ~θ·L; a looser eps (1e-12, θ ≈ 1e-6) left
# crossing, nearly parallel axes off by θ·L/2 (5e-7 m), which tests/test_kernels.py catches.
PARALLEL_EPS = 1e-16


@njit(cache=True)
def clamp01(x: float) -> float:
    return 0.0 if x < 0.0 else (min(x, 1.0))


@njit(cache=True)
def closest_on_segment(a: np.ndarray, b: np.ndarray, p: np.ndarray) -> float:
    """Parameter s ∈ [0, 1] of the point a + s(b − a) closest to p."""
    dx, dy, dz = b[0] - a[0], b[1] - a[1], b[2] - a[2]
    denom = dx * dx + dy * dy + dz * dz
    if denom == 0.0:
        return 0.0
    return clamp01(((p[0] - a[0]) * dx + (p[1] - a[1]) * dy + (p[2] - a[2]) * dz) / denom)


@njit(cache=True, nogil=True, inline="always")
def axis_distance2(segments: np.ndarray, i: int, x: float, y: float, z: float) -> float:
    """The squared distance [m²] from (x, y, z) to the axis of capsule i of ``segments`` (L, 2, 3)."""
    ax, ay, az = segments[i, 0, 0], segments[i, 0, 1], segments[i, 0, 2]
    ux, uy, uz = segments[i, 1, 0] - ax, segments[i, 1, 1] - ay, segments[i, 1, 2] - az
    uu = ux * ux + uy * uy + uz * uz
    s = 0.0
    if uu > 0.0:
        s = clamp01(((x - ax) * ux + (y - ay) * uy + (z - az) * uz) / uu)
    dx, dy, dz = x - ax - s * ux, y - ay - s * uy, z - az - s * uz
    return dx * dx + dy * dy + dz * dz


@njit(cache=True, nogil=True, inline="always")
def in_capsule(segments: np.ndarray, radii: np.ndarray, i: int, x: float, y: float, z: float) -> bool:
    """Whether (x, y, z) [m] lies within capsule i (axis ``segments`` (L, 2, 3), ``radii`` (L,) [m])."""
    return axis_distance2(segments, i, x, y, z) < radii[i] * radii[i]


@njit(cache=True)
def perpendicular(x: float, y: float, z: float, out: np.ndarray) -> None:
    """A unit vector ⊥ (x, y, z) and ⊥ the world axis least aligned with it (e_x for a zero vector)."""
    ax, ay, az = abs(x), abs(y), abs(z)
    if az <= ax and az <= ay:
        ex, ey, ez = 0.0, 0.0, 1.0
    elif ay <= ax:
        ex, ey, ez = 0.0, 1.0, 0.0
    else:
        ex, ey, ez = 1.0, 0.0, 0.0
    px, py, pz = y * ez - z * ey, z * ex - x * ez, x * ey - y * ex
    pn = math.sqrt(px * px + py * py + pz * pz)
    if pn > 0.0:
        out[0], out[1], out[2] = px / pn, py / pn, pz / pn
    else:
        out[0], out[1], out[2] = 1.0, 0.0, 0.0


@njit(cache=True)
def segment_segment(p1: np.ndarray, q1: np.ndarray, p2: np.ndarray, q2: np.ndarray) -> tuple[float, float]:
    """Parameters (s, t) of the closest points p1 + s(q1 − p1) and p2 + t(q2 − p2) of two segments
    (:func:`segment_params` with arrays)."""
    ux, uy, uz = q1[0] - p1[0], q1[1] - p1[1], q1[2] - p1[2]
    return segment_params(p1[0], p1[1], p1[2], ux, uy, uz, ux * ux + uy * uy + uz * uz, p2[0], p2[1], p2[2],
                          q2[0] - p2[0], q2[1] - p2[1], q2[2] - p2[2])


@njit(cache=True)
def segment_params(ax: float, ay: float, az: float, ux: float, uy: float, uz: float, uu: float,
                   cx: float, cy: float, cz: float, sx: float, sy: float, sz: float) -> tuple[float, float]:
    """(τ, σ) of the closest points a + τu and c + σs of two segments (uu = u·u; s = 0 for a point:
    the clamped projection of c), in scalars. Ericson, *Real-Time Collision Detection* (2005),
    §5.1.9; for parallel segments the first segment's point is its clamped start (one of the
    closest pairs)."""
    if sx == 0.0 and sy == 0.0 and sz == 0.0:
        if uu == 0.0:
            return 0.0, 0.0
        return clamp01(((cx - ax) * ux + (cy - ay) * uy + (cz - az) * uz) / uu), 0.0
    rx, ry, rz = ax - cx, ay - cy, az - cz
    e = sx * sx + sy * sy + sz * sz
    f = sx * rx + sy * ry + sz * rz
    if uu <= 1e-300:
        return 0.0, clamp01(f / e)
    c = ux * rx + uy * ry + uz * rz
    b = ux * sx + uy * sy + uz * sz
    denom = uu * e - b * b
    tau = clamp01((b * f - c * e) / denom) if denom > PARALLEL_EPS * uu * e else 0.0
    sigma = (b * tau + f) / e
    if sigma < 0.0:
        return clamp01(-c / uu), 0.0
    if sigma > 1.0:
        return clamp01((b - c) / uu), 1.0
    return tau, sigma


@njit(cache=True)
def contact_frame(px: float, py: float, pz: float, qx: float, qy: float, qz: float, wx: float, wy: float,
                  wz: float, wn: float, ux: float, uy: float, uz: float, sx: float, sy: float, sz: float,
                  r_link: float, r_obs: float, normal: np.ndarray, p_link: np.ndarray, p_obs: np.ndarray,
                  k: int) -> None:
    """Row k of ``normal``, ``p_link``, ``p_obs`` (each (K, 3)): the unit normal n = w/|w| (obstacle →
    link) of the closest axis points P (link) and Q (obstacle), w = P − Q, and the witness points
    P − r_link n and Q + r_obs n. Where the axes meet (|w| ≤ 1e-12) n is ⊥ both axes (u × s), or for
    a point obstacle or parallel axes ⊥ the link's axis and the world axis least aligned with it
    (:func:`perpendicular`). Rows by index, not views: a view in the pair loop costs an atomic
    reference count increment and decrement (:func:`qpctl.kernels.rigid.world_point`)."""
    if wn > 1e-12:
        nx, ny, nz = wx / wn, wy / wn, wz / wn
    else:
        cx, cy, cz = uy * sz - uz * sy, uz * sx - ux * sz, ux * sy - uy * sx
        cn = math.sqrt(cx * cx + cy * cy + cz * cz)
        if cn > 1e-12 * math.sqrt((ux * ux + uy * uy + uz * uz) * (sx * sx + sy * sy + sz * sz)) and cn > 0.0:
            nx, ny, nz = cx / cn, cy / cn, cz / cn
        else:
            perpendicular(ux, uy, uz, normal[k])
            nx, ny, nz = normal[k, 0], normal[k, 1], normal[k, 2]
    normal[k, 0], normal[k, 1], normal[k, 2] = nx, ny, nz
    p_link[k, 0], p_link[k, 1], p_link[k, 2] = px - r_link * nx, py - r_link * ny, pz - r_link * nz
    p_obs[k, 0], p_obs[k, 1], p_obs[k, 2] = qx + r_obs * nx, qy + r_obs * ny, qz + r_obs * nz


@njit(cache=True)
def capsule_pair(a: np.ndarray, b: np.ndarray, r_link: float, c0: np.ndarray, c1: np.ndarray, r_obs: float,
                 normal: np.ndarray, p_link: np.ndarray, p_obs: np.ndarray) -> float:
    """Signed distance [m] between the link capsule (axis a–b, radius r_link) and an obstacle capsule
    (axis c0–c1, radius r_obs; c0 = c1 for a sphere); writes the unit normal (obstacle → link) and
    the witness points on each surface (the kernels' pair loop does the same, inline)."""
    ux, uy, uz = b[0] - a[0], b[1] - a[1], b[2] - a[2]
    sx, sy, sz = c1[0] - c0[0], c1[1] - c0[1], c1[2] - c0[2]
    tl, to = segment_params(a[0], a[1], a[2], ux, uy, uz, ux * ux + uy * uy + uz * uz, c0[0], c0[1], c0[2],
                            sx, sy, sz)
    px, py, pz = a[0] + tl * ux, a[1] + tl * uy, a[2] + tl * uz
    qx, qy, qz = c0[0] + to * sx, c0[1] + to * sy, c0[2] + to * sz
    wx, wy, wz = px - qx, py - qy, pz - qz
    wn = math.sqrt(wx * wx + wy * wy + wz * wz)
    contact_frame(px, py, pz, qx, qy, qz, wx, wy, wz, wn, ux, uy, uz, sx, sy, sz, r_link, r_obs, normal.reshape((1, 3)),
                  p_link.reshape((1, 3)), p_obs.reshape((1, 3)), 0)
    return wn - r_link - r_obs


@njit(cache=True)
def sphere_bound(segments: np.ndarray, i: int, r_link: float, cx: float, cy: float, cz: float, r_bound: float) -> float:
    """A lower bound [m] on the distance between link capsule i (axis ``segments[i]``) and a shape
    inside the sphere of radius r_bound about (cx, cy, cz): the axis-to-centre distance less both
    radii (less 1e-9 for rounding). (:func:`closest_on_segment`'s parameter, inline.)"""
    ax, ay, az = segments[i, 0, 0], segments[i, 0, 1], segments[i, 0, 2]
    bx, by, bz = segments[i, 1, 0], segments[i, 1, 1], segments[i, 1, 2]
    dx, dy, dz = bx - ax, by - ay, bz - az
    denom = dx * dx + dy * dy + dz * dz
    s = 0.0 if denom == 0.0 else clamp01(((cx - ax) * dx + (cy - ay) * dy + (cz - az) * dz) / denom)
    wx = ax + s * (bx - ax) - cx
    wy = ay + s * (by - ay) - cy
    wz = az + s * (bz - az) - cz
    return math.sqrt(wx * wx + wy * wy + wz * wz) - r_link - r_bound - 1e-9
