"""Braking-aware rows on the Python path (issue 22, item 1): the numpy reference of
:mod:`qpctl.kernels.braking` (its docstring has the formulas). :class:`~qpctl.constraints.ObstacleBarrier`
and :class:`~qpctl.constraints.JointLimit` take a :class:`Braking` (``braking=``) and tighten their
bounds with it; the compiled tick does the same from the workspace's settings (``IP_BRAKING``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from qpctl.errors import ConfigError
from qpctl.kernels.stopping import max_closing_acceleration


@dataclass(frozen=True)
class Braking:
    """The brake the rows assume: a ``share`` (0, 1] of the drives' means at each point (A, J), a
    ``margin`` [m] kept at rest beyond d_safe, the control period ``dt`` [s]; the drives' limits
    τ_max [N·m], τ̇_max [N·m/s] and q̈_max [rad/s²] (n,)."""

    tau_max: np.ndarray
    tau_rate: np.ndarray
    qdd_max: np.ndarray
    share: float
    margin: float
    dt: float

    def __post_init__(self) -> None:
        if not (0 < self.share <= 1):
            raise ConfigError(f"must be in (0, 1], got {self.share}", key="controller.braking_share")
        if not (np.isfinite(self.margin) and self.margin >= 0):
            raise ConfigError(f"must be a distance >= 0 [m], got {self.margin}", key="controller.braking_margin")
        if not (np.isfinite(self.dt) and self.dt > 0):
            raise ConfigError(f"must be a period > 0 [s], got {self.dt}", key="controller.braking_period")

    def point(self, c: np.ndarray, M: np.ndarray, N: np.ndarray) -> tuple[float, float]:
        """(best-case deceleration [m/s²], jerk [m/s³]) the drives give a point whose closing rate is
        c q̇ (no share applied)."""
        y = np.linalg.solve(M, c)
        a_tau = float(np.abs(y) @ np.maximum(self.tau_max - np.abs(N), 0.0))
        with np.errstate(invalid="ignore"):
            a_qdd = float(np.sum(np.where(c != 0, np.abs(c) * self.qdd_max, 0.0)))
            jerk = float(np.sum(np.where(y != 0, np.abs(y) * self.tau_rate, 0.0)))
        return min(a_tau, a_qdd), jerk

    def barrier_lower(self, c: np.ndarray, d: float, d_safe: float, nvo: float, drift: float,
                      v: np.ndarray, M: np.ndarray, N: np.ndarray) -> float:
        """The braking lower bound on c q̈ of one pair (−inf where slack); d [m], nvo = nᵀv_obs [m/s],
        drift ḧ at q̈ = 0 [m/s²], v the joint velocities [rad/s]."""
        best, jerk = self.point(c, M, N)
        if not (0 < best < np.inf):
            return -np.inf
        a_star = max_closing_acceleration(d - d_safe, -float(c @ v), max(nvo, 0.0), self.dt, self.share * best,
                                          self.share * jerk, self.margin, best)
        return -np.inf if a_star >= best else -a_star - drift

    def joint_limits(self, q: np.ndarray, v: np.ndarray, q_min: np.ndarray, q_max: np.ndarray, M: np.ndarray,
                     N: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """lo, hi [rad/s²] tightened so that each joint can still stop before its limits."""
        lo, hi = lo.copy(), hi.copy()
        for i in range(q.size):
            m = M[i, i]
            best = min(self.qdd_max[i], max(self.tau_max[i] - abs(N[i]), 0.0) / m)
            if not (0 < best < np.inf):
                continue
            A, J = self.share * best, self.share * self.tau_rate[i] / m
            for h, speed, upper in ((q_max[i] - q[i], v[i], True), (q[i] - q_min[i], -v[i], False)):
                if not h < np.inf:
                    continue
                a_star = max_closing_acceleration(h, speed, 0.0, self.dt, A, J, 0.0, best)
                if a_star >= best:
                    continue
                if upper and a_star < hi[i]:
                    hi[i] = a_star
                elif not upper and -a_star > lo[i]:
                    lo[i] = -a_star
        return lo, hi
