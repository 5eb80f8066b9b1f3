"""The depth map in a simulated closed loop: camera → map → the controller's rows, on the simulated clock.

:class:`MapLoop` is a hook of the recording loop (:func:`qpctl.simulation.loop.record_run`): before
each tick it records q for the self-filter, takes a frame when the camera is due, builds the map
from it and applies the stale-map policy; after it, it measures what the map believed against the
truth.

**Latency on the simulated clock.** A frame stamped t is built at once (in the loop's thread) and
its snapshot becomes the controller's at the first tick at or after t + ``perception.latency``
(default 30 ms, a frame period at 30 Hz): a fixed latency, so a run's physics is the same on every
machine and under any load. The build's real cost is measured beside it — the building thread's CPU
time (``map_update_cpu_ms_*``: what a map worker on a core of its own would take) and the wall clock
(``map_update_ms_*``, which on a shared machine also counts the wait for a core) — and
``map_updates_over_latency`` counts the frames whose CPU time exceeded the declared latency (the
run was then more optimistic than this machine could be).

**Metrics** (:meth:`MapLoop.metrics`): ``map_min_clearance`` (the least rigid distance the map's
rows believed, from the link surfaces [m]), ``map_age_ms_max`` (the oldest the controller's map got,
after the first), ``map_updates_over_latency``, ``map_update_ms_median``/``_p99`` (frame to snapshot), ``map_latency_ms_p99``
(stamp to the first tick using it), ``min_soft_clearance`` (true, to the soft obstacles [m]),
``soft_contact_max_speed`` (the fastest a link's witness point moved while inside a soft obstacle
[m/s]) and ``soft_contact_max_approach_speed`` (its component into the obstacle, along the normal:
what the soft rows bound), ``phantom_rows`` (active rigid rows, checked every ``PHANTOM_EVERY`` ticks, whose field value at
their link's axis point is short of the true distance from there to the world's obstacles by more
than ``phantom_tolerance``: the map saw something where nothing is, the robot included),
``stale_slow_ticks`` and ``stale_stop_ticks``; ``lag_ticks`` (ticks at which the path waited for
the arm, κ_lag < 1), ``lag_max_m`` (the largest tracking error passed to the policy [m]),
``path_end_s`` (when the time-scaled path reached its end [s], NaN if not within the run),
``path_extra_s`` (that, less the path's nominal end time [s]) and ``fruits_picked``.

**Picking.** A grasp target that is one of the camera's scenery spheres (a canopy's fruit) is
picked when the controller's task point comes within the sphere's radius of its centre while it is
the current target (the gripper closes about it): the camera no longer sees it (it is harvested,
:attr:`~qpctl.simulation.camera.DepthCamera.visible`), so when the path moves on to the next fruit
the one just picked does not become a rigid obstacle at the hand. (Scenery is unlabelled, and an
unlabelled point is rigid: before this the picked fruit, still on its tree in the simulation,
reappeared in the rigid channel a few centimetres from the hand the moment the target moved on —
inside the rigid rows' margin, where the QP was infeasible for up to 1.3 s of safe stop.) A fruit
the hand never got that near stays on the tree and in the map.

**The waiting reference** (:mod:`qpctl.perception.stale`): before each tick the loop passes the
stale policy the task's tracking error e = |x − x_d| [m] of the controller's last tick (the task
point and the reference its output carries, over the position rows) when that tick's soft pairs put
a link within :meth:`~qpctl.perception.config.PerceptionConfig.lag_reach`
of a leaf's voxels (where the soft speed rows hold it to at most 2·``soft_speed``), and 0
elsewhere; κ_lag then slows the path while the arm lags in the leaves.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import fcl
import numpy as np

from qpctl.geometry.obstacles import Obstacle
from qpctl.perception.config import SQRT3_2
from qpctl.perception.misses import explain_misses
from qpctl.perception.perception import Perception
from qpctl.perception.rows import FieldBarrier
from qpctl.perception.snapshot import MapSnapshot
from qpctl.perception.stale import SLOW, STOP, TimeScaledPath
from qpctl.robot.model import RobotModel

PHANTOM_EVERY = 10  # ticks between two phantom-row checks
MAP_RECORD_EVERY = 0.5  # [s] between two snapshots whose occupied voxels the run keeps (the replay's map)


class MapLoop:
    """Camera → map → rows in a simulation (module docstring).

    Args:
        perception: the controller's map (inline: the loop builds it).
        barrier: the controller's field rows (their pairs are measured).
        camera: a :class:`~qpctl.simulation.camera.DepthCamera` (``due``, ``capture``), or None
            (the map stays as given).
        robot: the robot.
        rigid, soft: the world's true rigid and soft obstacles (perceived and known).
        path: the controller's time-scaled reference (None: the stale policy is only recorded).
        controller: the controller, whose last output's tracking error the waiting reference reads
            (None: the path never waits for the arm).
        dt: the control period [s].
        targets: the grasp targets in order (the path's waypoints) and the path times [s] from which
            each is current; None: no target exclusion.
    """

    def __init__(self, perception: Perception, barrier: FieldBarrier, camera: Any, robot: RobotModel,
                 rigid: Sequence[Obstacle], soft: Sequence[Obstacle], *, path: TimeScaledPath | None = None,
                 dt: float = 1e-3, targets: tuple[np.ndarray, np.ndarray] | None = None,
                 controller: Any = None) -> None:
        self.perception, self.barrier, self.camera, self.robot = perception, barrier, camera, robot
        self.path, self.controller = path, controller
        self.path_nominal_end = float(getattr(path.path, "end_time", math.nan)) if path is not None else math.nan
        self.dt = float(dt)
        self.targets = targets
        self.rigid, self.soft = list(rigid), list(soft)
        cfg = perception.config
        self.phantom_tolerance = 2 * SQRT3_2 * cfg.voxel + cfg.depth_noise  # [m]
        self.lag_reach = cfg.lag_reach()  # [m] a link this near a leaf's voxels: its lag slows the path
        self._pending: list[tuple[float, MapSnapshot]] = []
        self._soft_world: Any = None
        self._soft_dyn: Any = None
        self._manager: Any = None
        self._pick_shape = self._pick_shapes()
        self.reset()

    def _pick_shapes(self) -> list[tuple[int, float]]:
        """Per grasp target, the camera's scenery shape at it (index, radius [m]), or (−1, 0)."""
        if self.targets is None or self.camera is None or not getattr(self.camera, "scenery", None):
            return []
        base = len(self.camera.obstacles)
        out = []
        for p in self.targets[0]:
            match = (-1, 0.0)
            for j, o in enumerate(self.camera.scenery):
                if o.shape == "sphere" and float(np.linalg.norm(o.position - p)) <= 1e-9 + 1e-6 * o.radius:
                    match = (base + j, float(o.radius))
            out.append(match)
        return out

    def warmup(self, q: np.ndarray) -> None:
        """Compile (or load) the map's kernels on a frame at q, in a map of its own: the run's first
        frame then costs its build, not numba's compilation."""
        if self.camera is None:
            return
        from qpctl.perception.depth_map import DepthMap

        scratch = DepthMap(self.perception.config, self.robot)
        scratch.record(0.0, q)
        scratch.update(self.camera.capture(q, 0.0))

    def reset(self) -> None:
        self._pending.clear()
        self.build_ms: list[float] = []  # wall clock, frame to snapshot [ms]
        self.build_cpu_ms: list[float] = []  # the building thread's CPU time [ms]
        self.latency_ms: list[float] = []
        self.age_ms: list[float] = []
        self.map_clearance = math.inf
        self.soft_clearance = math.inf
        self.soft_speed_max = 0.0
        self.phantom = 0
        self.checked_rows = 0
        self.slow_ticks = 0
        self.stop_ticks = 0
        self.lag_ticks = 0
        self.lag_max = 0.0
        self.path_end = math.nan
        self.frames = 0
        self.soft_approach_max = 0.0
        self.sample: tuple[Any, np.ndarray, MapSnapshot, np.ndarray] | None = None
        self._sample_self = -1
        self._used: float = -math.inf
        self.series: dict[str, list[float]] = {"t": [], "map_clearance": [], "age_ms": [], "kappa": [], "lag": []}
        self._map_points: list[np.ndarray] = []
        self._map_stamps: list[np.ndarray] = []
        self._next_record = -math.inf
        self._target_index = -1
        self.picked = 0
        for idx, _ in self._pick_shape:  # every fruit back on its tree
            if idx >= 0:
                self.camera.visible[idx] = True
        self.perception.policy.reset()

    # -- the hook -------------------------------------------------------------------------------
    def before(self, t: float, q: np.ndarray, v: np.ndarray) -> None:
        p = self.perception
        p.record(t, q)
        if self.targets is not None:  # the waypoint the path is heading for, on the path's own clock
            points, starts = self.targets
            s = self.path.s if self.path is not None else t
            i = int(np.searchsorted(starts, s, side="right")) - 1
            self._target_index = max(i, 0)
            p.set_target(points[self._target_index])
        if self.camera is not None and self.camera.due(t, self.dt):
            frame = self.camera.capture(q, t)
            c0 = time.thread_time()
            snap = p.map.update(frame)
            cpu = time.thread_time() - c0
            self.build_ms.append(snap.build_ms)
            self.build_cpu_ms.append(cpu * 1e3)
            self.frames += 1
            self._pending.append((frame.stamp + p.config.latency, snap))
            rep = p.map.last_report
            if rep is not None and rep.counts["self"] >= self._sample_self:  # the figure's frame
                self._sample_self = rep.counts["self"]
                self.sample = (frame, rep.status, snap, np.array(q, float))
        ready = [s for when, s in self._pending if when <= t + 1e-12]
        if ready:
            p.publish(ready[-1])
            if t >= self._next_record - 1e-12:  # the map as the controller has it from t (the replay's)
                self._record_map(ready[-1], t)
                self._next_record = t + MAP_RECORD_EVERY
            self._pending = [(w, s) for w, s in self._pending if w > t + 1e-12]
        snap = p.snapshot
        if snap.stamp != self._used and math.isfinite(snap.stamp):
            self._used = snap.stamp
            self.latency_ms.append((t - snap.stamp) * 1e3)
        lag = self._lag()
        st = p.staleness(t, lag)
        if self.path is not None:
            self.path.advance(t, st.kappa)
            if math.isnan(self.path_end) and self.path.s >= self.path_nominal_end - 1e-9:
                self.path_end = t
        self.lag_ticks += st.lag_kappa < 1.0
        self.lag_max = max(self.lag_max, lag)
        if math.isfinite(st.age):
            self.age_ms.append(st.age * 1e3)
        self.slow_ticks += st.mode == SLOW
        self.stop_ticks += st.mode == STOP
        self.series["t"].append(t)
        self.series["age_ms"].append(st.age * 1e3 if math.isfinite(st.age) else np.nan)
        self.series["kappa"].append(st.kappa)
        self.series["lag"].append(lag)

    def _lag(self) -> float:
        """The tracking error |x − x_d| [m] the policy is given (module docstring): the controller's last
        output's, over the position rows; 0 before the first tick, without a time-scaled path or while
        the last tick's soft pairs keep every link farther than ``lag_reach`` from a leaf's voxels."""
        pairs = self.barrier.last
        last = getattr(self.controller, "last", None)
        if self.path is None or pairs is None or last is None:
            return 0.0
        soft = pairs.distance[pairs.soft]
        if not soft.size or not float(soft.min()) <= self.lag_reach:
            return 0.0
        m = self.robot.m_position
        return float(np.linalg.norm(last.x[:m] - last.ref.x[:m]))

    def after(self, k: int, t: float, q: np.ndarray, v: np.ndarray) -> None:
        pairs = self.barrier.last
        believed = math.inf
        if pairs is not None:
            rigid = pairs.active & ~pairs.soft
            if rigid.any():
                believed = float(pairs.distance[rigid].min())
                if k % PHANTOM_EVERY == 0:
                    r = self.barrier.radii[pairs.link[rigid]]
                    axis = pairs.point[rigid] + r[:, None] * pairs.normal[rigid]
                    self._check_phantoms(axis, pairs.distance[rigid] + r, t)
        self.map_clearance = min(self.map_clearance, believed)
        self.series["map_clearance"].append(believed)
        if self.soft:
            self._measure_soft(q, v, t)
        if self._pick_shape and self._target_index >= 0:
            self._try_pick()

    def _try_pick(self) -> None:
        """Pick the current target's fruit when the task point is within its radius (module docstring)."""
        idx, radius = self._pick_shape[self._target_index]
        last = getattr(self.controller, "last", None)
        if idx < 0 or last is None or not self.camera.visible[idx]:
            return
        centre = self.targets[0][self._target_index]  # type: ignore[index]
        if float(np.linalg.norm(np.asarray(last.x[:3]) - centre)) <= radius:
            self.camera.visible[idx] = False
            self.picked += 1

    def _record_map(self, snap: MapSnapshot, t: float) -> None:
        """Keep the snapshot's occupied voxel centres (both channels) [m], from t [s] on."""
        occupied = np.argwhere((snap.dist[0] <= 0.0) | (snap.dist[1] <= 0.0))
        self._map_points.append(snap.grid.centres(occupied))
        self._map_stamps.append(np.full(len(occupied), t))

    def explain_misses(self, traj: Any, fruits: np.ndarray) -> list[dict[str, Any]]:
        """The fruits (path order) the task point missed by more than 5 mm, each with its cause
        (:func:`qpctl.perception.misses.explain_misses`, on this run's records)."""
        n = min(len(traj.t), len(self.series["map_clearance"]), len(self.series["kappa"]))
        return explain_misses(fruits, traj.t[:n], traj.x, traj.x_ref, traj.q, q_min=self.robot.q_min,
                              q_max=self.robot.q_max, clearance=traj.clearance,
                              fallback=traj.qp_fallback, believed=np.asarray(self.series["map_clearance"][:n]),
                              margin=self.barrier.margin, kappa=np.asarray(self.series["kappa"][:n]))

    def map_points(self) -> tuple[np.ndarray, np.ndarray]:
        """The recorded maps (every ``MAP_RECORD_EVERY`` s of the run): occupied voxel centres (K, 3) [m]
        and the time each snapshot reached the controller (K,) [s] — the replay's ``map_points`` and
        ``map_stamps``."""
        if not self._map_points:
            return np.zeros((0, 3)), np.zeros(0)
        return np.concatenate(self._map_points), np.concatenate(self._map_stamps)

    # -- truth ------------------------------------------------------------------------------------
    def _check_phantoms(self, axis: np.ndarray, field: np.ndarray, t: float) -> None:
        """Count the rows whose field value at their axis point (``field`` [m]) is short of the true
        distance from that point to the world's obstacles by more than the tolerance: the map saw
        something nearer than anything there is (noise, a flying pixel, the robot itself)."""
        if self._manager is None:
            objs = [fcl.CollisionObject(o.geometry(), o.transform(0.0)) for o in self.rigid + self.soft]
            self._moving = [(obj, o) for obj, o in zip(objs, self.rigid + self.soft, strict=True) if o.moving]
            self._manager = fcl.DynamicAABBTreeCollisionManager()
            self._manager.registerObjects(objs)
            self._manager.setup()
            self._probe = fcl.CollisionObject(fcl.Sphere(1e-6))
        for obj, o in self._moving:
            obj.setTransform(o.transform(t))
        if self._moving:
            self._manager.update()
        for c, d in zip(axis, field, strict=True):
            self.checked_rows += 1
            true = math.inf
            if self.rigid or self.soft:
                self._probe.setTransform(fcl.Transform(c))
                data = fcl.DistanceData()
                self._manager.distance(self._probe, data, fcl.defaultDistanceCallback)
                true = data.result.min_distance
            if true - d > self.phantom_tolerance:
                self.phantom += 1

    def _measure_soft(self, q: np.ndarray, v: np.ndarray, t: float) -> None:
        from qpctl.dynamics import Dynamics
        from qpctl.tick import WorldClearance

        if self._soft_world is None:
            self._soft_world = WorldClearance(self.robot, self.soft)
            self._soft_dyn = Dynamics(self.robot, self.soft, cutoff=0.0)
        d = float(self._soft_world(q, t))
        self.soft_clearance = min(self.soft_clearance, d)
        if d < 0.0:
            state = self._soft_dyn.compute(q, v, t)
            inside = state.pairs.distance < 0.0
            if inside.any():
                vel = np.einsum("kin,n->ki", state.pair_jac[inside], v)
                self.soft_speed_max = max(self.soft_speed_max, float(np.linalg.norm(vel, axis=1).max()))
                approach = -np.einsum("ki,ki->k", state.pairs.normal[inside], vel)  # into the leaf
                self.soft_approach_max = max(self.soft_approach_max, float(approach.max()))

    # -- results ----------------------------------------------------------------------------------
    def metrics(self) -> dict[str, Any]:
        def stat(v: list[float], q: float) -> float:
            return float(np.percentile(v, q)) if v else math.nan

        return {
            "map_min_clearance": self.map_clearance,
            "map_age_ms_max": max(self.age_ms) if self.age_ms else math.nan,
            "map_update_ms_median": stat(self.build_ms, 50),
            "map_update_ms_p99": stat(self.build_ms, 99),
            "map_update_cpu_ms_median": stat(self.build_cpu_ms, 50),
            "map_update_cpu_ms_p99": stat(self.build_cpu_ms, 99),
            "map_latency_ms_p99": stat(self.latency_ms, 99),
            "map_frames": self.frames,
            "map_updates_over_latency": sum(c > self.perception.config.latency * 1e3 for c in self.build_cpu_ms),
            "min_soft_clearance": self.soft_clearance,
            "soft_contact_max_speed": self.soft_speed_max,
            "soft_contact_max_approach_speed": self.soft_approach_max,
            "phantom_rows": self.phantom,
            "phantom_rows_checked": self.checked_rows,
            "stale_slow_ticks": self.slow_ticks,
            "stale_stop_ticks": self.stop_ticks,
            "lag_ticks": self.lag_ticks,
            "lag_max_m": self.lag_max,
            "path_end_s": self.path_end,
            "path_extra_s": self.path_end - self.path_nominal_end,
            "fruits_picked": self.picked,
        }


    def write_figures(self, out: Path, t: np.ndarray, clearance: np.ndarray, d_safe: float) -> list[Path]:
        """The map's three figures into ``out``: a depth frame and its pixels' fate, a slice of the field
        at the hand's height, the true against the believed clearance."""
        from qpctl.perception.figures import clearance_figure, depth_frame_figure, field_slice_figure

        files = []
        if self.sample is not None:
            frame, status, snap, q = self.sample
            files.append(depth_frame_figure(out / "depth_frame.png", frame, status))
            segs = self.barrier.segments(q)
            files.append(field_slice_figure(out / "field_slice.png", snap, float(segs[-1, 1, 2]), segments=segs))
        n = min(len(t), len(self.series["map_clearance"]))
        files.append(clearance_figure(out / "clearance_true_vs_map.png", t[:n], clearance[:n],
                                      np.asarray(self.series["map_clearance"][:n]), d_safe, self.barrier.margin,
                                      np.asarray(self.series["age_ms"][:n])))
        return files


def attach(controller: Any, simulator: Any, config: Any, *, camera: Any = None, world: Sequence[Obstacle] = (),
           perception: Perception | None = None, time_scaled: bool = True,
           targets: tuple[np.ndarray, np.ndarray] | None = None) -> MapLoop:
    """Give a QP ``controller`` the depth map's rows and ``simulator`` the loop that feeds them.

    The controller gets a :class:`FieldBarrier` reading ``perception`` (a new one of ``config`` when
    None) and, with ``time_scaled``, its path wrapped in a :class:`TimeScaledPath` the stale policy
    drives; the simulator gets a :class:`MapLoop` hook. ``world``: the true obstacles (their
    ``material`` splits them for the metrics)."""
    robot = controller.robot
    p = perception if perception is not None else Perception(config, robot)
    barrier = p.rows_for(controller)
    scaled = None
    if time_scaled:
        scaled = TimeScaledPath(controller.path)
        controller.path = scaled
    controller._ws = None  # rebuilt on the next tick: the field's rows compiled, the path read in Python
    controller.warm = False
    rigid = [o for o in world if o.material != "soft"]
    soft = [o for o in world if o.material == "soft"]
    loop = MapLoop(p, barrier, camera, robot, rigid, soft, path=scaled, dt=simulator.dt, targets=targets,
                   controller=controller)
    loop.warmup(robot.q_home)
    simulator.hooks.append(loop)
    return loop
