"""Backends of the sweep engine: local processes (the default) and Ray.

* :class:`LocalBackend` — ``jobs`` worker processes (``concurrent.futures.ProcessPoolExecutor``),
  at most two items per worker in flight; with ``jobs <= 1`` the items run one after another in this
  process (what a benchmark that times ticks wants: a quiet process, no pickling). A worker that dies
  (killed, out of memory) breaks the pool: a new pool takes over and runs the items that were in
  flight again, one at a time; the one whose worker dies again, alone, is reported failed.
* :class:`RayBackend` — one Ray task per item (``num_cpus=1``), at most two per CPU in flight;
  ``address`` is ``auto``, ``ray://host:port`` or None (``ray.init()`` starts a local instance with
  ``num_cpus`` CPUs). Ray retries a task whose worker died once, then reports it failed.
"""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any

from qpctl.errors import ConfigError
from qpctl.sweep.engine import Backend, Outcome

BACKENDS = ("local", "ray")


class WorkerDied(RuntimeError):
    """A worker process died while running the item (for the local backend: twice, the second time alone)."""


def _call(fn: Callable[..., Any], args: tuple[Any, ...]) -> Any:
    return fn(*args)


class LocalBackend:
    """Local worker processes; ``jobs <= 1`` runs the items in this process."""

    name = "local"

    def __init__(self, jobs: int | None = None) -> None:
        self.workers = max(1, int(jobs if jobs is not None else (os.cpu_count() or 1)))

    def imap_unordered(self, fn: Callable[..., Any], items: Sequence[tuple[Any, ...]]) -> Iterator[Outcome]:
        if self.workers <= 1:
            for i, args in enumerate(items):
                try:
                    value = fn(*args)
                except Exception as exc:  # noqa: BLE001 — a failed item; the others go on
                    yield Outcome(i, error=exc)
                else:
                    yield Outcome(i, value)
            return
        yield from self._pool(fn, items)

    def _pool(self, fn: Callable[..., Any], items: Sequence[tuple[Any, ...]]) -> Iterator[Outcome]:
        todo = deque(range(len(items)))
        suspects: deque[int] = deque()  # in flight when a worker died: each is tried again, alone
        window = 2 * self.workers
        while todo or suspects:
            pool = ProcessPoolExecutor(max_workers=self.workers)
            running: dict[Future[Any], int] = {}
            alone = -1  # the suspect running by itself: if the pool breaks now, it is the one that kills
            broken = False
            try:
                while (todo or suspects or running) and not broken:
                    if suspects:
                        if not running:
                            alone = suspects.popleft()
                            running[pool.submit(_call, fn, items[alone])] = alone
                    else:
                        while todo and len(running) < window:
                            i = todo.popleft()
                            running[pool.submit(_call, fn, items[i])] = i
                    done, _ = wait(running, return_when=FIRST_COMPLETED)
                    for fut in done:
                        i = running.pop(fut)
                        exc = fut.exception()
                        if isinstance(exc, BrokenProcessPool):
                            broken = True
                            if i == alone:
                                yield Outcome(i, error=WorkerDied(f"the worker process died running it ({exc})"))
                            else:
                                suspects.append(i)
                        elif exc is not None:
                            yield Outcome(i, error=exc)
                        else:
                            yield Outcome(i, fut.result())
                suspects.extend(running.values())  # a broken pool took them down too
            finally:
                pool.shutdown(wait=not broken, cancel_futures=True)

    def close(self) -> None:
        pass


class RayBackend:
    """Ray tasks on a cluster (``address``) or on a local instance that ``ray.init()`` starts."""

    name = "ray"

    def __init__(self, address: str | None = None, num_cpus: int | None = None) -> None:
        try:
            import ray
        except ImportError as exc:
            raise ConfigError(f"Ray is not installed ({exc}); pip install 'qpctl[ray]'", key="--backend") from None
        self._ray = ray
        self._started = False
        if not ray.is_initialized():
            kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False,
                                      "configure_logging": False}
            if address is None:  # a new local instance, never a cluster that happens to run on this machine
                kwargs["num_cpus"] = num_cpus or os.cpu_count() or 1
            try:
                ray.init(address=address or "local", **kwargs)
            except (ConnectionError, ValueError, RuntimeError) as exc:
                raise ConfigError(f"cannot reach a Ray cluster at {address!r}: {exc}", key="--address") from None
            self._started = True
        self.workers = max(1, int(ray.cluster_resources().get("CPU", 1)))
        self._remote = ray.remote(num_cpus=1, max_retries=1)(_call)

    def imap_unordered(self, fn: Callable[..., Any], items: Sequence[tuple[Any, ...]]) -> Iterator[Outcome]:
        ray = self._ray
        fn_ref = ray.put(fn)
        todo = deque(range(len(items)))
        running: dict[Any, int] = {}
        window = 2 * self.workers
        while todo or running:
            while todo and len(running) < window:
                i = todo.popleft()
                running[self._remote.remote(fn_ref, items[i])] = i
            done, _ = ray.wait(list(running), num_returns=1)
            for ref in done:
                i = running.pop(ref)
                try:
                    value = ray.get(ref)
                except ray.exceptions.RayTaskError as exc:  # the call raised: its own exception
                    yield Outcome(i, error=getattr(exc, "cause", None) or exc)
                except ray.exceptions.RayError as exc:  # the worker died (after Ray's retry)
                    yield Outcome(i, error=WorkerDied(f"the Ray worker died running it ({type(exc).__name__})"))
                else:
                    yield Outcome(i, value)

    def close(self) -> None:
        if self._started:
            self._ray.shutdown()
            self._started = False


def make_backend(name: str = "local", *, jobs: int | None = None, address: str | None = None) -> Backend:
    """A backend by name: ``local`` (``jobs`` processes) or ``ray`` (``address``; a local instance with
    ``jobs`` CPUs when there is no address)."""
    if name == "local":
        if address:
            raise ConfigError("--address is for the ray backend", key="--address")
        return LocalBackend(jobs)
    if name == "ray":
        return RayBackend(address, num_cpus=jobs)
    raise ConfigError(f"unknown backend {name!r}; one of {', '.join(BACKENDS)}", key="--backend")
