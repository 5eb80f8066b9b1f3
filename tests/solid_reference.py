"""An independent reference for the box and cylinder kernels (tests/test_solids.py, tests/test_kernels.py):
the point–solid distance written out with numpy (clamps for a box; a radial scale and a clamp for a
cylinder; in the solid's frame, z along its axis), minimised along a link's axis by scipy's bounded
scalar minimiser from the best of 2,001 samples."""

from __future__ import annotations

import numpy as np
from scipy.optimize import minimize_scalar


def project_local(shape: str, p: np.ndarray, half: np.ndarray) -> np.ndarray:
    """The solid's points nearest to the points p (..., 3), all in the solid's frame (numpy)."""
    if shape == "box":
        return np.clip(p, -half, half)
    rho = np.hypot(p[..., 0], p[..., 1])
    s = np.minimum(1.0, half[0] / np.maximum(rho, 1e-300))[..., None]
    return np.concatenate([p[..., :2] * s, np.clip(p[..., 2:], -half[2], half[2])], axis=-1)


def point_distance(shape: str, p: np.ndarray, c, R, half) -> float:
    local = R.T @ (p - c)
    return float(np.linalg.norm(local - project_local(shape, local, half)))


def minimised_distance(shape: str, a, b, r, c, R, half) -> float:
    """min over τ of the axis point's distance to the solid, less r (apart pairs only)."""
    def f(t: float) -> float:
        return point_distance(shape, a + t * (b - a), c, R, half)

    ts = np.linspace(0.0, 1.0, 2001)
    local = (a[None] + ts[:, None] * (b - a)[None] - c) @ R
    k = int(np.argmin(np.linalg.norm(local - project_local(shape, local, half), axis=1)))
    res = minimize_scalar(f, bounds=(ts[max(k - 1, 0)], ts[min(k + 1, 2000)]), method="bounded",
                          options={"xatol": 1e-13})
    return min(float(res.fun), f(0.0), f(1.0)) - r
