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
the hull of the images in front of the camera) and intersects only those rays, so the cost grows
with the shapes' area on screen, not with pixels × shapes. :func:`cast_rays` is the
brute-force form (every ray against every shape) it is tested against.

Each intersection is the first t ≥ 0 at which the ray enters the solid (a union's first point is
the least of its parts': a capsule's lateral surface within its axis and its two end spheres; a
cylinder's lateral surface and its two end discs; a box's slabs). A shape whose interior holds the
ray's origin is not seen (a camera looks out of the link it sits in). The slow, obviously-correct
reference (:func:`reference_depth`) knows none of this: it sphere-traces each ray with python-fcl's
distance to each shape (``tests/test_camera_raycast.py`` holds both casters, this kernel and
``mujoco.mj_multiRay``, to it and to each other).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import fcl
import numpy as np
from numba import njit

SPHERE, CAPSULE, BOX, CYLINDER = 0, 1, 2, 3
KINDS = {"sphere": SPHERE, "capsule": CAPSULE, "box": BOX, "cylinder": CYLINDER}  # Obstacle.shape → kind

NEAR = 1e-6  # [m] a box corner nearer the camera's plane than this: the box is bounded by its sphere
HALF_PI = 0.5 * math.pi
PIECE = 0.05  # [m] a long capsule's or cylinder's axis is bounded on screen in pieces about this long


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
def _forward_slopes(lo: float, hi: float) -> tuple[float, float, bool]:
    """The slopes tan(a), tan(b) of the angular interval [lo, hi] (from the optical axis, radians, in
    any branch) cut to the forward half-plane (−π/2, π/2), ±inf where it reaches it; False if none."""
    for shift in (-2.0 * math.pi, 0.0, 2.0 * math.pi):
        a, b = max(lo + shift, -HALF_PI), min(hi + shift, HALF_PI)
        if a < b:
            return (math.tan(a) if a > -HALF_PI else -math.inf), (math.tan(b) if b < HALF_PI else math.inf), True
    return 0.0, 0.0, False


@njit(cache=True)
def axis_slopes(x0: float, z0: float, x1: float, z1: float, r: float) -> tuple[float, float, bool]:
    """(lo, hi, any) of x/z over the points with z > 0 of the planar capsule (the discs of radius r
    about (x0, z0) and (x1, z1) and their hull): the projection, on the x–z plane, of a 3-D capsule —
    or of a sphere (both ends the same) — whose image column (or row) range it bounds. When the planar
    capsule holds the origin every slope is possible; else its span, seen from the origin, is the
    union of the two discs' (angle θ ± asin(r/ρ) each), joined the short way (a convex set without
    the origin spans less than π)."""
    dx, dz = x1 - x0, z1 - z0
    ll = dx * dx + dz * dz
    s = 0.0 if ll == 0.0 else max(0.0, min(1.0, -(x0 * dx + z0 * dz) / ll))
    px, pz = x0 + s * dx, z0 + s * dz
    if px * px + pz * pz <= r * r:
        return -math.inf, math.inf, True
    t0, t1 = math.atan2(x0, z0), math.atan2(x1, z1)
    if t1 - t0 > math.pi:
        t1 -= 2.0 * math.pi
    elif t1 - t0 < -math.pi:
        t1 += 2.0 * math.pi
    a0 = math.asin(min(1.0, r / math.sqrt(x0 * x0 + z0 * z0)))
    a1 = math.asin(min(1.0, r / math.sqrt(x1 * x1 + z1 * z1)))
    return _forward_slopes(min(t0 - a0, t1 - a1), max(t0 + a0, t1 + a1))


@njit(cache=True)
def _pixel_range(lo: float, hi: float, f: float, c: float, n: int) -> tuple[int, int]:
    """The pixels [p0, p1] (inclusive, a pixel of margin) whose rays have slopes in [lo, hi]."""
    a = max(-2.0, min(n + 1.0, f * lo + c))
    b = max(-2.0, min(n + 1.0, f * hi + c))
    return max(0, math.floor(a) - 1), min(n - 1, math.ceil(b) + 1)


@njit(cache=True)
def pieces(i: int, kind: np.ndarray, size: np.ndarray) -> int:
    """How many pieces of its axis a capsule or cylinder is bounded by on screen (each about
    :data:`PIECE` long, or 4 radii, up to 32): a long thin one (a wire across the view) would
    otherwise be bounded by the rectangle of its whole slanted silhouette."""
    if kind[i] == SPHERE or kind[i] == BOX:
        return 1
    return min(32, max(1, math.ceil(2.0 * size[i, 1] / max(4.0 * size[i, 0], PIECE))))


@njit(cache=True)
def screen_rect(i: int, kind: np.ndarray, centre: np.ndarray, axes: np.ndarray, size: np.ndarray,
                origin: np.ndarray, R: np.ndarray, fx: float, fy: float, cx: float, cy: float, width: int,
                height: int, z_far: float, out: np.ndarray, piece: int = 0, of: int = 1) -> bool:
    """The pixels (u0, u1, v0, v1, inclusive, into out) that primitive i can cover in the camera at
    ``origin`` with rotation R (world ← optical frame); False when it covers none (behind the camera,
    beyond depth z_far, or off the image). A sphere is bounded by its own silhouette, a capsule or a
    cylinder by its axis swept by r (:func:`axis_slopes`, column and row range apart, exact for what
    lies in front of the camera) — or the ``piece``-th of ``of`` equal pieces of the axis swept by r,
    which together hold it —, a box in front of the camera by its 8 corners, else by its sphere."""
    shift = 0.0
    if of > 1:  # the piece's centre along the axis, and its half-length
        shift = size[i, 1] * (2.0 * (piece + 0.5) / of - 1.0)
    gx = centre[i, 0] + shift * axes[i, 0, 2] - origin[0]
    gy = centre[i, 1] + shift * axes[i, 1, 2] - origin[1]
    gz = centre[i, 2] + shift * axes[i, 2, 2] - origin[2]
    x = R[0, 0] * gx + R[1, 0] * gy + R[2, 0] * gz  # the centre in the optical frame (Rᵀ g)
    y = R[0, 1] * gx + R[1, 1] * gy + R[2, 1] * gz
    z = R[0, 2] * gx + R[1, 2] * gy + R[2, 2] * gz
    k = kind[i]
    hx = hy = hz = 0.0  # the half axis in the optical frame
    r = size[i, 0]
    if k == BOX:
        u_lo, u_hi, v_lo, v_hi = math.inf, -math.inf, math.inf, -math.inf
        z_lo, z_hi = math.inf, -math.inf
        for c in range(8):
            sx = size[i, 0] if c & 1 else -size[i, 0]
            sy = size[i, 1] if c & 2 else -size[i, 1]
            sz = size[i, 2] if c & 4 else -size[i, 2]
            wx = gx + axes[i, 0, 0] * sx + axes[i, 0, 1] * sy + axes[i, 0, 2] * sz
            wy = gy + axes[i, 1, 0] * sx + axes[i, 1, 1] * sy + axes[i, 1, 2] * sz
            wz = gz + axes[i, 2, 0] * sx + axes[i, 2, 1] * sy + axes[i, 2, 2] * sz
            px = R[0, 0] * wx + R[1, 0] * wy + R[2, 0] * wz
            py = R[0, 1] * wx + R[1, 1] * wy + R[2, 1] * wz
            pz = R[0, 2] * wx + R[1, 2] * wy + R[2, 2] * wz
            z_lo, z_hi = min(z_lo, pz), max(z_hi, pz)
            if pz > NEAR:
                u_lo, u_hi = min(u_lo, px / pz), max(u_hi, px / pz)
                v_lo, v_hi = min(v_lo, py / pz), max(v_hi, py / pz)
        if z_hi <= 0.0 or z_lo > z_far:
            return False
        if z_lo <= NEAR:  # reaches the camera's plane: its bounding sphere
            r = math.sqrt(size[i, 0] ** 2 + size[i, 1] ** 2 + size[i, 2] ** 2)
            u_lo, u_hi, seen_u = axis_slopes(x, z, x, z, r)
            v_lo, v_hi, seen_v = axis_slopes(y, z, y, z, r)
            if not (seen_u and seen_v):
                return False
    else:
        if k != SPHERE:
            h = size[i, 1] / of
            hx = h * (R[0, 0] * axes[i, 0, 2] + R[1, 0] * axes[i, 1, 2] + R[2, 0] * axes[i, 2, 2])
            hy = h * (R[0, 1] * axes[i, 0, 2] + R[1, 1] * axes[i, 1, 2] + R[2, 1] * axes[i, 2, 2])
            hz = h * (R[0, 2] * axes[i, 0, 2] + R[1, 2] * axes[i, 1, 2] + R[2, 2] * axes[i, 2, 2])
        if max(z - hz, z + hz) + r <= 0.0 or min(z - hz, z + hz) - r > z_far:
            return False
        u_lo, u_hi, seen_u = axis_slopes(x - hx, z - hz, x + hx, z + hz, r)
        v_lo, v_hi, seen_v = axis_slopes(y - hy, z - hz, y + hy, z + hz, r)
        if not (seen_u and seen_v):
            return False
    u0, u1 = _pixel_range(u_lo, u_hi, fx, cx, width)
    v0, v1 = _pixel_range(v_lo, v_hi, fy, cy, height)
    if u0 > u1 or v0 > v1:
        return False
    out[0], out[1], out[2], out[3] = u0, u1, v0, v1
    return True


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


# -- the slow, obviously-correct reference ---------------------------------------------------------
def _trace(point: fcl.CollisionObject, shape: fcl.CollisionObject, request: fcl.DistanceRequest, o: np.ndarray,
           unit: np.ndarray, s_max: float, tol: float, max_steps: int) -> float:
    """The distance s along the unit ray o + s·unit at which sphere tracing meets ``shape`` (inf: it
    passes s_max, or the origin is inside; NaN: undecided after max_steps)."""

    def gap(s: float) -> float:
        point.setTranslation(o + s * unit)
        return float(fcl.distance(point, shape, request, fcl.DistanceResult()))

    if gap(0.0) <= 0.0:
        return math.inf
    s = 0.0
    for _ in range(max_steps):
        d = gap(s)
        if d < tol:
            return s
        s += d
        if s > s_max:
            return math.inf
    return math.nan


def reference_depth(origin: np.ndarray, direction: np.ndarray, obstacles: Sequence[object], t: float = 0.0,
                    t_max: float = 10.0, tol: float = 1e-9, max_steps: int = 5000) -> tuple[float, int]:
    """(t, index) of the first obstacle the ray origin + t·direction meets within t_max (inf, −1: none)
    by sphere tracing each obstacle (:class:`~qpctl.geometry.obstacles.Obstacle`, at time ``t`` [s])
    with python-fcl's distance from the ray's point (its unsigned query, exact for a point against
    these shapes; the signed one runs GJK/EPA, ~2e-7 m long, and the trace would overshoot): step by
    the distance until it is below ``tol`` [m] (a hit) or the point passes t_max (a miss); an obstacle
    holding the origin (python-fcl: −1, in collision) is not seen. NaN when some trace neither hit nor
    missed within ``max_steps`` (a ray grazing a surface)."""
    from qpctl.geometry.obstacles import Obstacle

    o = np.asarray(origin, float)
    d = np.asarray(direction, float)
    scale = float(np.linalg.norm(d))
    unit = d / scale
    point = fcl.CollisionObject(fcl.Sphere(0.0), fcl.Transform(o))
    request = fcl.DistanceRequest()
    best, who = math.inf, -1
    for j, obs in enumerate(obstacles):
        assert isinstance(obs, Obstacle)
        s = _trace(point, fcl.CollisionObject(obs.geometry(), obs.transform(t)), request, o, unit, t_max * scale, tol,
                   max_steps)
        if math.isnan(s):
            return math.nan, -1
        if s / scale < best:
            best, who = s / scale, j
    return best, who

