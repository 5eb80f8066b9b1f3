"""The simulated depth camera's noise model, compiled (:mod:`qpctl.simulation.camera` states it).

One pass over the noise-free depth image: flying pixels at depth edges, depth noise σ(z) = σ₀ + k z²,
dropouts (grazing incidence, random), the range, the encoding, the labels and the truth's masks.

Its random numbers are counter-based: the k-th draw of pixel p is SplitMix64's output for the frame's
seed + (8p + k)·2⁶⁴/φ (Steele, Lea & Flood, "Fast splittable pseudorandom number generators", 2014;
the generator of Java's SplittableRandom), normals by Box–Muller, so a frame is a function of its
seed alone, and a draw costs about a nanosecond (numba's ``np.random``: 40). The model has no slower
twin to be compared with: ``tests/test_camera.py`` checks its statistics instead (the depth error's σ
against the formula, the dropout count, flying pixels only at edges and between the two surfaces).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)  # SplitMix64's increment, 2⁶⁴/φ
_M1, _M2 = np.uint64(0xBF58476D1CE4E5B9), np.uint64(0x94D049BB133111EB)
_S11, _S27, _S30, _S31 = np.uint64(11), np.uint64(27), np.uint64(30), np.uint64(31)


@njit(cache=True)
def uniform(seed: np.uint64, counter: np.uint64) -> float:
    """The counter-th draw of the stream ``seed``, uniform in [0, 1) (53 bits of SplitMix64's output)."""
    x = seed + counter * _GOLDEN
    x = (x ^ (x >> _S30)) * _M1
    x = (x ^ (x >> _S27)) * _M2
    x = x ^ (x >> _S31)
    return float(x >> _S11) * (1.0 / 9007199254740992.0)


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
def depth_frame(z_true: np.ndarray, cos_incidence: np.ndarray, hit: np.ndarray, label_of: np.ndarray,
                source_of: np.ndarray, noise: bool, seed: np.uint64, p_flying: float, jump_min: float, sigma_0: float,
                sigma_z2: float, cos_grazing: float, dropout: float, range_min: float, range_max: float,
                scale: float, depth_m: np.ndarray, depth_u: np.ndarray, labels: np.ndarray, truth_depth: np.ndarray,
                source: np.ndarray, flying: np.ndarray, dropped: np.ndarray) -> None:
    """One pass from a noise-free rendering (z_true (H, W) [m], inf: nothing; cos_incidence; hit, the
    shape seen, −1: none) to a frame, per pixel:

    * with ``noise``: where :func:`edge_jump` exceeds jump_min, with probability p_flying a flying
      pixel z + u·jump (u ~ U(0, 1)); then z + N(0, (σ₀ + σ_z2·z_true²)²); the return lost where
      cos_incidence < cos_grazing, or with probability dropout (five draws per pixel with a surface);
    * no return outside [range_min, range_max];
    * depth_m (float32 [m]; written when scale is 0) or depth_u (uint16 units of scale [m], rounded,
      at least 1), 0 for no return; labels = label_of[hit] where there is a return, else 0;
    * the truth: truth_depth (z_true, NaN: nothing), source = source_of[hit] (0: nothing), flying
      (a flying pixel that returned), dropped (a surface, no return).
    """
    H, W = z_true.shape
    stream = seed
    for v in range(H):
        for u in range(W):
            z = z_true[v, u]
            i = hit[v, u]
            fly = False
            if not math.isfinite(z):
                truth_depth[v, u] = math.nan
                source[v, u] = 0
                out = math.inf
            else:
                truth_depth[v, u] = z
                source[v, u] = source_of[i]
                out = z
                if noise:
                    c = np.uint64(8 * (v * W + u))
                    r_fly = uniform(stream, c)
                    r_mix = uniform(stream, c + np.uint64(1))
                    r_drop = uniform(stream, c + np.uint64(2))
                    gauss = math.sqrt(-2.0 * math.log(1.0 - uniform(stream, c + np.uint64(3)))) * \
                        math.cos(2.0 * math.pi * uniform(stream, c + np.uint64(4)))
                    jump = edge_jump(z_true, v, u)
                    if abs(jump) > jump_min and r_fly < p_flying:
                        out += r_mix * jump
                        fly = True
                    out += gauss * (sigma_0 + sigma_z2 * z * z)
                    if cos_incidence[v, u] < cos_grazing or r_drop < dropout:
                        out = math.inf
            ok = range_min <= out <= range_max
            flying[v, u] = fly and ok
            dropped[v, u] = math.isfinite(z) and not ok
            labels[v, u] = label_of[i] if ok else 0
            if scale > 0.0:
                depth_u[v, u] = min(65535, max(1, round(out / scale))) if ok else 0
            else:
                depth_m[v, u] = out if ok else 0.0
