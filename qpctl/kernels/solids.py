"""Closed-form distances between a link capsule and a box or a cylinder obstacle, compiled.

Both obstacles are convex solids that are products of simple sets in their own frame (z along the
obstacle's ``axis``): a box is [−h_x, h_x] × [−h_y, h_y] × [−h_z, h_z], a cylinder a disc of radius R
times [−h_z, h_z]. So the projection Π onto either is exact and cheap (clamps, one radial scale),
and so is the support function h(n) (Σ h_i|n_i|, or R·|n_xy| + h_z|n_z|). With the link's axis
p(τ) = a + τu, τ ∈ [0, 1], and its radius r:

* **apart** (the axis misses the solid): φ(τ) = ½|p(τ) − Π p(τ)|² is convex with the monotone
  slope φ'(τ) = (p − Π p)·u, whose root (a bracketed Illinois false position; exact on the linear
  pieces a box gives) is the closest axis point P; the distance is d = |P − Π P| − r, the normal
  n = (P − Π P)/|P − Π P| (obstacle → link), the witness points P − r n and Π P. Exact to rounding.
* **penetrating** (the axis meets the solid): the axis's signed distance is −min over unit n of
  F(n) = h(n) − min(n·a, n·b), the translation along n that frees it (the separating-axis view of
  EPA's penetration depth). F's minimum is where one end dominates — a local minimum of that end's
  own depth: a face normal (±x, ±y, ±z of a box; ±z or the end's radial direction of a cylinder) —
  or on the great circle n ⊥ u where both ends tie: the edge normals ±(u × e_i) of a box's projected
  outline; for a cylinder ±(z × u) and the minimum over that circle (sampled, then a golden-section
  refinement). Evaluating F on every candidate is exact for a box, and to ~1e-12 m for a cylinder.
  The link's witness point is its deepest axis point less r n, the obstacle's p_link − d n (on the
  solid's support plane along n).

The barrier's drift ḧ at q̈ = 0 (:func:`solid_drift`) is the second central difference of this
distance along the axis ends' and the centre's second-order motion (velocity and q̈ = 0
acceleration): d²/ds² of a function of the ends depends on their first two derivatives only, so it
is ḧ itself, to O(δ²) truncation and ~1e-7 m/s² of rounding (δ = 1e-4 s).

References (``tests/test_solids.py``): python-fcl's distance and nearest points on the same shapes
(GJK apart, EPA penetrating), a bounded scalar minimisation of the point–solid distance along the
axis, and finite differences of that distance along the arm's motion.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from qpctl.kernels.codes import KIND_BOX
from qpctl.kernels.geometry import perpendicular

ROOT_STEPS = 100  # Illinois steps at most (a box's linear pieces converge in a few)
CIRCLE_SAMPLES = 64  # the cylinder's great-circle search: samples, then golden-section steps
GOLDEN_STEPS = 48
MEETS = 1e-12  # [m]: an axis nearer than this to the solid takes the penetrating branch
DRIFT_STEP = 1e-4  # [s] the drift's central difference


@njit(cache=True)
def _clamp(x: float, h: float) -> float:
    return -h if x < -h else (min(x, h))


@njit(cache=True)
def project(kind: int, x: float, y: float, z: float, hx: float, hy: float,
            hz: float) -> tuple[float, float, float]:
    """Π(x, y, z): the solid's point nearest to (x, y, z), all in its own frame [m] (a cylinder's
    radius is hx)."""
    if kind == KIND_BOX:
        return _clamp(x, hx), _clamp(y, hy), _clamp(z, hz)
    rho2 = x * x + y * y
    s = hx / math.sqrt(rho2) if rho2 > hx * hx else 1.0
    return x * s, y * s, _clamp(z, hz)


@njit(cache=True)
def support(kind: int, nx: float, ny: float, nz: float, hx: float, hy: float, hz: float) -> float:
    """h(n) = max over the solid of n·x, in its own frame [m]."""
    if kind == KIND_BOX:
        return hx * abs(nx) + hy * abs(ny) + hz * abs(nz)
    return hx * math.sqrt(nx * nx + ny * ny) + hz * abs(nz)


@njit(cache=True)
def _slope(kind: int, t: float, ax: float, ay: float, az: float, ux: float, uy: float, uz: float, hx: float,
           hy: float, hz: float) -> float:
    """φ'(τ) = (p − Π p)·u at p = a + τu."""
    px, py, pz = ax + t * ux, ay + t * uy, az + t * uz
    qx, qy, qz = project(kind, px, py, pz, hx, hy, hz)
    return (px - qx) * ux + (py - qy) * uy + (pz - qz) * uz


@njit(cache=True)
def _slope_and_rate(kind: int, t: float, ax: float, ay: float, az: float, ux: float, uy: float, uz: float,
                    hx: float, hy: float, hz: float) -> tuple[float, float]:
    """φ'(τ) and φ''(τ) = uᵀ(I − DΠ)u at p = a + τu (DΠ: the projection's Jacobian there)."""
    px, py, pz = ax + t * ux, ay + t * uy, az + t * uz
    qx, qy, qz = project(kind, px, py, pz, hx, hy, hz)
    slope = (px - qx) * ux + (py - qy) * uy + (pz - qz) * uz
    rate = uz * uz if abs(pz) >= hz else 0.0
    if kind == KIND_BOX:
        rate += (ux * ux if abs(px) >= hx else 0.0) + (uy * uy if abs(py) >= hy else 0.0)
        return slope, rate
    rho2 = px * px + py * py
    if rho2 > hx * hx:
        rho = math.sqrt(rho2)
        uxy2 = ux * ux + uy * uy
        ur = (ux * px + uy * py) / rho
        rate += uxy2 - (hx / rho) * (uxy2 - ur * ur)
    return slope, rate


@njit(cache=True)
def newton_param(kind: int, t0: float, ax: float, ay: float, az: float, ux: float, uy: float, uz: float,
                 hx: float, hy: float, hz: float) -> float:
    """:func:`closest_param` by Newton's method from a nearby τ₀ (the drift's neighbouring instants
    start from the pair's own τ: one or two steps); −1 where it does not settle in a few steps."""
    uu = ux * ux + uy * uy + uz * uz
    if uu <= 1e-300:
        return 0.0
    tol = 1e-15 * uu
    t = t0
    for _ in range(8):
        g, dg = _slope_and_rate(kind, t, ax, ay, az, ux, uy, uz, hx, hy, hz)
        if (t <= 0.0 and g >= 0.0) or (t >= 1.0 and g <= 0.0) or abs(g) <= tol:
            return t
        if not dg > 1e-300:
            return -1.0
        step = min(max(t - g / dg, 0.0), 1.0)
        if step == t:
            return t
        t = step
    return -1.0


@njit(cache=True)
def closest_param(kind: int, ax: float, ay: float, az: float, ux: float, uy: float, uz: float, hx: float,
                  hy: float, hz: float) -> float:
    """τ ∈ [0, 1] of the axis point a + τu nearest to the solid (one of them where several are)."""
    uu = ux * ux + uy * uy + uz * uz
    if uu <= 1e-300:
        return 0.0
    fa = _slope(kind, 0.0, ax, ay, az, ux, uy, uz, hx, hy, hz)
    if fa >= 0.0:
        return 0.0
    fb = _slope(kind, 1.0, ax, ay, az, ux, uy, uz, hx, hy, hz)
    if fb <= 0.0:
        return 1.0
    lo, hi = 0.0, 1.0
    tol = 1e-15 * uu
    side = 0
    c = 0.5
    for _ in range(ROOT_STEPS):
        c = (lo * fb - hi * fa) / (fb - fa)
        if not lo < c < hi:
            c = 0.5 * (lo + hi)
        fc = _slope(kind, c, ax, ay, az, ux, uy, uz, hx, hy, hz)
        if abs(fc) <= tol or hi - lo <= 1e-15:
            break
        if fc > 0.0:
            hi, fb = c, fc
            if side == -1:
                fa *= 0.5
            side = -1
        else:
            lo, fa = c, fc
            if side == 1:
                fb *= 0.5
            side = 1
    return c


@njit(cache=True)
def _overlap(kind: int, nx: float, ny: float, nz: float, ax: float, ay: float, az: float, bx: float, by: float,
             bz: float, hx: float, hy: float, hz: float) -> float:
    """F(n) = h(n) − min(n·a, n·b): how far the axis must move along the unit n to leave the solid."""
    return support(kind, nx, ny, nz, hx, hy, hz) - min(nx * ax + ny * ay + nz * az, nx * bx + ny * by + nz * bz)


@njit(cache=True)
def penetration(kind: int, ax: float, ay: float, az: float, bx: float, by: float, bz: float, hx: float,
                hy: float, hz: float) -> tuple[float, float, float, float]:
    """(depth, n) for an axis a–b that meets the solid: the least F(n) over the candidates of the
    module docstring, and its unit direction n (the way out, solid → link), in the solid's frame."""
    best, mx, my, mz = np.inf, 0.0, 0.0, 1.0
    ux, uy, uz = bx - ax, by - ay, bz - az
    ul = math.sqrt(ux * ux + uy * uy + uz * uz)
    first = 0 if kind == KIND_BOX else 2  # a cylinder has one pair of faces, ±z
    for axis in range(first, 3):  # faces: ±e_i
        for sign in (1.0, -1.0):
            nx = sign if axis == 0 else 0.0
            ny = sign if axis == 1 else 0.0
            nz = sign if axis == 2 else 0.0
            f = _overlap(kind, nx, ny, nz, ax, ay, az, bx, by, bz, hx, hy, hz)
            if f < best:
                best, mx, my, mz = f, nx, ny, nz
    if kind != KIND_BOX:  # each end's radial direction
        for e in range(2):
            x, y = (ax, ay) if e == 0 else (bx, by)
            rho = math.sqrt(x * x + y * y)
            if rho > 0.0:
                nx, ny = x / rho, y / rho
                f = _overlap(kind, nx, ny, 0.0, ax, ay, az, bx, by, bz, hx, hy, hz)
                if f < best:
                    best, mx, my, mz = f, nx, ny, 0.0
    if ul <= 1e-300:
        return best, mx, my, mz
    ux, uy, uz = ux / ul, uy / ul, uz / ul
    # the great circle n ⊥ u: u × e_i (a box's outline edges; z × u for a cylinder's straight sides)
    for axis in range(first, 3):
        ex = 1.0 if axis == 0 else 0.0
        ey = 1.0 if axis == 1 else 0.0
        ez = 1.0 if axis == 2 else 0.0
        cx, cy, cz = uy * ez - uz * ey, uz * ex - ux * ez, ux * ey - uy * ex
        cn = math.sqrt(cx * cx + cy * cy + cz * cz)
        if cn <= 1e-12:
            continue
        for sign in (1.0, -1.0):
            nx, ny, nz = sign * cx / cn, sign * cy / cn, sign * cz / cn
            f = _overlap(kind, nx, ny, nz, ax, ay, az, bx, by, bz, hx, hy, hz)
            if f < best:
                best, mx, my, mz = f, nx, ny, nz
    if kind == KIND_BOX:
        return best, mx, my, mz
    # a cylinder's rims: the rest of that circle, n(β) = cos β e + sin β f
    e1 = np.empty(3)
    perpendicular(ux, uy, uz, e1)
    fx, fy, fz = uy * e1[2] - uz * e1[1], uz * e1[0] - ux * e1[2], ux * e1[1] - uy * e1[0]
    step = 2.0 * math.pi / CIRCLE_SAMPLES
    k_best, f_best = 0, np.inf
    for k in range(CIRCLE_SAMPLES):
        cb, sb = math.cos(k * step), math.sin(k * step)
        f = _overlap(kind, cb * e1[0] + sb * fx, cb * e1[1] + sb * fy, cb * e1[2] + sb * fz, ax, ay, az, bx, by, bz,
                     hx, hy, hz)
        if f < f_best:
            k_best, f_best = k, f
    lo, hi = (k_best - 1) * step, (k_best + 1) * step
    g = 0.5 * (math.sqrt(5.0) - 1.0)
    m1, m2 = hi - g * (hi - lo), lo + g * (hi - lo)
    f1 = _overlap(kind, math.cos(m1) * e1[0] + math.sin(m1) * fx, math.cos(m1) * e1[1] + math.sin(m1) * fy,
                  math.cos(m1) * e1[2] + math.sin(m1) * fz, ax, ay, az, bx, by, bz, hx, hy, hz)
    f2 = _overlap(kind, math.cos(m2) * e1[0] + math.sin(m2) * fx, math.cos(m2) * e1[1] + math.sin(m2) * fy,
                  math.cos(m2) * e1[2] + math.sin(m2) * fz, ax, ay, az, bx, by, bz, hx, hy, hz)
    for _ in range(GOLDEN_STEPS):
        if f1 <= f2:
            hi, m2, f2 = m2, m1, f1
            m1 = hi - g * (hi - lo)
            f1 = _overlap(kind, math.cos(m1) * e1[0] + math.sin(m1) * fx, math.cos(m1) * e1[1] + math.sin(m1) * fy,
                          math.cos(m1) * e1[2] + math.sin(m1) * fz, ax, ay, az, bx, by, bz, hx, hy, hz)
        else:
            lo, m1, f1 = m1, m2, f2
            m2 = lo + g * (hi - lo)
            f2 = _overlap(kind, math.cos(m2) * e1[0] + math.sin(m2) * fx, math.cos(m2) * e1[1] + math.sin(m2) * fy,
                          math.cos(m2) * e1[2] + math.sin(m2) * fz, ax, ay, az, bx, by, bz, hx, hy, hz)
    beta = m1 if f1 <= f2 else m2
    nx = math.cos(beta) * e1[0] + math.sin(beta) * fx
    ny = math.cos(beta) * e1[1] + math.sin(beta) * fy
    nz = math.cos(beta) * e1[2] + math.sin(beta) * fz
    f = _overlap(kind, nx, ny, nz, ax, ay, az, bx, by, bz, hx, hy, hz)
    if f < best:
        best, mx, my, mz = f, nx, ny, nz
    return best, mx, my, mz


@njit(cache=True)
def axis_distance(kind: int, ax: float, ay: float, az: float, bx: float, by: float, bz: float, hx: float,
                  hy: float, hz: float, t0: float = -1.0) -> tuple[float, float, float, float, float, float, float, float]:
    """The signed distance [m] of the axis a–b to the solid (negative: the penetration depth), the
    unit normal n (solid → axis), the axis's witness point P, all in the solid's frame, and P's τ.
    Newton's method from ``t0`` ∈ [0, 1] (a nearby τ; by default the axis point nearest the centre),
    the bracketed search where it does not settle."""
    ux, uy, uz = bx - ax, by - ay, bz - az
    if t0 < 0.0:  # start from the axis point nearest the centre
        uu = ux * ux + uy * uy + uz * uz
        t0 = min(max(-(ax * ux + ay * uy + az * uz) / uu, 0.0), 1.0) if uu > 1e-300 else 0.0
    t = newton_param(kind, t0, ax, ay, az, ux, uy, uz, hx, hy, hz)
    if t < 0.0:
        t = closest_param(kind, ax, ay, az, ux, uy, uz, hx, hy, hz)
    px, py, pz = ax + t * ux, ay + t * uy, az + t * uz
    qx, qy, qz = project(kind, px, py, pz, hx, hy, hz)
    wx, wy, wz = px - qx, py - qy, pz - qz
    wn = math.sqrt(wx * wx + wy * wy + wz * wz)
    if wn > MEETS:
        return wn, wx / wn, wy / wn, wz / wn, px, py, pz, t
    depth, nx, ny, nz = penetration(kind, ax, ay, az, bx, by, bz, hx, hy, hz)
    na, nb = nx * ax + ny * ay + nz * az, nx * bx + ny * by + nz * bz
    if abs(na - nb) > 1e-12 * (1.0 + abs(na)):  # the deeper end; on a tie the point inside the solid
        px, py, pz = (ax, ay, az) if na < nb else (bx, by, bz)
        t = 0.0 if na < nb else 1.0
    return -depth, nx, ny, nz, px, py, pz, t


@njit(cache=True)
def _to_local(rot: np.ndarray, c: np.ndarray, p: np.ndarray) -> tuple[float, float, float]:
    """Rᵀ(p − c): a world point in the solid's frame (R's columns are its axes)."""
    x, y, z = p[0] - c[0], p[1] - c[1], p[2] - c[2]
    return (rot[0, 0] * x + rot[1, 0] * y + rot[2, 0] * z, rot[0, 1] * x + rot[1, 1] * y + rot[2, 1] * z,
            rot[0, 2] * x + rot[1, 2] * y + rot[2, 2] * z)


@njit(cache=True)
def solid_pair(kind: int, a: np.ndarray, b: np.ndarray, r_link: float, centre: np.ndarray, rot: np.ndarray,
               half: np.ndarray, normal: np.ndarray, p_link: np.ndarray, p_obs: np.ndarray) -> float:
    """Signed distance [m] between the link capsule (axis a–b, radius r_link; world) and a box
    (half extents ``half``) or cylinder (radius half[0], half length half[2]) centred at ``centre``
    with axes the columns of ``rot``; writes the unit normal (obstacle → link) and the witness points
    on each surface, in the world."""
    ax, ay, az = _to_local(rot, centre, a)
    bx, by, bz = _to_local(rot, centre, b)
    d, nx, ny, nz, px, py, pz, _ = axis_distance(kind, ax, ay, az, bx, by, bz, half[0], half[1], half[2])
    d -= r_link
    for r in range(3):
        normal[r] = rot[r, 0] * nx + rot[r, 1] * ny + rot[r, 2] * nz
        p_link[r] = centre[r] + rot[r, 0] * px + rot[r, 1] * py + rot[r, 2] * pz - r_link * normal[r]
        p_obs[r] = p_link[r] - d * normal[r]
    return d


@njit(cache=True)
def solid_distance(kind: int, a: np.ndarray, b: np.ndarray, r_link: float, centre: np.ndarray, rot: np.ndarray,
                   half: np.ndarray) -> float:
    """:func:`solid_pair`'s signed distance [m] alone."""
    ax, ay, az = _to_local(rot, centre, a)
    bx, by, bz = _to_local(rot, centre, b)
    return axis_distance(kind, ax, ay, az, bx, by, bz, half[0], half[1], half[2])[0] - r_link


@njit(cache=True)
def _local_vec(rot: np.ndarray, p: np.ndarray, q: np.ndarray) -> tuple[float, float, float]:
    """Rᵀ(p − q)."""
    x, y, z = p[0] - q[0], p[1] - q[1], p[2] - q[2]
    return (rot[0, 0] * x + rot[1, 0] * y + rot[2, 0] * z, rot[0, 1] * x + rot[1, 1] * y + rot[2, 1] * z,
            rot[0, 2] * x + rot[1, 2] * y + rot[2, 2] * z)


@njit(cache=True)
def _hess(kind: int, px: float, py: float, pz: float, qx: float, qy: float, qz: float, nx: float, ny: float,
          nz: float, x: tuple[float, float, float], y: tuple[float, float, float], hx: float, hy: float,
          hz: float) -> float:
    """xᵀ(A − n nᵀ)y with A = I − DΠ(P): ρ times the Hessian of the distance to the solid at P
    (Π(P) = Q; DΠ is diagonal for a box, a radial scale in x–y for a cylinder)."""
    ax_ = 0.0 if abs(px) < hx else 1.0
    ay_ = 0.0 if abs(py) < hy else 1.0
    az_ = 0.0 if abs(pz) < hz else 1.0
    if kind == KIND_BOX:
        axy = ax_ * x[0] * y[0] + ay_ * x[1] * y[1]
    else:
        rho2 = px * px + py * py
        if rho2 > hx * hx:  # DΠ_xy = (R/ρ)(I − r rᵀ)
            rho = math.sqrt(rho2)
            rx, ry = px / rho, py / rho
            xr, yr = x[0] * rx + x[1] * ry, y[0] * rx + y[1] * ry
            axy = x[0] * y[0] + x[1] * y[1] - (hx / rho) * (x[0] * y[0] + x[1] * y[1] - xr * yr)
        else:
            axy = 0.0
    nxv = nx * x[0] + ny * x[1] + nz * x[2]
    nyv = nx * y[0] + ny * y[1] + nz * y[2]
    return axy + az_ * x[2] * y[2] - nxv * nyv


@njit(cache=True)
def _end_motion(bv: np.ndarray, off: np.ndarray, K: np.ndarray, p: np.ndarray, vc: np.ndarray, ac: np.ndarray,
                rot: np.ndarray) -> tuple[float, float, float, float, float, float]:
    """The body point p's velocity v + ω × p and q̈ = 0 acceleration off + K p, less the solid's
    (vc, ac), in the solid's frame."""
    vx = bv[0] + bv[4] * p[2] - bv[5] * p[1] - vc[0]
    vy = bv[1] + bv[5] * p[0] - bv[3] * p[2] - vc[1]
    vz = bv[2] + bv[3] * p[1] - bv[4] * p[0] - vc[2]
    gx = off[0] + K[0, 0] * p[0] + K[0, 1] * p[1] + K[0, 2] * p[2] - ac[0]
    gy = off[1] + K[1, 0] * p[0] + K[1, 1] * p[1] + K[1, 2] * p[2] - ac[1]
    gz = off[2] + K[2, 0] * p[0] + K[2, 1] * p[1] + K[2, 2] * p[2] - ac[2]
    return (rot[0, 0] * vx + rot[1, 0] * vy + rot[2, 0] * vz, rot[0, 1] * vx + rot[1, 1] * vy + rot[2, 1] * vz,
            rot[0, 2] * vx + rot[1, 2] * vy + rot[2, 2] * vz, rot[0, 0] * gx + rot[1, 0] * gy + rot[2, 0] * gz,
            rot[0, 1] * gx + rot[1, 1] * gy + rot[2, 1] * gz, rot[0, 2] * gx + rot[1, 2] * gy + rot[2, 2] * gz)


@njit(cache=True)
def solid_drift(kind: int, a: np.ndarray, b: np.ndarray, bv: np.ndarray, off: np.ndarray, K: np.ndarray,
                centre: np.ndarray, vc: np.ndarray, ac: np.ndarray, rot: np.ndarray, half: np.ndarray,
                t0: float) -> float:
    """ḧ [m/s²] at q̈ = 0 of the distance between the link axis a–b and the solid: the link body moves
    with the world spatial velocity ``bv`` (v at the origin, ω) and the q̈ = 0 acceleration field
    a(p) = off + K p; the solid translates (centre velocity vc, acceleration ac).

    In the solid's frame, x(τ) = a + τu, f(τ, t) = D(x) (D: the distance to the solid, ∇D = n,
    ρ∇²D = A − nnᵀ with A = I − DΠ) and h = min_τ f: ḧ = f_tt − f_τt²/f_ττ with
    f_tt = ẋᵀ∇²Dẋ + nᵀ(ä + τü), f_τt = uᵀ∇²Dẋ + nᵀu̇, f_ττ = uᵀ∇²Du (ẋ = ȧ + τu̇; the last term
    only where τ is interior). Where that has no meaning (penetrating; an interior τ with f_ττ ≈ 0:
    the axis parallel to a face) the second difference :func:`solid_drift_difference`. ``t0``: the
    closest axis point's τ now."""
    hx, hy, hz = half[0], half[1], half[2]
    ax, ay, az = _local_vec(rot, a, centre)
    bx, by, bz = _local_vec(rot, b, centre)
    d, nx, ny, nz, px, py, pz, t = axis_distance(kind, ax, ay, az, bx, by, bz, hx, hy, hz,
                                                 min(max(t0, 0.0), 1.0))
    if d <= MEETS:
        return solid_drift_difference(kind, a, b, bv, off, K, centre, vc, ac, rot, half, t)
    qx, qy, qz = project(kind, px, py, pz, hx, hy, hz)
    da0, da1, da2, dda0, dda1, dda2 = _end_motion(bv, off, K, a, vc, ac, rot)
    db0, db1, db2, ddb0, ddb1, ddb2 = _end_motion(bv, off, K, b, vc, ac, rot)
    u = (bx - ax, by - ay, bz - az)
    ud = (db0 - da0, db1 - da1, db2 - da2)
    xd = (da0 + t * ud[0], da1 + t * ud[1], da2 + t * ud[2])
    f_tt = _hess(kind, px, py, pz, qx, qy, qz, nx, ny, nz, xd, xd, hx, hy, hz) / d + (
        nx * (dda0 + t * (ddb0 - dda0)) + ny * (dda1 + t * (ddb1 - dda1)) + nz * (dda2 + t * (ddb2 - dda2)))
    if not 1e-9 < t < 1.0 - 1e-9:
        return f_tt
    uu = u[0] * u[0] + u[1] * u[1] + u[2] * u[2]
    f_ss = _hess(kind, px, py, pz, qx, qy, qz, nx, ny, nz, u, u, hx, hy, hz) / d
    if not f_ss > 1e-9 * uu / d:
        return solid_drift_difference(kind, a, b, bv, off, K, centre, vc, ac, rot, half, t)
    f_st = _hess(kind, px, py, pz, qx, qy, qz, nx, ny, nz, u, xd, hx, hy, hz) / d + (
        nx * ud[0] + ny * ud[1] + nz * ud[2])
    return f_tt - f_st * f_st / f_ss


@njit(cache=True)
def solid_drift_difference(kind: int, a: np.ndarray, b: np.ndarray, bv: np.ndarray, off: np.ndarray,
                           K: np.ndarray, centre: np.ndarray, vc: np.ndarray, ac: np.ndarray, rot: np.ndarray,
                           half: np.ndarray, t0: float) -> float:
    """:func:`solid_drift` as the second central difference (step DRIFT_STEP) of the distance along
    the ends' motion p + s ṗ + ½s² p̈ and the centre's c + s v + ½s² a (module docstring)."""
    h = DRIFT_STEP
    t0 = min(max(t0, 0.0), 1.0)
    ax, ay, az = _local_vec(rot, a, centre)
    bx, by, bz = _local_vec(rot, b, centre)
    da0, da1, da2, dda0, dda1, dda2 = _end_motion(bv, off, K, a, vc, ac, rot)
    db0, db1, db2, ddb0, ddb1, ddb2 = _end_motion(bv, off, K, b, vc, ac, rot)
    acc = 0.0
    for s, w in ((0.0, -2.0), (-h, 1.0), (h, 1.0)):
        s2 = 0.5 * s * s
        acc += w * axis_distance(kind, ax + s * da0 + s2 * dda0, ay + s * da1 + s2 * dda1, az + s * da2 + s2 * dda2,
                                 bx + s * db0 + s2 * ddb0, by + s * db1 + s2 * ddb1, bz + s * db2 + s2 * ddb2,
                                 half[0], half[1], half[2], t0)[0]
    return acc / (h * h)
