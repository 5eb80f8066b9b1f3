"""Stage 3 of the tick, the link–obstacle pairs: every pair within the cutoff with its distance,
normal, witness points, witness-point Jacobian and drift, and the barrier's drift ḧ(q̈ = 0).

:func:`find_pairs` lists the pairs link-major (through the broad-phase grid when there is one),
distances in closed form for spheres and capsules (:mod:`qpctl.kernels.geometry`) and for boxes and
cylinders (:mod:`qpctl.kernels.solids`); pairs with any other shape (python-fcl's: meshes, shapes a
user registers) are marked PAIR_FCL for Python to query. :func:`finish_pairs` then compacts the
list and adds the Jacobians, drifts and the exact barrier drift (:func:`barrier_drift`); pairs
without a closed-form drift (python-fcl's shapes; capsules with meeting or parallel axes) are
counted for Python's look-ahead difference (:meth:`qpctl.tick.Workspace._look_ahead`).

References (``tests/test_kernels.py``): python-fcl on every (link, obstacle) pair, a brute-force
segment distance, Pinocchio's point Jacobians; the drift against finite differences.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from qpctl.kernels.codes import (
    CNT_FCL,
    CNT_LOOKAHEAD,
    CNT_PAIRS,
    FP_CLEARANCE,
    FP_CUTOFF,
    FP_GRID_H,
    IP_BDRIFT,
    KIND_BOX,
    KIND_CYLINDER,
    KIND_FCL,
    KIND_SPHERE,
    PAIR_FAR,
    PAIR_FCL,
    PAIR_OK,
)
from qpctl.kernels.geometry import contact_frame, segment_params, sphere_bound
from qpctl.kernels.rigid import point_jacobian
from qpctl.kernels.solids import solid_drift, solid_pair


@njit(cache=True)
def _candidates(ws, i: int, out: np.ndarray) -> int:  # type: ignore[no-untyped-def]
    """The obstacles that may lie within the cutoff of capsule i, ascending: all of them, or with the
    grid, the static obstacles in the cells the inflated capsule's box touches plus every moving one."""
    O = ws.ob_kind.shape[0]
    dims = ws.grid_dims
    if dims[0] == 0:
        for j in range(O):
            out[j] = j
        return O
    a, b = ws.segments[i, 0], ws.segments[i, 1]
    reach = ws.cap_radius[i] + ws.fpar[FP_CUTOFF]
    h = ws.fpar[FP_GRID_H]
    lo = np.empty(3, np.int64)
    hi = np.empty(3, np.int64)
    for r in range(3):
        low = (min(a[r], b[r]) - reach - ws.grid_lo[r]) / h
        high = (max(a[r], b[r]) + reach - ws.grid_lo[r]) / h
        lo[r] = max(math.floor(low), 0)
        hi[r] = min(math.floor(high), dims[r] - 1)
    count = 0
    stamp = i + 1  # this link's mark (find_pairs clears the marks each tick)
    for cx in range(lo[0], hi[0] + 1):
        for cy in range(lo[1], hi[1] + 1):
            for cz in range(lo[2], hi[2] + 1):
                cell = (cx * dims[1] + cy) * dims[2] + cz
                for e in range(ws.grid_start[cell], ws.grid_start[cell + 1]):
                    j = ws.grid_items[e]
                    if ws.stamp[j] != stamp:
                        ws.stamp[j] = stamp
                        out[count] = j
                        count += 1
    for r in range(ws.moving.shape[0]):
        j = ws.moving[r]
        if ws.stamp[j] != stamp:
            ws.stamp[j] = stamp
            out[count] = j
            count += 1
    # ascending, as without the grid (insertion sort: a handful of candidates)
    for u in range(1, count):
        val = out[u]
        w = u - 1
        while w >= 0 and out[w] > val:
            out[w + 1] = out[w]
            w -= 1
        out[w + 1] = val
    return count


@njit(cache=True)
def find_pairs(ws) -> int:  # type: ignore[no-untyped-def]
    """Every link–obstacle pair within the cutoff, link-major and by obstacle index: distances,
    normals and witness points in closed form for spheres and capsules (:mod:`qpctl.kernels.geometry`),
    boxes and cylinders (:mod:`qpctl.kernels.solids`); pairs with python-fcl's shapes whose bounding
    sphere is within the cutoff are listed as PAIR_FCL for Python to query. Returns the number of PAIR_FCL pairs."""
    cutoff = ws.fpar[FP_CUTOFF]
    segments, cap_radius = ws.segments, ws.cap_radius
    ob_kind, ob_c, ob_axis, ob_radius, ob_bound = ws.ob_kind, ws.ob_c, ws.ob_axis, ws.ob_radius, ws.ob_bound
    pr_link, pr_obs, pr_state, pr_d = ws.pr_link, ws.pr_obs, ws.pr_state, ws.pr_d
    pr_n, pr_pl, pr_po = ws.pr_n, ws.pr_pl, ws.pr_po
    L = segments.shape[0]
    O = ob_kind.shape[0]
    grid = ws.grid_dims[0] != 0
    cand = np.empty(O if grid else 0, np.int64)
    if grid:
        ws.stamp[:] = 0
    k = 0
    nfcl = 0
    for i in range(L):
        ax, ay, az = segments[i, 0, 0], segments[i, 0, 1], segments[i, 0, 2]
        ux, uy, uz = segments[i, 1, 0] - ax, segments[i, 1, 1] - ay, segments[i, 1, 2] - az
        uu = ux * ux + uy * uy + uz * uz
        rl = cap_radius[i]
        # the cheap rejection: the capsule lies in the ball about its mid-point of radius |u|/2 + r,
        # the obstacle in its bounding ball, so a centre farther than both radii + the cutoff (+ 1e-9
        # for rounding) is a pair beyond the cutoff, without its closest points
        mx, my, mz = ax + 0.5 * ux, ay + 0.5 * uy, az + 0.5 * uz
        reach = 0.5 * math.sqrt(uu) + rl + cutoff + 1e-9
        nc = _candidates(ws, i, cand) if grid else O
        for e in range(nc):
            j = cand[e] if grid else e
            cx, cy, cz = ob_c[j, 0], ob_c[j, 1], ob_c[j, 2]
            far = reach + ob_bound[j]
            if (cx - mx) ** 2 + (cy - my) ** 2 + (cz - mz) ** 2 >= far * far:
                continue
            kind = ob_kind[j]
            if kind == KIND_SPHERE:
                sx = sy = sz = 0.0
            else:
                if sphere_bound(segments, i, rl, cx, cy, cz, ob_bound[j]) >= cutoff:
                    continue
                if kind == KIND_FCL:
                    pr_link[k], pr_obs[k], pr_state[k], pr_d[k] = i, j, PAIR_FCL, np.inf
                    k += 1
                    nfcl += 1
                    continue
                sx, sy, sz = ob_axis[j, 0], ob_axis[j, 1], ob_axis[j, 2]
            # obstacle axis c0 + t·s, c0 = centre − s/2 (a point for a sphere)
            c0x, c0y, c0z = cx - 0.5 * sx, cy - 0.5 * sy, cz - 0.5 * sz
            tl, to = segment_params(ax, ay, az, ux, uy, uz, uu, c0x, c0y, c0z, sx, sy, sz)
            px, py, pz = ax + tl * ux, ay + tl * uy, az + tl * uz
            qx, qy, qz = c0x + to * sx, c0y + to * sy, c0z + to * sz
            wx, wy, wz = px - qx, py - qy, pz - qz
            wn = math.sqrt(wx * wx + wy * wy + wz * wz)
            ro = ob_radius[j]
            d = wn - rl - ro
            if not d < cutoff:
                continue
            if kind == KIND_BOX or kind == KIND_CYLINDER:  # d was its bounding capsule's: a lower bound
                d = solid_pair(kind, segments[i, 0], segments[i, 1], rl, ob_c[j], ws.ob_rot[j], ws.ob_half[j],
                               pr_n[k], pr_pl[k], pr_po[k])
                if d < cutoff:
                    pr_link[k], pr_obs[k], pr_state[k], pr_d[k] = i, j, PAIR_OK, d
                    k += 1
                continue
            contact_frame(px, py, pz, qx, qy, qz, wx, wy, wz, wn, ux, uy, uz, sx, sy, sz, rl, ro, pr_n, pr_pl, pr_po, k)
            pr_link[k], pr_obs[k], pr_state[k], pr_d[k] = i, j, PAIR_OK, d
            k += 1
    ws.cnt[CNT_PAIRS] = k
    ws.cnt[CNT_FCL] = nfcl
    return nfcl


@njit(cache=True)
def _solid_drift(ws, r: int) -> float:  # type: ignore[no-untyped-def]
    """ḧ at q̈ = 0 [m/s²] of pair r, a link and a box or cylinder (:func:`~qpctl.kernels.solids.solid_drift`),
    from the link's axis ends' velocities v + ω × p and accelerations offset + K p."""
    i, j = ws.pr_link[r], ws.pr_obs[r]
    a, b = ws.segments[i, 0], ws.segments[i, 1]
    uu = tau = 0.0
    for c in range(3):  # the closest axis point's τ: p_link + r n = a + τu
        u = b[c] - a[c]
        uu += u * u
        tau += (ws.pr_pl[r, c] + ws.cap_radius[i] * ws.pr_n[r, c] - a[c]) * u
    tau = tau / uu if uu > 1e-300 else 0.0
    return solid_drift(ws.ob_kind[j], a, b, ws.body_vel[i], ws.acc_off[i], ws.acc_K[i], ws.ob_c[j], ws.ob_v[j],
                       ws.ob_a[j], ws.ob_rot[j], ws.ob_half[j], tau)


@njit(cache=True)
def barrier_drift(ws, r: int) -> bool:  # type: ignore[no-untyped-def]
    """ḧ at q̈ = 0 of pair r (∂ḣ/∂q q̇ + ∂ḣ/∂t) into pr_bdrift[r], in closed form for a sphere or
    capsule obstacle, a central difference of the closed-form distance for a box or cylinder; False
    where it has none (python-fcl's shapes, meeting or parallel axes).

    The axis points p = a + τu (link) and q = c₀ + σs (obstacle) are closest, so with w = p − q,
    ρ = |w|, n = w/ρ and h = ρ − radii − d_s: ḣ = nᵀẇ and ḧ = nᵀẅ + (|ẇ|² − (nᵀẇ)²)/ρ, where
    ẇ = v_p − v_q + τ̇u − σ̇s and nᵀẅ = nᵀ(a_p − a_q) + 2τ̇ nᵀu̇ (v_p, a_p: the body point's velocity
    and q̈ = 0 acceleration; u̇ = ω × u; obstacles translate, ṡ = 0; τ̈ drops out where τ is interior
    since n ⊥ u, and τ̇ = τ̈ = 0 where it is clamped; likewise σ). τ̇, σ̇ keep the closest-point
    conditions wᵀu = 0, wᵀs = 0 for the free parameters.
    """
    i, j = ws.pr_link[r], ws.pr_obs[r]
    kind = ws.ob_kind[j]
    if kind == KIND_FCL:
        return False
    if kind == KIND_BOX or kind == KIND_CYLINDER:
        ws.pr_bdrift[r] = _solid_drift(ws, r)
        return True
    pr_n, pr_pl, pr_po = ws.pr_n, ws.pr_pl, ws.pr_po
    nx, ny, nz = pr_n[r, 0], pr_n[r, 1], pr_n[r, 2]
    rl, ro = ws.cap_radius[i], ws.ob_radius[j]
    px, py, pz = pr_pl[r, 0] + rl * nx, pr_pl[r, 1] + rl * ny, pr_pl[r, 2] + rl * nz  # link axis
    qx, qy, qz = pr_po[r, 0] - ro * nx, pr_po[r, 1] - ro * ny, pr_po[r, 2] - ro * nz  # obstacle's
    wx, wy, wz = px - qx, py - qy, pz - qz
    seg = ws.segments  # (rows by index throughout: no views, see finish_pairs)
    a0, a1, a2 = seg[i, 0, 0], seg[i, 0, 1], seg[i, 0, 2]
    ux, uy, uz = seg[i, 1, 0] - a0, seg[i, 1, 1] - a1, seg[i, 1, 2] - a2
    ob_axis, ob_c = ws.ob_axis, ws.ob_c
    sx, sy, sz = ob_axis[j, 0], ob_axis[j, 1], ob_axis[j, 2]
    cx, cy, cz = ob_c[j, 0], ob_c[j, 1], ob_c[j, 2]
    bv = ws.body_vel
    vx, vy, vz, ox, oy, oz = bv[i, 0], bv[i, 1], bv[i, 2], bv[i, 3], bv[i, 4], bv[i, 5]
    vpx, vpy, vpz = vx + oy * pz - oz * py, vy + oz * px - ox * pz, vz + ox * py - oy * px  # v + ω × p
    udx, udy, udz = oy * uz - oz * uy, oz * ux - ox * uz, ox * uy - oy * ux  # u̇ = ω × u
    K, o = ws.acc_K, ws.acc_off
    apx = o[i, 0] + K[i, 0, 0] * px + K[i, 0, 1] * py + K[i, 0, 2] * pz  # a_p = offset + K p
    apy = o[i, 1] + K[i, 1, 0] * px + K[i, 1, 1] * py + K[i, 1, 2] * pz
    apz = o[i, 2] + K[i, 2, 0] * px + K[i, 2, 1] * py + K[i, 2, 2] * pz
    ob_v, ob_a = ws.ob_v, ws.ob_a
    dvx, dvy, dvz = vpx - ob_v[j, 0], vpy - ob_v[j, 1], vpz - ob_v[j, 2]
    L2 = ux * ux + uy * uy + uz * uz
    tau_l2 = (px - a0) * ux + (py - a1) * uy + (pz - a2) * uz  # τ L²
    S2 = sx * sx + sy * sy + sz * sz
    sigma_s2 = (qx - cx + 0.5 * sx) * sx + (qy - cy + 0.5 * sy) * sy + (qz - cz + 0.5 * sz) * sz  # σ |s|²
    t_free = L2 > 1e-18 and 1e-9 * L2 < tau_l2 < (1.0 - 1e-9) * L2
    s_free = S2 > 1e-18 and 1e-9 * S2 < sigma_s2 < (1.0 - 1e-9) * S2
    e1 = -(dvx * ux + dvy * uy + dvz * uz + wx * udx + wy * udy + wz * udz)  # L²τ̇ − (u·s)σ̇ = e1
    e2 = -(dvx * sx + dvy * sy + dvz * sz)  # (u·s)τ̇ − |s|²σ̇ = e2
    us = ux * sx + uy * sy + uz * sz
    tau_dot = sigma_dot = 0.0
    if t_free and s_free:
        det = us * us - L2 * S2
        if abs(det) <= 1e-9 * L2 * S2:  # parallel axes: the closest points are not unique
            return False
        tau_dot, sigma_dot = (us * e2 - S2 * e1) / det, (L2 * e2 - us * e1) / det
    elif t_free:
        tau_dot = e1 / L2
    elif s_free:
        sigma_dot = -e2 / S2
    rho2 = wx * wx + wy * wy + wz * wz
    if not rho2 > 1e-18:  # the axes meet: the normal is not differentiable
        return False
    wdx = dvx + tau_dot * ux - sigma_dot * sx
    wdy = dvy + tau_dot * uy - sigma_dot * sy
    wdz = dvz + tau_dot * uz - sigma_dot * sz
    nw = nx * wdx + ny * wdy + nz * wdz
    ws.pr_bdrift[r] = (nx * (apx - ob_a[j, 0]) + ny * (apy - ob_a[j, 1]) + nz * (apz - ob_a[j, 2])
                       + 2.0 * tau_dot * (nx * udx + ny * udy + nz * udz)
                       + (wdx * wdx + wdy * wdy + wdz * wdz - nw * nw) / math.sqrt(max(rho2, 1e-24)))
    return True


@njit(cache=True)
def finish_pairs(ws) -> int:  # type: ignore[no-untyped-def]
    """After python-fcl: drop the pairs it found beyond the cutoff (order kept), then each pair's
    witness-point Jacobian and drift, the barrier drift (closed form where it exists, when the QP
    needs it) and the clearance. Returns the number of pairs left for the look-ahead drift."""
    pr_link, pr_obs, pr_d, pr_state = ws.pr_link, ws.pr_obs, ws.pr_d, ws.pr_state
    pr_n, pr_pl, pr_po = ws.pr_n, ws.pr_pl, ws.pr_po
    k = 0
    for r in range(ws.cnt[CNT_PAIRS]):
        if pr_state[r] == PAIR_FAR:
            continue
        if k != r:
            pr_link[k], pr_obs[k], pr_d[k], pr_state[k] = pr_link[r], pr_obs[r], pr_d[r], pr_state[r]
            for c in range(3):
                pr_n[k, c], pr_pl[k, c], pr_po[k, c] = pr_n[r, c], pr_pl[r, c], pr_po[r, c]
        k += 1
    ws.cnt[CNT_PAIRS] = k
    ws.cnt[CNT_FCL] = 0
    clearance = np.inf
    look = 0
    need = ws.ipar[IP_BDRIFT] != 0
    # the arrays the loop reads, held once (rows by index: a view per pair costs atomic reference counts)
    cap_support, pr_jac, pr_drift, acc_off, acc_K = ws.cap_support, ws.pr_jac, ws.pr_drift, ws.acc_off, ws.acc_K
    pr_bok, pr_bdrift = ws.pr_bok, ws.pr_bdrift
    for r in range(k):
        i = pr_link[r]
        clearance = min(clearance, pr_d[r])
        point_jacobian(ws, cap_support, i, pr_pl, r, pr_jac, r)
        p0, p1, p2 = pr_pl[r, 0], pr_pl[r, 1], pr_pl[r, 2]
        for c in range(3):
            pr_drift[r, c] = acc_off[i, c] + acc_K[i, c, 0] * p0 + acc_K[i, c, 1] * p1 + acc_K[i, c, 2] * p2
        pr_bok[r] = 1
        if need and not barrier_drift(ws, r):
            pr_bok[r] = 0
            pr_bdrift[r] = 0.0
            look += 1
    ws.fpar[FP_CLEARANCE] = clearance
    ws.cnt[CNT_LOOKAHEAD] = look
    return look
