"""The tick's compiled kernels, one module per stage (docs/tick.md has the map); the entry points
Python calls are in :mod:`qpctl.kernels.tick`.

numba caches each kernel on disk and invalidates a cached kernel only when *its own* source file
changes: a kernel that calls one in another module (every entry point does) would keep the old
callee's code after that module is edited. So on import this package compares a digest of all its
modules' sources with the one stored beside numba's cache and, when they differ, removes the cached
kernels of this folder (they compile again, or load once recompiled): an edit to any stage reaches
every kernel that calls it.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

_STAMP = "qpctl-kernels.sha256"


def _cache_probe() -> None:
    """A function of this folder: numba's cache locator for it gives the folder's cache path."""


def _cache_path() -> str | None:
    """Where numba keeps this folder's cached kernels (None when it cannot tell)."""
    try:
        from numba.core.caching import CompileResultCacheImpl

        return str(CompileResultCacheImpl(_cache_probe).locator.get_cache_path())
    except Exception:  # noqa: BLE001 — another numba: no guard (numba's own invalidation still holds)
        return None


def sources_digest() -> str:
    """SHA-256 of every module of this package (name and contents)."""
    h = hashlib.sha256()
    for path in sorted(Path(__file__).parent.glob("*.py")):
        h.update(path.name.encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def invalidate_stale_cache() -> bool:
    """Remove this folder's cached kernels if any kernel module changed since they were cached;
    returns whether it removed them."""
    path = _cache_path()
    if path is None:
        return False
    try:
        os.makedirs(path, exist_ok=True)  # numba's own folder: kernels cached from now on are of this digest
    except OSError:
        return False
    digest = sources_digest()
    stamp = os.path.join(path, _STAMP)
    try:
        with open(stamp, encoding="ascii") as fh:
            if fh.read().strip() == digest:
                return False
    except OSError:
        pass
    modules = {p.stem for p in Path(__file__).parent.glob("*.py")}
    removed = False
    try:
        for name in os.listdir(path):
            if name.endswith((".nbi", ".nbc")) and name.split(".", 1)[0] in modules:
                os.remove(os.path.join(path, name))
                removed = True
        with open(stamp, "w", encoding="ascii") as fh:
            fh.write(digest)
    except OSError:  # a read-only cache (numba then uses another), or a concurrent clean-up
        pass
    return removed


invalidate_stale_cache()
