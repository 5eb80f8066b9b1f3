"""The sweep engine: call one function on many argument tuples through a backend, as results come.

:func:`execute` yields an :class:`Outcome` per item as soon as it is done (in completion order), with
a progress bar (tqdm) that shows the ETA and the failures; :func:`map_ordered` is the plain
"all results, in order, or the first error" form. Backends (:mod:`qpctl.sweep.backends`): local
processes (``concurrent.futures``; one job runs in this process) and Ray. A call that raises gives a
failed outcome with its message; the other items go on.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, Protocol


@dataclass(frozen=True)
class Outcome:
    """What one item gave: ``value`` or, if the call raised (or its worker died), ``error``."""

    index: int
    value: Any = None
    error: BaseException | None = None

    @property
    def ok(self) -> bool:
        return self.error is None

    @property
    def message(self) -> str:
        """The error as one line, ``Type: message`` ("" when the call succeeded)."""
        if self.error is None:
            return ""
        return f"{type(self.error).__name__}: " + " ".join(str(self.error).split())


class Backend(Protocol):
    """Runs ``fn(*args)`` for every item, yielding outcomes as they finish."""

    name: str
    workers: int

    def imap_unordered(self, fn: Callable[..., Any], items: Sequence[tuple[Any, ...]]) -> Iterator[Outcome]: ...

    def close(self) -> None: ...


def execute(fn: Callable[..., Any], items: Sequence[tuple[Any, ...]], backend: Backend, *, progress: bool = True,
            desc: str = "sweep", label: Callable[[int], str] | None = None,
            failed: Callable[[Outcome], bool] | None = None) -> Iterator[Outcome]:
    """``fn(*items[i])`` for every i through ``backend``: outcomes as they finish, with a progress bar
    (ETA; ``failures=N`` counts the outcomes that raised, or that ``failed`` says failed)."""
    from tqdm import tqdm

    bar = tqdm(total=len(items), desc=desc, unit="run", disable=not progress, dynamic_ncols=True)
    failures = 0
    try:
        for out in backend.imap_unordered(fn, items):
            if not out.ok or (failed is not None and failed(out)):
                failures += 1
            post = f"failures={failures}" if failures else ""
            if label is not None:
                post = f"{label(out.index)} {post}".strip()
            bar.set_postfix_str(post, refresh=False)
            bar.update()
            yield out
    finally:
        bar.close()


def map_ordered(fn: Callable[..., Any], items: Sequence[tuple[Any, ...]], backend: Backend, *,
                progress: bool = True, desc: str = "runs", label: Callable[[int], str] | None = None) -> list[Any]:
    """Every ``fn(*item)``, in the items' order; the first call that raises is raised here."""
    values: list[Any] = [None] * len(items)
    for out in execute(fn, items, backend, progress=progress, desc=desc, label=label):
        if out.error is not None:
            raise out.error
        values[out.index] = out.value
    return values
