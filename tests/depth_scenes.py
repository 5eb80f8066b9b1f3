"""Synthetic depth frames for the perception tests (qpctl.perception.synthetic at a small image size).

The frames are closed-form ray casts of spheres and walls; the pipeline under test never sees the
true points that :func:`true_points` back-projects, so they are an independent reference for it.
"""

from __future__ import annotations

import numpy as np

from qpctl.perception import DepthFrame, Intrinsics
from qpctl.perception.synthetic import Sphere, look_at, true_points
from qpctl.perception.synthetic import render as _render

K = Intrinsics(fx=300.0, fy=300.0, cx=159.5, cy=119.5, width=320, height=240)

__all__ = ["K", "Sphere", "look_at", "render", "true_points"]


def render(pose: np.ndarray, spheres: list[Sphere], wall_x: float | None = None, stamp: float = 0.0,
           labelled: bool = False) -> DepthFrame:
    """A 320×240 frame of the spheres and an optional wall x = wall_x [m]."""
    return _render(pose, spheres, K, wall_x=wall_x, stamp=stamp, labelled=labelled)
