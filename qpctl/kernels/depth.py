"""Compiled kernels that turn a depth image or a point cloud into the voxel map's occupancy.

The map keeps, per channel (0 rigid, 1 soft) and voxel, the stamp [s] at which the voxel was last
seen occupied (−inf: free or unknown). One pass over the pixels (:func:`integrate_depth`) or points
(:func:`integrate_points`) drops what must not become an obstacle and stamps the voxels the rest fall
in; a second pass clears the voxels a ray of this frame passed through (:func:`clear_depth`: the
image-space test, each occupied voxel's centre projected into the image; :func:`clear_rays`: a march
along each ray of a cloud with a sensor origin); :func:`occupancy` applies the decay. Every point
gets a status (:data:`KEPT` … :data:`OUTSIDE`) that the pipeline counts and the figures show.

All kernels are ``nogil``: the map worker's thread runs them beside the control loop without holding
the interpreter's lock. References: :mod:`qpctl.perception.reference` (numpy, per point) in
``tests/test_perception_map.py``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from qpctl.kernels.borrow import borrow
from qpctl.kernels.geometry import in_capsule
from qpctl.kernels.self_shadow import casting, in_shadow_pixel, in_shadow_point, shadow_spans

# A pixel's or point's fate (uint8): the tests are applied in the order NO_RETURN, OUT_OF_RANGE, FLYING,
# SELF, TARGET, SHADOW, OUTSIDE (SHADOW came last and has the last code).
KEPT, NO_RETURN, OUT_OF_RANGE, FLYING, SELF, TARGET, OUTSIDE, SHADOW = 0, 1, 2, 3, 4, 5, 6, 7
STATUS_NAMES = ("kept", "no_return", "out_of_range", "flying", "self", "target", "outside", "shadow")
SOFT_LABEL = 2  # qpctl.perception.frames.SOFT: the soft channel; every other label is rigid


@njit(cache=True, nogil=True)
def capsule_boxes(segments: np.ndarray, radii: np.ndarray, boxes: np.ndarray) -> None:
    """(L, 6) axis-aligned boxes (min xyz, max xyz) [m] of the capsules (segments (L, 2, 3), radii (L,))."""
    for i in range(segments.shape[0]):
        for a in range(3):
            lo = min(segments[i, 0, a], segments[i, 1, a])
            hi = max(segments[i, 0, a], segments[i, 1, a])
            boxes[i, a] = lo - radii[i]
            boxes[i, 3 + a] = hi + radii[i]


@njit(cache=True, nogil=True, inline="always")
def in_capsules(x: float, y: float, z: float, segments: np.ndarray, radii: np.ndarray, boxes: np.ndarray) -> bool:
    """Whether (x, y, z) [m] lies within one of the capsules (their boxes first)."""
    for i in range(segments.shape[0]):
        if (x < boxes[i, 0] or y < boxes[i, 1] or z < boxes[i, 2]
                or x > boxes[i, 3] or y > boxes[i, 4] or z > boxes[i, 5]):
            continue
        if in_capsule(segments, radii, i, x, y, z):
            return True
    return False


@njit(cache=True, nogil=True, inline="always")
def voxel_index(x: float, y: float, z: float, ox: float, oy: float, oz: float, inv: float, nx: int, ny: int,
                nz: int) -> int:
    """The flat index (C order) of the voxel holding (x, y, z) [m] in a grid of nx × ny × nz voxels of
    edge 1/inv [m] from the corner (ox, oy, oz); −1 outside it."""
    i = math.floor((x - ox) * inv)
    j = math.floor((y - oy) * inv)
    k = math.floor((z - oz) * inv)
    if i < 0 or j < 0 or k < 0 or i >= nx or j >= ny or k >= nz:
        return -1
    return (i * ny + j) * nz + k


@njit(cache=True, nogil=True, inline="always")
def classify_point(x: float, y: float, z: float, segments: np.ndarray, radii: np.ndarray, boxes: np.ndarray,
                   robot_box: np.ndarray, target: np.ndarray, target_radius: float, soft: bool) -> int:
    """A base-frame point's status before the bounds: :data:`SELF` (not ``soft`` and in an inflated
    capsule; ``robot_box`` (6,) bounds them all: a point labelled soft is a leaf, not the robot, and
    the leaf a link pushes through stays in the map), :data:`TARGET` (not ``soft`` and within
    ``target_radius`` of the grasp target: the fruit goes, the leaves in front of it stay soft
    obstacles) or :data:`KEPT`.
    (The integrating kernels test the boxes in scalars first and call this only for the unlabelled or
    rigid points in them — a soft point is always KEPT: a call per point that passes arrays costs
    more than the whole back-projection.)"""
    if (not soft and x >= robot_box[0] and y >= robot_box[1] and z >= robot_box[2] and x <= robot_box[3]
            and y <= robot_box[4] and z <= robot_box[5] and in_capsules(x, y, z, segments, radii, boxes)):
        return SELF
    if target_radius > 0.0 and not soft:
        dx, dy, dz = x - target[0], y - target[1], z - target[2]
        if dx * dx + dy * dy + dz * dz < target_radius * target_radius:
            return TARGET
    return KEPT


@njit(cache=True, nogil=True)
def zone_box(robot_box: np.ndarray, target: np.ndarray, target_radius: float) -> np.ndarray:
    """(6,) the box around the robot's capsules and the target's zone (what may not be KEPT)."""
    box = robot_box.copy()
    if target_radius > 0.0:
        for a in range(3):
            box[a] = min(box[a], target[a] - target_radius)
            box[3 + a] = max(box[3 + a], target[a] + target_radius)
    return box


@njit(cache=True, nogil=True)
def robot_bounds_into(segments: np.ndarray, radii: np.ndarray, boxes: np.ndarray, box: np.ndarray) -> None:
    """The capsules' boxes into ``boxes`` (L, 6) and the box around them all into ``box`` (6,) (empty: an
    inverted box)."""
    capsule_boxes(segments, radii, boxes)
    box[:3] = np.inf
    box[3:] = -np.inf
    for i in range(boxes.shape[0]):
        for a in range(3):
            box[a] = min(box[a], boxes[i, a])
            box[3 + a] = max(box[3 + a], boxes[i, 3 + a])


@njit(cache=True, nogil=True, inline="always")
def _valid(z: float) -> bool:
    return z > 0.0 and z < math.inf  # NaN fails both


@njit(cache=True, nogil=True)
def metric_depth(depth: np.ndarray, scale: float, z: np.ndarray) -> None:
    """``z`` (H + 2, W + 2) float64: the image's depths [m] (``depth`` × ``scale``) with a border of one
    pixel, 0 for no return (NaN, ±inf, 0, negative) and on the border — so that the neighbour tests
    read any neighbour without a bounds test, and a missing one, like a no-return one, never counts."""
    H, W = depth.shape
    for v in range(H):
        zv = z[v + 1]
        zv[0] = 0.0
        zv[W + 1] = 0.0
        for u in range(W):
            d = depth[v, u] * scale
            zv[u + 1] = d if _valid(d) else 0.0
    z[0, :] = 0.0
    z[H + 1, :] = 0.0


@njit(cache=True, nogil=True)
def flying_row(z: np.ndarray, a: int, flying: float, support: int, out: np.ndarray) -> None:
    """``out`` (W,) bool: whether each return of padded row ``a`` of ``z`` (:func:`metric_depth`) is
    flying, with thr = ``flying`` × its depth zc: a 4-neighbour returns nearer than zc − thr (it lies
    behind a depth edge), or fewer than ``support`` of its 8 neighbours return within thr of zc (a
    return on no surface: a flying pixel whose neighbours across the edge are flying too, or lost to a
    dropout); a missing neighbour (0) never counts. Written without a branch, so that the compiler
    vectorises the row (3.5 ms a 640×480 frame pixel by pixel with branches, 0.5 ms so). Meaningless
    where the depth is 0."""
    zrow, up, dn = z[a], z[a - 1], z[a + 1]
    for u in range(out.shape[0]):
        b = u + 1
        zc = zrow[b]
        thr = flying * zc
        near = zc - thr
        zl, zr, zu, zd = zrow[b - 1], zrow[b + 1], up[b], dn[b]
        edge = (((zl > 0.0) & (zl < near)) | ((zr > 0.0) & (zr < near)) | ((zu > 0.0) & (zu < near))
                | ((zd > 0.0) & (zd < near)))
        n = 0
        n += (zl > 0.0) & (abs(zl - zc) <= thr)
        n += (zr > 0.0) & (abs(zr - zc) <= thr)
        n += (zu > 0.0) & (abs(zu - zc) <= thr)
        n += (zd > 0.0) & (abs(zd - zc) <= thr)
        n += (up[b - 1] > 0.0) & (abs(up[b - 1] - zc) <= thr)
        n += (up[b + 1] > 0.0) & (abs(up[b + 1] - zc) <= thr)
        n += (dn[b - 1] > 0.0) & (abs(dn[b - 1] - zc) <= thr)
        n += (dn[b + 1] > 0.0) & (abs(dn[b + 1] - zc) <= thr)
        out[u] = edge | ((support > 0) & (n < support))


@njit(cache=True, nogil=True)
def integrate_depth(depth: np.ndarray, scale: float, labels: np.ndarray, fx: float, fy: float, cx: float,
                    cy: float, pose: np.ndarray, min_range: float, max_range: float, flying: float,
                    support: int, segments: np.ndarray, radii: np.ndarray, target: np.ndarray, target_radius: float,
                    origin: np.ndarray, voxel: float, last: np.ndarray, stamp: float, status: np.ndarray,
                    counts: np.ndarray, hits: np.ndarray, min_points: int, soft_depth: float,
                    zbuf: np.ndarray, shadow: bool, spans: np.ndarray, reach: np.ndarray, boxes: np.ndarray,
                    robot_box: np.ndarray) -> None:
    """Back-project a depth image (H×W, × ``scale`` [m]) through the pinhole (fx, fy, cx, cy) and the
    camera ``pose`` (4×4, optical frame in the base frame), classify every pixel into ``status``
    (H×W uint8; a return is :data:`FLYING` when a 4-neighbour is nearer than it by more than
    ``flying`` × z, or when fewer than ``support`` of its 8 neighbours lie within ``flying`` × z of it:
    :func:`flying_row`) and count them (``counts``, one per status), and stamp the voxels of the kept points
    in ``last`` (2, nx, ny, nz): channel 1 where ``labels`` (H×W, or 0×0 for none) says soft, else 0 —
    once ``min_points`` of this frame's points fall in it (``hits``, (2, nx, ny, nz) uint16 scratch,
    counts them): a lone point in free space is the noise's tail, not an obstacle. A soft voxel also
    stamps the voxels behind it along the pixel's ray, ``soft_depth`` [m] deep: a camera sees a
    leaf's front, and a link that passed it would otherwise be free of it inside. ``zbuf``
    (H + 2, W + 2) float64 is scratch (:func:`metric_depth`). With ``shadow``, a rigid or unlabelled
    return whose ray from the camera's centre passes through a capsule is :data:`SHADOW`
    (:mod:`qpctl.kernels.self_shadow`; ``spans`` (L, ≥H, 2) int32 and ``reach`` (L,) are its scratch).
    ``boxes`` (L, 6) and ``robot_box`` (6,) are scratch for the capsules' boxes (:func:`robot_bounds_into`).

    The arrays the per-pixel helpers take are borrowed (:mod:`qpctl.kernels.borrow`): each helper call
    that passes a counted array costs two atomic operations per array, and with the robot across the
    image those calls were most of the frame (the shadow test 2.5 ms of a labelled 640×480 frame's
    8.6 ms, 12 of an unlabelled one's 18).

    ``segments`` (L, 2, 3) and ``radii`` (L,) are the robot's capsules at the frame's stamp, already
    inflated by the self-filter's margin."""
    H, W = depth.shape
    has_labels = labels.shape[0] == H and labels.shape[1] == W
    nx, ny, nz = last.shape[1], last.shape[2], last.shape[3]
    flat = last.reshape(-1)
    soft = nx * ny * nz  # the soft channel's offset in flat
    ox, oy, oz, inv = origin[0], origin[1], origin[2], 1.0 / voxel
    segments, radii, target, spans, reach = borrow(segments), borrow(radii), borrow(target), borrow(spans), borrow(reach)
    boxes, robot_box = borrow(boxes), borrow(robot_box)
    robot_bounds_into(segments, radii, boxes, robot_box)
    zone = zone_box(robot_box, target, target_radius)
    zx0, zy0, zz0, zx1, zy1, zz1 = zone[0], zone[1], zone[2], zone[3], zone[4], zone[5]
    su0, sv0, su1, sv1 = W, H, -1, -1  # the pixels a capsule's shadow may fall on (none)
    if shadow and segments.shape[0] > 0:
        union = shadow_spans(segments, radii, pose, fx, fy, cx, cy, W, H, spans, reach)
        su0, sv0, su1, sv1 = union[0], union[1], union[2], union[3]
    r00, r01, r02, tx = pose[0, 0], pose[0, 1], pose[0, 2], pose[0, 3]
    r10, r11, r12, ty = pose[1, 0], pose[1, 1], pose[1, 2], pose[1, 3]
    r20, r21, r22, tz = pose[2, 0], pose[2, 1], pose[2, 2], pose[2, 3]
    ifx, ify = 1.0 / fx, 1.0 / fy
    back_steps = int(soft_depth / (0.5 * voxel)) if soft_depth > 0.0 else 0  # half a voxel each
    step = 0.5 * voxel * inv  # [voxels]
    metric_depth(depth, scale, zbuf)
    counts[:] = 0
    hit = hits.reshape(-1)
    hit[:] = 0
    fly = np.zeros(W, np.bool_)
    for v in range(H):
        yn = (v - cy) * ify
        zrow = zbuf[v + 1]
        if flying > 0.0:
            flying_row(zbuf, v + 1, flying, support, fly)
        for u in range(W):
            z = zrow[u + 1]
            if z == 0.0:
                st = NO_RETURN
            elif z < min_range or z > max_range:
                st = OUT_OF_RANGE
            elif fly[u]:
                st = FLYING
            else:
                xn = (u - cx) * ifx
                xc = xn * z
                yc = yn * z
                x = r00 * xc + r01 * yc + r02 * z + tx
                y = r10 * xc + r11 * yc + r12 * z + ty
                w = r20 * xc + r21 * yc + r22 * z + tz
                st = KEPT
                is_soft = has_labels and labels[v, u] == SOFT_LABEL
                if not is_soft and x >= zx0 and y >= zy0 and w >= zz0 and x <= zx1 and y <= zy1 and w <= zz1:
                    st = classify_point(x, y, w, segments, radii, boxes, robot_box, target, target_radius, is_soft)
                if (st == KEPT and not is_soft and su0 <= u <= su1 and sv0 <= v <= sv1
                        and in_shadow_pixel(u, v, tx, ty, tz, x, y, w, segments, radii, spans, reach)):
                    st = SHADOW
                if st == KEPT:
                    idx = voxel_index(x, y, w, ox, oy, oz, inv, nx, ny, nz)
                    if idx < 0:
                        st = OUTSIDE
                    else:
                        idx += soft if is_soft else 0
                        if hit[idx] < 65535:
                            hit[idx] += 1
                        if hit[idx] >= min_points:
                            flat[idx] = stamp
                            if is_soft and back_steps > 0:  # a leaf seen from the front has a back
                                # along the unit-depth ray (xn, yn, 1) rotated, in voxels a step
                                sx = (r00 * xn + r01 * yn + r02) * step
                                sy = (r10 * xn + r11 * yn + r12) * step
                                sz = (r20 * xn + r21 * yn + r22) * step
                                fi, fj, fk = (x - ox) * inv, (y - oy) * inv, (w - oz) * inv
                                for kk in range(1, back_steps + 1):
                                    i2 = math.floor(fi + kk * sx)
                                    j2 = math.floor(fj + kk * sy)
                                    k2 = math.floor(fk + kk * sz)
                                    if 0 <= i2 < nx and 0 <= j2 < ny and 0 <= k2 < nz:
                                        flat[soft + (i2 * ny + j2) * nz + k2] = stamp
            status[v, u] = st
            counts[st] += 1


@njit(cache=True, nogil=True)
def integrate_points(points: np.ndarray, labels: np.ndarray, segments: np.ndarray, radii: np.ndarray,
                     target: np.ndarray, target_radius: float, origin: np.ndarray, voxel: float, last: np.ndarray,
                     stamp: float, status: np.ndarray, counts: np.ndarray, sensor: np.ndarray, shadow: bool,
                     boxes: np.ndarray, robot_box: np.ndarray) -> None:
    """:func:`integrate_depth` for a point cloud (N×3, base frame [m]; ``labels`` (N,) or (0,)):
    non-finite points are :data:`NO_RETURN`; no range or flying-pixel test (a cloud has no image); with
    ``shadow``, the shadow test from the cloud's ``sensor`` (3,) [m] (:func:`in_shadow_point`). ``boxes``
    and ``robot_box`` are scratch, and the helpers' arrays borrowed, as there."""
    n = points.shape[0]
    has_labels = labels.shape[0] == n
    nx, ny, nz = last.shape[1], last.shape[2], last.shape[3]
    flat = last.reshape(-1)
    soft = nx * ny * nz
    ox, oy, oz, inv = origin[0], origin[1], origin[2], 1.0 / voxel
    segments, radii, target = borrow(segments), borrow(radii), borrow(target)
    boxes, robot_box = borrow(boxes), borrow(robot_box)
    robot_bounds_into(segments, radii, boxes, robot_box)
    zone = zone_box(robot_box, target, target_radius)
    zx0, zy0, zz0, zx1, zy1, zz1 = zone[0], zone[1], zone[2], zone[3], zone[4], zone[5]
    sx, sy, sz = sensor[0], sensor[1], sensor[2]
    casts = casting(segments, radii, sx, sy, sz)  # (counted: a borrowed local's memory could go before its use)
    counts[:] = 0
    for i in range(n):
        x, y, w = points[i, 0], points[i, 1], points[i, 2]
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(w)):
            st = NO_RETURN
        else:
            st = KEPT
            is_soft = has_labels and labels[i] == SOFT_LABEL
            if not is_soft and x >= zx0 and y >= zy0 and w >= zz0 and x <= zx1 and y <= zy1 and w <= zz1:
                st = classify_point(x, y, w, segments, radii, boxes, robot_box, target, target_radius, is_soft)
            if shadow and st == KEPT and not is_soft and in_shadow_point(sx, sy, sz, x, y, w, segments, radii,
                                                                        boxes, casts):
                st = SHADOW
            if st == KEPT:
                idx = voxel_index(x, y, w, ox, oy, oz, inv, nx, ny, nz)
                if idx < 0:
                    st = OUTSIDE
                else:
                    flat[idx + soft if is_soft else idx] = stamp
        status[i] = st
        counts[st] += 1


@njit(cache=True, nogil=True)
def clear_depth(depth: np.ndarray, scale: float, status: np.ndarray, fx: float, fy: float, cx: float, cy: float,
                pose: np.ndarray, margin: float, origin: np.ndarray, voxel: float, last: np.ndarray,
                stamp: float) -> int:
    """Free the voxels this image saw through: each voxel occupied before this frame (0 < stamp of
    ``last`` < ``stamp``) whose centre projects into the image in front of its pixel's return by more
    than ``margin`` [m] is cleared. Pixels without a return or marked :data:`FLYING` clear nothing (a
    mixed pixel's depth lies between two surfaces). A voxel (either channel) that projects onto a
    :data:`SELF` or :data:`SHADOW` pixel and is not cleared — hidden behind the robot's own body, or
    within ``margin`` in front of it — is **held**: stamped ``stamp``, as if seen (the robot hides it
    from the camera, which is no sign that it left: a leaf the hand waits in, the branch an arm passes
    in front of for longer than the decay). Returns the number of voxels cleared."""
    H, W = depth.shape
    nx, ny, nz = last.shape[1], last.shape[2], last.shape[3]
    # camera = Rᵀ (p − t)
    r00, r01, r02 = pose[0, 0], pose[1, 0], pose[2, 0]
    r10, r11, r12 = pose[0, 1], pose[1, 1], pose[2, 1]
    r20, r21, r22 = pose[0, 2], pose[1, 2], pose[2, 2]
    tx, ty, tz = pose[0, 3], pose[1, 3], pose[2, 3]
    cleared = 0
    for i in range(nx):
        px = origin[0] + (i + 0.5) * voxel - tx
        for j in range(ny):
            py = origin[1] + (j + 0.5) * voxel - ty
            for k in range(nz):
                a, b = last[0, i, j, k], last[1, i, j, k]
                if not ((a > -math.inf and a < stamp) or (b > -math.inf and b < stamp)):
                    continue
                pz = origin[2] + (k + 0.5) * voxel - tz
                zc = r20 * px + r21 * py + r22 * pz
                if zc <= 0.0:
                    continue
                u = math.floor(fx * (r00 * px + r01 * py + r02 * pz) / zc + cx + 0.5)
                v = math.floor(fy * (r10 * px + r11 * py + r12 * pz) / zc + cy + 0.5)
                if u < 0 or v < 0 or u >= W or v >= H or status[v, u] == NO_RETURN or status[v, u] == FLYING:
                    continue
                if depth[v, u] * scale > zc + margin:
                    if a < stamp:
                        last[0, i, j, k] = -math.inf
                    if b < stamp:
                        last[1, i, j, k] = -math.inf
                    cleared += 1
                elif status[v, u] == SELF or status[v, u] == SHADOW:  # behind the robot: held
                    if a > -math.inf and a < stamp:
                        last[0, i, j, k] = stamp
                    if b > -math.inf and b < stamp:
                        last[1, i, j, k] = stamp
    return cleared


@njit(cache=True, nogil=True)
def clear_rays(points: np.ndarray, status: np.ndarray, sensor: np.ndarray, margin: float, origin: np.ndarray,
               voxel: float, last: np.ndarray, stamp: float) -> int:
    """Free the voxels along each ray from ``sensor`` [m] to a returned point of a cloud, stopping
    ``margin`` [m] short of it, stepped at half a voxel; voxels stamped in this frame stay. Returns the
    number of voxel visits that cleared something."""
    nx, ny, nz = last.shape[1], last.shape[2], last.shape[3]
    step = 0.5 * voxel
    cleared = 0
    for n in range(points.shape[0]):
        if status[n] == NO_RETURN:
            continue
        dx, dy, dz = points[n, 0] - sensor[0], points[n, 1] - sensor[1], points[n, 2] - sensor[2]
        length = math.sqrt(dx * dx + dy * dy + dz * dz)
        if length <= margin:
            continue
        steps = int((length - margin) / step)
        for s in range(steps):
            f = (s + 0.5) * step / length
            i = math.floor((sensor[0] + f * dx - origin[0]) / voxel)
            j = math.floor((sensor[1] + f * dy - origin[1]) / voxel)
            k = math.floor((sensor[2] + f * dz - origin[2]) / voxel)
            if i < 0 or j < 0 or k < 0 or i >= nx or j >= ny or k >= nz:
                continue
            hit = False
            for c in range(2):
                t = last[c, i, j, k]
                if t > -math.inf and t < stamp:
                    last[c, i, j, k] = -math.inf
                    hit = True
            if hit:
                cleared += 1
    return cleared


@njit(cache=True, nogil=True)
def occupancy(last: np.ndarray, now: float, decay: float, occupied: np.ndarray) -> None:
    """``occupied`` (2, nx, ny, nz) bool: seen within ``decay`` [s] of ``now`` [s]; older voxels are
    forgotten (their stamp set to −inf)."""
    flat = last.reshape(-1)
    occ = occupied.reshape(-1)
    oldest = now - decay
    for i in range(flat.shape[0]):
        t = flat[i]
        if t >= oldest:
            occ[i] = True
        else:
            occ[i] = False
            if t > -math.inf:
                flat[i] = -math.inf
