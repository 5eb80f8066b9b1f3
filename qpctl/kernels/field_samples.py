"""The tick's field lookups in one pass: both channels' pairs and the soft speed points.

:func:`field_samples` writes what :func:`qpctl.kernels.field.field_pairs` writes for channel 0 and for
channel 1, and what :func:`qpctl.kernels.field.speed_points` writes for channel 1 — the same numbers,
operation for operation — from one walk along each link's axis. The separate kernels sample every
axis three times (the soft channel twice, at the same points with the same interpolation); here the
two channels' grids, which share one lattice (shape, origin, voxel), are read at each sample from one
cell (:func:`qpctl.kernels.field.cell`, computed once for both) in the snapshot's ``pairs`` layout
(nx, ny, nz, 2) — a voxel's two values in one 8-byte word, 8 reads a sample instead of 16 —, and the soft
channel's samples serve both its pairs and its speed points. The arithmetic is field.py's own
(:func:`~qpctl.kernels.field.cell_distance`'s lerps, :func:`~qpctl.kernels.field.pair_row`), so the
numbers are the same by construction.

The per-link early-out (the midpoint farther than the truncation plus half the axis) is kept as the
separate kernels have it, per channel, so that the outputs stay theirs; on a snapshot's field, which is
capped at the truncation (:mod:`qpctl.kernels.edt`), it cannot hold unless half the axis is shorter
than float32's rounding of the truncation (~10⁻⁸ m), so there every link is sampled.

Held to the separate kernels on random fields and capsules in ``tests/test_field.py``; used by
:func:`qpctl.kernels.field_rows.field_pairs_both`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from qpctl.kernels.borrow import borrow
from qpctl.kernels.field import (
    _lerp8,
    _refine,
    cell,
    pair_row,
    ranked_excess,
    second_minimum,
    speed_row,
)


@njit(cache=True, nogil=True, inline="always")
def distance_both(pairs: np.ndarray, origin: np.ndarray, voxel: float, truncation: float, x: float, y: float,
                  z: float) -> tuple[float, float]:
    """Both channels' trilinear distances at (x, y, z) [m] from ``pairs`` (nx, ny, nz, 2): one cell, each
    corner's two values read together, :func:`~qpctl.kernels.field.cell_distance`'s lerps per channel.
    Outside the bounds the truncation, chosen after the reads (a select, no branch: the cell is clamped)."""
    nx, ny, nz, _ = pairs.shape
    inside, i, j, k, i1, j1, k1, tx, ty, tz = cell(nx, ny, nz, origin, voxel, x, y, z)
    a0, a1 = pairs[i, j, k, 0], pairs[i, j, k, 1]
    b0, b1 = pairs[i1, j, k, 0], pairs[i1, j, k, 1]
    c0, c1 = pairs[i, j1, k, 0], pairs[i, j1, k, 1]
    d0, d1 = pairs[i1, j1, k, 0], pairs[i1, j1, k, 1]
    e0, e1 = pairs[i, j, k1, 0], pairs[i, j, k1, 1]
    f0, f1 = pairs[i1, j, k1, 0], pairs[i1, j, k1, 1]
    g0, g1 = pairs[i, j1, k1, 0], pairs[i, j1, k1, 1]
    h0, h1 = pairs[i1, j1, k1, 0], pairs[i1, j1, k1, 1]
    r = _lerp8(a0, b0, c0, d0, e0, f0, g0, h0, tx, ty, tz)
    s = _lerp8(a1, b1, c1, d1, e1, f1, g1, h1, tx, ty, tz)
    return (r if inside else truncation), (s if inside else truncation)


@njit(cache=True, nogil=True)
def field_samples(segments: np.ndarray, radii: np.ndarray, dist: np.ndarray, pairs: np.ndarray, grad: np.ndarray,
                  origin: np.ndarray, voxel: float, truncation: float, samples: int, rows: int, smooth: bool,
                  body_vel: np.ndarray, soft_speed: float, gain: float, vmargin: float, cutoff: float,
                  ds: np.ndarray, out_d: np.ndarray, out_n: np.ndarray, out_p: np.ndarray,
                  out_s: np.ndarray, out_vp: np.ndarray, out_vu: np.ndarray, out_vb: np.ndarray,
                  out_vd: np.ndarray) -> None:
    """Both channels' pairs and the soft channel's speed points (module docstring): ``dist`` (2, nx, ny,
    nz) and ``grad`` (2, nx, ny, nz, 3); ``out_d`` (2·L·rows,), ``out_n``, ``out_p`` (2·L·rows, 3) and
    ``out_s`` (2·L·rows,) channel-major, each channel's block as :func:`~qpctl.kernels.field.field_pairs`
    writes it; ``pairs`` (nx, ny, nz, 2) is ``dist`` with the channels side by side (the samples read it,
    the pairs' refined points ``dist`` and ``grad``: :attr:`qpctl.perception.MapSnapshot.pairs`);
    ``out_vp``, ``out_vu`` (2L, 3), ``out_vb``, ``out_vd`` (2L,) as
    :func:`~qpctl.kernels.field.speed_points` writes them for channel 1 (``body_vel``, ``soft_speed``,
    ``gain``, ``vmargin``, ``cutoff`` its arguments). ``ds`` (2, samples) is scratch."""
    L = segments.shape[0]
    # every array borrowed (qpctl.kernels.borrow): the helpers below take them without reference counts
    segments, radii, dist, grad, origin, body_vel, ds = (borrow(segments), borrow(radii), borrow(dist), borrow(grad),
                                                         borrow(origin), borrow(body_vel), borrow(ds))
    pairs = borrow(pairs)
    out_d, out_n, out_p, out_s = borrow(out_d), borrow(out_n), borrow(out_p), borrow(out_s)
    out_vp, out_vu, out_vb, out_vd = borrow(out_vp), borrow(out_vu), borrow(out_vb), borrow(out_vd)
    ds_r, ds_s = ds[0], ds[1]
    for l in range(L):
        r = radii[l]
        ax, ay, az = segments[l, 0, 0], segments[l, 0, 1], segments[l, 0, 2]
        ux, uy, uz = segments[l, 1, 0] - ax, segments[l, 1, 1] - ay, segments[l, 1, 2] - az
        for k in range(2):
            out_vb[2 * l + k] = math.inf
            out_vd[2 * l + k] = truncation - r
            out_vp[2 * l + k, 0], out_vp[2 * l + k, 1], out_vp[2 * l + k, 2] = ax, ay, az
            out_vu[2 * l + k, 0] = out_vu[2 * l + k, 1] = out_vu[2 * l + k, 2] = 0.0
        # the separate kernels' early-out, per channel (module docstring)
        half = 0.5 * math.sqrt(ux * ux + uy * uy + uz * uz)
        mx, my, mz = ax + 0.5 * ux, ay + 0.5 * uy, az + 0.5 * uz
        m0, m1 = distance_both(pairs, origin, voxel, truncation, mx, my, mz)
        far0, far1 = m0 >= truncation + half, m1 >= truncation + half
        for c in range(2):
            if (far0 if c == 0 else far1):
                for rr in range(rows):
                    row = (c * L + l) * rows + rr
                    out_d[row] = truncation - r
                    out_s[row] = 0.5
                    out_n[row, 0] = out_n[row, 1] = out_n[row, 2] = 0.0
                    out_p[row, 0], out_p[row, 1], out_p[row, 2] = mx, my, mz
        if far0 and far1:
            continue
        vx, vy, vz = body_vel[l, 0], body_vel[l, 1], body_vel[l, 2]
        wx, wy, wz = body_vel[l, 3], body_vel[l, 4], body_vel[l, 5]
        wn = math.sqrt(wx * wx + wy * wy + wz * wz)
        best0 = best1 = 0
        best, second = -1, -1
        e1 = e2 = -math.inf
        for j in range(samples):
            f = j / (samples - 1.0)
            px, py, pz = ax + f * ux, ay + f * uy, az + f * uz
            t0, t1 = distance_both(pairs, origin, voxel, truncation, px, py, pz)
            ds_r[j] = t0
            ds_s[j] = t1
            if t0 < ds_r[best0]:
                best0 = j
            if t1 < ds_s[best1]:
                best1 = j
            if far1:
                continue
            d = t1 - r
            if d + r >= truncation or d >= cutoff:
                continue
            excess = ranked_excess(px, py, pz, r, vx, vy, vz, wx, wy, wz, wn, d, soft_speed, gain, vmargin, e2)
            if excess > e1:
                second, e2 = best, e1
                best, e1 = j, excess
            elif excess > e2:
                second, e2 = j, excess
        # the pairs, channel by channel (field_pairs' second minimum)
        for c in range(2):
            if (far0 if c == 0 else far1):
                continue
            dc = ds_r if c == 0 else ds_s
            b = best0 if c == 0 else best1
            row0 = (c * L + l) * rows
            pair_row(segments, radii, l, _refine(dc, b, samples, smooth), dist[c], grad[c], origin, voxel,
                     truncation, smooth, row0, out_d, out_n, out_p, out_s)
            if rows < 2:
                continue
            sec = second_minimum(dc, b, samples, truncation)
            if sec < 0:  # one minimum only: the second row repeats the first's point, inactive
                out_d[row0 + 1] = truncation - r
                out_s[row0 + 1] = out_s[row0]
                out_n[row0 + 1, 0] = out_n[row0 + 1, 1] = out_n[row0 + 1, 2] = 0.0
                out_p[row0 + 1, 0], out_p[row0 + 1, 1], out_p[row0 + 1, 2] = out_p[row0, 0], out_p[row0, 1], out_p[row0, 2]
            else:
                pair_row(segments, radii, l, _refine(dc, sec, samples, smooth), dist[c], grad[c], origin, voxel,
                         truncation, smooth, row0 + 1, out_d, out_n, out_p, out_s)
        if far1:
            continue
        # the speed points (speed_points' second loop)
        for k in range(2):
            j = best if k == 0 else second
            if j < 0:
                continue
            f = j / (samples - 1.0)
            speed_row(ax + f * ux, ay + f * uy, az + f * uz, r, vx, vy, vz, wx, wy, wz, ds_s[j] - r, soft_speed, gain,
                      vmargin, 2 * l + k, out_vp, out_vu, out_vb, out_vd)
