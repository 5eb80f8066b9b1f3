"""Stage 1 of the tick, the rigid-body terms: M, N, the task points' x, ẋ, J, J̇q̇ (one per task
frame, rows stacked), the oriented frames' R, ω, α₀ and the link
capsules' world geometry, read from Pinocchio's arrays after :func:`qpctl.tick.rigid_pass`.

Pinocchio's data are bound once as numpy views (:func:`qpctl.tick.bind_pinocchio`): the joint
placements ``oMi``, the joints' q̈ = 0 accelerations in their own frames less gravity ``acc_gf``, the world
Jacobian columns ``Jt``, M's lower triangle ``Mt`` and ``nle``. From them: world points, point
Jacobians J_v − [p]× J_ω, and each capsule body's q̈ = 0 acceleration field a(p) = offset + K p,
which the pairs' drifts read (:mod:`qpctl.kernels.pairs`, :mod:`qpctl.kernels.self_pairs`).

References (``tests/test_kernels.py``): Pinocchio's crba, nonLinearEffects, getFrameJacobian and
getFrameClassicalAcceleration on probe frames of a separate model copy.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from qpctl.kernels.work import SJ_TASK, SV_A3, SV_P, SV_VEL


@njit(cache=True)
def _world_acceleration(ws, j: int, out: np.ndarray) -> None:  # type: ignore[no-untyped-def]
    """out (6,) = joint j's q̈ = 0 spatial acceleration in the world frame, at the world origin:
    (R a + p × R α, R α), a = a_gf + Rᵀg: Pinocchio's a_gf is the acceleration in a world that
    accelerates at −g (a uniform field, the same at every point), so R a = R a_gf + g, g read from the
    model itself (``ws.gravity``, a live view: a gravity changed after the workspace was built counts)."""
    P, A, g = ws.oMi, ws.acc_gf, ws.gravity
    for r in range(3):
        out[3 + r] = P[j, r] * A[j, 3] + P[j, r + 3] * A[j, 4] + P[j, r + 6] * A[j, 5]
        out[r] = P[j, r] * A[j, 0] + P[j, r + 3] * A[j, 1] + P[j, r + 6] * A[j, 2] + g[r]
    px, py, pz = P[j, 9], P[j, 10], P[j, 11]
    ax, ay, az = out[3], out[4], out[5]
    out[0] += py * az - pz * ay
    out[1] += pz * ax - px * az
    out[2] += px * ay - py * ax


@njit(cache=True)
def world_point(ws, j: int, lx: float, ly: float, lz: float) -> tuple[float, float, float]:  # type: ignore[no-untyped-def]
    """oMi[j] · (lx, ly, lz). Scalars in and out: no array view per call (a view of a row costs the
    tick an atomic reference increment and decrement, which inside the per-link and per-pair loops
    added up to microseconds)."""
    P = ws.oMi
    return (P[j, 0] * lx + P[j, 3] * ly + P[j, 6] * lz + P[j, 9],
            P[j, 1] * lx + P[j, 4] * ly + P[j, 7] * lz + P[j, 10],
            P[j, 2] * lx + P[j, 5] * ly + P[j, 8] * lz + P[j, 11])


@njit(cache=True)
def point_jacobian(ws, S: np.ndarray, si: int, P: np.ndarray, pi: int,  # type: ignore[no-untyped-def]
                   out: np.ndarray, oi: int) -> None:
    """out[oi] (3, n) = J_v − p × J_ω of the body whose joints are S[si] (world Jacobian columns),
    p = P[pi]: rows by index, not views (see :func:`world_point`)."""
    Jt = ws.Jt
    px, py, pz = P[pi, 0], P[pi, 1], P[pi, 2]
    for k in range(Jt.shape[0]):
        s = S[si, k]
        wx, wy, wz = Jt[k, 3] * s, Jt[k, 4] * s, Jt[k, 5] * s
        out[oi, 0, k] = Jt[k, 0] * s - (py * wz - pz * wy)
        out[oi, 1, k] = Jt[k, 1] * s - (pz * wx - px * wz)
        out[oi, 2, k] = Jt[k, 2] * s - (px * wy - py * wx)


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
    :func:`qpctl.tick.rigid_pass`); False if N is not finite (speeds so large that C(q, q̇)q̇ overflows)."""
    M, N, Mt, nle, Jt = ws.M, ws.N, ws.Mt, ws.nle, ws.Jt
    n = N.shape[0]
    for i in range(n):
        N[i] = nle[i]
        if not math.isfinite(nle[i]):
            return False
        for j in range(i + 1):
            M[i, j] = M[j, i] = Mt[i, j]
    acc = ws.w3  # scratch (≥ 6)
    vel, p, J3 = ws.sv[SV_VEL], ws.sv[SV_P], ws.sj[SJ_TASK]
    # task points: one per task frame (tk_*; the first is ee_*), their rows stacked in ws.axes' order
    axes, x, drift, J, xdot = ws.axes, ws.x, ws.drift, ws.J, ws.xdot
    a3 = ws.sv[SV_A3]
    frames = ws.tk_joint.shape[0]
    per = axes.shape[0] // frames
    tk_support, tk_local, sv, sj = ws.tk_support, ws.tk_local, ws.sv, ws.sj
    for tk in range(frames):
        p[0], p[1], p[2] = world_point(ws, ws.tk_joint[tk], tk_local[tk, 0], tk_local[tk, 1], tk_local[tk, 2])
        point_jacobian(ws, tk_support, tk, sv, SV_P, sj, SJ_TASK)
        for r in range(6):
            s = 0.0
            for k in range(n):
                s += Jt[k, r] * tk_support[tk, k] * v[k]
            vel[r] = s
        _world_acceleration(ws, ws.tk_joint[tk], acc)
        _classical_acceleration(vel, acc, p, a3)
        for r in range(tk * per, (tk + 1) * per):
            ax = axes[r]
            x[r] = p[ax]
            drift[r] = a3[ax]
            s = 0.0
            for k in range(n):
                J[r, k] = J3[ax, k]
                s += J3[ax, k] * v[k]
            xdot[r] = s
        if ws.ori_rows.shape[0]:  # an oriented frame's R, ω, α₀ for its orientation rows
            for f in range(ws.ori_tk.shape[0]):
                if ws.ori_tk[f] == tk:
                    _frame_rotation(ws, f)
                    for c in range(3):
                        ws.ee_w[f, c], ws.ee_w[f, 3 + c] = vel[3 + c], acc[3 + c]
    # capsules
    cap_joint, cap_local, cap_support = ws.cap_joint, ws.cap_local, ws.cap_support
    segments, body_vel = ws.segments, ws.body_vel
    link_jac, acc_off, acc_K = ws.link_jac, ws.acc_off, ws.acc_K
    for i in range(cap_joint.shape[0]):
        j = cap_joint[i]
        for e in range(2):
            x, y, z = world_point(ws, j, cap_local[i, e, 0], cap_local[i, e, 1], cap_local[i, e, 2])
            segments[i, e, 0], segments[i, e, 1], segments[i, e, 2] = x, y, z
        for r in range(6):  # the body's world spatial velocity: its support's Jacobian columns times q̇
            s = 0.0
            for k in range(n):
                s += Jt[k, r] * cap_support[i, k] * v[k]
            body_vel[i, r] = s
        for r in range(3):
            p[r] = 0.5 * (segments[i, 0, r] + segments[i, 1, r])
        point_jacobian(ws, cap_support, i, sv, SV_P, link_jac, i)
        # q̈ = 0 acceleration field of the body: a(p) = offset + K p, offset = a + ω × v, K = [α]× + [ω]×²
        _world_acceleration(ws, j, acc)
        vx, vy, vz, wx, wy, wz = body_vel[i, 0], body_vel[i, 1], body_vel[i, 2], body_vel[i, 3], body_vel[i, 4], body_vel[i, 5]
        acc_off[i, 0] = acc[0] + wy * vz - wz * vy
        acc_off[i, 1] = acc[1] + wz * vx - wx * vz
        acc_off[i, 2] = acc[2] + wx * vy - wy * vx
        acc_K[i, 0, 0], acc_K[i, 0, 1], acc_K[i, 0, 2] = -(wy * wy + wz * wz), -acc[5] + wx * wy, acc[4] + wx * wz
        acc_K[i, 1, 0], acc_K[i, 1, 1], acc_K[i, 1, 2] = acc[5] + wx * wy, -(wx * wx + wz * wz), -acc[3] + wy * wz
        acc_K[i, 2, 0], acc_K[i, 2, 1], acc_K[i, 2, 2] = -acc[4] + wx * wz, acc[3] + wy * wz, -(wx * wx + wy * wy)
    return True


@njit(cache=True)
def _frame_rotation(ws, f: int) -> None:  # type: ignore[no-untyped-def]
    """ws.ee_R[f] = oriented task frame f's world rotation (its joint's, times the frame's in the joint)."""
    P, Rl, R = ws.oMi, ws.ee_rot[f], ws.ee_R[f]
    j = ws.tk_joint[ws.ori_tk[f]]
    for r in range(3):
        for c in range(3):
            R[r, c] = P[j, r] * Rl[0, c] + P[j, r + 3] * Rl[1, c] + P[j, r + 6] * Rl[2, c]


@njit(cache=True)
def body_point(ws, i: int, px: float, py: float, pz: float) -> tuple[float, float, float, float, float, float]:  # type: ignore[no-untyped-def]
    """Velocity and q̈ = 0 acceleration (vx, vy, vz, ax, ay, az) of the point (px, py, pz) fixed to
    capsule i's body."""
    bv, K, o = ws.body_vel, ws.acc_K, ws.acc_off
    return (bv[i, 0] + bv[i, 4] * pz - bv[i, 5] * py,
            bv[i, 1] + bv[i, 5] * px - bv[i, 3] * pz,
            bv[i, 2] + bv[i, 3] * py - bv[i, 4] * px,
            o[i, 0] + K[i, 0, 0] * px + K[i, 0, 1] * py + K[i, 0, 2] * pz,
            o[i, 1] + K[i, 1, 0] * px + K[i, 1, 1] * py + K[i, 1, 2] * pz,
            o[i, 2] + K[i, 2, 0] * px + K[i, 2, 1] * py + K[i, 2, 2] * pz)
