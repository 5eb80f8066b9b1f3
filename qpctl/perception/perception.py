"""The user's handle on the depth map: frames in, the newest snapshot and its staleness out.

A :class:`Perception` is what a controller reads (``QPController(..., perception=p)``) and what a
camera driver feeds (:meth:`Perception.update_map` with a depth image, its intrinsics, the camera's
pose and the stamp, or :meth:`Perception.submit` with a frame or cloud). With ``threaded=True`` a
:class:`~qpctl.perception.worker.MapWorker` builds the map beside the control loop; otherwise each
frame is built in the caller's thread. Either way the controller's tick only reads
:attr:`Perception.snapshot` — it never waits for a map — and :meth:`Perception.staleness` applies the
stale-map policy (:mod:`qpctl.perception.stale`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from qpctl.perception.config import PerceptionConfig
from qpctl.perception.depth_map import DepthMap, Frame
from qpctl.perception.frames import DepthFrame, Intrinsics
from qpctl.perception.snapshot import MapSnapshot
from qpctl.perception.stale import Staleness, StalePolicy
from qpctl.perception.worker import MapWorker
from qpctl.robot.model import RobotModel

if TYPE_CHECKING:
    from typing_extensions import Self


class Perception:
    """A depth map, its newest snapshot and the stale-map policy (module docstring).

    Args:
        config: the ``[perception]`` settings (defaults: :class:`PerceptionConfig`'s).
        robot: the robot to self-filter (None: none).
        threaded: build maps in a worker thread (:meth:`close` stops it).
    """

    def __init__(self, config: PerceptionConfig | None = None, robot: RobotModel | None = None, *,
                 threaded: bool = False) -> None:
        self.config = config or PerceptionConfig()
        self.map = DepthMap(self.config, robot)
        c = self.config
        self.policy = StalePolicy(c.stale_slow, c.stale_stop, lag_slow=c.lag_slow, lag_stop=c.lag_stop or None,
                                  lag_rate=c.lag_rate)
        self._latest = MapSnapshot.empty(self.map.grid, self.config.truncation)
        self.build_ms: list[float] = []  # each snapshot's build time (frame arrival to snapshot) [ms]
        self.worker = MapWorker(self.map, on_snapshot=self._built).start() if threaded else None

    def _built(self, snap: MapSnapshot) -> None:
        self.build_ms.append(snap.build_ms)

    @property
    def snapshot(self) -> MapSnapshot:
        """The newest complete map (an empty one, stamped −inf, before the first frame)."""
        return self.worker.latest if self.worker is not None else self._latest

    def submit(self, frame: Frame) -> None:
        """A frame or cloud for the map: built now (unthreaded) or by the worker (threaded)."""
        if self.worker is not None:
            self.worker.submit(frame)
            return
        self._latest = self.map.update(frame)
        self._built(self._latest)

    def publish(self, snapshot: MapSnapshot) -> None:
        """Make ``snapshot`` the controller's map (a simulation does, when its build time has passed
        on the simulated clock: :mod:`qpctl.perception.closed_loop`)."""
        if self.worker is not None:
            self.worker.latest = snapshot
        else:
            self._latest = snapshot

    def update_map(self, depth: np.ndarray, intrinsics: Intrinsics, pose: np.ndarray, stamp: float, *,
                   labels: np.ndarray | None = None, depth_scale: float = 1.0) -> None:
        """A depth image (H×W [m], or integers × ``depth_scale`` [m/unit]) with its pinhole
        ``intrinsics``, the camera's ``pose`` in the base frame (4×4, optical frame) and its ``stamp``
        [s] on the controller's clock; optional per-pixel ``labels`` (rigid/soft)."""
        self.submit(DepthFrame(depth, intrinsics, pose, stamp, labels=labels, depth_scale=depth_scale))

    def rows_for(self, controller: Any) -> Any:
        """Give a QP ``controller`` this map's barrier rows (a :class:`~qpctl.perception.rows.FieldBarrier`
        with its d_safe, influence distance and barrier gains) and return them."""
        from qpctl.perception.rows import FieldBarrier

        cfg = getattr(controller, "config", None)
        barrier = FieldBarrier(self, controller.robot, self.config, d_safe=controller.gains.d_safe,
                               cutoff=controller.cutoff, k0=getattr(cfg, "barrier_k0", 400.0),
                               k1=getattr(cfg, "barrier_k1", 40.0), torque=controller.torque_limit())
        controller.add_constraint(barrier)
        return barrier

    def record(self, t: float, q: np.ndarray) -> None:
        """The robot's joint positions q [rad] at t [s] (the self-filter looks them up at a frame's stamp)."""
        self.map.record(t, q)

    def set_target(self, target: np.ndarray | None) -> None:
        """The grasp target [m] (its zone is not an obstacle), or None."""
        self.map.set_target(target)

    def staleness(self, t: float, lag: float = 0.0) -> Staleness:
        """The stale-map policy's verdict at t [s] for the newest snapshot and the task's tracking error
        ``lag`` [m] (pass it while a link is within :meth:`PerceptionConfig.lag_reach` of a leaf, 0
        elsewhere: the path then waits for an arm held back in the leaves; :mod:`qpctl.perception.stale`)."""
        return self.policy(t, self.snapshot.age(t), lag)

    def close(self) -> None:
        """Stop the worker thread, if any."""
        if self.worker is not None:
            self.worker.stop()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

