"""The map the tick reads: an immutable, timestamped distance field per channel.

A :class:`MapSnapshot` is built whole by :meth:`qpctl.perception.DepthMap.snapshot` and never
changes afterwards (its arrays are read-only): a reader that holds one — the tick, a metric, a
figure — can never see a half-built map, and handing a new one over is one reference assignment.
"""

from __future__ import annotations

import math
import time
from dataclasses import InitVar, dataclass, field

import numpy as np

from qpctl.kernels import field as KF

RIGID_CHANNEL, SOFT_CHANNEL = 0, 1
CHANNELS = ("rigid", "soft")


@dataclass(frozen=True)
class VoxelGrid:
    """A box of ``shape`` voxels of edge ``voxel`` [m] whose lower corner is ``origin`` [m] (base frame)."""

    origin: np.ndarray  # (3,)
    voxel: float
    shape: tuple[int, int, int]

    @staticmethod
    def from_bounds(lo: np.ndarray | list[float], hi: np.ndarray | list[float], voxel: float) -> VoxelGrid:
        """The grid of ``voxel`` [m] covering the box lo–hi [m] (the upper side rounded up to whole voxels)."""
        lo_a, hi_a = np.asarray(lo, float), np.asarray(hi, float)
        n = np.maximum(np.ceil((hi_a - lo_a) / voxel - 1e-9).astype(int), 1)
        return VoxelGrid(lo_a.copy(), float(voxel), (int(n[0]), int(n[1]), int(n[2])))

    @property
    def upper(self) -> np.ndarray:
        """The box's upper corner [m]."""
        return self.origin + np.asarray(self.shape) * self.voxel

    def centres(self, index: np.ndarray) -> np.ndarray:
        """(k, 3) centres [m] of the voxels at integer ``index`` (k, 3)."""
        return self.origin + (np.asarray(index) + 0.5) * self.voxel


def side_by_side(dist: np.ndarray) -> np.ndarray:
    """``dist`` (2, nx, ny, nz) as (nx, ny, nz, 2) float32: each voxel's two channels in one 8-byte word
    (two strided writes, 0.13 ms for 80×60×50 voxels here; ``np.moveaxis`` and a copy take 0.8 ms)."""
    pairs = np.empty((*dist.shape[1:], 2), np.float32)
    pairs[..., 0], pairs[..., 1] = dist[0], dist[1]
    return pairs


def _frozen(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


@dataclass(frozen=True)
class MapSnapshot:
    """The distance field of one map state, read-only.

    ``dist`` (2, nx, ny, nz) float32 [m]: per channel (0 rigid, 1 soft) the distance from each voxel
    centre to the nearest occupied voxel centre, capped at ``truncation``; ``grad`` (2, nx, ny, nz, 3)
    float32 its central-difference gradient; ``pairs`` (nx, ny, nz, 2) float32 the same distances with
    the two channels side by side, derived from ``dist`` here (the tick samples both at each point, and
    a voxel's two values in one 8-byte word halve the cache lines it reads:
    :mod:`qpctl.kernels.field_samples`). ``stamp`` [s] is the newest frame's (on the controller's
    clock); ``build_ms`` [ms] the time from ``started`` (``time.perf_counter()`` when that frame arrived;
    0 without it) to this snapshot's completion, its derived grid included;
    ``occupied`` the occupied voxels per channel; ``frames`` the frames integrated so far.
    """

    grid: VoxelGrid
    truncation: float
    dist: np.ndarray
    grad: np.ndarray
    stamp: float
    started: InitVar[float | None] = None  # perf_counter when the newest frame arrived (class docstring)
    occupied: tuple[int, int] = (0, 0)
    frames: int = 0
    counts: dict[str, int] = field(default_factory=dict)  # the newest frame's pixels or points by status
    build_ms: float = field(init=False, default=0.0)
    pairs: np.ndarray = field(init=False, repr=False, compare=False)  # derived from dist (class docstring)

    def __post_init__(self, started: float | None) -> None:
        nx, ny, nz = self.grid.shape
        if self.dist.shape != (2, nx, ny, nz) or self.grad.shape != (2, nx, ny, nz, 3):
            raise ValueError(f"a snapshot of grid {self.grid.shape} needs dist (2, {nx}, {ny}, {nz}) and grad "
                             f"(2, {nx}, {ny}, {nz}, 3), got {self.dist.shape} and {self.grad.shape}")
        object.__setattr__(self, "dist", _frozen(np.ascontiguousarray(self.dist, dtype=np.float32)))
        object.__setattr__(self, "grad", _frozen(np.ascontiguousarray(self.grad, dtype=np.float32)))
        object.__setattr__(self, "pairs", _frozen(side_by_side(self.dist)))  # never given: never stale
        if started is not None:
            object.__setattr__(self, "build_ms", (time.perf_counter() - started) * 1e3)

    @staticmethod
    def empty(grid: VoxelGrid, truncation: float, stamp: float = -math.inf) -> MapSnapshot:
        """A map with nothing in it (the field at its truncation everywhere)."""
        nx, ny, nz = grid.shape
        return MapSnapshot(grid, float(truncation), np.full((2, nx, ny, nz), truncation, np.float32),
                           np.zeros((2, nx, ny, nz, 3), np.float32), stamp)

    def age(self, t: float) -> float:
        """How old the map is at time ``t`` [s] (its newest frame's stamp to t) [s]."""
        return float(t) - self.stamp

    def distance(self, points: np.ndarray, channel: int = RIGID_CHANNEL, *, smooth: bool = True
                 ) -> tuple[np.ndarray, np.ndarray]:
        """The field at ``points`` (k, 3) [m]: distances (k,) [m] and gradients (k, 3) (trilinear;
        ``truncation`` and 0 outside the bounds). Not for the tick (a Python loop per point)."""
        pts = np.asarray(points, float).reshape(-1, 3)
        d = np.empty(len(pts))
        g = np.empty((len(pts), 3))
        for i, p in enumerate(pts):
            d[i] = KF.trilinear(self.dist[channel], self.grad[channel], self.grid.origin, self.grid.voxel,
                                self.truncation, p[0], p[1], p[2], smooth, g[i])
        return d, g
