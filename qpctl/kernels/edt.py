"""Compiled exact Euclidean distance transform of a voxel grid, truncated, and its gradient.

Felzenszwalb & Huttenlocher, *Distance Transforms of Sampled Functions* (Theory of Computing 8, 2012):
the squared distance to the nearest occupied voxel centre is separable — a 1-D distance along z, then
the lower envelope of parabolas along y over the result, then along x — O(voxels) and exact below
the truncation. It is tested
against scipy's ``distance_transform_edt`` (``tests/test_field.py``) and measured against it and the
``edt`` package in ``benchmarks/perception.py``; it is used because it is faster on the map's grids
and, being ``nogil``, lets the map worker's thread run beside the control loop (scipy's holds the
interpreter's lock).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

BIG = 1e20  # "no occupied voxel on this line": finite so that the envelope's arithmetic stays exact


@njit(cache=True, nogil=True)
def _envelope(f: np.ndarray, n: int, cap: float, out: np.ndarray, v: np.ndarray, zz: np.ndarray) -> None:
    """out[q] = min_p (q − p)² + f[p] over p < n (the lower envelope of the parabolas rooted at f),
    where that is below ``cap``, else ≥ cap. A parabola with f[p] ≥ cap is never below it and is left
    out of the envelope: on a sparse map most lines hold none or a few (the truncation's gain)."""
    k = -1
    for q in range(n):
        fq = f[q]
        if fq >= cap:
            continue
        fq += q * q
        if k < 0:
            k = 0
            v[0] = q
            zz[0] = -math.inf
            zz[1] = math.inf
            continue
        p = v[k]
        s = (fq - (f[p] + p * p)) / (2.0 * (q - p))
        while s <= zz[k]:  # never for k = 0 (zz[0] = −inf; s is finite)
            k -= 1
            p = v[k]
            s = (fq - (f[p] + p * p)) / (2.0 * (q - p))
        k += 1
        v[k] = q
        zz[k] = s
        zz[k + 1] = math.inf
    if k < 0:
        for q in range(n):
            out[q] = BIG
        return
    k = 0
    for q in range(n):
        while zz[k + 1] < q:
            k += 1
        p = v[k]
        out[q] = (q - p) * (q - p) + f[p]


@njit(cache=True, nogil=True)
def squared_edt(occupied: np.ndarray, cap: float, out: np.ndarray) -> None:
    """``out`` (nx, ny, nz) float64: the squared distance [voxels²] from each voxel centre to the
    nearest occupied one (``occupied`` (nx, ny, nz) bool) where it is below ``cap`` [voxels²]; ≥ cap
    (BIG where nothing is near) elsewhere. The first pass runs along the contiguous axis z (two sweeps,
    exact for a binary line), then the envelopes along y and x."""
    nx, ny, nz = occupied.shape
    n = max(nx, ny, nz)
    f = np.empty(n)
    g = np.empty(n)
    v = np.empty(n, dtype=np.int64)
    zz = np.empty(n + 1)
    for i in range(nx):
        for j in range(ny):
            d = BIG
            for k in range(nz):
                if occupied[i, j, k]:
                    d = 0.0
                elif d < BIG:
                    d += 1.0
                out[i, j, k] = d
            d = BIG
            for k in range(nz - 1, -1, -1):
                if occupied[i, j, k]:
                    d = 0.0
                elif d < BIG:
                    d += 1.0
                x = min(d, out[i, j, k])
                out[i, j, k] = x * x if x < BIG else BIG
    for i in range(nx):
        for k in range(nz):
            for j in range(ny):
                f[j] = out[i, j, k]
            _envelope(f, ny, cap, g, v, zz)
            for j in range(ny):
                out[i, j, k] = g[j]
    for j in range(ny):
        for k in range(nz):
            for i in range(nx):
                f[i] = out[i, j, k]
            _envelope(f, nx, cap, g, v, zz)
            for i in range(nx):
                out[i, j, k] = g[i]


@njit(cache=True, nogil=True)
def distance_field(occupied: np.ndarray, voxel: float, truncation: float, work: np.ndarray,
                   dist: np.ndarray) -> int:
    """``dist`` (nx, ny, nz) float32 [m]: the Euclidean distance from each voxel centre to the nearest
    occupied voxel centre, capped at ``truncation`` [m] (everywhere, when nothing is occupied).
    ``work`` (nx, ny, nz) float64 is scratch. Returns the number of occupied voxels."""
    count = 0
    flat = occupied.reshape(-1)
    for i in range(flat.shape[0]):
        if flat[i]:
            count += 1
    d = dist.reshape(-1)
    if count == 0:
        d[:] = truncation
        return 0
    cap = (truncation / voxel) ** 2
    squared_edt(occupied, cap, work)
    w = work.reshape(-1)
    for i in range(w.shape[0]):
        d[i] = truncation if w[i] >= cap else math.sqrt(w[i]) * voxel
    return count


@njit(cache=True, nogil=True)
def gradient(dist: np.ndarray, voxel: float, grad: np.ndarray) -> None:
    """``grad`` (nx, ny, nz, 3) float32: ∇dist by central differences [m/m] (one-sided at the grid's
    faces); zero where the field is flat at its truncation."""
    nx, ny, nz = dist.shape
    for i in range(nx):
        i0, i1 = max(i - 1, 0), min(i + 1, nx - 1)
        for j in range(ny):
            j0, j1 = max(j - 1, 0), min(j + 1, ny - 1)
            for k in range(nz):
                k0, k1 = max(k - 1, 0), min(k + 1, nz - 1)
                grad[i, j, k, 0] = (dist[i1, j, k] - dist[i0, j, k]) / ((i1 - i0) * voxel) if i1 > i0 else 0.0
                grad[i, j, k, 1] = (dist[i, j1, k] - dist[i, j0, k]) / ((j1 - j0) * voxel) if j1 > j0 else 0.0
                grad[i, j, k, 2] = (dist[i, j, k1] - dist[i, j, k0]) / ((k1 - k0) * voxel) if k1 > k0 else 0.0
