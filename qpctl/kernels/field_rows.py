"""The depth map's barrier rows in the compiled tick: the field's pairs and their rows on q̈.

The workspace holds the newest :class:`~qpctl.perception.snapshot.MapSnapshot`'s grids (read-only
views, swapped by :func:`set_field` when a new snapshot arrives: no copy). :func:`field_rows` samples
each link capsule's axis in both channels in one pass (:func:`qpctl.kernels.field_samples.field_samples`:
per channel, :func:`qpctl.kernels.field.field_pairs`' nearest one or two points, smoothed), then writes
each pair as a row of the obstacle barrier's form with the static map's ḣ = nᵀJ_p q̇ and the
rigid-point drift nᵀJ̇_p q̇ (the witness point's Jacobian and acceleration from the capsule body's,
:func:`qpctl.kernels.rigid.point_jacobian`):

* rigid (channel 0): nᵀJ_p q̈ ≥ −k₁ḣ − k₀(d − m) − nᵀJ̇_p q̇, m the rigid margin
  (d_safe + √3/2·voxel + depth noise); inside the margin (d < m: a voxel a new frame put within
  the margin's uncertainty) away no faster than v_s, nᵀJ_p q̈ ≥ −k_r(ḣ − min(k₀/k₁ (m − d), v_s))
  − nᵀJ̇_p q̇ (k_r the recovery gain, ``perception.recovery_gain``), and at most ℓ − ρ(ℓ − ℓ₋),
  ℓ₋ … ℓ the range of nᵀJ_p q̈ over this tick's torque window (:func:`qpctl.kernels.drives.row_range`),
  ρ = :data:`REACH_SHARE` — the recovery asks no more than the drives can give in one tick (without it the QP was infeasible there, tick after tick,
  under a torque-rate limit);
* soft (channel 1): nᵀJ_p q̈ ≥ −k₁(ḣ + v_s) − k₀ max(d − m_s, 0) − nᵀJ̇_p q̇, v_s = ``soft_speed``,
  m_s the soft margin (``perception.soft_margin``).

Then two soft speed rows per link (:func:`speed_rows`), for the points of
:func:`qpctl.kernels.field.speed_points` (where the link may be inside a leaf, or the nearest to one;
found in the same pass, from the soft channel's samples): the point's velocity a horizon h ahead,
w⁺ = J_p q̇ + (J_p q̈ + J̇_p q̇)h, along the direction u of its velocity now no faster than the bound b:
−uᵀJ_p q̈ ≥ (uᵀJ_p q̇ − b)/h + uᵀJ̇_p q̇.

A pair farther than the cutoff, or without a normal, is an inactive row (zero, −∞), and so is a
speed row without a point (inf bound). Reference:
:class:`qpctl.perception.rows.FieldBarrier` (the Python path), in ``tests/test_field_rows.py``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from qpctl.kernels.borrow import borrow
from qpctl.kernels.codes import (
    FP_FD_CUT,
    FP_FD_HORIZON,
    FP_FD_K0,
    FP_FD_K1,
    FP_FD_KR,
    FP_FD_MARGIN,
    FP_FD_SMARGIN,
    FP_FD_TRUNC,
    FP_FD_VMARGIN,
    FP_FD_VOXEL,
    FP_FD_VS,
    FP_FD_VSLOPE,
    IP_FD_RPL,
    IP_FD_SAMPLES,
)
from qpctl.kernels.drives import REACH_SHARE, row_range
from qpctl.kernels.field_samples import field_samples
from qpctl.kernels.rigid import point_jacobian


@njit(cache=True)
def set_field(ws, dist: np.ndarray, grad: np.ndarray, pairs: np.ndarray) -> None:  # type: ignore[no-untyped-def]
    """The tick reads these grids from now on: ``dist`` (2, nx, ny, nz), ``grad`` (2, nx, ny, nz, 3) and
    ``pairs`` (nx, ny, nz, 2), float32, read-only (a snapshot's own arrays)."""
    ws.fd_dist = borrow(dist)  # (borrowed, as every workspace array: Python's Workspace keeps the snapshot)
    ws.fd_grad = borrow(grad)
    ws.fd_pairs = borrow(pairs)


@njit(cache=True)
def field_pairs_both(ws) -> None:  # type: ignore[no-untyped-def]
    """Both channels' pairs for the capsules at this tick into fd_d, fd_n, fd_p (channel-major), and the
    soft channel's speed points into fd_vp, fd_vu, fd_vb, fd_vd: one pass along each axis
    (:func:`qpctl.kernels.field_samples.field_samples`, the numbers of the separate kernels)."""
    fp = ws.fpar
    field_samples(ws.segments, ws.cap_radius, ws.fd_dist, ws.fd_pairs, ws.fd_grad, ws.fd_origin, fp[FP_FD_VOXEL], fp[FP_FD_TRUNC],
                  ws.ipar[IP_FD_SAMPLES], ws.ipar[IP_FD_RPL], True, ws.body_vel, fp[FP_FD_VS], fp[FP_FD_VSLOPE],
                  fp[FP_FD_VMARGIN], fp[FP_FD_CUT], ws.fd_ds, ws.fd_d, ws.fd_n, ws.fd_p, ws.fd_s, ws.fd_vp,
                  ws.fd_vu, ws.fd_vb, ws.fd_vd)


@njit(cache=True)
def speed_rows(ws, C: np.ndarray, lower: np.ndarray) -> None:  # type: ignore[no-untyped-def]
    """The soft speed rows (module docstring) into ``C`` (2L, n) and ``lower`` (2L,), for the speed points
    :func:`field_pairs_both` wrote this tick."""
    n = ws.N.shape[0]
    fp = ws.fpar
    h = fp[FP_FD_HORIZON]
    Jp = ws.fd_vjac
    Jp3 = Jp.reshape((1, 3, n))  # (the scratch as point_jacobian's out[0])
    # the arrays the loop reads, held once (rows by index: see qpctl.kernels.rigid.world_point)
    fd_vb, fd_vp, fd_vu, cap_support, acc_K, acc_off, v = ws.fd_vb, ws.fd_vp, ws.fd_vu, ws.cap_support, ws.acc_K, \
        ws.acc_off, ws.v
    for r in range(C.shape[0]):
        b = fd_vb[r]
        if not (b < math.inf):
            for c in range(n):
                C[r, c] = 0.0
            lower[r] = -math.inf
            continue
        link = r // 2
        point_jacobian(ws, cap_support, link, fd_vp, r, Jp3, 0)
        p0, p1, p2 = fd_vp[r, 0], fd_vp[r, 1], fd_vp[r, 2]
        ux, uy, uz = fd_vu[r, 0], fd_vu[r, 1], fd_vu[r, 2]
        drift = 0.0
        for c in range(3):
            drift += fd_vu[r, c] * (acc_off[link, c] + acc_K[link, c, 0] * p0 + acc_K[link, c, 1] * p1
                                    + acc_K[link, c, 2] * p2)
        w = 0.0
        for c in range(n):
            val = ux * Jp[0, c] + uy * Jp[1, c] + uz * Jp[2, c]
            C[r, c] = -val
            w += val * v[c]
        lower[r] = (w - b) / h + drift


@njit(cache=True)
def field_rows(ws, C: np.ndarray, lower: np.ndarray) -> None:  # type: ignore[no-untyped-def]
    """The field's rows (module docstring) into ``C`` (R + 2L, n) and ``lower`` (R + 2L,): the R pair
    rows (both channels), then the soft speed rows."""
    R = ws.fd_d.shape[0]
    field_pairs_both(ws)
    speed_rows(ws, C[R:], lower[R:])
    n = ws.N.shape[0]
    L = ws.segments.shape[0]
    rpl = ws.ipar[IP_FD_RPL]
    k = L * rpl
    cut, margin, vs = ws.fpar[FP_FD_CUT], ws.fpar[FP_FD_MARGIN], ws.fpar[FP_FD_VS]
    k0, k1, ms, kr = ws.fpar[FP_FD_K0], ws.fpar[FP_FD_K1], ws.fpar[FP_FD_SMARGIN], ws.fpar[FP_FD_KR]
    fd_n, fd_d, fd_p, fd_jac, fd_drift = ws.fd_n, ws.fd_d, ws.fd_p, ws.fd_jac, ws.fd_drift  # (held, as in speed_rows)
    cap_support, acc_K, acc_off, v = ws.cap_support, ws.acc_K, ws.acc_off, ws.v
    for r in range(R):
        nx, ny, nz = fd_n[r, 0], fd_n[r, 1], fd_n[r, 2]
        d = fd_d[r]
        if not (d < cut) or (nx == 0.0 and ny == 0.0 and nz == 0.0):
            for c in range(n):
                C[r, c] = 0.0
            lower[r] = -math.inf
            continue
        link = (r % k) // rpl
        point_jacobian(ws, cap_support, link, fd_p, r, fd_jac, r)
        p0, p1, p2 = fd_p[r, 0], fd_p[r, 1], fd_p[r, 2]
        drift = 0.0
        for c in range(3):
            a = acc_off[link, c] + acc_K[link, c, 0] * p0 + acc_K[link, c, 1] * p1 + acc_K[link, c, 2] * p2
            fd_drift[r, c] = a
            drift += fd_n[r, c] * a
        hdot = 0.0
        for c in range(n):
            val = nx * fd_jac[r, 0, c] + ny * fd_jac[r, 1, c] + nz * fd_jac[r, 2, c]
            C[r, c] = val
            hdot += val * v[c]
        if r >= k:  # soft: the approach no faster than v_s; contact allowed
            lower[r] = -k1 * (hdot + vs) - k0 * max(d - ms, 0.0) - drift
        elif d < margin:  # inside the margin: away at no more than v_s, no more than the drives give
            lower[r] = -kr * (hdot - min(k0 / k1 * (margin - d), vs)) - drift
            lo, hi = row_range(ws, C[r], ws.w1)
            cap = hi - REACH_SHARE * (hi - lo)
            if cap < lower[r]:  # noqa: PLR1730 (False for a NaN cap, no torque limits: min() would take it)
                lower[r] = cap
        else:
            lower[r] = -k1 * hdot - k0 * (d - margin) - drift
