"""The stale-map policy: an old map slows the task, a very old one stops the arm.

The map's age at time t is t − the stamp of its newest frame. Up to ``stale_slow`` [s] the task runs
at full speed; from ``stale_slow`` to ``stale_stop`` its reference is time-scaled by κ falling
linearly from 1 to 0 (the path is followed, slower, and halts by ``stale_stop``); past ``stale_stop``
the controller brakes to rest (the safe stop) until a fresher map arrives. κ moves at most at
1/(stale_stop − stale_slow) per second both ways, so a fresh map resumes the task without a jump.

:class:`TimeScaledPath` is the time-scaled reference: path time s advances at ṡ = κ, and the
reference is x_d(s), κ x_d'(s), κ² x_d''(s) + κ̇ x_d'(s).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from qpctl.paths import Reference

OK, SLOW, STOP = "ok", "slow", "stop"


@dataclass(frozen=True)
class Staleness:
    """The policy's verdict at one time: the map's ``age`` [s], the reference's time scale ``kappa``
    ∈ [0, 1] (rate-limited), and ``mode`` (:data:`OK`, :data:`SLOW` or :data:`STOP`)."""

    age: float
    kappa: float
    mode: str


class StalePolicy:
    """κ and the mode from the map's age (module docstring); ``slow`` < ``stop`` [s]."""

    def __init__(self, slow: float, stop: float) -> None:
        if not (0 < slow < stop):
            raise ValueError(f"stale thresholds must satisfy 0 < slow < stop, got {slow}, {stop}")
        self.slow, self.stop = float(slow), float(stop)
        self.rate = 1.0 / (self.stop - self.slow)  # [1/s] the most κ changes per second
        self.kappa = 1.0
        self._t: float | None = None

    def reset(self) -> None:
        self.kappa = 1.0
        self._t = None

    def target(self, age: float) -> float:
        """The κ the age asks for: 1 up to ``slow``, linear to 0 at ``stop``."""
        if age <= self.slow:
            return 1.0
        if age >= self.stop:
            return 0.0
        return (self.stop - age) / (self.stop - self.slow)

    def __call__(self, t: float, age: float) -> Staleness:
        """The verdict at time t [s] for a map ``age`` [s] old (κ rate-limited since the last call)."""
        goal = self.target(age)
        if self._t is None:
            self.kappa = goal
        elif t > self._t:
            step = self.rate * (t - self._t)
            self.kappa = min(max(goal, self.kappa - step), self.kappa + step)
        self._t = t
        mode = STOP if not age < self.stop else (SLOW if age > self.slow or self.kappa < 1.0 else OK)
        return Staleness(float(age), float(self.kappa), mode)


class TimeScaledPath:
    """A path whose clock runs at κ (set each tick with :meth:`advance`): wraps any path callable
    ``path(t) -> Reference``; other attributes (``dim``, ``points`` …) are the path's."""

    def __init__(self, path: Any, start: float = 0.0) -> None:
        self.path = path
        self.s = float(start)  # the path's own time [s]
        self.kappa = 1.0
        self.kappa_rate = 0.0  # κ̇ [1/s]
        self._t = float(start)

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

    def __call__(self, t: float) -> Reference:
        """The reference at the clock's time (``t`` is taken from :meth:`advance`; a t beyond it is
        extrapolated at the current κ)."""
        s = self.s + self.kappa * max(0.0, float(t) - self._t)
        ref = self.path(s)
        k = self.kappa
        xdd = k * k * ref.xdd + self.kappa_rate * ref.xd
        return Reference(ref.x, k * ref.xd, xdd if math.isfinite(self.kappa_rate) else k * k * ref.xdd)

    def orientation(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A pose path's (R_d, ω_d, ω̇_d) at the clock's time, scaled like the position."""
        s = self.s + self.kappa * max(0.0, float(t) - self._t)
        R, w, wd = self.path.orientation(s)
        k = self.kappa
        return R, k * w, k * k * wd + self.kappa_rate * w
