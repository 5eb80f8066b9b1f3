"""The stale-map policy and the waiting reference: an old map slows the task, a very old one stops
the arm; a link held back in a leaf makes the path wait for it.

The map's age at time t is t − the stamp of its newest frame. Up to ``stale_slow`` [s] the task runs
at full speed; from ``stale_slow`` to ``stale_stop`` its reference is time-scaled by κ falling
linearly from 1 to 0 (the path is followed, slower, and halts by ``stale_stop``); past ``stale_stop``
the controller brakes to rest (the safe stop) until a fresher map arrives. κ moves at most at
1/(stale_stop − stale_slow) per second both ways, so a fresh map resumes the task without a jump.

**The lag** (issue 21: the soft speed rows hold a link in a leaf to ``soft_speed``, and a fixed-time
path runs away from it). The same time scale has a second factor, κ_lag, from the task's tracking
error e = |x − x_d| [m] while a link is in a leaf's reach (the caller passes e there, 0 elsewhere:
:class:`~qpctl.perception.closed_loop.MapLoop`): 1 up to ``lag_slow`` [m], linear to 0 at
``lag_stop`` [m], moving at most ``lag_rate`` [1/s] both ways. κ = min(κ_age, κ_lag): the path's
progress ṡ = κ drops while the arm lags in the leaves, so the reference waits for it instead of
running on to the next waypoint, and resumes at full rate when the arm has caught up (e ≤ lag_slow)
or has left the leaves. Causal: e and the leaves' reach are the controller's last tick's (its
output's task point and reference; its field pairs).

:class:`TimeScaledPath` is the time-scaled reference: path time s advances at ṡ = κ, and the
reference is x_d(s), κ x_d'(s), κ² x_d''(s) + κ̇ x_d'(s).
"""

from __future__ import annotations

from dataclasses import dataclass

from qpctl.paths import TimeScaledPath

OK, SLOW, STOP = "ok", "slow", "stop"
__all__ = ["OK", "SLOW", "STOP", "StalePolicy", "Staleness", "TimeScaledPath"]


@dataclass(frozen=True)
class Staleness:
    """The policy's verdict at one time: the map's ``age`` [s], the reference's time scale ``kappa``
    ∈ [0, 1] (rate-limited; the lesser of the age's and the lag's), ``mode`` (:data:`OK`,
    :data:`SLOW` or :data:`STOP`: the map's age alone), the tracking ``lag`` [m] it was given and the
    lag's own factor ``lag_kappa`` (< 1: the path waits for the arm)."""

    age: float
    kappa: float
    mode: str
    lag: float = 0.0
    lag_kappa: float = 1.0


class StalePolicy:
    """κ and the mode from the map's age and the task's lag (module docstring); ``slow`` < ``stop`` [s];
    ``lag_slow`` < ``lag_stop`` [m] and ``lag_rate`` > 0 [1/s] (``lag_stop`` None: the lag is ignored)."""

    def __init__(self, slow: float, stop: float, *, lag_slow: float = 0.0, lag_stop: float | None = None,
                 lag_rate: float = 1.0) -> None:
        if not (0 < slow < stop):
            raise ValueError(f"stale thresholds must satisfy 0 < slow < stop, got {slow}, {stop}")
        if lag_stop is not None and not (0 <= lag_slow < lag_stop and lag_rate > 0):
            raise ValueError(f"lag thresholds must satisfy 0 <= lag_slow < lag_stop and lag_rate > 0, got "
                             f"{lag_slow}, {lag_stop}, {lag_rate}")
        self.slow, self.stop = float(slow), float(stop)
        self.rate = 1.0 / (self.stop - self.slow)  # [1/s] the most κ_age changes per second
        self.lag_slow = float(lag_slow)
        self.lag_stop = None if lag_stop is None else float(lag_stop)
        self.lag_rate = float(lag_rate)  # [1/s] the most κ_lag changes per second
        self.kappa = 1.0
        self.kappa_age = 1.0
        self.kappa_lag = 1.0
        self._t: float | None = None

    def reset(self) -> None:
        self.kappa = self.kappa_age = self.kappa_lag = 1.0
        self._t = None

    def lag_target(self, lag: float) -> float:
        """The κ_lag a tracking error ``lag`` [m] asks for: 1 up to ``lag_slow``, linear to 0 at ``lag_stop``."""
        if self.lag_stop is None or not lag > self.lag_slow:
            return 1.0
        if lag >= self.lag_stop:
            return 0.0
        return (self.lag_stop - lag) / (self.lag_stop - self.lag_slow)

    def target(self, age: float) -> float:
        """The κ the age asks for: 1 up to ``slow``, linear to 0 at ``stop``."""
        if age <= self.slow:
            return 1.0
        if age >= self.stop:
            return 0.0
        return (self.stop - age) / (self.stop - self.slow)

    def __call__(self, t: float, age: float, lag: float = 0.0) -> Staleness:
        """The verdict at time t [s] for a map ``age`` [s] old and a tracking error ``lag`` [m] (0: none,
        or no link in a leaf's reach); κ_age and κ_lag each rate-limited since the last call."""
        goal, goal_lag = self.target(age), self.lag_target(lag)
        if self._t is None:
            self.kappa_age, self.kappa_lag = goal, goal_lag
        elif t > self._t:
            step, step_lag = self.rate * (t - self._t), self.lag_rate * (t - self._t)
            self.kappa_age = min(max(goal, self.kappa_age - step), self.kappa_age + step)
            self.kappa_lag = min(max(goal_lag, self.kappa_lag - step_lag), self.kappa_lag + step_lag)
        self._t = t
        self.kappa = min(self.kappa_age, self.kappa_lag)
        mode = STOP if not age < self.stop else (SLOW if age > self.slow or self.kappa_age < 1.0 else OK)
        return Staleness(float(age), float(self.kappa), mode, float(lag), float(self.kappa_lag))
