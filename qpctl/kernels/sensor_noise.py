"""The simulated depth camera's noise model, compiled (:mod:`qpctl.simulation.camera` states it).

One pass over the noise-free depth image: flying pixels at depth edges, depth noise σ(z) = σ₀ + k z²,
dropouts (grazing incidence, random). Its random numbers come from numba's own generator, seeded for
each frame (``np.random.seed`` inside a compiled function seeds numba's, not NumPy's), four draws per
pixel that holds a surface, so a frame is a function of its seed alone. It has no slower twin to be
compared with: ``tests/test_camera.py`` checks its statistics instead (the depth error's σ against
the formula, the dropout fraction, flying pixels only at edges and between the two surfaces).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def edge_jump(z: np.ndarray, v: int, u: int) -> float:
    """The signed depth step z_n − z [m] to the 4-neighbour of pixel (v, u) that differs most (both
    with a surface; 0 when none has one)."""
    H, W = z.shape
    best = 0.0
    zc = z[v, u]
    for dv, du in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        a, b = v + dv, u + du
        if 0 <= a < H and 0 <= b < W:
            zn = z[a, b]
            if math.isfinite(zn) and abs(zn - zc) > abs(best):
                best = zn - zc
    return best


@njit(cache=True)
def depth_noise(z_true: np.ndarray, cos_incidence: np.ndarray, seed: int, p_flying: float, jump_min: float,
                sigma_0: float, sigma_z2: float, cos_grazing: float, dropout: float, z_out: np.ndarray,
                flying: np.ndarray) -> None:
    """z_out (H, W) [m]: the noisy depth of each pixel of z_true (inf where there is no surface, or
    its return is lost); flying (H, W) bool: the pixel became a flying pixel. Per pixel with a
    surface at depth z: where :func:`edge_jump` exceeds jump_min, with probability p_flying,
    z ← z + u·jump (u ~ U(0, 1)); then z ← z + N(0, (σ₀ + σ_z2·z_true²)²); the return is lost where
    cos_incidence < cos_grazing, or with probability dropout."""
    np.random.seed(seed)
    H, W = z_true.shape
    for v in range(H):
        for u in range(W):
            z = z_true[v, u]
            flying[v, u] = False
            if not math.isfinite(z):
                z_out[v, u] = math.inf
                continue
            r_fly, r_mix, r_drop = np.random.random(), np.random.random(), np.random.random()
            gauss = np.random.standard_normal()
            out = z
            jump = edge_jump(z_true, v, u)
            if abs(jump) > jump_min and r_fly < p_flying:
                out += r_mix * jump
                flying[v, u] = True
            out += gauss * (sigma_0 + sigma_z2 * z * z)
            if cos_incidence[v, u] < cos_grazing or r_drop < dropout:
                out = math.inf
                flying[v, u] = False
            z_out[v, u] = out
