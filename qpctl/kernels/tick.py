"""The tick's compiled kernels: (q, q̇, t) and Pinocchio's arrays in, torques and QP rows out.

DESIGN.md §5. Each kernel reads and writes the fixed-shape arrays of one :class:`TickWork` (its
fields are listed in :mod:`qpctl.kernels.work`); nothing here allocates per pair or per row, and the
number of pairs changes the work inside a loop, never the number of Python calls. The stages, in
tick order:

* :func:`state` — the rigid-body terms from ``computeAllTerms``'s arrays (M, N, the task point's x,
  J and J̇q̇, the capsules' segments, body Jacobians and q̈ = 0 acceleration fields), the obstacles
  at t, the reference x_d(t), and the link–obstacle pairs within the cutoff: closed form for spheres
  and capsules (:mod:`qpctl.kernels.geometry`), marked for python-fcl for the other shapes;
* :func:`finish_pairs` — once python-fcl has filled its pairs: compaction, witness-point Jacobians
  and drifts, the barrier's exact drift in closed form (:func:`barrier_drift`), the clearance;
* :func:`law_terms` — a, g, e_N, q̈₀ of :mod:`qpctl.law` (paper eq. 7, 12, 18, 19);
* :func:`closed_form` — the paper's q̈ = J_M⁺ a + (I − J_M⁺J) q̈₀, or Hsu's, and τ = M q̈ + N;
* :func:`qp_build` — the QP's cost and rows written in place in DAQP's layout (``qpctl.tick``);
* :func:`qp_finish` — the solution checked against the hard rows, τ = M q̈ + N within ±τ_max.

References, which ``tests/test_kernels.py`` holds these against: Pinocchio's per-frame functions and
finite differences (rigid terms), python-fcl (distances), :mod:`qpctl.law`, :mod:`qpctl.linalg`,
:class:`qpctl.formulation.Formulation` and the tasks and constraints (law terms and QP rows).
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
from numba import njit, types

from qpctl.kernels.geometry import contact_frame, segment_params, sphere_bound
from qpctl.kernels.rotation import exp3, log3, matmul3, matmul3_bt
from qpctl.kernels.small import (
    add_trace_ridge,
    chol_solve,
    cholesky,
    pinv_t_normal,
    solve_lower,
    solve_lower_t,
)
from qpctl.solvers.daqp_native import UPDATE_ALL, daqp_solve, update_ldp

# The process's monotonic clock (time.perf_counter's) inside kernels: stage timings without a return
# to Python. clock_gettime(clockid, struct timespec*) from the C library; the pointer as an integer.
_clock_gettime: Any = types.ExternalFunction("clock_gettime", types.intc(types.intc, types.intp))
_MONOTONIC = time.CLOCK_MONOTONIC

# Obstacle kinds
KIND_SPHERE, KIND_CAPSULE, KIND_FCL = 0, 1, 2
# Pair states
PAIR_OK, PAIR_FCL, PAIR_FAR = 0, 1, 2

# Float settings (TickWork.fpar)
FP_KP, FP_KV, FP_KN, FP_VREF, FP_DI, FP_DS, FP_GDAMP, FP_PINV_EPS, FP_CUTOFF = range(9)
FP_BK0, FP_BK1, FP_JK0, FP_JK1, FP_JKV, FP_SL1, FP_SL2, FP_WACC, FP_WPOST, FP_PKP, FP_PKD = range(9, 20)
FP_GRID_H, FP_CLEARANCE, FP_T, FP_DAMP, FP_DAMP_KD = 20, 21, 22, 23, 24
FP_SK0, FP_SK1, FP_SDS, FP_SELF_CLEARANCE, FP_SCUT = 25, 26, 27, 28, 29
FP_SIZE = 30
# Int settings (TickWork.ipar)
IP_JDOT_EN, IP_DRIFT_RIGID, IP_CAPACITY, IP_TORQUE_ROW0, IP_BARRIER_ROW0, IP_JOINT_LIMITS = range(6)
IP_POSTURE, IP_N_IN, IP_BDRIFT, IP_DAMPING, IP_SELF_ROW0 = range(6, 11)
IP_SIZE = 11
# Counters (TickWork.cnt)
CNT_PAIRS, CNT_FCL, CNT_LOOKAHEAD, CNT_DROPPED = range(4)
CNT_SIZE = 4
# Flags (TickWork.flags)
FLAG_SINGULAR_TERMS, FLAG_SINGULAR_CF, FLAG_CLIPPED = range(3)
FLAG_SIZE = 3

# The output record (TickWork.rec): tau, qdd (n), x_d, ẋ_d, ẍ_d, x (m), e_N (n), then scalars
#   clearance [m], singular (0/1), pairs, pairs dropped (beyond the barrier's rows), slack norm,
#   active rows, the answer's largest relative violation, the torque clip [N·m], solver iterations,
#   stage times [µs] (state kernel, law and rows, solve), active families (bit 0: a torque-limit row,
#   bit 1: an obstacle-barrier row), joints whose torque moved by its whole rate limit
R_CLEARANCE, R_SINGULAR, R_PAIRS, R_DROPPED, R_SLACK, R_ACTIVE, R_VIOLATION, R_CLIPPED = range(8)
R_ITERATIONS, R_STATE_US, R_BUILD_US, R_SOLVE_US, R_ACTIVE_MASK, R_RATE_HITS = range(8, 14)
R_SCALARS = 14


@njit(cache=True)
def record_scalars(n: int, m: int) -> int:
    """Offset of the record's scalars: after τ, q̈, x_d, ẋ_d, ẍ_d, x and e_N."""
    return 3 * n + 4 * m


# ---------------------------------------------------------------------------------------------------
# Rigid-body terms
# ---------------------------------------------------------------------------------------------------
@njit(cache=True)
def _world_acceleration(ws, j: int, out: np.ndarray) -> None:  # type: ignore[no-untyped-def]
    """out (6,) = joint j's q̈ = 0 spatial acceleration in the world frame, at the world origin:
    (R a + p × R α, R α)."""
    P, A = ws.oMi, ws.acc_local
    for r in range(3):
        out[3 + r] = P[j, r] * A[j, 3] + P[j, r + 3] * A[j, 4] + P[j, r + 6] * A[j, 5]
        out[r] = P[j, r] * A[j, 0] + P[j, r + 3] * A[j, 1] + P[j, r + 6] * A[j, 2]
    px, py, pz = P[j, 9], P[j, 10], P[j, 11]
    ax, ay, az = out[3], out[4], out[5]
    out[0] += py * az - pz * ay
    out[1] += pz * ax - px * az
    out[2] += px * ay - py * ax


@njit(cache=True)
def _world_point(ws, j: int, local: np.ndarray, out: np.ndarray) -> None:  # type: ignore[no-untyped-def]
    """out (3,) = oMi[j] · local."""
    P = ws.oMi
    for r in range(3):
        out[r] = P[j, r] * local[0] + P[j, r + 3] * local[1] + P[j, r + 6] * local[2] + P[j, 9 + r]


@njit(cache=True)
def _point_jacobian(ws, support: np.ndarray, p: np.ndarray, out: np.ndarray) -> None:  # type: ignore[no-untyped-def]
    """out (3, n) = J_v − p × J_ω of the body whose joints are ``support`` (world Jacobian columns)."""
    Jt = ws.Jt
    for k in range(Jt.shape[0]):
        s = support[k]
        wx, wy, wz = Jt[k, 3] * s, Jt[k, 4] * s, Jt[k, 5] * s
        out[0, k] = Jt[k, 0] * s - (p[1] * wz - p[2] * wy)
        out[1, k] = Jt[k, 1] * s - (p[2] * wx - p[0] * wz)
        out[2, k] = Jt[k, 2] * s - (p[0] * wy - p[1] * wx)


@njit(cache=True)
def _classical_acceleration(vel: np.ndarray, acc: np.ndarray, p: np.ndarray, out: np.ndarray) -> None:
    """out (3,) = the classical acceleration of body point p at q̈ = 0: a + α × p + ω × (v + ω × p),
    from the body's world spatial velocity (v, ω) and acceleration (a, α) at the world origin."""
    wx, wy, wz = vel[3], vel[4], vel[5]
    vx = vel[0] + wy * p[2] - wz * p[1]
    vy = vel[1] + wz * p[0] - wx * p[2]
    vz = vel[2] + wx * p[1] - wy * p[0]
    out[0] = acc[0] + acc[4] * p[2] - acc[5] * p[1] + wy * vz - wz * vy
    out[1] = acc[1] + acc[5] * p[0] - acc[3] * p[2] + wz * vx - wx * vz
    out[2] = acc[2] + acc[3] * p[1] - acc[4] * p[0] + wx * vy - wy * vx


@njit(cache=True)
def rigid_terms(ws, v: np.ndarray) -> bool:  # type: ignore[no-untyped-def]
    """M, N, the task point's x, ẋ, J, J̇q̇ and the capsules' geometry from Pinocchio's arrays (after
    ``computeAllTerms``); False if N is not finite (speeds so large that C(q, q̇)q̇ overflows)."""
    M, N, Mt, nle, Jt = ws.M, ws.N, ws.Mt, ws.nle, ws.Jt
    n = N.shape[0]
    for i in range(n):
        N[i] = nle[i]
        if not math.isfinite(nle[i]):
            return False
        for j in range(i + 1):
            M[i, j] = M[j, i] = Mt[i, j]
    acc = ws.w3  # scratch (≥ 6)
    vel = np.empty(6)
    p = np.empty(3)
    J3 = np.empty((3, n))
    # task point
    support = ws.ee_support
    _world_point(ws, ws.ee_joint, ws.ee_local, p)
    _point_jacobian(ws, support, p, J3)
    for r in range(6):
        s = 0.0
        for k in range(n):
            s += Jt[k, r] * support[k] * v[k]
        vel[r] = s
    _world_acceleration(ws, ws.ee_joint, acc)
    a3 = np.empty(3)
    _classical_acceleration(vel, acc, p, a3)
    axes, x, drift, J, xdot = ws.axes, ws.x, ws.drift, ws.J, ws.xdot
    for r in range(axes.shape[0]):
        ax = axes[r]
        x[r] = p[ax]
        drift[r] = a3[ax]
        s = 0.0
        for k in range(n):
            J[r, k] = J3[ax, k]
            s += J3[ax, k] * v[k]
        xdot[r] = s
    if ws.ori_rows.shape[0]:  # the frame's R, ω, α₀ for the orientation rows (orientation_reference)
        _frame_rotation(ws)
        for c in range(3):
            ws.ee_w[c], ws.ee_w[3 + c] = vel[3 + c], acc[3 + c]
    # capsules
    cap_joint, cap_local, cap_support = ws.cap_joint, ws.cap_local, ws.cap_support
    segments, body_jac, body_vel = ws.segments, ws.body_jac, ws.body_vel
    link_jac, acc_off, acc_K = ws.link_jac, ws.acc_off, ws.acc_K
    for i in range(cap_joint.shape[0]):
        j = cap_joint[i]
        _world_point(ws, j, cap_local[i, 0], segments[i, 0])
        _world_point(ws, j, cap_local[i, 1], segments[i, 1])
        for r in range(6):
            s = 0.0
            for k in range(n):
                val = Jt[k, r] * cap_support[i, k]
                body_jac[i, r, k] = val
                s += val * v[k]
            body_vel[i, r] = s
        for r in range(3):
            p[r] = 0.5 * (segments[i, 0, r] + segments[i, 1, r])
        _point_jacobian(ws, cap_support[i], p, link_jac[i])
        # q̈ = 0 acceleration field of the body: a(p) = offset + K p, offset = a + ω × v, K = [α]× + [ω]×²
        _world_acceleration(ws, j, acc)
        vx, vy, vz, wx, wy, wz = body_vel[i, 0], body_vel[i, 1], body_vel[i, 2], body_vel[i, 3], body_vel[i, 4], body_vel[i, 5]
        acc_off[i, 0] = acc[0] + wy * vz - wz * vy
        acc_off[i, 1] = acc[1] + wz * vx - wx * vz
        acc_off[i, 2] = acc[2] + wx * vy - wy * vx
        K = acc_K[i]
        K[0, 0], K[0, 1], K[0, 2] = -(wy * wy + wz * wz), -acc[5] + wx * wy, acc[4] + wx * wz
        K[1, 0], K[1, 1], K[1, 2] = acc[5] + wx * wy, -(wx * wx + wz * wz), -acc[3] + wy * wz
        K[2, 0], K[2, 1], K[2, 2] = -acc[4] + wx * wz, acc[3] + wy * wz, -(wx * wx + wy * wy)
    return True


@njit(cache=True)
def _frame_rotation(ws) -> None:  # type: ignore[no-untyped-def]
    """ws.ee_R = the task frame's world rotation (its joint's, times the frame's in the joint)."""
    P, Rl, R = ws.oMi, ws.ee_rot, ws.ee_R
    j = ws.ee_joint
    for r in range(3):
        for c in range(3):
            R[r, c] = P[j, r] * Rl[0, c] + P[j, r + 3] * Rl[1, c] + P[j, r + 6] * Rl[2, c]


@njit(cache=True)
def _cross(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    out[0], out[1], out[2] = a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]


@njit(cache=True)
def _dot(a: np.ndarray, b: np.ndarray) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@njit(cache=True)
def _rotate(R: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    for r in range(3):
        out[r] = R[r, 0] * b[0] + R[r, 1] * b[1] + R[r, 2] * b[2]


@njit(cache=True)
def orientation_reference(ws, k: int, s: float, ds: float, dds: float) -> None:  # type: ignore[no-untyped-def]
    """The orientation rows (qpctl.orientation) on path segment k at s, ṡ [1/s], s̈ [1/s²]: R_d, ω_d,
    ω̇_d of the PosePath, then each row's x, ẋ, J, J̇q̇ (from the frame's R, ω, α₀ of
    :func:`rigid_terms`) and x_d, ẋ_d, ẍ_d."""
    th = ws.rot_theta[k]
    wd, ad, sv = np.empty(3), np.empty(3), np.empty(3)
    for c in range(3):
        wd[c] = ds * th[c]
        ad[c] = dds * th[c]
        sv[c] = s * th[c]
    E, Rd = np.empty((3, 3)), np.empty((3, 3))
    exp3(sv, E)
    matmul3(E, ws.rot_pts[k], Rd)  # R_d = exp(s θ_k) R_k
    R, Jt, support = ws.ee_R, ws.Jt, ws.ee_support
    n, m_p = Jt.shape[0], ws.axes.shape[0]
    w, a0 = ws.ee_w[:3], ws.ee_w[3:]
    u, err = np.empty(3), np.empty(3)
    if ws.ori_rows.shape[0] and ws.ori_rows[0] < 3:  # pose: world axes, x = 0, x_d = log(R_d Rᵀ)
        matmul3_bt(Rd, R, E)
        log3(E, err)
        for i in range(ws.ori_rows.shape[0]):
            r, c = m_p + i, ws.ori_rows[i]
            ws.x[r], ws.xdot[r], ws.drift[r] = 0.0, w[c], a0[c]
            for j in range(n):
                ws.J[r, j] = Jt[j, 3 + c] * support[j]
            ws.ref[0, r], ws.ref[1, r], ws.ref[2, r] = err[c], wd[c], ad[c]
        return
    # approach: y_k = v_k·z with z = R c, v_k = R_d b_k; J = (z × v_k)ᵀJ_ω, exact (qpctl.orientation)
    z, v, zw, vd, zdot, t1 = np.empty(3), np.empty(3), np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    _rotate(R, ws.ori_axis, z)
    _cross(w, z, zdot)  # ż = ω × z
    dw = np.empty(3)
    for c in range(3):
        dw[c] = w[c] - wd[c]
    for i in range(ws.ori_rows.shape[0]):
        r = m_p + i
        _rotate(Rd, ws.ori_basis[ws.ori_rows[i] - 3], v)
        _cross(z, v, zw)  # z × v_k
        _cross(wd, v, vd)  # v̇_k = ω_d × v_k
        ws.x[r] = _dot(v, z)
        ws.xdot[r] = _dot(zw, w)
        _cross(zdot, v, u)  # ż × v_k
        _cross(z, vd, t1)  # z × v̇_k
        ws.drift[r] = _dot(zw, a0) + _dot(u, dw) + _dot(t1, w)
        for j in range(n):
            ws.J[r, j] = (zw[0] * Jt[j, 3] + zw[1] * Jt[j, 4] + zw[2] * Jt[j, 5]) * support[j]
        ws.ref[0, r] = 0.0
        ws.ref[1, r] = _dot(zw, wd)
        ws.ref[2, r] = _dot(t1, wd) + _dot(zw, ad)


# ---------------------------------------------------------------------------------------------------
# Scene and reference at t
# ---------------------------------------------------------------------------------------------------
@njit(cache=True)
def obstacles_at(ws, t: float) -> None:  # type: ignore[no-untyped-def]
    """Centres, velocities and accelerations of the moving obstacles at t [s] (Obstacle.position_at)."""
    for r in range(ws.moving.shape[0]):
        j = ws.moving[r]
        w = ws.ob_omega[j]
        st, ct = math.sin(w * t), math.cos(w * t)
        for i in range(3):
            ws.ob_c[j, i] = ws.ob_pos0[j, i] + ws.ob_vel0[j, i] * t + ws.ob_amp[j, i] * st
            ws.ob_v[j, i] = ws.ob_vel0[j, i] + ws.ob_amp[j, i] * w * ct
            ws.ob_a[j, i] = -ws.ob_amp[j, i] * w * w * st


@njit(cache=True)
def reference(ws, t: float) -> None:  # type: ignore[no-untyped-def]
    """x_d, ẋ_d, ẍ_d at t [s] into ws.ref: straight segments with quintic timing (WaypointPath), and
    the orientation rows' (PosePath, after :func:`rigid_terms`)."""
    t0, T_all = ws.path_t0, ws.path_T
    nseg = T_all.shape[0]
    k = 0
    while k < nseg and t0[k] <= t:
        k += 1
    k = min(max(k - 1, 0), nseg - 1)
    T = T_all[k]
    tau = (t - t0[k]) / T
    if tau <= 0.0:
        s = ds = dds = 0.0
    elif tau >= 1.0:
        s, ds, dds = 1.0, 0.0, 0.0
    else:
        t2 = tau * tau
        s = t2 * tau * (10 - 15 * tau + 6 * t2)
        ds = 30 * t2 * (1 - tau) ** 2
        dds = 60 * tau * (1 - tau) * (1 - 2 * tau)
    pts = ws.path_pts
    for r in range(pts.shape[1]):
        delta = pts[k + 1, r] - pts[k, r]
        ws.ref[0, r] = pts[k, r] + s * delta
        ws.ref[1, r] = (ds / T) * delta
        ws.ref[2, r] = (dds / T**2) * delta
    if ws.ori_rows.shape[0]:
        orientation_reference(ws, k, s, ds / T, dds / T**2)


# ---------------------------------------------------------------------------------------------------
# Pairs
# ---------------------------------------------------------------------------------------------------
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
    normals and witness points in closed form for spheres and capsules (:mod:`qpctl.kernels.geometry`);
    pairs with python-fcl's shapes whose bounding sphere is within the cutoff are listed as PAIR_FCL
    for Python to query. Returns the number of PAIR_FCL pairs."""
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
        nc = _candidates(ws, i, cand) if grid else O
        for e in range(nc):
            j = cand[e] if grid else e
            kind = ob_kind[j]
            cx, cy, cz = ob_c[j, 0], ob_c[j, 1], ob_c[j, 2]
            if kind == KIND_SPHERE:
                sx = sy = sz = 0.0
            else:
                if sphere_bound(segments[i, 0], segments[i, 1], rl, ob_c[j], ob_bound[j]) >= cutoff:
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
            contact_frame(px, py, pz, qx, qy, qz, wx, wy, wz, wn, ux, uy, uz, sx, sy, sz, rl, ro,
                          pr_n[k], pr_pl[k], pr_po[k])
            pr_link[k], pr_obs[k], pr_state[k], pr_d[k] = i, j, PAIR_OK, d
            k += 1
    ws.cnt[CNT_PAIRS] = k
    ws.cnt[CNT_FCL] = nfcl
    return nfcl


@njit(cache=True)
def barrier_drift(ws, r: int) -> bool:  # type: ignore[no-untyped-def]
    """ḧ at q̈ = 0 of pair r (∂ḣ/∂q q̇ + ∂ḣ/∂t) into pr_bdrift[r], in closed form for a sphere or
    capsule obstacle; False where it has none (python-fcl's shapes, meeting or parallel axes).

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
    nx, ny, nz = ws.pr_n[r, 0], ws.pr_n[r, 1], ws.pr_n[r, 2]
    rl, ro = ws.cap_radius[i], ws.ob_radius[j]
    px, py, pz = ws.pr_pl[r, 0] + rl * nx, ws.pr_pl[r, 1] + rl * ny, ws.pr_pl[r, 2] + rl * nz  # link axis
    qx, qy, qz = ws.pr_po[r, 0] - ro * nx, ws.pr_po[r, 1] - ro * ny, ws.pr_po[r, 2] - ro * nz  # obstacle's
    wx, wy, wz = px - qx, py - qy, pz - qz
    a, b = ws.segments[i, 0], ws.segments[i, 1]
    ux, uy, uz = b[0] - a[0], b[1] - a[1], b[2] - a[2]
    sx, sy, sz = ws.ob_axis[j, 0], ws.ob_axis[j, 1], ws.ob_axis[j, 2]
    cx, cy, cz = ws.ob_c[j, 0], ws.ob_c[j, 1], ws.ob_c[j, 2]
    bv = ws.body_vel[i]
    vx, vy, vz, ox, oy, oz = bv[0], bv[1], bv[2], bv[3], bv[4], bv[5]
    vpx, vpy, vpz = vx + oy * pz - oz * py, vy + oz * px - ox * pz, vz + ox * py - oy * px  # v + ω × p
    udx, udy, udz = oy * uz - oz * uy, oz * ux - ox * uz, ox * uy - oy * ux  # u̇ = ω × u
    K = ws.acc_K[i]
    o = ws.acc_off[i]
    apx = o[0] + K[0, 0] * px + K[0, 1] * py + K[0, 2] * pz  # a_p = offset + K p
    apy = o[1] + K[1, 0] * px + K[1, 1] * py + K[1, 2] * pz
    apz = o[2] + K[2, 0] * px + K[2, 1] * py + K[2, 2] * pz
    vo, ao = ws.ob_v[j], ws.ob_a[j]
    dvx, dvy, dvz = vpx - vo[0], vpy - vo[1], vpz - vo[2]
    L2 = ux * ux + uy * uy + uz * uz
    tau_l2 = (px - a[0]) * ux + (py - a[1]) * uy + (pz - a[2]) * uz  # τ L²
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
    ws.pr_bdrift[r] = (nx * (apx - ao[0]) + ny * (apy - ao[1]) + nz * (apz - ao[2])
                       + 2.0 * tau_dot * (nx * udx + ny * udy + nz * udz)
                       + (wdx * wdx + wdy * wdy + wdz * wdz - nw * nw) / math.sqrt(max(rho2, 1e-24)))
    return True


@njit(cache=True)
def finish_pairs(ws) -> int:  # type: ignore[no-untyped-def]
    """After python-fcl: drop the pairs it found beyond the cutoff (order kept), then each pair's
    witness-point Jacobian and drift, the barrier drift (closed form where it exists, when the QP
    needs it) and the clearance. Returns the number of pairs left for the look-ahead drift."""
    k = 0
    for r in range(ws.cnt[CNT_PAIRS]):
        if ws.pr_state[r] == PAIR_FAR:
            continue
        if k != r:
            ws.pr_link[k], ws.pr_obs[k], ws.pr_d[k], ws.pr_state[k] = (ws.pr_link[r], ws.pr_obs[r], ws.pr_d[r],
                                                                         ws.pr_state[r])
            for c in range(3):
                ws.pr_n[k, c], ws.pr_pl[k, c], ws.pr_po[k, c] = ws.pr_n[r, c], ws.pr_pl[r, c], ws.pr_po[r, c]
        k += 1
    ws.cnt[CNT_PAIRS] = k
    ws.cnt[CNT_FCL] = 0
    clearance = np.inf
    look = 0
    need = ws.ipar[IP_BDRIFT] != 0
    for r in range(k):
        i = ws.pr_link[r]
        clearance = min(clearance, ws.pr_d[r])
        _point_jacobian(ws, ws.cap_support[i], ws.pr_pl[r], ws.pr_jac[r])
        p = ws.pr_pl[r]
        K = ws.acc_K[i]
        for c in range(3):
            ws.pr_drift[r, c] = ws.acc_off[i, c] + K[c, 0] * p[0] + K[c, 1] * p[1] + K[c, 2] * p[2]
        ws.pr_bok[r] = 1
        if need and not barrier_drift(ws, r):
            ws.pr_bok[r] = 0
            ws.pr_bdrift[r] = 0.0
            look += 1
    ws.fpar[FP_CLEARANCE] = clearance
    ws.cnt[CNT_LOOKAHEAD] = look
    return look


@njit(cache=True)
def _body_point(ws, i: int, p: np.ndarray, vel: np.ndarray, acc: np.ndarray) -> None:  # type: ignore[no-untyped-def]
    """Velocity and q̈ = 0 acceleration of the point p fixed to capsule i's body."""
    bv, K, o = ws.body_vel[i], ws.acc_K[i], ws.acc_off[i]
    vel[0] = bv[0] + bv[4] * p[2] - bv[5] * p[1]
    vel[1] = bv[1] + bv[5] * p[0] - bv[3] * p[2]
    vel[2] = bv[2] + bv[3] * p[1] - bv[4] * p[0]
    for c in range(3):
        acc[c] = o[c] + K[c, 0] * p[0] + K[c, 1] * p[1] + K[c, 2] * p[2]


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
    Jp, Jq = np.empty((3, n)), np.empty((3, n))
    p, q, vp, vq, ap, aq = np.empty(3), np.empty(3), np.empty(3), np.empty(3), np.empty(3), np.empty(3)
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
        _point_jacobian(ws, cap_support[i], p, Jp)
        _point_jacobian(ws, cap_support[j], q, Jq)
        hdot = 0.0
        for k in range(n):
            val = nx * (Jp[0, k] - Jq[0, k]) + ny * (Jp[1, k] - Jq[1, k]) + nz * (Jp[2, k] - Jq[2, k])
            ws.sc_row[r, k] = val
            hdot += val * ws.v[k]
        ws.sc_hdot[r] = hdot
        _body_point(ws, i, p, vp, ap)
        _body_point(ws, j, q, vq, aq)
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


@njit(cache=True)
def self_rows(ws, C: np.ndarray, lower: np.ndarray) -> None:  # type: ignore[no-untyped-def]
    """ḧ + k₁ḣ + k₀(h − d_s) ≥ 0 for the self-collision pairs within their cutoff (the rest inactive:
    zero rows, −∞ bounds), as the obstacle barrier's rows (:func:`barrier_rows`)."""
    n = ws.v.shape[0]
    k0, k1, ds, cut = ws.fpar[FP_SK0], ws.fpar[FP_SK1], ws.fpar[FP_SDS], ws.fpar[FP_SCUT]
    for r in range(C.shape[0]):
        d = ws.sc_d[r]
        if d < cut:
            for c in range(n):
                C[r, c] = ws.sc_row[r, c]
            lower[r] = -k1 * ws.sc_hdot[r] - k0 * (d - ds) - ws.sc_drift[r]
        else:
            for c in range(n):
                C[r, c] = 0.0
            lower[r] = -np.inf


@njit(cache=True)
def state(ws, q: np.ndarray, v: np.ndarray, t: float) -> int:  # type: ignore[no-untyped-def]
    """The tick's state after ``computeAllTerms(q, v)``: rigid terms, obstacles and reference at t,
    pairs. Returns −1 when the dynamics overflow, else the number of pairs python-fcl must query
    (when 0, :func:`finish_pairs` has run too)."""
    for i in range(q.shape[0]):
        ws.q[i], ws.v[i] = q[i], v[i]
    ws.fpar[FP_T] = t
    if not rigid_terms(ws, v):
        return -1
    if ws.sc_pairs.shape[0]:
        self_pairs(ws)
    obstacles_at(ws, t)
    reference(ws, t)
    nfcl = find_pairs(ws)
    if nfcl == 0:
        finish_pairs(ws)
    return nfcl


# ---------------------------------------------------------------------------------------------------
# The law's terms and the closed forms
# ---------------------------------------------------------------------------------------------------
@njit(cache=True)
def reference_velocity(ws) -> None:  # type: ignore[no-untyped-def]
    """g [rad/s]: the joint velocity that best realises u = v_ref α(d) n at every link point within d_i
    (rows and targets weighed by √α; damped least squares, λ = g_damping). An obstacle whose own
    v_ref is 0 keeps its rows, asking its links to hold still; g = 0 when no pair is within d_i or
    every such pair's v_ref is 0 (qpctl.law.reference_velocity)."""
    n = ws.g.shape[0]
    di, ds = ws.fpar[FP_DI], ws.fpar[FP_DS]
    v_ref = ws.fpar[FP_VREF]
    pr_d, pr_obs, pr_n, pr_jac, ob_vref = ws.pr_d, ws.pr_obs, ws.pr_n, ws.pr_jac, ws.ob_vref
    H, rhs = ws.S, ws.g
    H[:, :] = 0.0
    rhs[:] = 0.0
    any_moving = False
    for r in range(ws.cnt[CNT_PAIRS]):
        d = pr_d[r]
        if not d < di:
            continue
        own = ob_vref[pr_obs[r]]
        vr = v_ref if math.isnan(own) else own
        any_moving = any_moving or vr != 0.0
        alpha = min(max((di - d) / (di - ds), 0.0), 1.0)
        w = math.sqrt(alpha)
        for c in range(3):
            b = w * ((vr * alpha) * pr_n[r, c])
            for i in range(n):
                ai = w * pr_jac[r, c, i]
                rhs[i] += ai * b
                for j in range(i + 1):
                    H[i, j] += ai * (w * pr_jac[r, c, j])
    if not any_moving:
        rhs[:] = 0.0
        return
    lam2 = ws.fpar[FP_GDAMP] ** 2
    for i in range(n):
        H[i, i] += lam2
    if not cholesky(H, ws.Lb):  # λ = 0 and too few rows: regularise as W_b is
        add_trace_ridge(H)
        cholesky(H, ws.Lb)
    chol_solve(ws.Lb, rhs)


@njit(cache=True)
def _weighted_pinv(ws, L: np.ndarray, out: np.ndarray, mode: int) -> bool:  # type: ignore[no-untyped-def]
    """out (n, m) = J_W⁺ of the task Jacobian: mode 0 unweighted, 1 with W = L Lᵀ (a Cholesky factor),
    2 with W = MᵀM (L is M's Cholesky factor). Returns whether the damping was used."""
    n, m = ws.Bt.shape
    Bt = ws.Bt
    for i in range(n):
        for r in range(m):
            Bt[i, r] = ws.J[r, i]
    if mode == 1:
        solve_lower(L, Bt)  # J̃ᵀ = L⁻¹ Jᵀ
    elif mode == 2:
        chol_solve(L, Bt)  # J̃ᵀ = M⁻¹ Jᵀ
    singular, _ratio = pinv_t_normal(Bt, ws.fpar[FP_PINV_EPS], ws.Vm, out)
    if mode == 1:
        solve_lower_t(L, out)  # L⁻ᵀ J̃⁺
    elif mode == 2:
        chol_solve(L, out)  # M⁻¹ J̃⁺
    return singular


@njit(cache=True)
def law_terms(ws, weighted: bool) -> bool:  # type: ignore[no-untyped-def]
    """a, g, e_N, q̈₀ (qpctl.law) into the workspace; False if M is not positive definite."""
    n, m = ws.g.shape[0], ws.a.shape[0]
    kp, kv, kn = ws.fpar[FP_KP], ws.fpar[FP_KV], ws.fpar[FP_KN]
    for r in range(m):
        ws.e[r] = ws.ref[0, r] - ws.x[r]
        ws.edot[r] = ws.ref[1, r] - ws.xdot[r]
        ws.a[r] = ws.ref[2, r] + kv * ws.edot[r] + kp * ws.e[r] - ws.drift[r]
    if not cholesky(ws.M, ws.Lm):
        return False
    reference_velocity(ws)
    if weighted:  # Ryu's W_b = Σ J_iᵀJ_i over the links' mid-points, + 1e-9·max(tr, 1)·I
        W = ws.S
        W[:, :] = 0.0
        for i in range(ws.link_jac.shape[0]):
            Jl = ws.link_jac[i]
            for c in range(3):
                for a in range(n):
                    for b in range(a + 1):
                        W[a, b] += Jl[c, a] * Jl[c, b]
        add_trace_ridge(W)
        cholesky(W, ws.Lb)
        singular = _weighted_pinv(ws, ws.Lb, ws.Jb, 1)
    else:
        singular = _weighted_pinv(ws, ws.Lb, ws.Jb, 0)
    ws.flags[FLAG_SINGULAR_TERMS] = 1 if singular else 0
    # e_N = (I − J_b⁺J)(g − q̇)
    gv, Jgv = ws.w1, ws.w3
    for i in range(n):
        gv[i] = ws.g[i] - ws.v[i]
    for r in range(m):
        s = 0.0
        for i in range(n):
            s += ws.J[r, i] * gv[i]
        Jgv[r] = s
    for i in range(n):
        s = gv[i]
        for r in range(m):
            s -= ws.Jb[i, r] * Jgv[r]
        ws.e_null[i] = s
    if ws.ipar[IP_JDOT_EN] != 0:
        for r in range(m):
            s = 0.0
            for i in range(n):
                s += ws.Jdot[r, i] * ws.e_null[i]
            ws.a[r] += s
    # q̈₀ = −M⁻¹N + K_N e_N (paper), K_N e_N (Hsu)
    if weighted:
        for i in range(n):
            ws.w2[i] = ws.N[i]
        chol_solve(ws.Lm, ws.w2)
        for i in range(n):
            ws.qdd0[i] = -ws.w2[i] + kn * ws.e_null[i]
    else:
        for i in range(n):
            ws.qdd0[i] = kn * ws.e_null[i]
    return True


@njit(cache=True)
def write_record(ws, singular: bool) -> None:  # type: ignore[no-untyped-def]
    """The tick's outputs into ws.rec: τ, q̈, x_d, ẋ_d, ẍ_d, x, e_N, then the scalars R_*."""
    n, m = ws.tau.shape[0], ws.a.shape[0]
    rec = ws.rec
    for i in range(n):
        rec[i] = ws.tau[i]
        rec[n + i] = ws.qdd[i]
        rec[2 * n + 4 * m + i] = ws.e_null[i]
    for r in range(m):
        rec[2 * n + r] = ws.ref[0, r]
        rec[2 * n + m + r] = ws.ref[1, r]
        rec[2 * n + 2 * m + r] = ws.ref[2, r]
        rec[2 * n + 3 * m + r] = ws.x[r]
    s = 3 * n + 4 * m
    rec[s + R_CLEARANCE] = ws.fpar[FP_CLEARANCE]
    rec[s + R_SINGULAR] = 1.0 if singular else 0.0
    rec[s + R_PAIRS] = ws.cnt[CNT_PAIRS]
    rec[s + R_DROPPED] = ws.cnt[CNT_DROPPED]
    # the torque commanded, for the next tick's rate limit (TorqueLimit.previous, shared)
    for i in range(n):
        ws.tau_prev[i] = ws.tau[i]
    ws.t_prev[0] = ws.fpar[FP_T]


@njit(cache=True)
def torque_of(ws) -> None:  # type: ignore[no-untyped-def]
    """τ = M q̈ + N."""
    n = ws.tau.shape[0]
    for i in range(n):
        s = 0.0
        for j in range(n):
            s += ws.M[i, j] * ws.qdd[j]
        ws.tau[i] = s + ws.N[i]


@njit(cache=True)
def closed_form(ws, weighted: bool) -> bool:  # type: ignore[no-untyped-def]
    """The paper's law (weighted, W = MᵀM) or Hsu's (unweighted) after :func:`law_terms`:
    q̈ = J_W⁺ a + (I − J_W⁺J) q̈₀, τ = M q̈ + N; returns whether a pseudo-inverse was damped."""
    n, m = ws.qdd.shape[0], ws.a.shape[0]
    singular = _weighted_pinv(ws, ws.Lm, ws.Jp, 2 if weighted else 0)
    Jq0 = ws.w3
    for r in range(m):
        s = 0.0
        for i in range(n):
            s += ws.J[r, i] * ws.qdd0[i]
        Jq0[r] = s
    for i in range(n):
        s1 = 0.0
        s2 = 0.0
        for r in range(m):
            s1 += ws.Jp[i, r] * ws.a[r]
            s2 += ws.Jp[i, r] * Jq0[r]
        ws.qdd[i] = s1 + ws.qdd0[i] - s2
    torque_of(ws)
    singular = singular or ws.flags[FLAG_SINGULAR_TERMS] != 0
    ws.flags[FLAG_SINGULAR_CF] = 1 if singular else 0
    return singular


@njit(cache=True)
def closed_form_tick(ws, weighted: bool) -> int:  # type: ignore[no-untyped-def]
    """Law terms, the closed form and the record: 0, or 1 when M is not positive definite."""
    if not law_terms(ws, weighted):
        return 1
    singular = closed_form(ws, weighted)
    write_record(ws, singular)
    return 0


# ---------------------------------------------------------------------------------------------------
# The QP in DAQP's layout: x = [q̈ (n), s⁺ (k), s⁻ (k)];  bounds on x (nv), then the inequality rows
# (n_in), then the equality rows (m): rows = [C; A], bu = [ub; u; b], bl = [lb; l; b]
# ---------------------------------------------------------------------------------------------------
@njit(cache=True)
def joint_bounds(ws, lo: np.ndarray, hi: np.ndarray) -> None:  # type: ignore[no-untyped-def]
    """JointLimit's bounds on q̈ [rad/s²]: ḧ + k₁ḣ + k₀h ≥ 0 on the positions, ḣ + k_v h ≥ 0 on the
    speeds; ∞ − ∞ (NaN) counts as no bound; crossed bounds both become their mean. Then within
    ±q̈_max, the drive's acceleration limit; where the position or speed barrier asks for more than
    that, both bounds become the limit on that side (the most the drive may do)."""
    k0, k1, kv = ws.fpar[FP_JK0], ws.fpar[FP_JK1], ws.fpar[FP_JKV]
    for i in range(lo.shape[0]):
        q, v = ws.q[i], ws.v[i]
        low = max(-k1 * v - k0 * (q - ws.q_min[i]), -kv * (ws.v_max[i] + v))
        high = min(-k1 * v + k0 * (ws.q_max[i] - q), kv * (ws.v_max[i] - v))
        if math.isnan(low):
            low = -np.inf
        if math.isnan(high):
            high = np.inf
        if low > high:
            low = high = 0.5 * (low + high)
        a = ws.qdd_max[i]
        low2, high2 = max(low, -a), min(high, a)
        if low2 > high2:
            low2 = high2 = min(max(0.5 * (low + high), -a), a)
        lo[i], hi[i] = low2, high2


@njit(cache=True)
def torque_window(ws, i: int) -> tuple[float, float]:
    """The torque joint i may be commanded this tick [N·m]: within ±τ_max and, once a torque was
    commanded at t_prev < t, within τ_prev ± τ̇_max (t − t_prev). Where the two do not meet (τ_prev
    beyond τ_max: the limit changed) the torque limit wins."""
    lim = ws.tau_max[i]
    lo, hi = -lim, lim
    dt = ws.fpar[FP_T] - ws.t_prev[0]
    if dt > 0.0:  # False for NaN: no torque commanded yet
        w = ws.tau_rate[i] * dt
        lo2, hi2 = max(lo, ws.tau_prev[i] - w), min(hi, ws.tau_prev[i] + w)
        if lo2 <= hi2:
            return lo2, hi2
    return lo, hi


@njit(cache=True)
def qp_build(ws, H: np.ndarray, f: np.ndarray, rows: np.ndarray, bu: np.ndarray,  # type: ignore[no-untyped-def]
             bl: np.ndarray) -> None:
    """The tick's cost and rows, in place (the slack columns, their costs and bounds, and the
    inactive rows' infinite bounds are set once by qpctl.tick and not touched here)."""
    n, m = ws.N.shape[0], ws.a.shape[0]
    nv = H.shape[0]
    n_in = ws.ipar[IP_N_IN]
    M = ws.M
    wacc = ws.fpar[FP_WACC]
    # ½ w‖M(q̈ − q̈₀)‖²: H = w MᵀM, f = −w MᵀM q̈₀ (AccelerationTask)
    for i in range(n):
        for j in range(i + 1):
            s = 0.0
            for k in range(n):
                s += M[k, i] * M[k, j]
            H[i, j] = H[j, i] = wacc * s
    for i in range(n):
        s = 0.0
        for j in range(n):
            s += H[i, j] * ws.qdd0[j]
        f[i] = -s
    if ws.ipar[IP_POSTURE] != 0:  # ½ w‖q̈ − (K_p(q_ref − q) − K_d q̇)‖² (PostureTask)
        w, pkp, pkd = ws.fpar[FP_WPOST], ws.fpar[FP_PKP], ws.fpar[FP_PKD]
        for i in range(n):
            H[i, i] += w
            f[i] += -w * (pkp * (ws.q_ref[i] - ws.q[i]) - pkd * ws.v[i])
    if ws.ipar[IP_DAMPING] != 0:  # ½ w‖q̈ + K_d q̇‖², w = ρ tr(MᵀM)/n (DampingTask)
        trmm = 0.0
        for i in range(n):
            for k in range(n):
                trmm += M[k, i] * M[k, i]
        w, kd = ws.fpar[FP_DAMP] * trmm / n, ws.fpar[FP_DAMP_KD]
        for i in range(n):
            H[i, i] += w
            f[i] += w * kd * ws.v[i]
    # J q̈ + s = a (EndEffectorTask)
    e0 = nv + n_in
    for r in range(m):
        w = ws.task_w[r]
        for k in range(n):
            rows[n_in + r, k] = w * ws.J[r, k]
        bu[e0 + r] = bl[e0 + r] = w * ws.a[r]
    # −τ_max ≤ M q̈ + N ≤ τ_max and |M q̈ + N − τ_prev| ≤ τ̇_max dt (TorqueLimit)
    t0 = ws.ipar[IP_TORQUE_ROW0]
    if t0 >= 0:
        for i in range(n):
            for k in range(n):
                rows[t0 + i, k] = M[i, k]
            lo, hi = torque_window(ws, i)
            bl[nv + t0 + i] = lo - ws.N[i]
            bu[nv + t0 + i] = hi - ws.N[i]
    # joint position and speed limits as bounds on q̈ (JointLimit)
    if ws.ipar[IP_JOINT_LIMITS] != 0:
        joint_bounds(ws, bl[:n], bu[:n])
    # ḧ + k₁ḣ + k₀h ≥ 0 for the nearest pairs (ObstacleBarrier)
    b0 = ws.ipar[IP_BARRIER_ROW0]
    if b0 >= 0:
        barrier_rows(ws, rows[b0:b0 + ws.ipar[IP_CAPACITY]], bl[nv + b0:nv + b0 + ws.ipar[IP_CAPACITY]])
    # the same between the arm's own links (SelfCollisionBarrier)
    s0 = ws.ipar[IP_SELF_ROW0]
    if s0 >= 0:
        P = ws.sc_pairs.shape[0]
        self_rows(ws, rows[s0:s0 + P], bl[nv + s0:nv + s0 + P])


@njit(cache=True)
def barrier_rows(ws, C: np.ndarray, lower: np.ndarray) -> None:  # type: ignore[no-untyped-def]
    """nᵀJ_p q̈ ≥ −k₁ḣ − k₀h − drift for the nearest pairs, as many as there are rows (the rest
    inactive: zero rows, −∞ bounds); h = d − d_s, ḣ = nᵀ(J_p q̇ − v_obs)."""
    n = ws.N.shape[0]
    k = ws.cnt[CNT_PAIRS]
    cap = C.shape[0]
    order = np.argsort(ws.pr_d[:k], kind="mergesort")
    used = min(k, cap)
    ws.cnt[CNT_DROPPED] = k - used
    k0, k1, ds = ws.fpar[FP_BK0], ws.fpar[FP_BK1], ws.fpar[FP_DS]
    rigid = ws.ipar[IP_DRIFT_RIGID] != 0
    for r in range(used):
        p = order[r]
        ws.order[r] = p
        j = ws.pr_obs[p]
        nx, ny, nz = ws.pr_n[p, 0], ws.pr_n[p, 1], ws.pr_n[p, 2]
        Jp = ws.pr_jac[p]
        hdot = 0.0
        for c in range(n):
            val = nx * Jp[0, c] + ny * Jp[1, c] + nz * Jp[2, c]
            C[r, c] = val
            hdot += val * ws.v[c]
        vo = ws.ob_v[j]
        hdot -= nx * vo[0] + ny * vo[1] + nz * vo[2]
        if rigid:
            ao = ws.ob_a[j]
            dr = ws.pr_drift[p]
            drift = nx * (dr[0] - ao[0]) + ny * (dr[1] - ao[1]) + nz * (dr[2] - ao[2])
        else:
            drift = ws.pr_bdrift[p]
        lower[r] = -k1 * hdot - k0 * (ws.pr_d[p] - ds) - drift
    for r in range(used, cap):
        for c in range(n):
            C[r, c] = 0.0
        lower[r] = -np.inf


@njit(cache=True)
def violation(x: np.ndarray, n: int, n_in: int, rows: np.ndarray, bu: np.ndarray, bl: np.ndarray,
              Cx: np.ndarray) -> float:
    """Largest violation at x of the inequality rows and of the bounds on q̈, each relative to
    1 + |its bound| (infinite bounds never count); the task's equality is the solver's business.
    Leaves C x in ``Cx`` (n_in,)."""
    nv = x.shape[0]
    worst = 0.0
    for r in range(n_in + n):
        if r < n_in:
            s = 0.0
            for c in range(nv):
                s += rows[r, c] * x[c]
            Cx[r] = s
            lo, hi = bl[nv + r], bu[nv + r]
        else:
            s = x[r - n_in]
            lo, hi = bl[r - n_in], bu[r - n_in]
        if lo - s > 0.0 and math.isfinite(lo):
            worst = max(worst, (lo - s) / (1.0 + abs(lo)))
        if s - hi > 0.0 and math.isfinite(hi):
            worst = max(worst, (s - hi) / (1.0 + abs(hi)))
    return worst


@njit(cache=True)
def qp_finish(ws, x: np.ndarray, rows: np.ndarray, bu: np.ndarray, bl: np.ndarray,  # type: ignore[no-untyped-def]
              tol: float) -> bool:
    """Check the solver's x against the hard rows (relative violation ≤ tol); if it holds, τ = M q̈ + N
    within ±τ_max (the solver's residue clipped, q̈ recomputed), slack and active-row counts, and the
    record. False (nothing written) if x is not finite or violates a row."""
    n = ws.N.shape[0]
    ip = ws.ipar
    n_in = ip[IP_N_IN]
    nv = x.shape[0]
    for c in range(nv):
        if not math.isfinite(x[c]):
            return False
    Cx = np.empty(n_in)
    viol = violation(x, n, n_in, rows, bu, bl, Cx)
    if viol > tol:
        return False
    for i in range(n):
        ws.qdd[i] = x[i]
    finish_torque(ws)
    half = (nv - n) // 2
    sl = 0.0
    for r in range(half):
        d = x[n + r] - x[n + half + r]
        sl += d * d
    active = 0
    mask = 0
    t0, b0, cap = ip[IP_TORQUE_ROW0], ip[IP_BARRIER_ROW0], ip[IP_CAPACITY]
    for r in range(n_in):
        cx = Cx[r]
        if min(abs(cx - bl[nv + r]), abs(cx - bu[nv + r])) <= 1e-6 * (1.0 + abs(cx)):
            active += 1
            if t0 >= 0 and t0 <= r < t0 + n:
                mask |= 1
            if b0 >= 0 and b0 <= r < b0 + cap:
                mask |= 2
    for i in range(n):
        if min(abs(x[i] - bl[i]), abs(x[i] - bu[i])) <= 1e-6:
            active += 1
    write_record(ws, ws.flags[FLAG_SINGULAR_TERMS] != 0)
    s = record_scalars(n, ws.a.shape[0])
    rec = ws.rec
    rec[s + R_SLACK] = math.sqrt(sl)
    rec[s + R_ACTIVE] = active
    rec[s + R_ACTIVE_MASK] = mask
    rec[s + R_VIOLATION] = viol
    return True


@njit(cache=True)
def finish_torque(ws) -> float:  # type: ignore[no-untyped-def]
    """τ = M q̈ + N, clipped to the torque window (±τ_max and the rate limit, :func:`torque_window`)
    where the drive limits are constraints (q̈ then follows from the clipped τ); returns the largest
    clip [N·m] (0 if none), also in the record, with the joints whose torque moved by its whole rate
    limit."""
    n = ws.N.shape[0]
    torque_of(ws)
    clip = 0.0
    hits = 0
    if ws.ipar[IP_TORQUE_ROW0] >= 0:
        dt = ws.fpar[FP_T] - ws.t_prev[0]
        for i in range(n):
            lo, hi = torque_window(ws, i)
            t = min(max(ws.tau[i], lo), hi)
            clip = max(clip, abs(t - ws.tau[i]))
            ws.tau[i] = t
            if dt > 0.0 and abs(t - ws.tau_prev[i]) >= ws.tau_rate[i] * dt * (1.0 - 1e-6):
                hits += 1
        if clip > 0.0:
            for i in range(n):
                ws.qdd[i] = ws.tau[i] - ws.N[i]
            chol_solve(ws.Lm, ws.qdd)
    s = record_scalars(n, ws.a.shape[0])
    ws.rec[s + R_CLIPPED] = clip
    ws.rec[s + R_RATE_HITS] = hits
    ws.flags[FLAG_CLIPPED] = 1 if clip > 0.0 else 0
    return clip


@njit(cache=True)
def finite_problem(H: np.ndarray, f: np.ndarray, rows: np.ndarray, bu: np.ndarray, bl: np.ndarray) -> bool:
    """No NaN anywhere and no infinity outside the bounds (where ±∞ means "no bound")."""
    acc = 0.0
    for i in range(H.shape[0]):
        acc += f[i] * 0.0
        for j in range(H.shape[1]):
            acc += H[i, j] * 0.0
    for i in range(rows.shape[0]):
        for j in range(rows.shape[1]):
            acc += rows[i, j] * 0.0
    if acc != 0.0:  # NaN (0·∞ or NaN itself)
        return False
    for i in range(bu.shape[0]):
        if math.isnan(bu[i]) or math.isnan(bl[i]):
            return False
    return True


@njit(cache=True)
def qp_rebuild(ws, H: np.ndarray, f: np.ndarray, rows: np.ndarray, bu: np.ndarray,  # type: ignore[no-untyped-def]
               bl: np.ndarray) -> int:
    """The QP's rows in another layout from this tick's terms (the relaxed layout after the hard one
    failed): 0, or 2 if the problem's data are not finite."""
    qp_build(ws, H, f, rows, bu, bl)
    return 0 if finite_problem(H, f, rows, bu, bl) else 2


@njit(cache=True)
def qp_terms_and_build(ws, H: np.ndarray, f: np.ndarray, rows: np.ndarray, bu: np.ndarray,  # type: ignore[no-untyped-def]
                       bl: np.ndarray) -> int:
    """The QP law's terms (the paper's, weighted) and its rows: 0; 1 if M is not positive definite;
    2 if the problem's data are not finite (no solver may be trusted with it)."""
    if not law_terms(ws, True):
        return 1
    qp_build(ws, H, f, rows, bu, bl)
    return 0 if finite_problem(H, f, rows, bu, bl) else 2


@njit(cache=True)
def native_solve(work: int, problem: int, result: int, flag: np.ndarray) -> int:
    """DAQP's update and solve on a workspace set up by :class:`qpctl.solvers.daqp_native.NativeDAQP`
    (the QP's arrays changed in place): DAQP's exit flag (> 0 solved)."""
    update_ldp(UPDATE_ALL, work, problem)
    daqp_solve(result, work)
    return flag[0]


@njit(cache=True)
def now_us(ts: np.ndarray) -> float:
    """The monotonic clock [µs]; ``ts`` is an int64 (2,) scratch for the timespec."""
    _clock_gettime(_MONOTONIC, ts.ctypes.data)
    return ts[0] * 1e6 + ts[1] * 1e-3


@njit(cache=True)
def qp_tick_native(ws, H: np.ndarray, f: np.ndarray, rows: np.ndarray, bu: np.ndarray,  # type: ignore[no-untyped-def]
                   bl: np.ndarray, work: int, problem: int, result: int, flag: np.ndarray, x: np.ndarray,
                   tol: float) -> int:
    """The whole QP tick after the state, on DAQP's C API: law terms, rows, solve, check, record
    (with the build and solve times [µs]). 0: solved and accepted; 1: M not positive definite;
    2: non-finite problem (not solved); 3: DAQP failed (its exit flag in ``flag[0]``); 4: x violates a
    hard row or is not finite."""
    ts = np.empty(2, np.int64)
    t0 = now_us(ts)
    code = qp_terms_and_build(ws, H, f, rows, bu, bl)
    t1 = now_us(ts)
    s = record_scalars(ws.N.shape[0], ws.a.shape[0])
    ws.rec[s + R_BUILD_US] = t1 - t0
    ws.rec[s + R_SOLVE_US] = 0.0
    if code != 0:
        return code
    ok = native_solve(work, problem, result, flag) > 0
    ws.rec[s + R_SOLVE_US] = now_us(ts) - t1
    if not ok:
        return 3
    if not qp_finish(ws, x, rows, bu, bl, tol):
        return 4
    ws.rec[s + R_ITERATIONS] = flag[1]
    return 0


@njit(cache=True)
def native_solve_finish(ws, rows: np.ndarray, bu: np.ndarray, bl: np.ndarray, work: int,  # type: ignore[no-untyped-def]
                        problem: int, result: int, flag: np.ndarray, x: np.ndarray, tol: float) -> int:
    """:func:`qp_tick_native` after its rows are built (the tick that set DAQP's workspace up)."""
    if native_solve(work, problem, result, flag) <= 0:
        return 3
    if not qp_finish(ws, x, rows, bu, bl, tol):
        return 4
    ws.rec[record_scalars(ws.N.shape[0], ws.a.shape[0]) + R_ITERATIONS] = flag[1]
    return 0


# ---------------------------------------------------------------------------------------------------
# Whole ticks in one call (after computeAllTerms), for scenes with closed-form shapes only
# ---------------------------------------------------------------------------------------------------
STATE_PYTHON = 5  # the state needs Python (python-fcl's pairs or a look-ahead drift) before the law


@njit(cache=True)
def _state_timed(ws, q: np.ndarray, v: np.ndarray, t: float, ts: np.ndarray) -> int:  # type: ignore[no-untyped-def]
    """:func:`state`, its time [µs] into the record; −1 overflow, STATE_PYTHON if Python must finish
    the state (python-fcl's pairs, or a look-ahead barrier drift), else 0."""
    t0 = now_us(ts)
    st = state(ws, q, v, t)
    ws.rec[record_scalars(ws.N.shape[0], ws.a.shape[0]) + R_STATE_US] = now_us(ts) - t0
    if st < 0:
        return -1
    if st > 0 or ws.cnt[CNT_LOOKAHEAD] > 0:
        return STATE_PYTHON
    return 0


@njit(cache=True)
def tick_closed_form(ws, q: np.ndarray, v: np.ndarray, t: float, weighted: bool) -> int:  # type: ignore[no-untyped-def]
    """State, law terms and closed form in one call: 0; −1 the dynamics overflow; 1 M not positive
    definite; STATE_PYTHON: the state is waiting for Python (then call :func:`closed_form_tick`)."""
    ts = np.empty(2, np.int64)
    code = _state_timed(ws, q, v, t, ts)
    if code != 0:
        return code
    t1 = now_us(ts)
    code = closed_form_tick(ws, weighted)
    ws.rec[record_scalars(ws.N.shape[0], ws.a.shape[0]) + R_BUILD_US] = now_us(ts) - t1
    return code


@njit(cache=True)
def tick_qp_native(ws, q: np.ndarray, v: np.ndarray, t: float, H: np.ndarray, f: np.ndarray,  # type: ignore[no-untyped-def]
                   rows: np.ndarray, bu: np.ndarray, bl: np.ndarray, work: int, problem: int, result: int,
                   flag: np.ndarray, x: np.ndarray, tol: float) -> int:
    """State and :func:`qp_tick_native` in one call: its codes, or −1 (the dynamics overflow) or
    STATE_PYTHON (the state is waiting for Python; then call :func:`qp_tick_native`)."""
    ts = np.empty(2, np.int64)
    code = _state_timed(ws, q, v, t, ts)
    if code != 0:
        return code
    return qp_tick_native(ws, H, f, rows, bu, bl, work, problem, result, flag, x, tol)


@njit(cache=True)
def min_distance(ws, t: float) -> float:  # type: ignore[no-untyped-def]
    """The least signed distance [m] between any link capsule and any sphere or capsule obstacle at
    t [s], every pair, no cutoff (a simulator's clearance; python-fcl's shapes are left to Python),
    from the joint placements only (after ``forwardKinematics``); the segments are left in ws."""
    segments = ws.segments
    for i in range(ws.cap_joint.shape[0]):
        _world_point(ws, ws.cap_joint[i], ws.cap_local[i, 0], segments[i, 0])
        _world_point(ws, ws.cap_joint[i], ws.cap_local[i, 1], segments[i, 1])
    obstacles_at(ws, t)
    best = np.inf
    for i in range(segments.shape[0]):
        ax, ay, az = segments[i, 0, 0], segments[i, 0, 1], segments[i, 0, 2]
        ux, uy, uz = segments[i, 1, 0] - ax, segments[i, 1, 1] - ay, segments[i, 1, 2] - az
        uu = ux * ux + uy * uy + uz * uz
        for j in range(ws.ob_kind.shape[0]):
            if ws.ob_kind[j] == KIND_FCL:
                continue
            sx, sy, sz = ws.ob_axis[j, 0], ws.ob_axis[j, 1], ws.ob_axis[j, 2]
            c0x, c0y, c0z = ws.ob_c[j, 0] - 0.5 * sx, ws.ob_c[j, 1] - 0.5 * sy, ws.ob_c[j, 2] - 0.5 * sz
            tl, to = segment_params(ax, ay, az, ux, uy, uz, uu, c0x, c0y, c0z, sx, sy, sz)
            wx = ax + tl * ux - (c0x + to * sx)
            wy = ay + tl * uy - (c0y + to * sy)
            wz = az + tl * uz - (c0z + to * sz)
            best = min(best, math.sqrt(wx * wx + wy * wy + wz * wz) - ws.cap_radius[i] - ws.ob_radius[j])
    return best


@njit(cache=True)
def min_self_distance(ws) -> float:  # type: ignore[no-untyped-def]
    """The least distance [m] between the self-collision pairs' capsules, from the segments that
    :func:`min_distance` left in ws (a simulator's self clearance)."""
    seg = ws.segments
    best = np.inf
    for r in range(ws.sc_pairs.shape[0]):
        i, j = ws.sc_pairs[r, 0], ws.sc_pairs[r, 1]
        a, c = seg[i, 0], seg[j, 0]
        ux, uy, uz = seg[i, 1, 0] - a[0], seg[i, 1, 1] - a[1], seg[i, 1, 2] - a[2]
        sx, sy, sz = seg[j, 1, 0] - c[0], seg[j, 1, 1] - c[1], seg[j, 1, 2] - c[2]
        tl, to = segment_params(a[0], a[1], a[2], ux, uy, uz, ux * ux + uy * uy + uz * uz, c[0], c[1], c[2],
                                sx, sy, sz)
        wx = a[0] + tl * ux - (c[0] + to * sx)
        wy = a[1] + tl * uy - (c[1] + to * sy)
        wz = a[2] + tl * uz - (c[2] + to * sz)
        best = min(best, math.sqrt(wx * wx + wy * wy + wz * wz) - ws.cap_radius[i] - ws.cap_radius[j])
    return best


# ---------------------------------------------------------------------------------------------------
# The task hard first, on DAQP's C API: the relaxed QP (with the task's slack) only where it differs
# ---------------------------------------------------------------------------------------------------
@njit(cache=True)
def penalty_exact(lam: np.ndarray, first: int, m: int, l1: float) -> bool:
    """Whether the hard QP's answer is the relaxed QP's too: every task row's multiplier (DAQP's
    λ of the equality rows, ``first`` … ``first + m``) within the ℓ₁ slack weight, |λ_i| ≤ l1 — the
    exact-penalty condition (:func:`qpctl.qp.penalty_is_exact`, which finds λ without the solver)."""
    for r in range(m):
        if not abs(lam[first + r]) <= l1:
            return False
    return True


@njit(cache=True)
def task_rows_hold(x: np.ndarray, rows: np.ndarray, bu: np.ndarray, n_in: int, m: int, tol: float) -> bool:
    """Whether the hard QP's x meets its task rows (rows ``n_in`` … ``n_in + m`` of ``rows``, equalities
    at ``bu``) within ``tol`` relative to the larger of 1, |b| and the row's |A_i|·|x|. DAQP may drop
    an equality row that is nearly dependent (the planar arm outstretched: the x row of J ~1e-5) and
    report the rest solved; :func:`qp_finish` checks the inequality rows only."""
    nv = x.shape[0]
    for r in range(n_in, n_in + m):
        ax = 0.0
        mag = 0.0
        for c in range(nv):
            ax += rows[r, c] * x[c]
            mag += abs(rows[r, c] * x[c])
        b = bu[nv + r]
        if not abs(ax - b) <= tol * max(1.0, abs(b), mag):
            return False
    return True


@njit(cache=True)
def qp_tick_native_hard_first(ws, Hh: np.ndarray, fh: np.ndarray, rowsh: np.ndarray,  # type: ignore[no-untyped-def]
                              buh: np.ndarray, blh: np.ndarray, workh: int, problemh: int, resulth: int,
                              flagh: np.ndarray, xh: np.ndarray, lamh: np.ndarray, Hr: np.ndarray, fr: np.ndarray,
                              rowsr: np.ndarray, bur: np.ndarray, blr: np.ndarray, workr: int, problemr: int,
                              resultr: int, flagr: np.ndarray, xr: np.ndarray, tol: float, l1: float,
                              try_hard: bool) -> tuple[int, int]:
    """The QP tick after the state with the task hard first (no slack variables: a smaller QP), its
    answer kept where the exact-penalty condition says the relaxed QP's is the same
    (:func:`penalty_exact`), the relaxed QP solved otherwise (or when not ``try_hard``). Returns
    (code, hard): code as :func:`qp_tick_native`'s, for the answer used; hard: −1 not tried, 0 the
    hard answer used, 3 DAQP failed on it, 4 rejected by the check of its rows (the task rows,
    :func:`task_rows_hold`, or the others, :func:`qp_finish`), 7 not the relaxed QP's answer."""
    ts = np.empty(2, np.int64)
    s = record_scalars(ws.N.shape[0], ws.a.shape[0])
    build = solve = 0.0
    hard = -1
    t0 = now_us(ts)
    if try_hard:
        code = qp_terms_and_build(ws, Hh, fh, rowsh, buh, blh)
        t1 = now_us(ts)
        build += t1 - t0
        if code != 0:
            ws.rec[s + R_BUILD_US], ws.rec[s + R_SOLVE_US] = build, 0.0
            return code, hard
        ok = native_solve(workh, problemh, resulth, flagh) > 0
        t2 = now_us(ts)
        solve += t2 - t1
        nvh = Hh.shape[0]
        n_in = ws.ipar[IP_N_IN]
        m = ws.a.shape[0]
        if not ok:
            hard = 3
        elif not task_rows_hold(xh, rowsh, buh, n_in, m, tol):
            hard = 4
        elif not penalty_exact(lamh, nvh + n_in, m, l1):
            hard = 7
        elif not qp_finish(ws, xh, rowsh, buh, blh, tol):
            hard = 4
        else:
            ws.rec[s + R_BUILD_US], ws.rec[s + R_SOLVE_US] = build, solve
            ws.rec[s + R_ITERATIONS] = flagh[1]
            return 0, 0
        t0 = now_us(ts)
        code = qp_rebuild(ws, Hr, fr, rowsr, bur, blr)
    else:
        code = qp_terms_and_build(ws, Hr, fr, rowsr, bur, blr)
    t1 = now_us(ts)
    build += t1 - t0
    ws.rec[s + R_BUILD_US], ws.rec[s + R_SOLVE_US] = build, solve
    if code != 0:
        return code, hard
    code = native_solve_finish(ws, rowsr, bur, blr, workr, problemr, resultr, flagr, xr, tol)
    ws.rec[s + R_SOLVE_US] = solve + now_us(ts) - t1  # the solve and the check of its answer
    return code, hard


@njit(cache=True)
def tick_qp_native_hard_first(ws, q: np.ndarray, v: np.ndarray, t: float, Hh: np.ndarray,  # type: ignore[no-untyped-def]
                              fh: np.ndarray, rowsh: np.ndarray, buh: np.ndarray, blh: np.ndarray, workh: int,
                              problemh: int, resulth: int, flagh: np.ndarray, xh: np.ndarray, lamh: np.ndarray,
                              Hr: np.ndarray, fr: np.ndarray, rowsr: np.ndarray, bur: np.ndarray, blr: np.ndarray,
                              workr: int, problemr: int, resultr: int, flagr: np.ndarray, xr: np.ndarray, tol: float,
                              l1: float, try_hard: bool) -> tuple[int, int]:
    """State and :func:`qp_tick_native_hard_first` in one call: its pair, or (−1 | STATE_PYTHON, −1)
    as :func:`tick_qp_native`."""
    ts = np.empty(2, np.int64)
    code = _state_timed(ws, q, v, t, ts)
    if code != 0:
        return code, -1
    return qp_tick_native_hard_first(ws, Hh, fh, rowsh, buh, blh, workh, problemh, resulth, flagh, xh, lamh, Hr, fr,
                                     rowsr, bur, blr, workr, problemr, resultr, flagr, xr, tol, l1, try_hard)
