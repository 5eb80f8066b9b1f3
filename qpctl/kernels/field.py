"""Compiled lookups in the depth map's distance field: the tick's link–field pairs.

The field is sampled at the voxel centres c_ijk = origin + (i + ½, j + ½, k + ½)·voxel: ``dist``
(nx, ny, nz) [m] and its central-difference gradient ``grad`` (nx, ny, nz, 3), both float32
(:mod:`qpctl.kernels.edt`). :func:`trilinear` interpolates both at a point; outside the map's bounds
the field is its truncation (nothing known, no row).

:func:`field_pairs` samples points along each link capsule's axis, keeps the nearest one or two
(the global minimum and the lowest other local minimum at least two samples away), and writes them
as pairs shaped like the primitives' (:mod:`qpctl.kernels.geometry`): signed distance d = field − r
[m] (r the capsule's radius), unit normal n (the field's gradient, pointing away from the obstacle)
and the witness point on the link's surface, axis point − r n [m].

Smooth rows (``smooth=True``, the default): the sample of the minimum is refined by the parabola
through it and its neighbours (its axis parameter then moves continuously as the link moves, rather
than jumping from sample to sample), and the normal is the trilinear interpolation of the gradient
grid (continuous across voxel faces). Without it: the best sample as it is, and the analytic
gradient of the trilinear distance, which jumps at every voxel face; ``benchmarks/perception.py``
measures the difference in |τ̇|.

Inside an obstacle's voxels the field is flat (zero, and so is its gradient): such a pair keeps its
distance (−r) and the axis point as its witness point, with a zero normal — no barrier row (there is
no direction to push along).

:func:`speed_points` gives the soft channel's speed rows their points (:mod:`qpctl.kernels.field_rows`,
:mod:`qpctl.perception.rows`): each sample along a link's axis (within the cutoff) has the speed
bound b(d) = v_s + g·max(d − vmargin, 0) [m/s] — v_s where the capsule's surface may be inside a
leaf (within ``vmargin`` of its voxels), opening farther out — and a fastest point, the point of
the capsule's ball about the sample that moves fastest now; per link the two samples whose fastest
points exceed their bounds the most (or fall short the least) give the rows their points, with the
direction of each point's velocity now.

The compiled tick makes both channels' :func:`field_pairs` and the soft channel's :func:`speed_points`
in one pass (:func:`qpctl.kernels.field_samples.field_samples`, the same numbers); these are the
Python path's kernels and that pass's reference.

References: :func:`qpctl.perception.reference.field_pairs` (scipy's ``map_coordinates``) and finite
differences, in ``tests/test_field.py``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, inline="always")
def cell(nx: int, ny: int, nz: int, origin: np.ndarray, voxel: float, x: float, y: float, z: float
         ) -> tuple[bool, int, int, int, int, int, int, float, float, float]:
    """The lattice cell of voxel centres around (x, y, z) [m]: (inside the bounds, i, j, k, i+1, j+1,
    k+1, tx, ty, tz), the centres clamped to the outermost ones within the bounds."""
    inv = 1.0 / voxel  # one division, not three (5 % of the tick's lookups)
    fx = (x - origin[0]) * inv
    fy = (y - origin[1]) * inv
    fz = (z - origin[2]) * inv
    inside = 0.0 <= fx <= nx and 0.0 <= fy <= ny and 0.0 <= fz <= nz
    fx = min(max(fx - 0.5, 0.0), nx - 1.0)
    fy = min(max(fy - 0.5, 0.0), ny - 1.0)
    fz = min(max(fz - 0.5, 0.0), nz - 1.0)
    i = min(int(fx), nx - 2) if nx > 1 else 0
    j = min(int(fy), ny - 2) if ny > 1 else 0
    k = min(int(fz), nz - 2) if nz > 1 else 0
    return (inside, i, j, k, min(i + 1, nx - 1), min(j + 1, ny - 1), min(k + 1, nz - 1), fx - i, fy - j,
            fz - k)


@njit(cache=True, nogil=True, inline="always")
def _lerp8(c0: float, c1: float, c2: float, c3: float, c4: float, c5: float, c6: float, c7: float, tx: float,
           ty: float, tz: float) -> float:
    """The trilinear lerps on a cell's eight corner values (c[4z + 2y + x]): along x, then y, then z
    (:func:`cell_distance` of the distance grid, :func:`cell_gradient3` of each gradient component)."""
    d00 = c0 + tx * (c1 - c0)
    d10 = c2 + tx * (c3 - c2)
    d01 = c4 + tx * (c5 - c4)
    d11 = c6 + tx * (c7 - c6)
    d0 = d00 + ty * (d10 - d00)
    d1 = d01 + ty * (d11 - d01)
    return d0 + tz * (d1 - d0)


@njit(cache=True, nogil=True, inline="always")
def cell_distance(dist: np.ndarray, i: int, j: int, k: int, i1: int, j1: int, k1: int, tx: float, ty: float,
                  tz: float) -> float:
    """The trilinear distance [m] of the 3-D grid ``dist`` in the cell (i, j, k)–(i1, j1, k1) at the
    fractions (tx, ty, tz) (:func:`cell`): along x, then y, then z, in float32 differences."""
    return _lerp8(dist[i, j, k], dist[i1, j, k], dist[i, j1, k], dist[i1, j1, k], dist[i, j, k1], dist[i1, j, k1],
                  dist[i, j1, k1], dist[i1, j1, k1], tx, ty, tz)


@njit(cache=True, nogil=True, inline="always")
def cell_gradient3(grad: np.ndarray, i: int, j: int, k: int, i1: int, j1: int, k1: int, tx: float, ty: float,
                   tz: float) -> tuple[float, float, float]:
    """The gradient grid ``grad`` (nx, ny, nz, 3) interpolated in a cell (the smooth normal), the three
    components at once: the eight corners' component vectors (contiguous, the grid's last axis) read
    once each, every component interpolated with :func:`cell_distance`'s lerps in its order."""
    gx0, gy0, gz0 = grad[i, j, k, 0], grad[i, j, k, 1], grad[i, j, k, 2]
    gx1, gy1, gz1 = grad[i1, j, k, 0], grad[i1, j, k, 1], grad[i1, j, k, 2]
    gx2, gy2, gz2 = grad[i, j1, k, 0], grad[i, j1, k, 1], grad[i, j1, k, 2]
    gx3, gy3, gz3 = grad[i1, j1, k, 0], grad[i1, j1, k, 1], grad[i1, j1, k, 2]
    gx4, gy4, gz4 = grad[i, j, k1, 0], grad[i, j, k1, 1], grad[i, j, k1, 2]
    gx5, gy5, gz5 = grad[i1, j, k1, 0], grad[i1, j, k1, 1], grad[i1, j, k1, 2]
    gx6, gy6, gz6 = grad[i, j1, k1, 0], grad[i, j1, k1, 1], grad[i, j1, k1, 2]
    gx7, gy7, gz7 = grad[i1, j1, k1, 0], grad[i1, j1, k1, 1], grad[i1, j1, k1, 2]
    return (_lerp8(gx0, gx1, gx2, gx3, gx4, gx5, gx6, gx7, tx, ty, tz),
            _lerp8(gy0, gy1, gy2, gy3, gy4, gy5, gy6, gy7, tx, ty, tz),
            _lerp8(gz0, gz1, gz2, gz3, gz4, gz5, gz6, gz7, tx, ty, tz))


@njit(cache=True, nogil=True, inline="always")
def field_at(dist: np.ndarray, grad: np.ndarray, origin: np.ndarray, voxel: float, truncation: float, x: float,
             y: float, z: float, smooth: bool, far_gradient: bool) -> tuple[float, float, float, float]:
    """The field at (x, y, z) [m] as (d [m], ∇d): the interpolated gradient grid (``smooth``) or the
    trilinear interpolant's own gradient. Outside the bounds: ``truncation`` and a zero gradient;
    within them, the centres' lattice is clamped to the outermost centres. Without ``far_gradient``
    the gradient is zero where d is at or beyond the truncation (a pair there is inactive whatever it is)."""
    nx, ny, nz = dist.shape
    inside, i, j, k, i1, j1, k1, tx, ty, tz = cell(nx, ny, nz, origin, voxel, x, y, z)
    if not inside:
        return truncation, 0.0, 0.0, 0.0
    d = cell_distance(dist, i, j, k, i1, j1, k1, tx, ty, tz)
    if not far_gradient and d >= truncation:
        return d, 0.0, 0.0, 0.0
    if smooth:
        gx, gy, gz = cell_gradient3(grad, i, j, k, i1, j1, k1, tx, ty, tz)
        return d, gx, gy, gz
    gx, gy, gz = cell_raw_gradient(dist, i, j, k, i1, j1, k1, tx, ty, tz)
    return d, gx / voxel, gy / voxel, gz / voxel


@njit(cache=True, nogil=True, inline="always")
def cell_raw_gradient(dist: np.ndarray, i: int, j: int, k: int, i1: int, j1: int, k1: int, tx: float, ty: float,
                      tz: float) -> tuple[float, float, float]:
    """∂/∂(tx, ty, tz) of :func:`cell_distance`'s trilinear form in a cell, zero along an axis of one
    voxel (i1 = i): the raw field's gradient times the voxel."""
    d000, d100, d010, d110 = dist[i, j, k], dist[i1, j, k], dist[i, j1, k], dist[i1, j1, k]
    d001, d101, d011, d111 = dist[i, j, k1], dist[i1, j, k1], dist[i, j1, k1], dist[i1, j1, k1]
    d00 = d000 + tx * (d100 - d000)
    d10 = d010 + tx * (d110 - d010)
    d01 = d001 + tx * (d101 - d001)
    d11 = d011 + tx * (d111 - d011)
    d0 = d00 + ty * (d10 - d00)
    d1 = d01 + ty * (d11 - d01)
    ex = 0.0 if i1 == i else 1.0
    ey = 0.0 if j1 == j else 1.0
    ez = 0.0 if k1 == k else 1.0
    ddx = (1 - tz) * ((1 - ty) * (d100 - d000) + ty * (d110 - d010)) + tz * ((1 - ty) * (d101 - d001)
                                                                           + ty * (d111 - d011))
    ddy = (1 - tz) * (d10 - d00) + tz * (d11 - d01)
    return ex * ddx, ey * ddy, ez * (d1 - d0)


@njit(cache=True, nogil=True, inline="always")
def trilinear(dist: np.ndarray, grad: np.ndarray, origin: np.ndarray, voxel: float, truncation: float,
              x: float, y: float, z: float, smooth: bool, out: np.ndarray) -> float:
    """:func:`field_at` (the gradient everywhere) as the distance [m], its gradient written to ``out`` (3,)."""
    d, out[0], out[1], out[2] = field_at(dist, grad, origin, voxel, truncation, x, y, z, smooth, True)
    return d


@njit(cache=True, nogil=True, inline="always")
def trilinear_distance(dist: np.ndarray, origin: np.ndarray, voxel: float, truncation: float, x: float, y: float,
                       z: float) -> float:
    """:func:`trilinear`'s distance alone [m] (the samples along a link need no gradient)."""
    nx, ny, nz = dist.shape
    inside, i, j, k, i1, j1, k1, tx, ty, tz = cell(nx, ny, nz, origin, voxel, x, y, z)
    if not inside:
        return truncation
    return cell_distance(dist, i, j, k, i1, j1, k1, tx, ty, tz)


@njit(cache=True, nogil=True, inline="always")
def _refine(ds: np.ndarray, j: int, samples: int, smooth: bool) -> float:
    """The axis parameter s ∈ [0, 1] of the minimum near sample j (the parabola's vertex, smooth)."""
    s = j / (samples - 1.0)
    if not smooth or j == 0 or j == samples - 1:
        return s
    a, b, c = ds[j - 1], ds[j], ds[j + 1]
    curv = a - 2.0 * b + c
    if curv <= 0.0:
        return s
    delta = min(max(0.5 * (a - c) / curv, -0.5), 0.5)
    return (j + delta) / (samples - 1.0)


@njit(cache=True, nogil=True, inline="always")
def pair_row(segments: np.ndarray, radii: np.ndarray, l: int, s: float, dist: np.ndarray, grad: np.ndarray,
             origin: np.ndarray, voxel: float, truncation: float, smooth: bool, row: int, out_d: np.ndarray,
             out_n: np.ndarray, out_p: np.ndarray, out_s: np.ndarray) -> None:
    """Link l's pair at its axis parameter s, in one channel's grids, into row ``row`` of the outputs."""
    ax, ay, az = segments[l, 0, 0], segments[l, 0, 1], segments[l, 0, 2]
    px = ax + s * (segments[l, 1, 0] - ax)
    py = ay + s * (segments[l, 1, 1] - ay)
    pz = az + s * (segments[l, 1, 2] - az)
    d, gx, gy, gz = field_at(dist, grad, origin, voxel, truncation, px, py, pz, smooth, False)
    gn = math.sqrt(gx * gx + gy * gy + gz * gz)
    r = radii[l]
    out_s[row] = s
    # nothing within the truncation (an inactive row), or inside the voxels where the field is flat: no normal
    if d >= truncation or gn < 1e-9:
        out_d[row] = min(d, truncation) - r
        out_n[row, 0] = 0.0
        out_n[row, 1] = 0.0
        out_n[row, 2] = 0.0
        out_p[row, 0], out_p[row, 1], out_p[row, 2] = px, py, pz
        return
    nx, ny, nz = gx / gn, gy / gn, gz / gn
    out_d[row] = d - r
    out_n[row, 0], out_n[row, 1], out_n[row, 2] = nx, ny, nz
    out_p[row, 0], out_p[row, 1], out_p[row, 2] = px - r * nx, py - r * ny, pz - r * nz


@njit(cache=True, nogil=True, inline="always")
def second_minimum(ds: np.ndarray, best: int, samples: int, truncation: float) -> int:
    """The lowest local minimum of the samples ``ds`` at least two samples from ``best`` and within
    the truncation (−1: none): the second row's sample."""
    second = -1
    for j in range(samples):
        if abs(j - best) < 2 or ds[j] >= truncation:
            continue
        if (j > 0 and ds[j - 1] < ds[j]) or (j < samples - 1 and ds[j + 1] < ds[j]):
            continue  # not a local minimum
        if second < 0 or ds[j] < ds[second]:
            second = j
    return second


@njit(cache=True, nogil=True, inline="always")
def ranked_excess(px: float, py: float, pz: float, r: float, vx: float, vy: float, vz: float, wx: float, wy: float,
                  wz: float, wn: float, d: float, soft_speed: float, gain: float, vmargin: float, e2: float) -> float:
    """How much the fastest point of the ball of radius r about the axis point (px, py, pz) [m] (inside
    the capsule) outruns its bound b(d) [m/s]: the axis point's velocity c (body velocity v at the
    origin, ω) plus r ω × e, e = (c × ω)/|c × ω| maximising cᵀ(ω × e): |c| + r|ω ⊥ c| − b(d). −inf
    where it cannot rank among a link's two largest: |ω ⊥ c| ≤ |ω| = ``wn``, so |c| + r·wn − b(d)
    bounds it, and a bound below the second largest so far ``e2`` (less 1e-9 relative, far above
    rounding) leaves the selection as it is — the same samples chosen, one square root and a
    division fewer."""
    cx, cy, cz = vx + wy * pz - wz * py, vy + wz * px - wx * pz, vz + wx * py - wy * px
    c = math.sqrt(cx * cx + cy * cy + cz * cz)
    b = soft_speed + gain * max(d - vmargin, 0.0)
    if c + r * wn - b < e2 - 1e-9 * (1.0 + abs(e2)):
        return -math.inf
    ex, ey, ez = cy * wz - cz * wy, cz * wx - cx * wz, cx * wy - cy * wx
    return c + r * math.sqrt(ex * ex + ey * ey + ez * ez) / max(c, 1e-300) - b


@njit(cache=True, nogil=True, inline="always")
def speed_row(px: float, py: float, pz: float, r: float, vx: float, vy: float, vz: float, wx: float, wy: float,
              wz: float, d: float, soft_speed: float, gain: float, vmargin: float, row: int, out_p: np.ndarray,
              out_u: np.ndarray, out_b: np.ndarray, out_d: np.ndarray) -> None:
    """A speed row's point for the axis point (px, py, pz) [m] of its sample (field distance d from the
    capsule's surface [m]): the ball's fastest point, the direction of its velocity and its bound."""
    cx, cy, cz = vx + wy * pz - wz * py, vy + wz * px - wx * pz, vz + wx * py - wy * px
    c = math.sqrt(cx * cx + cy * cy + cz * cz)
    if c > 1e-12:
        ex, ey, ez = cy * wz - cz * wy, cz * wx - cx * wz, cx * wy - cy * wx
        e = math.sqrt(ex * ex + ey * ey + ez * ez)
        if e > 1e-12 * c:
            px, py, pz = px + r * ex / e, py + r * ey / e, pz + r * ez / e
    cx, cy, cz = vx + wy * pz - wz * py, vy + wz * px - wx * pz, vz + wx * py - wy * px
    c = math.sqrt(cx * cx + cy * cy + cz * cz)
    out_p[row, 0], out_p[row, 1], out_p[row, 2] = px, py, pz
    out_d[row] = d
    if c <= 1e-9:  # at rest: no direction to bound (the next tick's point has one)
        return
    out_u[row, 0], out_u[row, 1], out_u[row, 2] = cx / c, cy / c, cz / c
    out_b[row] = soft_speed + gain * max(d - vmargin, 0.0)


@njit(cache=True, nogil=True)
def field_pairs(segments: np.ndarray, radii: np.ndarray, dist: np.ndarray, grad: np.ndarray,
                origin: np.ndarray, voxel: float, truncation: float, samples: int, rows: int, smooth: bool,
                ds: np.ndarray, out_d: np.ndarray, out_n: np.ndarray, out_p: np.ndarray,
                out_s: np.ndarray) -> None:
    """The link–field pairs of one channel: for link l (``segments`` (L, 2, 3) [m], ``radii`` (L,)),
    rows l·rows … l·rows + rows − 1 of ``out_d`` (L·rows,) distance [m], ``out_n`` (L·rows, 3) unit
    normal (zero for an inactive row: distance = truncation − r), ``out_p`` (L·rows, 3) witness point
    on the link [m] and ``out_s`` its axis parameter. ``ds`` (samples,) is scratch."""
    for l in range(segments.shape[0]):
        ax, ay, az = segments[l, 0, 0], segments[l, 0, 1], segments[l, 0, 2]
        ux, uy, uz = segments[l, 1, 0] - ax, segments[l, 1, 1] - ay, segments[l, 1, 2] - az
        # the field is 1-Lipschitz: nothing within the truncation anywhere on the axis when the
        # axis's midpoint is farther than the truncation plus half the axis (one lookup, no rows)
        half = 0.5 * math.sqrt(ux * ux + uy * uy + uz * uz)
        if trilinear_distance(dist, origin, voxel, truncation, ax + 0.5 * ux, ay + 0.5 * uy,
                              az + 0.5 * uz) >= truncation + half:
            for r in range(rows):
                row = l * rows + r
                out_d[row] = truncation - radii[l]
                out_s[row] = 0.5
                out_n[row, :] = 0.0
                out_p[row, 0], out_p[row, 1], out_p[row, 2] = ax + 0.5 * ux, ay + 0.5 * uy, az + 0.5 * uz
            continue
        best = 0
        for j in range(samples):
            f = j / (samples - 1.0)
            ds[j] = trilinear_distance(dist, origin, voxel, truncation, ax + f * ux, ay + f * uy, az + f * uz)
            if ds[j] < ds[best]:
                best = j
        pair_row(segments, radii, l, _refine(ds, best, samples, smooth), dist, grad, origin, voxel, truncation,
                 smooth, l * rows, out_d, out_n, out_p, out_s)
        if rows < 2:
            continue
        second = second_minimum(ds, best, samples, truncation)
        if second < 0:  # one minimum only: the second row repeats the first's point, inactive
            row = l * rows + 1
            out_d[row] = truncation - radii[l]
            out_s[row] = out_s[l * rows]
            out_n[row, :] = 0.0
            out_p[row, :] = out_p[l * rows, :]
        else:
            pair_row(segments, radii, l, _refine(ds, second, samples, smooth), dist, grad, origin, voxel,
                     truncation, smooth, l * rows + 1, out_d, out_n, out_p, out_s)


@njit(cache=True, nogil=True)
def speed_points(segments: np.ndarray, radii: np.ndarray, dist: np.ndarray, origin: np.ndarray, voxel: float,
                 truncation: float, samples: int, body_vel: np.ndarray, soft_speed: float, gain: float,
                 vmargin: float, cutoff: float, ds: np.ndarray, out_p: np.ndarray, out_u: np.ndarray,
                 out_b: np.ndarray, out_d: np.ndarray) -> None:
    """The speed rows' points of one channel (module docstring): for link l, rows 2l and 2l + 1 of
    ``out_p`` (2L, 3) the body point [m], ``out_u`` (2L, 3) the unit direction of its velocity now
    (from ``body_vel`` (L, 6): each body's world velocity at the origin and ω), ``out_b`` (2L,) its
    bound b(d) [m/s] (inf: no row), ``out_d`` (2L,) the field's distance d from the capsule's surface
    at its sample [m]. ``ds`` (samples,) is scratch."""
    for l in range(segments.shape[0]):
        r = radii[l]
        ax, ay, az = segments[l, 0, 0], segments[l, 0, 1], segments[l, 0, 2]
        ux, uy, uz = segments[l, 1, 0] - ax, segments[l, 1, 1] - ay, segments[l, 1, 2] - az
        for k in range(2):
            out_b[2 * l + k] = math.inf
            out_d[2 * l + k] = truncation - r
            out_p[2 * l + k, 0], out_p[2 * l + k, 1], out_p[2 * l + k, 2] = ax, ay, az
            out_u[2 * l + k, :] = 0.0
        half = 0.5 * math.sqrt(ux * ux + uy * uy + uz * uz)
        if trilinear_distance(dist, origin, voxel, truncation, ax + 0.5 * ux, ay + 0.5 * uy,
                              az + 0.5 * uz) >= truncation + half:
            continue  # nothing within the truncation on this axis (1-Lipschitz)
        vx, vy, vz = body_vel[l, 0], body_vel[l, 1], body_vel[l, 2]
        wx, wy, wz = body_vel[l, 3], body_vel[l, 4], body_vel[l, 5]
        wn = math.sqrt(wx * wx + wy * wy + wz * wz)
        best, second = -1, -1
        e1 = e2 = -math.inf
        for j in range(samples):
            f = j / (samples - 1.0)
            px, py, pz = ax + f * ux, ay + f * uy, az + f * uz
            d = trilinear_distance(dist, origin, voxel, truncation, px, py, pz) - r
            ds[j] = d
            if d + r >= truncation or d >= cutoff:
                continue
            excess = ranked_excess(px, py, pz, r, vx, vy, vz, wx, wy, wz, wn, d, soft_speed, gain, vmargin, e2)
            if excess > e1:
                second, e2 = best, e1
                best, e1 = j, excess
            elif excess > e2:
                second, e2 = j, excess
        for k in range(2):
            j = best if k == 0 else second
            if j < 0:
                continue
            f = j / (samples - 1.0)
            speed_row(ax + f * ux, ay + f * uy, az + f * uz, r, vx, vy, vz, wx, wy, wz, ds[j], soft_speed, gain,
                      vmargin, 2 * l + k, out_p, out_u, out_b, out_d)
