"""The slow, obviously-correct reference of the ray caster (:mod:`qpctl.kernels.raycast`): each ray
sphere-traced against each obstacle with python-fcl's distance (``tests/test_camera_raycast.py``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import fcl
import numpy as np

from qpctl.geometry.obstacles import Obstacle


def _trace(point: fcl.CollisionObject, shape: fcl.CollisionObject, request: fcl.DistanceRequest, o: np.ndarray,
           unit: np.ndarray, s_max: float, tol: float, max_steps: int) -> float:
    """The distance s along the unit ray o + s·unit at which sphere tracing meets ``shape`` (inf: it
    passes s_max, or the origin is inside; NaN: undecided after max_steps)."""

    def gap(s: float) -> float:
        point.setTranslation(o + s * unit)
        return float(fcl.distance(point, shape, request, fcl.DistanceResult()))

    if gap(0.0) <= 0.0:
        return math.inf
    s = 0.0
    for _ in range(max_steps):
        d = gap(s)
        if d < tol:
            return s
        s += d
        if s > s_max:
            return math.inf
    return math.nan


def reference_depth(origin: np.ndarray, direction: np.ndarray, obstacles: Sequence[Obstacle], t: float = 0.0,
                    t_max: float = 10.0, tol: float = 1e-9, max_steps: int = 5000) -> tuple[float, int]:
    """(t, index) of the first obstacle the ray origin + t·direction meets within t_max (inf, −1: none)
    by sphere tracing each obstacle (:class:`~qpctl.geometry.obstacles.Obstacle`, at time ``t`` [s])
    with python-fcl's distance from the ray's point (its unsigned query, exact for a point against
    these shapes; the signed one runs GJK/EPA, ~2e-7 m long, and the trace would overshoot): step by
    the distance until it is below ``tol`` [m] (a hit) or the point passes t_max (a miss); an obstacle
    holding the origin (python-fcl: −1, in collision) is not seen. NaN when some trace neither hit nor
    missed within ``max_steps`` (a ray grazing a surface)."""
    o = np.asarray(origin, float)
    d = np.asarray(direction, float)
    scale = float(np.linalg.norm(d))
    unit = d / scale
    point = fcl.CollisionObject(fcl.Sphere(0.0), fcl.Transform(o))
    request = fcl.DistanceRequest()
    best, who = math.inf, -1
    for j, obs in enumerate(obstacles):
        s = _trace(point, fcl.CollisionObject(obs.geometry(), obs.transform(t)), request, o, unit, t_max * scale, tol,
                   max_steps)
        if math.isnan(s):
            return math.nan, -1
        if s / scale < best:
            best, who = s / scale, j
    return best, who
