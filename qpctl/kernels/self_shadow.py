"""The robot's shadow: returns whose ray from the sensor passes through one of its inflated capsules.

A pixel on the robot's silhouette sees the link and what lies behind it at once; a sensor reports a
mixed depth somewhere between the two (a *flying pixel*), on no surface. The image-space flying-pixel
test (:func:`qpctl.kernels.depth.flying_row`) drops most of them, but not one whose nearer neighbour is
itself a dropout or another flying pixel; such a point lies behind the link's silhouette, beyond the
self-filter's inflated capsule, and becomes a rigid voxel a few centimetres from the link — inside
the rigid rows' margin, where the QP has no feasible torque (measured on ``panda_canopy_depth``, canopy
seed 18, 23 s: 180 flying returns within 0.1 m of the inflated capsules kept, 57 of them occupying
voxels, the nearest 0.2 mm outside a capsule; docs/perception.md, "The robot's shadow").

The test, as ROS's ``robot_self_filter`` classifies its SHADOW points: a return p is in the robot's
shadow when the segment from the sensor's centre o to p comes within a capsule's (inflated) radius of
its axis — the sensor looked through the robot's body, or within ``self_margin`` of it, to see p. A
real surface behind the robot is lost only in that band around the silhouette (it is hidden by the
robot anyway); a flying pixel, which lies on its ray between the link and the background, always is. A
capsule that holds o (a camera on the wrist, inside its own link's inflated capsule) casts no shadow:
every ray leaves it.

For an image, :func:`shadow_spans` bounds each capsule's image once per frame, row by row (pieces of
the capsule, each within its end spheres' tangent planes; the whole image where a piece reaches the
camera's plane), and :func:`in_shadow_pixel` tests a pixel only against the capsules whose span of its
row holds it; for a cloud, :func:`in_shadow_point` tests the capsules whose box meets the ray's. Both
are held to python-fcl's capsule–capsule collision in ``tests/test_self_shadow.py``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from qpctl.kernels.geometry import axis_distance2, in_capsule, segment_params

PIECES = 8  # a capsule's image is bounded row by row by this many pieces of it (shadow_spans)


@njit(cache=True, nogil=True, inline="always")
def ray_meets_capsule(ox: float, oy: float, oz: float, x: float, y: float, w: float, segments: np.ndarray,
                      radii: np.ndarray, i: int) -> bool:
    """Whether the segment from (ox, oy, oz) to (x, y, w) [m] comes within capsule i's radius of its axis."""
    dx, dy, dz = x - ox, y - oy, w - oz
    ax, ay, az = segments[i, 0, 0], segments[i, 0, 1], segments[i, 0, 2]
    ux, uy, uz = segments[i, 1, 0] - ax, segments[i, 1, 1] - ay, segments[i, 1, 2] - az
    s, t = segment_params(ox, oy, oz, dx, dy, dz, dx * dx + dy * dy + dz * dz, ax, ay, az, ux, uy, uz)
    ex = ox + s * dx - ax - t * ux
    ey = oy + s * dy - ay - t * uy
    ez = oz + s * dz - az - t * uz
    return ex * ex + ey * ey + ez * ez < radii[i] * radii[i]


@njit(cache=True, nogil=True, inline="always")
def _tangents(c: float, cz: float, r: float) -> tuple[float, float]:
    """The slopes t = x/z of the two planes x = t z tangent to a sphere of radius r whose centre is at
    (c, cz) in the plane's coordinates (cz > r: in front of the camera), lower first:
    (c − t cz)² = r² (1 + t²)."""
    a = cz * cz - r * r
    h = r * math.sqrt(max(c * c + a, 0.0))
    return (c * cz - h) / a, (c * cz + h) / a


@njit(cache=True, nogil=True, inline="always")
def _sphere_rect(px: float, py: float, pz: float, r: float, pose: np.ndarray, fx: float, fy: float, cx: float,
                 cy: float) -> tuple[bool, float, float, float, float]:
    """The exact bounding rectangle (u_min, u_max, v_min, v_max) [pixels] of the image of a sphere of
    radius r [m] about (px, py, pz) [m] (base frame, relative to the camera's centre), or False where
    it reaches the camera's plane."""
    # camera = Rᵀ (p − t)
    xc = pose[0, 0] * px + pose[1, 0] * py + pose[2, 0] * pz
    yc = pose[0, 1] * px + pose[1, 1] * py + pose[2, 1] * pz
    zc = pose[0, 2] * px + pose[1, 2] * py + pose[2, 2] * pz
    if zc <= r * (1.0 + 1e-9):
        return False, 0.0, 0.0, 0.0, 0.0
    ulo, uhi = _tangents(xc, zc, r)
    vlo, vhi = _tangents(yc, zc, r)
    return True, fx * ulo + cx, fx * uhi + cx, fy * vlo + cy, fy * vhi + cy


@njit(cache=True, nogil=True)
def shadow_spans(segments: np.ndarray, radii: np.ndarray, pose: np.ndarray, fx: float, fy: float, cx: float,
                 cy: float, W: int, H: int, spans: np.ndarray, reach: np.ndarray) -> np.ndarray:
    """Per capsule (segments (L, 2, 3), radii (L,) [m]) and image row, the pixels ``spans`` (L, ≥H, 2)
    int32 (u0, u1, inclusive; empty: u0 > u1) that hold its image through the pinhole (fx, fy, cx, cy)
    of a W×H image from ``pose`` (4×4, optical frame in the base frame), with a pixel to spare: the
    capsule cut into :data:`PIECES` capsules along its axis, each bounded by the union of its two end
    spheres' exact rectangles (a capsule is the convex hull of its end spheres, and so is its image of
    theirs); every pixel of the image where a piece reaches the camera's plane; nothing for a capsule
    that holds the camera's centre (it casts no shadow). ``reach`` (L,) gets the square of each
    capsule's distance from the camera's centre [m²] (a return nearer than that is in front of it).
    Returns the rectangle (u0, v0, u1, v1) (4,) that holds every span (empty: u0 > u1)."""
    tx, ty, tz = pose[0, 3], pose[1, 3], pose[2, 3]
    union = np.array([W, H, -1, -1], np.int64)
    for i in range(segments.shape[0]):
        for v in range(H):
            spans[i, v, 0], spans[i, v, 1] = W, -1
        reach[i] = 0.0
        r = radii[i]
        d2 = axis_distance2(segments, i, tx, ty, tz)
        if d2 < r * r:  # it holds the camera (in_capsule's test)
            continue
        reach[i] = (math.sqrt(d2) - r) ** 2
        ax, ay, az = segments[i, 0, 0] - tx, segments[i, 0, 1] - ty, segments[i, 0, 2] - tz
        ux, uy, uz = segments[i, 1, 0] - segments[i, 0, 0], segments[i, 1, 1] - segments[i, 0, 1], \
            segments[i, 1, 2] - segments[i, 0, 2]
        # piece k runs between the end spheres k and k + 1: each sphere's rectangle once
        ok0, ua, ub, va, vb = _sphere_rect(ax, ay, az, r, pose, fx, fy, cx, cy)
        for k in range(PIECES):
            f = (k + 1) / PIECES
            ok1, uc, ud, vc, vd = _sphere_rect(ax + f * ux, ay + f * uy, az + f * uz, r, pose, fx, fy, cx, cy)
            if not (ok0 and ok1):
                u0, v0, u1, v1 = 0, 0, W - 1, H - 1
            else:
                u0 = max(math.floor(min(ua, uc)) - 1, 0)
                u1 = min(math.ceil(max(ub, ud)) + 1, W - 1)
                v0 = max(math.floor(min(va, vc)) - 1, 0)
                v1 = min(math.ceil(max(vb, vd)) + 1, H - 1)
            ok0, ua, ub, va, vb = ok1, uc, ud, vc, vd
            if u0 > u1 or v0 > v1:
                continue
            for v in range(v0, v1 + 1):
                spans[i, v, 0] = min(spans[i, v, 0], u0)
                spans[i, v, 1] = max(spans[i, v, 1], u1)
            union[0], union[1] = min(union[0], u0), min(union[1], v0)
            union[2], union[3] = max(union[2], u1), max(union[3], v1)
    return union


@njit(cache=True, nogil=True, inline="always")
def in_shadow_pixel(u: int, v: int, ox: float, oy: float, oz: float, x: float, y: float, w: float,
                    segments: np.ndarray, radii: np.ndarray, spans: np.ndarray, reach: np.ndarray) -> bool:
    """Whether pixel (u, v)'s return at (x, y, w) [m], seen from the camera's centre (ox, oy, oz), is in
    the shadow of a capsule whose span of row v (:func:`shadow_spans`) holds the pixel and that is not
    farther from the camera than the return (``reach``)."""
    dd = (x - ox) * (x - ox) + (y - oy) * (y - oy) + (w - oz) * (w - oz)
    for i in range(segments.shape[0]):
        if u < spans[i, v, 0] or u > spans[i, v, 1] or dd < reach[i]:
            continue
        if ray_meets_capsule(ox, oy, oz, x, y, w, segments, radii, i):
            return True
    return False


@njit(cache=True, nogil=True, inline="always")
def in_shadow_point(ox: float, oy: float, oz: float, x: float, y: float, w: float, segments: np.ndarray,
                    radii: np.ndarray, boxes: np.ndarray, casts: np.ndarray) -> bool:
    """Whether the point (x, y, w) [m] of a cloud whose sensor is at (ox, oy, oz) is in the shadow of a
    capsule that ``casts`` (L,) bool one (its box (L, 6) meeting the ray's first)."""
    lx, hx = min(ox, x), max(ox, x)
    ly, hy = min(oy, y), max(oy, y)
    lz, hz = min(oz, w), max(oz, w)
    for i in range(segments.shape[0]):
        if not casts[i] or hx < boxes[i, 0] or hy < boxes[i, 1] or hz < boxes[i, 2] or lx > boxes[i, 3] \
                or ly > boxes[i, 4] or lz > boxes[i, 5]:
            continue
        if ray_meets_capsule(ox, oy, oz, x, y, w, segments, radii, i):
            return True
    return False


@njit(cache=True, nogil=True)
def casting(segments: np.ndarray, radii: np.ndarray, ox: float, oy: float, oz: float) -> np.ndarray:
    """(L,) bool: the capsules that do not hold the sensor's centre (they cast a shadow)."""
    out = np.empty(segments.shape[0], np.bool_)
    for i in range(segments.shape[0]):
        out[i] = not in_capsule(segments, radii, i, ox, oy, oz)
    return out
