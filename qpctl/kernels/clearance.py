"""The world's clearance for a simulator: the least distance between any link and any sphere,
capsule, box or cylinder obstacle, and between the self-collision pairs, every pair, no cutoff
(:class:`qpctl.tick.WorldClearance`; python-fcl's shapes are left to Python).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from qpctl.kernels.codes import KIND_BOX, KIND_CYLINDER, KIND_FCL
from qpctl.kernels.geometry import segment_params
from qpctl.kernels.rigid import world_point
from qpctl.kernels.scene import obstacles_at
from qpctl.kernels.solids import solid_distance


@njit(cache=True)
def min_distance(ws, t: float) -> float:  # type: ignore[no-untyped-def]
    """The least signed distance [m] between any link capsule and any sphere, capsule, box or
    cylinder obstacle at t [s], every pair, no cutoff (a simulator's clearance; python-fcl's shapes
    are left to Python), from the joint placements only (after ``forwardKinematics``); the segments are left in ws."""
    segments, cap_joint, cap_local = ws.segments, ws.cap_joint, ws.cap_local
    for i in range(cap_joint.shape[0]):
        for e in range(2):
            x, y, z = world_point(ws, cap_joint[i], cap_local[i, e, 0], cap_local[i, e, 1], cap_local[i, e, 2])
            segments[i, e, 0], segments[i, e, 1], segments[i, e, 2] = x, y, z
    obstacles_at(ws, t)
    best = np.inf
    for i in range(segments.shape[0]):
        ax, ay, az = segments[i, 0, 0], segments[i, 0, 1], segments[i, 0, 2]
        ux, uy, uz = segments[i, 1, 0] - ax, segments[i, 1, 1] - ay, segments[i, 1, 2] - az
        uu = ux * ux + uy * uy + uz * uz
        for j in range(ws.ob_kind.shape[0]):
            kind = ws.ob_kind[j]
            if kind == KIND_FCL:
                continue
            if kind == KIND_BOX or kind == KIND_CYLINDER:
                best = min(best, solid_distance(kind, segments[i, 0], segments[i, 1], ws.cap_radius[i], ws.ob_c[j],
                                                ws.ob_rot[j], ws.ob_half[j]))
                continue
            sx, sy, sz = ws.ob_axis[j, 0], ws.ob_axis[j, 1], ws.ob_axis[j, 2]
            c0x, c0y, c0z = ws.ob_c[j, 0] - 0.5 * sx, ws.ob_c[j, 1] - 0.5 * sy, ws.ob_c[j, 2] - 0.5 * sz
            tl, to = segment_params(ax, ay, az, ux, uy, uz, uu, c0x, c0y, c0z, sx, sy, sz)
            wx = ax + tl * ux - (c0x + to * sx)
            wy = ay + tl * uy - (c0y + to * sy)
            wz = az + tl * uz - (c0z + to * sz)
            best = min(best, math.sqrt(wx * wx + wy * wy + wz * wz) - ws.cap_radius[i] - ws.ob_radius[j])
    return best


@njit(cache=True)
def min_self_distance(ws) -> float:  # type: ignore[no-untyped-def]
    """The least distance [m] between the self-collision pairs' capsules, from the segments that
    :func:`min_distance` left in ws (a simulator's self clearance)."""
    seg = ws.segments
    best = np.inf
    for r in range(ws.sc_pairs.shape[0]):
        i, j = ws.sc_pairs[r, 0], ws.sc_pairs[r, 1]
        a, c = seg[i, 0], seg[j, 0]
        ux, uy, uz = seg[i, 1, 0] - a[0], seg[i, 1, 1] - a[1], seg[i, 1, 2] - a[2]
        sx, sy, sz = seg[j, 1, 0] - c[0], seg[j, 1, 1] - c[1], seg[j, 1, 2] - c[2]
        tl, to = segment_params(a[0], a[1], a[2], ux, uy, uz, ux * ux + uy * uy + uz * uz, c[0], c[1], c[2],
                                sx, sy, sz)
        wx = a[0] + tl * ux - (c[0] + to * sx)
        wy = a[1] + tl * uy - (c[1] + to * sy)
        wz = a[2] + tl * uz - (c[2] + to * sz)
        best = min(best, math.sqrt(wx * wx + wy * wy + wz * wz) - ws.cap_radius[i] - ws.cap_radius[j])
    return best
