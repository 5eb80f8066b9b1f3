"""The perception pipeline: depth frames and point clouds → a robot-local voxel map → a distance field.

DESIGN.md §6. :class:`DepthMap` holds the map's state (per channel and voxel, the stamp at which
the voxel was last seen occupied) and turns each frame into it (:meth:`DepthMap.integrate`):

1. filtering: no-return pixels (NaN, ±inf, 0, negative) and returns outside [min_range, max_range]
   are dropped and counted; so are *flying pixels*: a pixel with a 4-neighbour nearer than it by more
   than ``flying_pixel`` × its depth lies behind a depth edge, where a sensor's footprint straddling
   two surfaces reports a mixed depth on neither (the edge's near side is kept; its far side loses a
   pixel, seen elsewhere); and so is a return with fewer than ``flying_support`` of its 8 neighbours
   within that fraction of its depth (a flying pixel whose neighbours across the edge are flying too,
   or lost to a grazing dropout, has no nearer neighbour but no surface either);
2. back-projection through the pinhole intrinsics and the camera's pose;
3. self-filtering: points within the robot's capsules at the frame's stamp, inflated by
   ``self_margin`` (:mod:`qpctl.perception.self_filter`), or within ``target_radius`` of the grasp
   target, are dropped; with ``self_shadow``, so are rigid or unlabelled points whose ray from the
   sensor passes through one of those capsules (:mod:`qpctl.kernels.self_shadow`: a flying pixel at
   the robot's silhouette lies there, beyond the capsule; a cloud without a sensor origin has no
   rays); so are points outside the map's bounds;
4. the rest stamp their voxel, in the soft channel where labelled soft, the rigid one otherwise —
   from a depth image, once ``min_points`` pixels of the frame fall in it (a lone return in free
   space is the noise's tail); a cloud's points count one each (a cloud is taken as filtered); a
   soft voxel seen in a depth image fills ``soft_depth`` behind it along the ray (a leaf's body);
5. free-space clearing: a voxel seen before whose centre projects into this image in front of its
   pixel's return by more than √3/2 voxel + ``depth_noise`` is freed (a cloud with a sensor origin:
   the voxels along each ray);

and :meth:`DepthMap.snapshot` forgets the rigid voxels within ``target_radius`` of the grasp target
(seen before it was the target), applies the decay (a voxel not seen for ``decay`` seconds is forgotten)
and computes the truncated Euclidean distance field and its gradient per channel
(:mod:`qpctl.kernels.edt`) into an immutable :class:`~qpctl.perception.snapshot.MapSnapshot`.

All the per-pixel and per-voxel work is in ``nogil`` kernels (:mod:`qpctl.kernels.depth`).
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from qpctl.errors import PerceptionError
from qpctl.kernels import depth as KD
from qpctl.kernels import edt as KE
from qpctl.perception.config import SQRT3_2, PerceptionConfig
from qpctl.perception.frames import DepthFrame, PointCloud
from qpctl.perception.self_filter import JointHistory, SelfFilter
from qpctl.perception.snapshot import MapSnapshot, VoxelGrid
from qpctl.robot.model import RobotModel

Frame = DepthFrame | PointCloud


@dataclass(frozen=True)
class FrameReport:
    """What one frame did to the map: its pixels or points by fate (:data:`qpctl.kernels.depth.STATUS_NAMES`),
    the voxels it cleared, and the time [ms] it took to integrate."""

    stamp: float
    counts: dict[str, int]
    cleared: int
    integrate_ms: float
    status: np.ndarray = field(repr=False)  # per pixel (H×W) or point (N,): a status code each

    @property
    def dropped(self) -> int:
        """Pixels or points that did not become obstacles (everything but ``kept``)."""
        return sum(v for k, v in self.counts.items() if k != "kept")


class DepthMap:
    """A robot-local voxel map with rigid and soft channels, built from depth frames and point clouds.

    Args:
        config: the ``[perception]`` settings.
        robot: the robot whose capsules are self-filtered (None: no self-filter).
        history: the joint positions at the frames' stamps (:meth:`record` fills it); one of its own
            when None.
    """

    def __init__(self, config: PerceptionConfig | None = None, robot: RobotModel | None = None,
                 history: JointHistory | None = None) -> None:
        self.config = config or PerceptionConfig()
        c = self.config
        self.grid = VoxelGrid.from_bounds(c.bounds_min, c.bounds_max, c.voxel)
        nx, ny, nz = self.grid.shape
        self.last = np.full((2, nx, ny, nz), -np.inf)  # per channel, the stamp each voxel was last seen [s]
        self._occupied = np.zeros((2, nx, ny, nz), bool)
        self._hits = np.zeros((2, nx, ny, nz), np.uint16)
        self._work = np.empty((2, nx, ny, nz), np.float32)  # the EDT's scratch
        self._zbuf = np.empty((0, 0))  # the depth image's (_depth_scratch)
        self.robot = robot
        self.self_filter = SelfFilter(robot, c.self_margin) if robot is not None else None
        if history is None and robot is not None:  # q: the configuration (nq), interpolated on its group
            history = JointHistory(robot.nq, interpolate=robot.interpolate if robot.lie else None)
        self.history = history
        self.target: np.ndarray | None = None
        self.stamp = -math.inf  # the newest frame's
        self.frames = 0
        self.last_report: FrameReport | None = None
        self._lock = threading.Lock()  # one frame at a time (a worker and a user may both call)
        self._no_capsules = (np.zeros((0, 2, 3)), np.zeros(0))
        self._spans = np.zeros((len(robot.capsules) if robot is not None else 0, 0, 2), np.int32)  # the shadow's
        self._reach = np.zeros(self._spans.shape[0])  # ... scratch
        self._boxes = np.zeros((self._spans.shape[0], 6))  # the capsules' boxes (qpctl.kernels.depth.robot_bounds_into)
        self._robot_box = np.zeros(6)

    # -- what the controller tells the map --------------------------------------------------------
    def record(self, t: float, q: np.ndarray) -> None:
        """The robot's joint positions q [rad] at time t [s] (for the self-filter at a frame's stamp)."""
        if self.history is not None:
            self.history.record(t, q)

    def set_target(self, target: np.ndarray | None) -> None:
        """The grasp target [m] (base frame): nothing within ``target_radius`` of it is an obstacle (None: none)."""
        if target is None:
            self.target = None
            return
        p = np.asarray(target, float).reshape(-1)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise PerceptionError(f"the grasp target must be 3 finite numbers [m], got {target!r}")
        self.target = p

    def capsules_at(self, stamp: float) -> tuple[np.ndarray, np.ndarray]:
        """The robot's inflated capsules (segments (L, 2, 3), radii (L,)) [m] at ``stamp`` [s]."""
        if self.self_filter is None or self.history is None:
            return self._no_capsules
        q = self.history.at(stamp)
        if q is None:
            return self._no_capsules
        return self.self_filter.segments(q), self.self_filter.radii

    # -- frames -------------------------------------------------------------------------------------
    def _depth_scratch(self, shape: tuple[int, ...]) -> np.ndarray:
        """The (H + 2, W + 2) metric-depth scratch of an H×W image (kept: a camera's images keep their shape)."""
        if self._zbuf.shape != (shape[0] + 2, shape[1] + 2):
            self._zbuf = np.empty((shape[0] + 2, shape[1] + 2))
        return self._zbuf

    def _shadow_scratch(self, rows: int) -> np.ndarray:
        """The (L, rows, 2) spans of the robot's shadow (kept: a camera's images keep their shape)."""
        if self._spans.shape[1] < rows:
            self._spans = np.zeros((self._spans.shape[0], rows, 2), np.int32)
        return self._spans

    def integrate(self, frame: Frame) -> FrameReport:
        """Add one frame to the map (module docstring, steps 1–5). :class:`PerceptionError` when its
        stamp is older than the last frame's."""
        if not isinstance(frame, (DepthFrame, PointCloud)):
            raise PerceptionError(f"a frame is a DepthFrame or a PointCloud, got {type(frame).__name__}")
        with self._lock:
            if frame.stamp < self.stamp:
                raise PerceptionError(f"frame stamps went backwards: {frame.stamp} s after {self.stamp} s")
            start = time.perf_counter()
            c, g = self.config, self.grid
            segs, radii = self.capsules_at(frame.stamp)
            target = self.target if self.target is not None else np.zeros(3)
            target_r = c.target_radius if self.target is not None else 0.0
            counts = np.zeros(len(KD.STATUS_NAMES), np.int64)
            margin = SQRT3_2 * c.voxel + c.depth_noise
            if isinstance(frame, DepthFrame):
                K = frame.intrinsics
                depth = frame.depth
                scale = float(frame.depth_scale)
                if depth.dtype == np.float16:
                    depth = depth.astype(np.float32)
                labels = frame.labels if frame.labels is not None else np.zeros((0, 0), np.uint8)
                status: np.ndarray = np.empty(depth.shape, np.uint8)
                KD.integrate_depth(depth, scale, labels, K.fx, K.fy, K.cx, K.cy, frame.pose, c.min_range,
                                   c.max_range, c.flying_pixel, c.flying_support, segs, radii, target, target_r, g.origin, g.voxel,
                                   self.last, frame.stamp, status, counts, self._hits, c.min_points,
                                   c.soft_depth, self._depth_scratch(depth.shape), c.self_shadow,
                                   self._shadow_scratch(depth.shape[0])[:len(radii)], self._reach[:len(radii)],
                                   self._boxes[:len(radii)], self._robot_box)
                cleared = KD.clear_depth(depth, scale, status, K.fx, K.fy, K.cx, K.cy, frame.pose, margin,
                                         g.origin, g.voxel, self.last, frame.stamp)
            else:
                point_labels = frame.labels if frame.labels is not None else np.zeros(0, np.uint8)
                status = np.empty(frame.points.shape[0], np.uint8)
                sensor = frame.origin if frame.origin is not None else np.zeros(3)
                KD.integrate_points(frame.points, point_labels, segs, radii, target, target_r, g.origin, g.voxel,
                                    self.last, frame.stamp, status, counts, sensor,
                                    c.self_shadow and frame.origin is not None, self._boxes[:len(radii)],
                                    self._robot_box)
                cleared = 0
                if frame.origin is not None:
                    cleared = KD.clear_rays(frame.points, status, frame.origin, margin, g.origin, g.voxel,
                                            self.last, frame.stamp)
            self.stamp = frame.stamp
            self.frames += 1
            report = FrameReport(frame.stamp, dict(zip(KD.STATUS_NAMES, (int(n) for n in counts), strict=True)),
                                 int(cleared), (time.perf_counter() - start) * 1e3, status)
            self.last_report = report
            return report

    def snapshot(self, now: float | None = None, *, started: float | None = None) -> MapSnapshot:
        """The distance field of the map as it is (after the decay at ``now`` [s], default the newest
        frame's stamp), as an immutable snapshot. ``started`` (``time.perf_counter()``) is when the
        newest frame arrived: the snapshot's ``build_ms`` counts from it (default: this call)."""
        with self._lock:
            t0 = time.perf_counter() if started is None else started
            c = self.config
            now = self.stamp if now is None else float(now)
            self._forget_target_zone()
            KD.occupancy(self.last, now, c.decay, self._occupied)
            nx, ny, nz = self.grid.shape
            dist = np.empty((2, nx, ny, nz), np.float32)
            grad = np.empty((2, nx, ny, nz, 3), np.float32)
            occupied = [0, 0]
            for ch in range(2):
                occupied[ch] = int(KE.distance_field(self._occupied[ch], c.voxel, c.truncation, self._work, dist[ch]))
                if occupied[ch]:
                    KE.gradient(dist[ch], c.voxel, grad[ch])
                else:
                    grad[ch] = 0.0
            counts = dict(self.last_report.counts) if self.last_report is not None else {}
            return MapSnapshot(self.grid, c.truncation, dist, grad, self.stamp, t0, (occupied[0], occupied[1]),
                               self.frames, counts)

    def _forget_target_zone(self) -> None:
        """Forget the rigid voxels whose centres lie within ``target_radius`` of the grasp target: the
        frames seen since it became the target drop their points there (step 3), and those seen before
        — when it was not yet the target, or a flying pixel between the fruit and the leaf in front
        of it that no later ray reaches to clear — must not stay an obstacle to the gripper either.
        The soft channel keeps its voxels (the leaves in front of the fruit stay leaves)."""
        r, target = self.config.target_radius, self.target  # (read once: set_target may run in another thread)
        if target is None or r <= 0.0:
            return
        g = self.grid
        lo = np.maximum(np.floor((target - r - g.origin) / g.voxel).astype(np.int64), 0)
        hi = np.minimum(np.floor((target + r - g.origin) / g.voxel).astype(np.int64) + 1, g.shape)
        if np.any(hi <= lo):
            return
        axes = [np.arange(lo[k], hi[k]) for k in range(3)]
        centres = [g.origin[k] + (axes[k] + 0.5) * g.voxel - target[k] for k in range(3)]
        inside = (centres[0][:, None, None] ** 2 + centres[1][None, :, None] ** 2
                  + centres[2][None, None, :] ** 2) <= r * r
        box = self.last[0, lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
        box[inside] = -np.inf

    def update(self, frame: Frame) -> MapSnapshot:
        """:meth:`integrate` the frame, then :meth:`snapshot`: the map with it, timed from the call."""
        start = time.perf_counter()
        self.integrate(frame)
        return self.snapshot(started=start)

    def occupied_centres(self, channel: int = 0) -> np.ndarray:
        """(k, 3) centres [m] of the voxels occupied in ``channel`` at the last snapshot."""
        return self.grid.centres(np.argwhere(self._occupied[channel]))
