"""The verified backup (issue 22, item 2): a controller's torque is applied only if, from the state it
leads to, a brake of the family (:mod:`qpctl.safety.oracle`) brings the arm to rest without contact in
a rollout on the controller's own model; otherwise the stored verified brake continues.

Each tick at (q, q̇, t) with the torque τ_prev applied last:

1. the controller proposes τ (its ``step``);
2. where the arm's least clearance is below ``check_distance`` [m] (default: everywhere; farther, τ
   is applied unchecked and the stored brake forgotten, since it was verified from another state),
   the successor (q₁, q̇₁) — τ held over one step, the
   built-in simulator's RK4 — is rolled out with the stored brake's gain first, then the others; the
   first that comes to rest with the clearance above ``margin`` all along is stored and τ applied;
3. if none does, the stored brake's torque from (q, q̇, τ_prev) is applied instead (the brake was
   verified from this very state one tick ago, and the rollout is the simulator's own integration, so
   under the exact model following it stays verified), and the tick's info says ``backup``.

Before the first verified brake (the start) the controller's torque is applied. The rollouts are
Python (Pinocchio and the simulator's step), milliseconds each: the guard is a measurement of what the
guarantee costs and does, not yet a 1 kHz implementation.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from qpctl.constraints.constraints import TorqueLimit
from qpctl.safety.oracle import BRAKE_GAINS, brake_torque, rollout
from qpctl.simulation.simulator import Simulator


class GuardedOutput:
    """A controller's output with the torque the guard applied (every other attribute the output's)."""

    def __init__(self, out: Any, tau: np.ndarray, info: dict[str, Any]) -> None:
        self._out, self.tau, self.info = out, tau, info

    def __getattr__(self, name: str) -> Any:
        return getattr(self._out, name)


class BackupGuard:
    """A controller behind the verified backup (module docstring); every other attribute is the
    controller's, so it runs wherever the controller does. ``dt`` [s]: the control period (the
    simulator's step), ``check_distance`` [m], ``margin`` [m] (kept at rest), ``horizon`` [s]."""

    def __init__(self, controller: Any, dt: float, *, check_distance: float = np.inf, margin: float = 0.0,
                 horizon: float = 3.0, gains: tuple[float, ...] = BRAKE_GAINS) -> None:
        self.controller = controller
        self.dt, self.check_distance, self.margin, self.horizon = float(dt), float(check_distance), float(margin), \
            float(horizon)
        self.gains = tuple(gains)
        self._sim = Simulator(controller, dt=self.dt, duration=self.dt)
        self._data = controller.robot.model.createData()
        self._limit = next((c for c in getattr(controller, "constraints", []) if isinstance(c, TorqueLimit)), None)
        self.stats: dict[str, Any] = {"checked": 0, "backup": 0, "unverified": 0, "check_us": []}
        self._reset_backup()

    def __getattr__(self, name: str) -> Any:
        return getattr(self.controller, name)

    def _reset_backup(self) -> None:
        self._gain: float | None = None
        self._tau_prev = np.full(self.controller.robot.nv, np.nan)

    def reset(self) -> None:
        self.controller.reset()
        self._reset_backup()

    def warmup(self) -> float:
        out = self.controller.warmup()
        self._reset_backup()
        return out

    def _verified(self, q: np.ndarray, v: np.ndarray, tau: np.ndarray, t: float) -> float | None:
        """The gain of a brake verified from the successor of τ held at (q, q̇, t), or None."""
        sim = self._sim
        sim.reset(q, v)
        sim.apply(tau)
        sim.step(t)
        q1, v1 = (a.copy() for a in sim.read())
        order = ([self._gain] if self._gain is not None else []) + [g for g in self.gains if g != self._gain]
        for g in order:
            c = rollout(sim, q1, v1, tau, t + self.dt, g, horizon=self.horizon, margin=self.margin,
                        stop_below=self.margin)
            if c.viable:
                return g
        return None

    def step(self, q: np.ndarray, v: np.ndarray, t: float) -> Any:
        out = self.controller.step(q, v, t)
        tau = np.array(out.tau, float)
        info = dict(out.info)
        near = self._sim.clearance(q, t) < self.check_distance
        if near:
            t0 = time.perf_counter()
            gain = self._verified(q, v, tau, t)
            self.stats["check_us"].append((time.perf_counter() - t0) * 1e6)
            self.stats["checked"] += 1
            if gain is not None:
                self._gain = gain
            elif self._gain is None:  # nothing verified yet (the start, or after unchecked ticks)
                self.stats["unverified"] += 1
            else:  # the stored brake continues
                tau = brake_torque(self.controller.robot, self._data, np.asarray(q, float), np.asarray(v, float),
                                   self._tau_prev, self._gain, self.dt)
                info["backup"] = self._gain
                self.stats["backup"] += 1
                if self._limit is not None:  # the rate window of the next tick is about the torque applied
                    self._limit.remember(tau, t)
        else:
            self._gain = None
        self._tau_prev = tau
        return GuardedOutput(out, tau, info)

    def torque(self, q: np.ndarray, v: np.ndarray, t: float) -> np.ndarray:
        return np.asarray(self.step(q, v, t).tau)
