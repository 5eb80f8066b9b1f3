"""Small frames and vectors of the world's geometry: 3-vectors from a scenario's numbers, and the
rotation that takes the z axis onto an obstacle's (or a capsule's) axis."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from qpctl.errors import ConfigError


def vec3(value: Sequence[float] | np.ndarray, key: str) -> np.ndarray:
    """A 3-vector from 2 (z = 0: the planar scenarios) or 3 finite numbers; ConfigError naming
    ``key`` otherwise."""
    arr = np.asarray(value, dtype=float).reshape(-1)
    if arr.shape == (2,):
        arr = np.append(arr, 0.0)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ConfigError(f"must be 2 or 3 finite numbers, got {value!r}", key=key)
    return arr


def quaternion_z_to(x: float, y: float, z: float) -> tuple[float, float, float, float]:
    """(w, x, y, z) of the shortest rotation taking the z axis onto the non-zero direction (x, y, z).

    With a = (x, y, z)/‖·‖ and c = a_z: q = (1 + c, z × a)/√(2(1 + c)), z × a = (−a_y, a_x, 0); a
    half turn about x when a = −z. Plain floats: it runs for every link capsule at every tick.
    """
    norm = math.sqrt(x * x + y * y + z * z)
    c = z / norm
    if c > 1 - 1e-12:
        return (1.0, 0.0, 0.0, 0.0)
    if c < -1 + 1e-12:
        return (0.0, 1.0, 0.0, 0.0)
    w = 1.0 + c
    s = math.sqrt(2.0 * w) * norm
    return (w * norm / s, -y / s, x / s, 0.0)


def rotation_z_to(axis: np.ndarray) -> np.ndarray:
    """A rotation matrix taking the z axis onto the unit vector ``axis`` (see :func:`quaternion_z_to`)."""
    w, x, y, z = quaternion_z_to(*(float(c) for c in axis))
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
