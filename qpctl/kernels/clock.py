"""The process's monotonic clock inside kernels: stage timings without a return to Python.

``clock_gettime(CLOCK_MONOTONIC, struct timespec*)`` from the C library (the clock of
``time.perf_counter``), the pointer passed as an integer.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
from numba import njit, types

_clock_gettime: Any = types.ExternalFunction("clock_gettime", types.intc(types.intc, types.intp))
_MONOTONIC = time.CLOCK_MONOTONIC

@njit(cache=True)
def now_us(ts: np.ndarray) -> float:
    """The monotonic clock [µs]; ``ts`` is an int64 (2,) scratch for the timespec."""
    _clock_gettime(_MONOTONIC, ts.ctypes.data)
    return ts[0] * 1e6 + ts[1] * 1e-3
