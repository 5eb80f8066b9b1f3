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
from qpctl.kernels.work import SJ_SP, SJ_SQ, SV_SAP, SV_SAQ, SV_SP, SV_SQ, SV_SVP, SV_SVQ


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
    seg, cap_support = ws.segments, ws.cap_support
    Jp, Jq = ws.sj[SJ_SP], ws.sj[SJ_SQ]
    sv = ws.sv
    p, q, vp, vq, ap, aq = sv[SV_SP], sv[SV_SQ], sv[SV_SVP], sv[SV_SVQ], sv[SV_SAP], sv[SV_SAQ]
    best = np.inf
    for r in range(P):
        i, j = ws.sc_pairs[r, 0], ws.sc_pairs[r, 1]
        a, c = seg[i, 0], seg[j, 0]
        ux, uy, uz = seg[i, 1, 0] - a[0], seg[i, 1, 1] - a[1], seg[i, 1, 2] - a[2]
        sx, sy, sz = seg[j, 1, 0] - c[0], seg[j, 1, 1] - c[1], seg[j, 1, 2] - c[2]
        uu = ux * ux + uy * uy + uz * uz
        # bounding spheres first: a pair surely beyond the cutoff keeps that lower bound as its distance
        mx, my, mz = a[0] + 0.5 * ux - c[0] - 0.5 * sx, a[1] + 0.5 * uy - c[1] - 0.5 * sy, a[2] + 0.5 * uz - c[2] - 0.5 * sz
        bound = (math.sqrt(mx * mx + my * my + mz * mz) - 0.5 * math.sqrt(uu) - 0.5 * math.sqrt(sx * sx + sy * sy + sz * sz)
                 - ws.cap_radius[i] - ws.cap_radius[j])
        if bound >= cut:
            ws.sc_d[r] = bound
            best = min(best, bound)
            continue
        tau, sigma = segment_params(a[0], a[1], a[2], ux, uy, uz, uu, c[0], c[1], c[2], sx, sy, sz)
        p[0], p[1], p[2] = a[0] + tau * ux, a[1] + tau * uy, a[2] + tau * uz
        q[0], q[1], q[2] = c[0] + sigma * sx, c[1] + sigma * sy, c[2] + sigma * sz
        wx, wy, wz = p[0] - q[0], p[1] - q[1], p[2] - q[2]
        rho = math.sqrt(wx * wx + wy * wy + wz * wz)
        d = rho - ws.cap_radius[i] - ws.cap_radius[j]
        ws.sc_d[r] = d
        best = min(best, d)
        if rho > 1e-12:
            nx, ny, nz = wx / rho, wy / rho, wz / rho
        else:  # the axes meet: any direction normal to both (the distance is not differentiable here)
            nx, ny, nz = uy * sz - uz * sy, uz * sx - ux * sz, ux * sy - uy * sx
            nn = math.sqrt(nx * nx + ny * ny + nz * nz)
            nx, ny, nz = (nx / nn, ny / nn, nz / nn) if nn > 1e-12 else (0.0, 0.0, 1.0)
        ws.sc_n[r, 0], ws.sc_n[r, 1], ws.sc_n[r, 2] = nx, ny, nz
        if not d < cut:  # beyond the influence distance: no row this tick (self_rows), nothing more
            continue
        point_jacobian(ws, cap_support[i], p, Jp)
        point_jacobian(ws, cap_support[j], q, Jq)
        hdot = 0.0
        for k in range(n):
            val = nx * (Jp[0, k] - Jq[0, k]) + ny * (Jp[1, k] - Jq[1, k]) + nz * (Jp[2, k] - Jq[2, k])
            ws.sc_row[r, k] = val
            hdot += val * ws.v[k]
        ws.sc_hdot[r] = hdot
        body_point(ws, i, p, vp, ap)
        body_point(ws, j, q, vq, aq)
        rigid = nx * (ap[0] - aq[0]) + ny * (ap[1] - aq[1]) + nz * (ap[2] - aq[2])
        wi, wj = ws.body_vel[i], ws.body_vel[j]
        udx, udy, udz = wi[4] * uz - wi[5] * uy, wi[5] * ux - wi[3] * uz, wi[3] * uy - wi[4] * ux  # ω_i × u
        sdx, sdy, sdz = wj[4] * sz - wj[5] * sy, wj[5] * sx - wj[3] * sz, wj[3] * sy - wj[4] * sx  # ω_j × s
        dvx, dvy, dvz = vp[0] - vq[0], vp[1] - vq[1], vp[2] - vq[2]
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
            ws.sc_drift[r] = rigid
            continue
        wdx = dvx + tau_dot * ux - sigma_dot * sx
        wdy = dvy + tau_dot * uy - sigma_dot * sy
        wdz = dvz + tau_dot * uz - sigma_dot * sz
        nw = nx * wdx + ny * wdy + nz * wdz
        ws.sc_drift[r] = (rigid + 2.0 * tau_dot * (nx * udx + ny * udy + nz * udz)
                          - 2.0 * sigma_dot * (nx * sdx + ny * sdy + nz * sdz)
                          + (wdx * wdx + wdy * wdy + wdz * wdz - nw * nw) / rho)
    ws.fpar[FP_SELF_CLEARANCE] = best
