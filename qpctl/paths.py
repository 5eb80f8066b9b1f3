"""Reference paths for the task point: straight segments through waypoints, quintic time scaling.

Each segment from p_k to p_{k+1} takes T_k seconds and follows p(t) = p_k + s(τ)(p_{k+1} − p_k),
τ = (t − t_k)/T_k, s(τ) = 10τ³ − 15τ⁴ + 6τ⁵, so velocity and acceleration are zero at every waypoint
(the paper's "zero initial and final velocities"). Before the start and after the end the
reference holds still.

A :class:`PosePath` adds a rotation at every waypoint, interpolated on SO(3) with the same timing
(slerp): R_d(t) = exp(s(τ) [θ_k]×) R_k with θ_k = log(R_{k+1} R_kᵀ) in the world frame, so the
angular velocity ω_d = (ṡ/T_k) θ_k and acceleration ω̇_d = (s̈/T_k²) θ_k keep one axis per segment.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from qpctl.errors import ConfigError


class Reference(NamedTuple):
    """x_d [m], ẋ_d [m/s], ẍ_d [m/s²] at one time."""

    x: np.ndarray
    xd: np.ndarray
    xdd: np.ndarray


def quintic(tau: float) -> tuple[float, float, float]:
    """s, ds/dτ, d²s/dτ² of the quintic 10τ³ − 15τ⁴ + 6τ⁵ on [0, 1] (clamped outside)."""
    if tau <= 0.0:
        return 0.0, 0.0, 0.0
    if tau >= 1.0:
        return 1.0, 0.0, 0.0
    t2 = tau * tau
    return (t2 * tau * (10 - 15 * tau + 6 * t2), 30 * t2 * (1 - tau) ** 2, 60 * tau * (1 - tau) * (1 - 2 * tau))


@dataclass(frozen=True, kw_only=True)
class PathConfig:
    """The ``[path]`` keys of a scenario (each declared here once; :func:`qpctl.config.schema_of`).

    start [m]: the first point (None: the task point at q0); waypoints [m]: the points after it
    (required, unless a ``[canopy]`` gives them: its reachable fruits). duration [s] (shared by
    segment length) or durations [s] (per segment): one of them.
    start_time [s], dwell [s]: when the path starts, the pause at each waypoint.
    orientations: a pose task's quaternions (x, y, z, w) at each waypoint; approach: an approach task's
    world directions at each waypoint; start_orientation: the first (None: the task frame's at q0).
    """

    start: list[float] | None = None
    waypoints: list[list[float]] | None = None
    duration: float | None = None
    durations: list[float] | None = None
    start_time: float = 0.0
    dwell: float = 0.0
    orientations: list[list[float]] | None = None
    start_orientation: list[float] | None = None
    approach: list[list[float]] | None = None


@dataclass(frozen=True, kw_only=True)
class TaskConfig:
    """One ``[[tasks]]`` table: a task frame and its own path (several arms on one torso).

    frame: the task frame (its origin is the task point); waypoints [m]: its points after the start,
    one per ``path`` segment (every task has as many: they share ``[path]``'s durations and dwell);
    start [m]: its first point (None: the frame's position at q0); weights: its position rows' slack
    weights in the QP (one, or one per row; 1 by default: ``controller.task_weights``' rows).
    task: its frame's orientation task, "position" (none), "pose" or "approach", with the same keys as
    the single frame's (``controller.task_mask``, ``controller.approach_axis``, ``path.orientations``,
    ``path.approach``, ``path.start_orientation``): task_mask, approach_axis, orientations, approach,
    start_orientation (:mod:`qpctl.scenario_orientation`). The first task's frame is ``robot.ee_frame``;
    without a ``task`` of its own it carries ``controller.task``'s orientation rows.
    """

    frame: str = ""
    waypoints: list[list[float]] | None = None
    start: list[float] | None = None
    weights: float | list[float] | None = None
    task: str | None = None
    task_mask: list[float] | None = None
    approach_axis: list[float] | None = None
    orientations: list[list[float]] | None = None
    approach: list[list[float]] | None = None
    start_orientation: list[float] | None = None


class WaypointPath:
    """Straight segments through ``points`` ((k+1, m) [m]), each with quintic timing.

    Args:
        points: the start point followed by the waypoints.
        durations: seconds per segment; or
        duration: total seconds, shared among segments in proportion to their length.
        start_time: when the first segment starts [s].
        dwell: pause at each intermediate waypoint [s].
    """

    def __init__(self, points: Sequence[Sequence[float] | np.ndarray] | np.ndarray, *, duration: float | None = None,
                 durations: Sequence[float] | None = None, start_time: float = PathConfig.start_time,
                 dwell: float = PathConfig.dwell):
        pts = np.asarray(points, dtype=float)
        if pts.ndim != 2 or pts.shape[0] < 2 or not np.all(np.isfinite(pts)):
            raise ConfigError("needs a start point and at least one finite waypoint", key="path.waypoints")
        self.points = pts
        lengths = self._lengths()
        if durations is not None:
            T = np.asarray(durations, dtype=float)
            if T.shape != lengths.shape:
                raise ConfigError(f"needs {lengths.size} durations, got {T.size}", key="path.durations")
        else:
            if duration is None:
                raise ConfigError("give duration or durations", key="path.duration")
            total = float(lengths.sum())
            T = np.full(lengths.size, duration / lengths.size) if total == 0 else duration * lengths / total
        # A zero duration is allowed only on a zero-length segment; a negative one never.
        if not np.all(np.isfinite(T)) or np.any(T < 0) or np.any(lengths[T <= 0] > 0):
            raise ConfigError(f"segment durations must be positive, got {T.tolist()}", key="path.duration")
        if not (np.isfinite(dwell) and dwell >= 0):
            raise ConfigError(f"must be >= 0, got {dwell}", key="path.dwell")
        if not np.isfinite(start_time):
            raise ConfigError(f"must be a finite number of seconds, got {start_time}", key="path.start_time")
        self.durations = np.maximum(T, 1e-9)
        starts = [start_time]
        for Tk in self.durations[:-1]:
            starts.append(starts[-1] + Tk + dwell)
        self.starts = np.array(starts)
        self.end_time = float(self.starts[-1] + self.durations[-1])

    def _lengths(self) -> np.ndarray:
        """Each segment's length, by which a total ``duration`` is shared [m]."""
        return np.linalg.norm(np.diff(self.points, axis=0), axis=1)

    @property
    def dim(self) -> int:
        return int(self.points.shape[1])

    def timing(self, t: float) -> tuple[int, float, float, float]:
        """(segment k, s, ṡ [1/s], s̈ [1/s²]) at time t [s]."""
        k = int(np.searchsorted(self.starts, t, side="right") - 1)
        k = min(max(k, 0), len(self.durations) - 1)
        T = self.durations[k]
        s, ds, dds = quintic((t - self.starts[k]) / T)
        return k, s, ds / T, dds / T**2

    def __call__(self, t: float) -> Reference:
        """The reference at time t [s]."""
        k, s, ds, dds = self.timing(t)
        delta = self.points[k + 1] - self.points[k]
        return Reference(self.points[k] + s * delta, ds * delta, dds * delta)


# How a rotation counts in sharing a PosePath's total duration: a turn of θ [rad] as a move of
# ROTATION_LENGTH·θ [m] (a point 0.1 m from the axis), so a pure turn gets time in proportion.
ROTATION_LENGTH = 0.1


class PosePath(WaypointPath):
    """A :class:`WaypointPath` with a rotation at every point ((k+1, 3, 3), world frame), slerped with
    the same quintic timing; with several oriented task frames, one set of rotations per frame
    ((F, k+1, 3, 3), :attr:`RobotModel.oriented_frames`' order). A total ``duration`` is shared by
    max(‖Δp‖, ROTATION_LENGTH·|θ|) per segment (the largest θ over the frames).
    :meth:`orientation` gives R_d, ω_d [rad/s], ω̇_d [rad/s²]."""

    def __init__(self, points: Sequence[Sequence[float]] | np.ndarray,
                 rotations: Sequence[np.ndarray] | np.ndarray, **kwargs: Any) -> None:
        import pinocchio as pin

        R = np.asarray(rotations, dtype=float)
        pts = np.asarray(points, dtype=float)
        sets = R[None] if R.ndim == 3 else R
        if sets.ndim != 4 or sets.shape[2:] != (3, 3) or pts.ndim != 2 or sets.shape[1] != pts.shape[0]:
            raise ConfigError(f"needs one rotation per point ({pts.shape[0] if pts.ndim == 2 else '?'}), "
                              f"got an array of shape {R.shape}", key="path.orientations")
        for k, Rk in enumerate(sets.reshape(-1, 3, 3)):
            if not (np.all(np.isfinite(Rk)) and np.allclose(Rk @ Rk.T, np.eye(3), atol=1e-6)
                    and np.linalg.det(Rk) > 0):
                raise ConfigError(f"rotation {k % sets.shape[1]} is not a rotation matrix", key="path.orientations")
        #: (F, k+1, 3, 3) each oriented frame's rotations and (F, k, 3) its segments' rotation vectors
        self.frame_rotations = np.array([[pin.Quaternion(Rk).normalized().matrix() for Rk in Rf] for Rf in sets])
        self.frame_theta = np.array([[pin.log3(Rf[k + 1] @ Rf[k].T) for k in range(len(Rf) - 1)]
                                     for Rf in self.frame_rotations]).reshape(len(sets), len(pts) - 1, 3)
        self.rotations, self.theta = self.frame_rotations[0], self.frame_theta[0]  # the first frame's
        super().__init__(pts, **kwargs)

    @property
    def frames(self) -> int:
        """How many frames' rotations it holds."""
        return int(self.frame_rotations.shape[0])

    def check_frames(self, oriented: int) -> None:
        """A ConfigError (``path.orientations``) unless it holds rotations for ``oriented`` frames."""
        if self.frames != oriented:
            raise ConfigError(f"{oriented} task frames have orientation rows but the path holds rotations for "
                              f"{self.frames}", key="path.orientations")

    def _lengths(self) -> np.ndarray:
        moves = np.linalg.norm(np.diff(self.points, axis=0), axis=1)
        return np.maximum(moves, ROTATION_LENGTH * np.linalg.norm(self.frame_theta, axis=2).max(axis=0))

    def orientation(self, t: float, frame: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """R_d (3, 3), ω_d [rad/s] and ω̇_d [rad/s²] (world frame) at time t [s], of the path's
        ``frame``-th set of rotations."""
        import pinocchio as pin

        k, s, ds, dds = self.timing(t)
        th = self.frame_theta[frame, k]
        return pin.exp3(s * th) @ self.frame_rotations[frame, k], ds * th, dds * th


class TimeScaledPath:
    """A path whose clock runs at κ (set each tick with :meth:`advance`): wraps any path callable
    ``path(t) -> Reference``; other attributes (``dim``, ``points`` …) are the path's. The stale-map
    policy and the waiting reference drive it (:mod:`qpctl.perception.stale`).

    Over a plain :class:`WaypointPath` the compiled tick evaluates it itself: a workspace that takes
    it (:meth:`bind`: its parameter array), and every :meth:`advance` writes the clock (s, κ, κ̇ and
    the time of the advance) there (:func:`qpctl.kernels.scene.reference`), so that the tick stays one
    kernel call with a time-scaled path."""

    def __init__(self, path: Any, start: float = 0.0) -> None:
        self.path = path
        self.s = float(start)  # the path's own time [s]
        self.kappa = 1.0
        self.kappa_rate = 0.0  # κ̇ [1/s]
        self._t = float(start)
        self._sinks: list[np.ndarray] = []  # the bound workspaces' clocks: (s, κ, κ̇, t) each

    @property
    def compiled(self) -> bool:
        """Whether the compiled tick can evaluate it (the wrapped path is a plain WaypointPath)."""
        return type(self.path) is WaypointPath

    def bind(self, sink: np.ndarray) -> None:
        """Keep ``sink`` (4,) — a workspace's view of its clock parameters — written on every advance."""
        self._sinks.append(sink)
        self._write(sink)

    def _write(self, sink: np.ndarray) -> None:
        sink[0], sink[1], sink[2], sink[3] = self.s, self.kappa, self.kappa_rate, self._t

    def __getattr__(self, name: str) -> Any:
        return getattr(self.__dict__["path"], name)

    def advance(self, t: float, kappa: float) -> None:
        """Move the clock to t [s] at the κ in force since the last call, then set κ for what follows."""
        if t > self._t:
            dt = t - self._t
            self.s += self.kappa * dt
            self.kappa_rate = (kappa - self.kappa) / dt
            self._t = t
        self.kappa = float(kappa)
        for sink in self._sinks:
            self._write(sink)

    def time_at(self, t: float) -> float:
        """The path's own time [s] at t [s]: the clock's, extrapolated at the current κ beyond the last
        :meth:`advance`."""
        return self.s + self.kappa * max(0.0, float(t) - self._t)

    def _rate(self) -> float:
        """κ̇ as the acceleration's term uses it: 0 where it is not finite (κ² x'' alone; the kernel's rule)."""
        return self.kappa_rate if math.isfinite(self.kappa_rate) else 0.0

    def __call__(self, t: float) -> Reference:
        """The reference at the clock's time (``t`` is taken from :meth:`advance`; a t beyond it is
        extrapolated at the current κ)."""
        ref = self.path(self.time_at(t))
        k = self.kappa
        return Reference(ref.x, k * ref.xd, k * k * ref.xdd + self._rate() * ref.xd)

    def orientation(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A pose path's (R_d, ω_d, ω̇_d) at the clock's time, scaled like the position."""
        R, w, wd = self.path.orientation(self.time_at(t))
        k = self.kappa
        return R, k * w, k * k * wd + self._rate() * w
