"""Backends of the sweep engine: local processes (the default) and Ray.

* :class:`LocalBackend` — ``jobs`` worker processes (``concurrent.futures.ProcessPoolExecutor``),
  at most two items per worker in flight; with ``jobs <= 1`` the items run one after another in this
  process (what a benchmark that times ticks wants: a quiet process, no pickling). A worker that dies
  (killed, out of memory) breaks the pool: a new pool takes over, the items that were in flight are
  tried once more, and an item in flight at two deaths is reported failed.
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
    """A worker process died while running the item (twice, for the local backend)."""


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
        deaths = [0] * len(items)
        window = 2 * self.workers
        while todo:
            pool = ProcessPoolExecutor(max_workers=self.workers)
            running: dict[Future[Any], int] = {}
            broken = False
            try:
                while (todo or running) and not broken:
                    while todo and len(running) < window:
                        i = todo.popleft()
                        running[pool.submit(_call, fn, items[i])] = i
                    done, _ = wait(running, return_when=FIRST_COMPLETED)
                    for fut in done:
                        i = running.pop(fut)
                        exc = fut.exception()
                        if isinstance(exc, BrokenProcessPool):
                            broken = True
                            deaths[i] += 1
                            if deaths[i] >= 2:
                                yield Outcome(i, error=WorkerDied(f"the worker process died running it ({exc})"))
                            else:
                                todo.appendleft(i)
                        elif exc is not None:
                            yield Outcome(i, error=exc)
                        else:
                            yield Outcome(i, fut.result())
                if broken:  # every item still in flight went down with the pool: try each again
                    for fut, i in running.items():
                        deaths[i] += 1
                        if deaths[i] >= 2:
                            yield Outcome(i, error=WorkerDied("the worker process died running it"))
                        else:
                            todo.appendleft(i)
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
            if address is None:
                kwargs["num_cpus"] = num_cpus or os.cpu_count() or 1
                # the workers import qpctl as this process does (an installed or editable package)
                kwargs["runtime_env"] = {"env_vars": {"RAY_DEDUP_LOGS": "0"}}
            try:
                ray.init(address=address, **kwargs)
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
                    cause = exc.as_instanceof_cause()
                    yield Outcome(i, error=getattr(cause, "cause", None) or cause)
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
