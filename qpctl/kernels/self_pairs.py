"""Stage 3b of the tick, the arm's own pairs: each self-collision pair's distance and normal and,
within its cutoff, ḣ's row and ḧ at q̈ = 0 (both capsules moving).

References (``tests/test_self_collision.py``): python-fcl's capsule–capsule distance and finite
differences of the distance along the motion.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from qpctl.kernels.codes import FP_SCUT, FP_SELF_CLEARANCE
from qpctl.kernels.geometry import segment_params
from qpctl.kernels.rigid import body_point, point_jacobian
from qpctl.kernels.work import SJ_SP, SJ_SQ, SV_SP, SV_SQ


@njit(cache=True)
def self_pairs(ws) -> None:  # type: ignore[no-untyped-def]
    """Every self-collision pair's distance and normal, and, for those within the cutoff, ḣ's row and ḧ
    at q̈ = 0 (the least distance into fpar[FP_SELF_CLEARANCE]). A pair whose bounding spheres are
    already beyond the cutoff gets their gap, a lower bound ≥ the cutoff, as its distance.

    As in :func:`barrier_drift`, with both capsules moving: p = a + τu on capsule i's axis, q = c + σs
    on capsule j's, w = p − q, ρ = |w|, n = w/ρ, h = ρ − r_i − r_j; ḣ = nᵀ(v_p − v_q) (the body points'
    velocities: n ⊥ u, s where τ, σ are free), ḧ = nᵀẅ + (|ẇ|² − (nᵀẇ)²)/ρ with ẇ = v_p − v_q + τ̇u − σ̇s
    and nᵀẅ = nᵀ(a_p − a_q) + 2τ̇ nᵀu̇ − 2σ̇ nᵀṡ, u̇ = ω_i × u, ṡ = ω_j × s; τ̇, σ̇ from the closest-point
    conditions wᵀu = wᵀs = 0. Where the axes are parallel or meet, the rigid part nᵀ(a_p − a_q) alone.
    """
    P = ws.sc_pairs.shape[0]
    n = ws.v.shape[0]
    cut = ws.fpar[FP_SCUT]
    # every array read in the loop, held once (a field or a row view taken inside the loop costs an
    # atomic reference count increment and decrement each time: see qpctl.kernels.rigid.world_point)
    seg, cap_support, cap_radius, body_vel = ws.segments, ws.cap_support, ws.cap_radius, ws.body_vel
    sc_pairs, sc_d, sc_n, sc_row, sc_hdot, sc_drift, qd = ws.sc_pairs, ws.sc_d, ws.sc_n, ws.sc_row, ws.sc_hdot, \
        ws.sc_drift, ws.v
    sj, sv = ws.sj, ws.sv
    best = np.inf
    for r in range(P):
        i, j = sc_pairs[r, 0], sc_pairs[r, 1]
        a0, a1, a2, c0, c1, c2 = seg[i, 0, 0], seg[i, 0, 1], seg[i, 0, 2], seg[j, 0, 0], seg[j, 0, 1], seg[j, 0, 2]
        ux, uy, uz = seg[i, 1, 0] - a0, seg[i, 1, 1] - a1, seg[i, 1, 2] - a2
        sx, sy, sz = seg[j, 1, 0] - c0, seg[j, 1, 1] - c1, seg[j, 1, 2] - c2
        uu = ux * ux + uy * uy + uz * uz
        # bounding spheres first: a pair surely beyond the cutoff keeps that lower bound as its distance
        mx, my, mz = a0 + 0.5 * ux - c0 - 0.5 * sx, a1 + 0.5 * uy - c1 - 0.5 * sy, a2 + 0.5 * uz - c2 - 0.5 * sz
        bound = (math.sqrt(mx * mx + my * my + mz * mz) - 0.5 * math.sqrt(uu) - 0.5 * math.sqrt(sx * sx + sy * sy + sz * sz)
                 - cap_radius[i] - cap_radius[j])
        if bound >= cut:
            sc_d[r] = bound
            best = min(best, bound)
            continue
        tau, sigma = segment_params(a0, a1, a2, ux, uy, uz, uu, c0, c1, c2, sx, sy, sz)
        p0, p1, p2 = a0 + tau * ux, a1 + tau * uy, a2 + tau * uz
        q0, q1, q2 = c0 + sigma * sx, c1 + sigma * sy, c2 + sigma * sz
        sv[SV_SP, 0], sv[SV_SP, 1], sv[SV_SP, 2] = p0, p1, p2
        sv[SV_SQ, 0], sv[SV_SQ, 1], sv[SV_SQ, 2] = q0, q1, q2
        wx, wy, wz = p0 - q0, p1 - q1, p2 - q2
        rho = math.sqrt(wx * wx + wy * wy + wz * wz)
        d = rho - cap_radius[i] - cap_radius[j]
        sc_d[r] = d
        best = min(best, d)
        if rho > 1e-12:
            nx, ny, nz = wx / rho, wy / rho, wz / rho
        else:  # the axes meet: any direction normal to both (the distance is not differentiable here)
            nx, ny, nz = uy * sz - uz * sy, uz * sx - ux * sz, ux * sy - uy * sx
            nn = math.sqrt(nx * nx + ny * ny + nz * nz)
            nx, ny, nz = (nx / nn, ny / nn, nz / nn) if nn > 1e-12 else (0.0, 0.0, 1.0)
        sc_n[r, 0], sc_n[r, 1], sc_n[r, 2] = nx, ny, nz
        if not d < cut:  # beyond the influence distance: no row this tick (self_rows), nothing more
            continue
        point_jacobian(ws, cap_support, i, sv, SV_SP, sj, SJ_SP)
        point_jacobian(ws, cap_support, j, sv, SV_SQ, sj, SJ_SQ)
        hdot = 0.0
        for k in range(n):
            val = (nx * (sj[SJ_SP, 0, k] - sj[SJ_SQ, 0, k]) + ny * (sj[SJ_SP, 1, k] - sj[SJ_SQ, 1, k])
                   + nz * (sj[SJ_SP, 2, k] - sj[SJ_SQ, 2, k]))
            sc_row[r, k] = val
            hdot += val * qd[k]
        sc_hdot[r] = hdot
        vp0, vp1, vp2, ap0, ap1, ap2 = body_point(ws, i, p0, p1, p2)
        vq0, vq1, vq2, aq0, aq1, aq2 = body_point(ws, j, q0, q1, q2)
        rigid = nx * (ap0 - aq0) + ny * (ap1 - aq1) + nz * (ap2 - aq2)
        wi3, wi4, wi5 = body_vel[i, 3], body_vel[i, 4], body_vel[i, 5]
        wj3, wj4, wj5 = body_vel[j, 3], body_vel[j, 4], body_vel[j, 5]
        udx, udy, udz = wi4 * uz - wi5 * uy, wi5 * ux - wi3 * uz, wi3 * uy - wi4 * ux  # ω_i × u
        sdx, sdy, sdz = wj4 * sz - wj5 * sy, wj5 * sx - wj3 * sz, wj3 * sy - wj4 * sx  # ω_j × s
        dvx, dvy, dvz = vp0 - vq0, vp1 - vq1, vp2 - vq2
        L2, S2 = uu, sx * sx + sy * sy + sz * sz
        t_free = L2 > 1e-18 and 1e-9 < tau < 1.0 - 1e-9
        s_free = S2 > 1e-18 and 1e-9 < sigma < 1.0 - 1e-9
        e1 = -(dvx * ux + dvy * uy + dvz * uz + wx * udx + wy * udy + wz * udz)
        e2 = -(dvx * sx + dvy * sy + dvz * sz + wx * sdx + wy * sdy + wz * sdz)
        us = ux * sx + uy * sy + uz * sz
        tau_dot = sigma_dot = 0.0
        ok = rho > 1e-9
        if t_free and s_free:
            det = us * us - L2 * S2
            if abs(det) <= 1e-9 * L2 * S2:
                ok = False
            else:
                tau_dot, sigma_dot = (us * e2 - S2 * e1) / det, (L2 * e2 - us * e1) / det
        elif t_free:
            tau_dot = e1 / L2
        elif s_free:
            sigma_dot = -e2 / S2
        if not ok:
            sc_drift[r] = rigid
            continue
        wdx = dvx + tau_dot * ux - sigma_dot * sx
        wdy = dvy + tau_dot * uy - sigma_dot * sy
        wdz = dvz + tau_dot * uz - sigma_dot * sz
        nw = nx * wdx + ny * wdy + nz * wdz
        sc_drift[r] = (rigid + 2.0 * tau_dot * (nx * udx + ny * udy + nz * udz)
                       - 2.0 * sigma_dot * (nx * sdx + ny * sdy + nz * sdz)
                       + (wdx * wdx + wdy * wdy + wdz * wdz - nw * nw) / rho)
    ws.fpar[FP_SELF_CLEARANCE] = best
