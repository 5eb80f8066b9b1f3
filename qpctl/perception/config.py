"""The depth map's settings: the scenario's ``[perception]`` table (DESIGN.md §6, issue 21).

Every key is a field of :class:`PerceptionConfig` (:mod:`qpctl.config`: a key is declared once, where
its value is used), documented in ``docs/scenarios.md`` and ``docs/perception.md``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from qpctl.config import check_fields, setting
from qpctl.errors import ConfigError

SQRT3_2 = math.sqrt(3.0) / 2.0  # a voxel centre's largest distance to a point of its voxel, in voxels


@dataclass(frozen=True)
class PerceptionConfig:
    """How depth frames become the map the tick reads (units in brackets)."""

    voxel: float = setting(0.02, valid="positive", unit="m")  # edge of a voxel [m]
    bounds_min: list[float] = dataclasses.field(
        default_factory=lambda: [-0.8, -0.6, 0.0], metadata={"unit": "m"})  # the map's lower corner, base frame [m]
    bounds_max: list[float] = dataclasses.field(
        default_factory=lambda: [0.8, 0.6, 1.0], metadata={"unit": "m"})  # its upper corner [m]
    min_range: float = setting(0.1, valid="nonnegative", unit="m")  # nearer returns are dropped [m]
    max_range: float = setting(3.0, valid="positive", unit="m")  # farther returns are dropped (they still clear) [m]
    flying_pixel: float = setting(0.02, valid="nonnegative")  # a pixel with a 4-neighbour nearer by more than
    #                                  this fraction of its depth is dropped: behind a depth edge (0: off)
    flying_support: int = setting(2)  # ... and so is one with fewer than this many of its 8 neighbours within
    #                                  that fraction of its depth: a return on no surface (0: off)
    min_points: int = setting(2)  # a voxel is occupied by a depth image once this many of its pixels fall in it
    self_margin: float = setting(0.03, valid="nonnegative", unit="m")  # the robot's capsules, inflated by this, are not obstacles [m]
    self_shadow: bool = setting(True)  # nor is a rigid return whose ray from the sensor passes through one of them
    #                                  (a flying pixel at the robot's silhouette; docs/perception.md, "The robot's shadow")
    soft_depth: float = setting(0.04, valid="nonnegative", unit="m")  # a soft surface fills this behind it along the ray [m]
    target_radius: float = setting(0.1, valid="nonnegative", unit="m")  # nothing within this of the grasp target is an obstacle [m]
    #                                  (the fruit and the hand about it)
    decay: float = setting(3.0, valid="seconds", unit="s")  # a voxel not seen again for this long is forgotten [s]
    depth_noise: float = setting(0.015, valid="nonnegative", unit="m")  # the sensor's depth error (3σ at the
    #                                  working range) [m]: added to the rigid rows' margin and to the clearing test
    truncation: float = setting(0.3, valid="positive", unit="m")  # the field is exact up to this distance [m]
    samples: int = setting(12)  # points sampled along each link capsule's axis for the field's rows
    rows_per_link: int = setting(2)  # field rows per link and channel (the nearest one or two)
    soft_speed: float = setting(0.05, valid="nonnegative", unit="m/s")  # the fastest a link may pass through a leaf [m/s]
    soft_margin: float = setting(0.0, valid="nonnegative", unit="m")  # the soft rows slow a link to soft_speed
    #                                  from this far from the leaf's voxels [m] (√3/2 voxel + depth_noise would
    #                                  reach the leaf's true surface at soft_speed; see docs/perception.md)
    soft_horizon: float = setting(0.001, valid="seconds", unit="s")  # the speed rows bound a soft contact's
    #                                  point velocity this far ahead, J_p(q̇ + q̈·h) + J̇_p q̇·h [s] (one control
    #                                  period at 1 kHz: the next tick's velocity)
    soft_funnel: float = setting(10.0, valid="nonnegative", unit="1/s")  # beyond soft_speed_margin() of a leaf's
    #                                  voxels the speed rows' bound opens by this per metre, soft_speed + g·(d − m_v)
    #                                  (10: the barrier's k0/k1 at its defaults; larger: faster near leaves, a harder brake)
    recovery_gain: float = setting(10.0, valid="positive", unit="1/s")  # a link inside a rigid row's margin
    #                                  speeds away at min(k0/k1·(m − d), soft_speed) with this gain, ḧ ≥ −k_r(ḣ − v_a)
    #                                  (10: a quarter of the barrier's k1 at its defaults)
    soft_weight: float = setting(1e7, valid="nonnegative", unit="(N·m)²/(m/s²)")  # ℓ₁ weight of each link's slack (its
    #                                  soft rows share it; above the task's slack_l1: the task lags before a leaf is
    #                                  pushed faster; 0: the soft rows are hard)
    stale_slow: float = setting(0.15, valid="seconds", unit="s")  # a map older than this slows the task [s]
    stale_stop: float = setting(0.5, valid="seconds", unit="s")  # older than this, the arm stops [s]
    lag_slow: float = setting(0.01, valid="nonnegative", unit="m")  # with a link within the soft speed rows'
    #                                  reach of a leaf, a tracking error |x − x_d| above this slows the path [m]
    lag_stop: float = setting(0.05, valid="nonnegative", unit="m")  # ... and at this it waits for the arm [m]
    #                                  (0: the path never waits; docs/perception.md, "The waiting reference")
    lag_rate: float = setting(5.0, valid="positive", unit="1/s")  # the most the lag's time scale κ_lag moves
    #                                  per second, both ways [1/s] (1 → 0 in 1/lag_rate s)
    latency: float = setting(0.03, valid="nonnegative", unit="s")  # in a simulated loop, a frame's map reaches
    #                                  the rows this long after its stamp [s]: fixed, so a run is the same on
    #                                  every machine (the build's measured cost is reported beside it)

    def __post_init__(self) -> None:
        check_fields(self, "perception")
        lo, hi = np.asarray(self.bounds_min, float), np.asarray(self.bounds_max, float)
        for name, arr in (("bounds_min", lo), ("bounds_max", hi)):
            if arr.shape != (3,) or not np.all(np.isfinite(arr)):
                raise ConfigError(f"must be 3 finite numbers [m], got {list(arr)}", key=f"perception.{name}")
        if np.any(hi - lo < self.voxel):
            raise ConfigError(f"must exceed bounds_min by at least one voxel on every axis, got {list(hi)}",
                              key="perception.bounds_max")
        if self.max_range <= self.min_range:
            raise ConfigError(f"must exceed min_range ({self.min_range}), got {self.max_range}",
                              key="perception.max_range")
        if not 1 <= self.min_points <= 1000:
            raise ConfigError(f"must be an integer from 1 to 1000, got {self.min_points}", key="perception.min_points")
        if not 0 <= self.flying_support <= 8:
            raise ConfigError(f"must be an integer from 0 to 8, got {self.flying_support}",
                              key="perception.flying_support")
        if not 2 <= self.samples <= 64:
            raise ConfigError(f"must be an integer from 2 to 64, got {self.samples}", key="perception.samples")
        if self.rows_per_link not in (1, 2):
            raise ConfigError(f"must be 1 or 2, got {self.rows_per_link}", key="perception.rows_per_link")
        if self.stale_stop <= self.stale_slow:
            raise ConfigError(f"must exceed stale_slow ({self.stale_slow}), got {self.stale_stop}",
                              key="perception.stale_stop")
        if self.lag_stop and self.lag_stop <= self.lag_slow:
            raise ConfigError(f"must exceed lag_slow ({self.lag_slow}) or be 0 (the path never waits), got "
                              f"{self.lag_stop}", key="perception.lag_stop")
        if self.truncation < 2 * self.voxel:
            raise ConfigError(f"must be at least two voxels ({2 * self.voxel}), got {self.truncation}",
                              key="perception.truncation")

    def rigid_margin(self, d_safe: float) -> float:
        """The rigid rows' margin [m]: d_safe + √3/2 voxel (an occupied voxel's centre to its farthest
        point) + the depth noise."""
        return float(d_safe) + SQRT3_2 * self.voxel + self.depth_noise

    def lag_reach(self) -> float:
        """How near a leaf's voxels [m] a link's surface must be for its lag to slow the path: where the
        soft speed rows' bound b(d) = soft_speed + soft_funnel·(d − m_v) is at most twice soft_speed,
        d ≤ m_v + soft_speed/soft_funnel (every distance with the funnel off)."""
        if self.soft_funnel <= 0.0:
            return math.inf
        return self.soft_speed_margin() + self.soft_speed / self.soft_funnel

    def soft_speed_margin(self) -> float:
        """Where the speed rows reach ``soft_speed`` [m]: √3/2 voxel + the depth noise from a leaf's voxel
        centres, as far as its true surface may be in front of them."""
        return SQRT3_2 * self.voxel + self.depth_noise
