"""Off the control loop: the map built at camera rate in a worker thread, handed over as a snapshot.

:class:`MapWorker` owns a thread that takes the newest submitted frame (a one-frame mailbox: a frame
that arrives while the previous one is being built replaces the waiting one, and is counted as
dropped), runs :meth:`~qpctl.perception.DepthMap.update` on it and publishes the resulting
:class:`~qpctl.perception.MapSnapshot` by one reference assignment. The control loop reads
:attr:`MapWorker.latest` and never waits: a snapshot is complete before it is published and never
changes afterwards. The map's kernels release the interpreter's lock (numba ``nogil``), so the
thread costs the control loop little; ``benchmarks/perception.py`` measures the tick's p99 with the
worker at 30 Hz beside it.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from qpctl.errors import PerceptionError
from qpctl.perception.depth_map import DepthMap, Frame
from qpctl.perception.snapshot import MapSnapshot

if TYPE_CHECKING:
    from typing_extensions import Self


class MapWorker:
    """A thread that turns submitted frames into snapshots (module docstring).

    Args:
        depth_map: the map it updates (only this thread touches it while the worker runs).
        on_snapshot: called in the worker's thread with each new snapshot (e.g. to log it).
    """

    def __init__(self, depth_map: DepthMap, on_snapshot: Callable[[MapSnapshot], None] | None = None) -> None:
        self.map = depth_map
        self.on_snapshot = on_snapshot
        self.latest: MapSnapshot = MapSnapshot.empty(depth_map.grid, depth_map.config.truncation)
        self.dropped = 0  # frames replaced in the mailbox before they were built
        self.built = 0
        self.error: BaseException | None = None  # what stopped the thread, if anything did
        self._pending: tuple[Frame, float] | None = None
        self._cv = threading.Condition()
        self._stop = False
        self._thread: threading.Thread | None = None

    def start(self) -> MapWorker:
        if self._thread is None:
            self._stop = False
            self._thread = threading.Thread(target=self._run, name="qpctl-map-worker", daemon=True)
            self._thread.start()
        return self

    def stop(self, timeout: float = 5.0) -> None:
        """Stop the thread after the frame it is building (the mailbox's frame is discarded)."""
        with self._cv:
            self._stop = True
            self._cv.notify()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def submit(self, frame: Frame) -> None:
        """Hand a frame to the worker; returns at once. A frame still waiting is replaced (dropped).
        Raises the :class:`PerceptionError` that stopped the worker, if one did."""
        if self.error is not None:
            raise PerceptionError(f"the map worker stopped: {self.error}") from self.error
        if self._thread is None:
            raise PerceptionError("the map worker is not running (call start())")
        with self._cv:
            if self._pending is not None:
                self.dropped += 1
            self._pending = (frame, time.perf_counter())
            self._cv.notify()

    def wait_idle(self, timeout: float = 10.0) -> bool:
        """Block until the mailbox is empty and the last frame is built (for tests and scripts)."""
        end = time.perf_counter() + timeout
        while time.perf_counter() < end:
            with self._cv:
                if self._pending is None and not self._busy:
                    return True
            time.sleep(0.001)
        return False

    _busy = False

    def _run(self) -> None:
        while True:
            with self._cv:
                while self._pending is None and not self._stop:
                    self._cv.wait()
                if self._stop:
                    return
                assert self._pending is not None
                frame, arrived = self._pending
                self._pending = None
                self._busy = True
            try:
                self.map.integrate(frame)
                snap = self.map.snapshot(started=arrived)
            except BaseException as exc:  # noqa: BLE001 - kept and re-raised to the submitter
                self.error = exc
                self._busy = False
                return
            self.latest = snap  # one assignment: readers see the old snapshot or the new one, whole
            self.built += 1
            self._busy = False
            if self.on_snapshot is not None:
                self.on_snapshot(snap)
