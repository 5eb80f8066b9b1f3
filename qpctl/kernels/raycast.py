"""Ray casting against primitives, compiled: what a simulated depth camera sees, on the CPU without OpenGL.

A scene is four fixed-shape arrays (:class:`Primitives`): ``kind`` (P,) — :data:`SPHERE`,
:data:`CAPSULE`, :data:`BOX` or :data:`CYLINDER` —, ``centre`` (P, 3) [m], ``axes`` (P, 3, 3), the
rotation world ← shape (its columns are the shape's x, y, z in the world; a capsule's or cylinder's
axis is its z) and ``size`` (P, 3) [m]: a sphere's (r, 0, 0), a capsule's or cylinder's (r, h, 0)
with h the half-length of the axis, a box's half extents. A ray is o + t d with d *not* normalised:
a camera passes d = R (x_n, y_n, 1) so that t is the depth along its optical axis.

:func:`cast_image` renders a pinhole image with a z-buffer: for each primitive it bounds the pixels
its silhouette can cover (per image axis, the slopes its projection on that axis's plane spans in
front of the camera: the tangents of a sphere, of a capsule's or cylinder's axis swept by its radius,
shapes reaching behind the camera included; a box's 8 corners — the image of a convex hull lies in
the hull of the images in front of the camera; :mod:`qpctl.kernels.screen_cull`) and intersects only those rays, so the cost grows
with the shapes' area on screen, not with pixels × shapes. :func:`cast_rays` is the
brute-force form (every ray against every shape) it is tested against.

Each intersection is the first t ≥ 0 at which the ray enters the solid (a union's first point is
the least of its parts': a capsule's lateral surface within its axis and its two end spheres; a
cylinder's lateral surface and its two end discs; a box's slabs). A shape whose interior holds the
ray's origin is not seen (a camera looks out of the link it sits in). The slow, obviously-correct
reference (:func:`qpctl.simulation.raycast_reference.reference_depth`) knows none of this: it sphere-traces each ray with python-fcl's
distance to each shape (``tests/test_camera_raycast.py`` holds both casters, this kernel and
``mujoco.mj_multiRay``, to it and to each other).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from qpctl.kernels.screen_cull import BOX, CAPSULE, CYLINDER, SPHERE, pieces, screen_rect

KINDS = {"sphere": SPHERE, "capsule": CAPSULE, "box": BOX, "cylinder": CYLINDER}  # Obstacle.shape → kind


class Primitives(NamedTuple):
    """The scene's shapes as fixed-shape arrays (module docstring)."""

    kind: np.ndarray  # (P,) int64
    centre: np.ndarray  # (P, 3) [m]
    axes: np.ndarray  # (P, 3, 3) rotation world ← shape
    size: np.ndarray  # (P, 3) [m]

    @classmethod
    def empty(cls, count: int) -> Primitives:
        axes = np.zeros((count, 3, 3))
        axes[:] = np.eye(3)
        return cls(np.zeros(count, np.int64), np.zeros((count, 3)), axes, np.zeros((count, 3)))


def obstacle_primitive(obs: object, t: float, out: Primitives, i: int) -> None:
    """Write the obstacle ``obs`` (a :class:`~qpctl.geometry.obstacles.Obstacle`) at time ``t`` [s] into
    row ``i`` of ``out``: its kind, centre, the rotation python-fcl places it with, its size."""
    from qpctl.geometry.obstacles import Obstacle, rotation_z_to

    assert isinstance(obs, Obstacle)
    if obs.shape not in KINDS:
        raise ValueError(f"the ray caster has no closed form for shape {obs.shape!r}; one of {', '.join(KINDS)}")
    out.kind[i] = KINDS[obs.shape]
    out.centre[i] = obs.position_at(t)
    out.axes[i] = rotation_z_to(obs.axis)
    if obs.shape == "sphere":
        out.size[i] = (obs.radius, 0.0, 0.0)
    elif obs.shape == "box":
        assert obs.size is not None
        out.size[i] = 0.5 * np.asarray(obs.size, float)
    else:
        out.size[i] = (obs.radius, 0.5 * obs.length, 0.0)


def capsule_rows(a: np.ndarray, b: np.ndarray, radius: np.ndarray, out: Primitives, start: int) -> None:
    """Write capsules with axes a[k]–b[k] ((L, 3) [m], world) and radii (L,) [m] into rows start… of
    ``out`` (a zero-length axis is a sphere-ended point: any axis will do)."""
    n = len(radius)
    rows = slice(start, start + n)
    axis = b - a
    length = np.linalg.norm(axis, axis=1)
    unit = np.where(length[:, None] > 1e-12, axis / np.maximum(length, 1e-300)[:, None], np.array([0.0, 0.0, 1.0]))
    out.kind[rows] = CAPSULE
    out.centre[rows] = 0.5 * (a + b)
    out.axes[rows, :, 2] = unit  # only the axis is read for a capsule
    out.size[rows, 0] = radius
    out.size[rows, 1] = 0.5 * length
    out.size[rows, 2] = 0.0


# -- one ray against one shape --------------------------------------------------------------------
@njit(cache=True)
def _sphere_t(ox: float, oy: float, oz: float, dx: float, dy: float, dz: float, dd: float,
              cx: float, cy: float, cz: float, r: float) -> float:
    """First t ≥ 0 of the ray in the ball (inf: none, or the origin inside)."""
    px, py, pz = ox - cx, oy - cy, oz - cz
    b = px * dx + py * dy + pz * dz
    c = px * px + py * py + pz * pz - r * r
    disc = b * b - dd * c
    if disc < 0.0:
        return math.inf
    t = (-b - math.sqrt(disc)) / dd
    return t if t >= 0.0 else math.inf


@njit(cache=True)
def _lateral_t(ox: float, oy: float, oz: float, dx: float, dy: float, dz: float, dd: float,
               ax: float, ay: float, az: float, wx: float, wy: float, wz: float, length: float, r: float) -> float:
    """First t ≥ 0 at which the ray enters the infinite cylinder of radius r about the line a + s w
    (w unit) with the entry point's s in [0, length] (inf: none)."""
    px, py, pz = ox - ax, oy - ay, oz - az
    dw = dx * wx + dy * wy + dz * wz
    pw = px * wx + py * wy + pz * wz
    A = dd - dw * dw
    if A <= 1e-14 * dd:  # parallel to the axis: only the ends (caps) can be hit
        return math.inf
    B = px * dx + py * dy + pz * dz - pw * dw
    C = px * px + py * py + pz * pz - pw * pw - r * r
    disc = B * B - A * C
    if disc < 0.0:
        return math.inf
    t = (-B - math.sqrt(disc)) / A
    if t < 0.0:
        return math.inf
    s = pw + t * dw
    return t if 0.0 <= s <= length else math.inf


@njit(cache=True)
def _disc_t(ox: float, oy: float, oz: float, dx: float, dy: float, dz: float,
            cx: float, cy: float, cz: float, wx: float, wy: float, wz: float, r: float) -> float:
    """First t ≥ 0 at which the ray meets the disc of radius r about c normal to w (inf: none)."""
    dw = dx * wx + dy * wy + dz * wz
    if dw == 0.0:
        return math.inf
    t = ((cx - ox) * wx + (cy - oy) * wy + (cz - oz) * wz) / dw
    if t < 0.0:
        return math.inf
    qx, qy, qz = ox + t * dx - cx, oy + t * dy - cy, oz + t * dz - cz
    return t if qx * qx + qy * qy + qz * qz <= r * r else math.inf


@njit(cache=True)
def ray_primitive(i: int, kind: np.ndarray, centre: np.ndarray, axes: np.ndarray, size: np.ndarray,
                  ox: float, oy: float, oz: float, dx: float, dy: float, dz: float) -> float:
    """First t ≥ 0 at which the ray o + t d enters primitive i (inf: it misses). The origin must lie
    outside the shape (a shape holding it: see :func:`contains`)."""
    dd = dx * dx + dy * dy + dz * dz
    k = kind[i]
    cx, cy, cz = centre[i, 0], centre[i, 1], centre[i, 2]
    if k == SPHERE:
        return _sphere_t(ox, oy, oz, dx, dy, dz, dd, cx, cy, cz, size[i, 0])
    if k == BOX:
        t_near, t_far = -math.inf, math.inf
        px, py, pz = ox - cx, oy - cy, oz - cz
        for j in range(3):
            ex, ey, ez = axes[i, 0, j], axes[i, 1, j], axes[i, 2, j]
            o = px * ex + py * ey + pz * ez
            d = dx * ex + dy * ey + dz * ez
            h = size[i, j]
            if d == 0.0:
                if o < -h or o > h:
                    return math.inf
                continue
            t1, t2 = (-h - o) / d, (h - o) / d
            if t1 > t2:
                t1, t2 = t2, t1
            t_near = max(t_near, t1)
            t_far = min(t_far, t2)
            if t_near > t_far:
                return math.inf
        if t_far < 0.0 or t_near < 0.0:
            return math.inf
        return t_near
    r, h = size[i, 0], size[i, 1]
    wx, wy, wz = axes[i, 0, 2], axes[i, 1, 2], axes[i, 2, 2]
    ax, ay, az = cx - h * wx, cy - h * wy, cz - h * wz
    bx, by, bz = cx + h * wx, cy + h * wy, cz + h * wz
    t = _lateral_t(ox, oy, oz, dx, dy, dz, dd, ax, ay, az, wx, wy, wz, 2.0 * h, r)
    if k == CAPSULE:
        t = min(t, _sphere_t(ox, oy, oz, dx, dy, dz, dd, ax, ay, az, r))
        return min(t, _sphere_t(ox, oy, oz, dx, dy, dz, dd, bx, by, bz, r))
    t = min(t, _disc_t(ox, oy, oz, dx, dy, dz, ax, ay, az, wx, wy, wz, r))
    return min(t, _disc_t(ox, oy, oz, dx, dy, dz, bx, by, bz, wx, wy, wz, r))


@njit(cache=True)
def contains(i: int, kind: np.ndarray, centre: np.ndarray, axes: np.ndarray, size: np.ndarray,
             px: float, py: float, pz: float) -> bool:
    """Whether the point p lies inside primitive i (on its surface counts as inside)."""
    k = kind[i]
    qx, qy, qz = px - centre[i, 0], py - centre[i, 1], pz - centre[i, 2]
    if k == SPHERE:
        return qx * qx + qy * qy + qz * qz <= size[i, 0] ** 2
    if k == BOX:
        for j in range(3):
            if abs(qx * axes[i, 0, j] + qy * axes[i, 1, j] + qz * axes[i, 2, j]) > size[i, j]:
                return False
        return True
    r, h = size[i, 0], size[i, 1]
    s = qx * axes[i, 0, 2] + qy * axes[i, 1, 2] + qz * axes[i, 2, 2]
    if k == CAPSULE:
        s = max(-h, min(h, s))
    elif abs(s) > h:
        return False
    rx, ry, rz = qx - s * axes[i, 0, 2], qy - s * axes[i, 1, 2], qz - s * axes[i, 2, 2]
    return rx * rx + ry * ry + rz * rz <= r * r


@njit(cache=True)
def contains_point(kind: np.ndarray, centre: np.ndarray, axes: np.ndarray, size: np.ndarray, p: np.ndarray,
                   out: np.ndarray) -> None:
    """out[i] = primitive i holds the point p (P,) bool."""
    for i in range(len(kind)):
        out[i] = contains(i, kind, centre, axes, size, p[0], p[1], p[2])


@njit(cache=True)
def surface_normal(i: int, kind: np.ndarray, centre: np.ndarray, axes: np.ndarray, size: np.ndarray,
                   px: float, py: float, pz: float, n: np.ndarray) -> None:
    """The outward unit normal of primitive i at its surface point p, into n (3,)."""
    k = kind[i]
    qx, qy, qz = px - centre[i, 0], py - centre[i, 1], pz - centre[i, 2]
    if k == BOX:
        best, jb, sign = -1.0, 0, 1.0
        for j in range(3):
            o = qx * axes[i, 0, j] + qy * axes[i, 1, j] + qz * axes[i, 2, j]
            f = abs(o) / size[i, j]
            if f > best:
                best, jb, sign = f, j, (1.0 if o >= 0.0 else -1.0)
        n[0], n[1], n[2] = sign * axes[i, 0, jb], sign * axes[i, 1, jb], sign * axes[i, 2, jb]
        return
    if k != SPHERE:
        r, h = size[i, 0], size[i, 1]
        wx, wy, wz = axes[i, 0, 2], axes[i, 1, 2], axes[i, 2, 2]
        s = qx * wx + qy * wy + qz * wz
        if k == CAPSULE:
            s = max(-h, min(h, s))
        else:
            rx, ry, rz = qx - s * wx, qy - s * wy, qz - s * wz
            rho = math.sqrt(rx * rx + ry * ry + rz * rz)
            if h - abs(s) < abs(rho - r):  # nearer an end disc than the lateral surface
                sign = 1.0 if s >= 0.0 else -1.0
                n[0], n[1], n[2] = sign * wx, sign * wy, sign * wz
                return
        qx, qy, qz = qx - s * wx, qy - s * wy, qz - s * wz
    norm = math.sqrt(qx * qx + qy * qy + qz * qz)
    if norm > 0.0:
        n[0], n[1], n[2] = qx / norm, qy / norm, qz / norm
    else:
        n[0], n[1], n[2] = 0.0, 0.0, 1.0


# -- many rays ------------------------------------------------------------------------------------
@njit(cache=True)
def cast_rays(origin: np.ndarray, dirs: np.ndarray, kind: np.ndarray, centre: np.ndarray, axes: np.ndarray,
              size: np.ndarray, t_max: float, t_out: np.ndarray, hit_out: np.ndarray) -> None:
    """Brute force: every ray o + t dirs[k] against every primitive not holding o; the first hit's t
    into t_out[k] (inf: none within t_max) and its primitive into hit_out[k] (−1: none)."""
    P = len(kind)
    inside = np.zeros(P, np.bool_)
    contains_point(kind, centre, axes, size, origin, inside)
    for k in range(dirs.shape[0]):
        best, who = math.inf, -1
        for i in range(P):
            if inside[i]:
                continue
            t = ray_primitive(i, kind, centre, axes, size, origin[0], origin[1], origin[2],
                              dirs[k, 0], dirs[k, 1], dirs[k, 2])
            if t < best and t <= t_max:
                best, who = t, i
        t_out[k] = best
        hit_out[k] = who


@njit(cache=True)
def cast_image(origin: np.ndarray, R: np.ndarray, fx: float, fy: float, cx: float, cy: float,
               kind: np.ndarray, centre: np.ndarray, axes: np.ndarray, size: np.ndarray, visible: np.ndarray,
               z_far: float, depth: np.ndarray, hit: np.ndarray, cos_incidence: np.ndarray) -> int:
    """Render the depth image of the camera at ``origin`` [m] with rotation R (world ← optical frame:
    x right, y down, z forward) and pinhole intrinsics fx, fy, cx, cy [pixels] into depth (H, W) [m]
    (inf: no shape within depth z_far), hit (H, W) (the primitive seen, −1: none) and cos_incidence
    (H, W) (|cos| of the angle between the ray and the surface normal, 0: none). Primitives with
    ``visible[i]`` False, or holding the origin, are not seen. Returns the rays intersected."""
    H, W = depth.shape
    P = len(kind)
    depth[:] = math.inf
    hit[:] = -1
    rect = np.zeros(4, np.int64)
    ox, oy, oz = origin[0], origin[1], origin[2]
    tests = 0
    for i in range(P):
        if not visible[i] or contains(i, kind, centre, axes, size, ox, oy, oz):
            continue
        of = pieces(i, kind, size)
        for piece in range(of):  # (pixels where two pieces' bounds overlap are tested twice: harmless)
            if not screen_rect(i, kind, centre, axes, size, origin, R, fx, fy, cx, cy, W, H, z_far, rect, piece, of):
                continue
            for v in range(rect[2], rect[3] + 1):
                yn = (v - cy) / fy
                bx = R[0, 1] * yn + R[0, 2]
                by = R[1, 1] * yn + R[1, 2]
                bz = R[2, 1] * yn + R[2, 2]
                for u in range(rect[0], rect[1] + 1):
                    xn = (u - cx) / fx
                    t = ray_primitive(i, kind, centre, axes, size, ox, oy, oz,
                                      R[0, 0] * xn + bx, R[1, 0] * xn + by, R[2, 0] * xn + bz)
                    if t < depth[v, u] and t <= z_far:
                        depth[v, u] = t
                        hit[v, u] = i
                tests += rect[1] - rect[0] + 1
    n = np.zeros(3)
    for v in range(H):
        yn = (v - cy) / fy
        for u in range(W):
            i = hit[v, u]
            if i < 0:
                cos_incidence[v, u] = 0.0
                continue
            xn = (u - cx) / fx
            dx = R[0, 0] * xn + R[0, 1] * yn + R[0, 2]
            dy = R[1, 0] * xn + R[1, 1] * yn + R[1, 2]
            dz = R[2, 0] * xn + R[2, 1] * yn + R[2, 2]
            t = depth[v, u]
            surface_normal(i, kind, centre, axes, size, ox + t * dx, oy + t * dy, oz + t * dz, n)
            cos_incidence[v, u] = abs(n[0] * dx + n[1] * dy + n[2] * dz) / math.sqrt(dx * dx + dy * dy + dz * dz)
    return tests


@njit(cache=True)
def rotate_rays(rays: np.ndarray, R: np.ndarray, out: np.ndarray) -> None:
    """out[k] = R rays[k] ((N, 3) each): a camera's ray directions in the world (no BLAS call, whose
    threads crowd a loaded machine)."""
    for k in range(rays.shape[0]):
        x, y, z = rays[k, 0], rays[k, 1], rays[k, 2]
        for j in range(3):
            out[k, j] = R[j, 0] * x + R[j, 1] * y + R[j, 2] * z
