"""Rotations for the tick's compiled kernels: SO(3)'s exponential and logarithm, in place.

The references are Pinocchio's ``pin.exp3`` and ``pin.log3``; ``tests/test_orientation.py`` holds
these against them, near the identity and near a half turn too (where the logarithm's axis is taken
from R + Rᵀ, not from R − Rᵀ, which vanishes there).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def exp3(w: np.ndarray, out: np.ndarray) -> None:
    """out (3, 3) = exp([w]×), Rodrigues' formula (series near w = 0)."""
    th2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    th = math.sqrt(th2)
    if th < 1e-6:
        a, b = 1.0 - th2 / 6.0, 0.5 - th2 / 24.0
    else:
        a, b = math.sin(th) / th, (1.0 - math.cos(th)) / th2
    x, y, z = w[0], w[1], w[2]
    out[0, 0] = 1.0 - b * (y * y + z * z)
    out[1, 1] = 1.0 - b * (x * x + z * z)
    out[2, 2] = 1.0 - b * (x * x + y * y)
    out[0, 1], out[1, 0] = -a * z + b * x * y, a * z + b * x * y
    out[0, 2], out[2, 0] = a * y + b * x * z, -a * y + b * x * z
    out[1, 2], out[2, 1] = -a * x + b * y * z, a * x + b * y * z


@njit(cache=True)
def log3(R: np.ndarray, out: np.ndarray) -> float:
    """out (3,) = w with exp([w]×) = R, |w| ≤ π; returns |w| [rad]."""
    vx, vy, vz = 0.5 * (R[2, 1] - R[1, 2]), 0.5 * (R[0, 2] - R[2, 0]), 0.5 * (R[1, 0] - R[0, 1])
    s = math.sqrt(vx * vx + vy * vy + vz * vz)
    c = min(max(0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0), -1.0), 1.0)
    th = math.atan2(s, c)
    if c > -0.9:  # away from a half turn: the axis from the skew part, well conditioned
        k = th / s if s > 1e-12 else 1.0 + s * s / 6.0
        out[0], out[1], out[2] = k * vx, k * vy, k * vz
        return th
    # near a half turn: (R + Rᵀ)/2 = c I + (1 − c) a aᵀ, so a from its largest diagonal's column
    best, i = -1.0, 0
    for r in range(3):
        d = R[r, r] - c
        if d > best:
            best, i = d, r
    scale = math.sqrt(max(best, 0.0) * (1.0 - c))
    a0, a1, a2 = 0.5 * (R[0, i] + R[i, 0]), 0.5 * (R[1, i] + R[i, 1]), 0.5 * (R[2, i] + R[i, 2])
    if i == 0:
        a0 = R[0, 0] - c
    elif i == 1:
        a1 = R[1, 1] - c
    else:
        a2 = R[2, 2] - c
    a0, a1, a2 = a0 / scale, a1 / scale, a2 / scale
    if a0 * vx + a1 * vy + a2 * vz < 0.0:  # the skew part's sign (sin θ a), where it is not lost
        a0, a1, a2 = -a0, -a1, -a2
    out[0], out[1], out[2] = th * a0, th * a1, th * a2
    return th


@njit(cache=True)
def matmul3(A: np.ndarray, B: np.ndarray, out: np.ndarray) -> None:
    """out = A B (3×3)."""
    for i in range(3):
        for j in range(3):
            out[i, j] = A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j]


@njit(cache=True)
def matmul3_bt(A: np.ndarray, B: np.ndarray, out: np.ndarray) -> None:
    """out = A Bᵀ (3×3)."""
    for i in range(3):
        for j in range(3):
            out[i, j] = A[i, 0] * B[j, 0] + A[i, 1] * B[j, 1] + A[i, 2] * B[j, 2]
