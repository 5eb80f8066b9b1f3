"""Screen-space culling for the ray caster (:func:`qpctl.kernels.raycast.cast_image`): the pixels a
primitive's silhouette can cover, per image axis the slopes its projection on that axis's plane
spans in front of the camera (a sphere's tangents; a capsule's or cylinder's axis swept by its
radius, in pieces; a box's 8 corners), so that only those rays are intersected. The shape kinds
(:data:`SPHERE`, :data:`CAPSULE`, :data:`BOX`, :data:`CYLINDER`) are the caster's.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

SPHERE, CAPSULE, BOX, CYLINDER = 0, 1, 2, 3

NEAR = 1e-6  # [m] a box corner nearer the camera's plane than this: the box is bounded by its sphere
HALF_PI = 0.5 * math.pi
PIECE = 0.05  # [m] a long capsule's or cylinder's axis is bounded on screen in pieces about this long


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
