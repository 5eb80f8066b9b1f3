"""Stage 2 of the tick, the scene and the reference at t: the moving obstacles' centres,
velocities and accelerations, and x_d, ẋ_d, ẍ_d of the path (straight segments with quintic timing,
``WaypointPath``; the orientation rows of a ``PosePath``).

References: ``Obstacle.position_at`` / ``velocity_at`` / ``acceleration_at``, ``WaypointPath``'s and
``PosePath``'s own evaluation, :func:`qpctl.orientation.orientation_reference`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from qpctl.kernels.codes import FP_TS, IP_TIME_SCALED
from qpctl.kernels.rotation import exp3, log3, matmul3, matmul3_bt


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
    """The orientation rows (qpctl.orientation) on path segment k at s, ṡ [1/s], s̈ [1/s²], oriented
    frame after frame: R_d, ω_d, ω̇_d of the PosePath, then each row's x, ẋ, J, J̇q̇ (from the frame's
    R, ω, α₀ of :func:`rigid_terms`) and x_d, ẋ_d, ẍ_d."""
    for f in range(ws.ori_tk.shape[0]):
        _frame_reference(ws, f, k, s, ds, dds)


@njit(cache=True)
def _frame_reference(ws, f: int, k: int, s: float, ds: float, dds: float) -> None:  # type: ignore[no-untyped-def]
    """:func:`orientation_reference`'s rows of oriented frame f."""
    th = ws.rot_theta[f, k]
    wd, ad, sv = np.empty(3), np.empty(3), np.empty(3)
    for c in range(3):
        wd[c] = ds * th[c]
        ad[c] = dds * th[c]
        sv[c] = s * th[c]
    E, Rd = np.empty((3, 3)), np.empty((3, 3))
    exp3(sv, E)
    matmul3(E, ws.rot_pts[f, k], Rd)  # R_d = exp(s θ_k) R_k
    R, Jt, support = ws.ee_R[f], ws.Jt, ws.tk_support[ws.ori_tk[f]]
    n, m_p = Jt.shape[0], ws.axes.shape[0]
    w, a0 = ws.ee_w[f, :3], ws.ee_w[f, 3:]
    u, err = np.empty(3), np.empty(3)
    first, last = ws.ori_start[f], ws.ori_start[f + 1]
    if ws.ori_rows[first] < 3:  # pose: world axes, x = 0, x_d = log(R_d Rᵀ)
        matmul3_bt(Rd, R, E)
        log3(E, err)
        for i in range(first, last):
            r, c = m_p + i, ws.ori_rows[i]
            ws.x[r], ws.xdot[r], ws.drift[r] = 0.0, w[c], a0[c]
            for j in range(n):
                ws.J[r, j] = Jt[j, 3 + c] * support[j]
            ws.ref[0, r], ws.ref[1, r], ws.ref[2, r] = err[c], wd[c], ad[c]
        return
    # approach: y_k = v_k·z with z = R c, v_k = R_d b_k; J = (z × v_k)ᵀJ_ω, exact (qpctl.orientation)
    z, v, zw, vd, zdot, t1 = np.empty(3), np.empty(3), np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    _rotate(R, ws.ori_axis[f], z)
    _cross(w, z, zdot)  # ż = ω × z
    dw = np.empty(3)
    for c in range(3):
        dw[c] = w[c] - wd[c]
    for i in range(first, last):
        r = m_p + i
        _rotate(Rd, ws.ori_basis[f, ws.ori_rows[i] - 3], v)
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
    the orientation rows' (PosePath, after :func:`rigid_terms`). A time-scaled path
    (:class:`qpctl.paths.TimeScaledPath` over a WaypointPath; IP_TIME_SCALED) is evaluated at its own
    time s = s₀ + κ·max(0, t − t₀), with ẋ_d = κ x'(s) and ẍ_d = κ² x''(s) + κ̇ x'(s) (κ² x''(s) alone
    where κ̇ is not finite), as its ``__call__`` does."""
    scaled = ws.ipar[IP_TIME_SCALED] != 0
    if scaled:
        fp = ws.fpar
        kappa, rate = fp[FP_TS + 1], fp[FP_TS + 2]
        if not np.isfinite(rate):  # (κ² x'' alone)
            rate = 0.0
        t = fp[FP_TS] + kappa * max(0.0, t - fp[FP_TS + 3])
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
        if scaled:
            xd = ws.ref[1, r]
            ws.ref[1, r] = kappa * xd
            ws.ref[2, r] = kappa * kappa * ws.ref[2, r] + rate * xd
    if ws.ori_rows.shape[0]:
        orientation_reference(ws, k, s, ds / T, dds / T**2)
