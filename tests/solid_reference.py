"""An independent reference for the box and cylinder kernels (tests/test_solids.py, tests/test_kernels.py):
the point–solid distance written out with numpy (clamps for a box; a radial scale and a clamp for a
cylinder; in the solid's frame, z along its axis), minimised along a link's axis by scipy's bounded
scalar minimiser from the best of 2,001 samples; and python-fcl's capsule of a segment (tests/test_kernels.py,
tests/test_self_shadow.py)."""

from __future__ import annotations

import fcl
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


def frame_z_to(u: np.ndarray) -> np.ndarray:
    """A rotation whose third column is the unit vector along u (an orthonormal frame built by cross
    products; independent of qpctl's quaternion)."""
    u = np.asarray(u, float) / np.linalg.norm(u)
    helper = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(helper, u)
    e1 /= np.linalg.norm(e1)
    return np.column_stack([e1, np.cross(u, e1), u])


def fcl_segment(a: np.ndarray, b: np.ndarray, r: float) -> fcl.CollisionObject:
    """The capsule of axis a–b and radius r (a sphere when a = b) as a python-fcl object."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    length = float(np.linalg.norm(b - a))
    if length == 0.0:
        return fcl.CollisionObject(fcl.Sphere(r), fcl.Transform(a))
    return fcl.CollisionObject(fcl.Capsule(r, length), fcl.Transform(frame_z_to(b - a), 0.5 * (a + b)))
