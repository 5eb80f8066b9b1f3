"""Settled retreats (issue 22, item 2: the check cheap enough for 1 kHz): a retreat's steering walked
in closed form instead of stepped.

A retreat (:mod:`qpctl.safety.retreat`) steers with q̈* = ω²(q* − q) − 2ωq̇ for SETTLE/ω seconds — 833
steps of 1 ms at ω = 6 rad/s — before it brakes, and a rollout steps all of them on Pinocchio's ABA
(~9 µs a step on the Panda): a stored retreat cost every proposal's check 5–25 ms on the fresh set's
Panda scenes at 1 kHz. Where the steering's torque is clipped by neither limit, the arm follows the
commanded acceleration, and the steering is a critically damped linear system with a closed form: with
e₀ = q₀ − q* and c = q̇₀ + ω·e₀,

    q(s) = q* + (e₀ + c·s)e^{−ωs},    q̇(s) = (q̇₀ − ω·c·s)e^{−ωs}      (s after the walk's start).

**The walk.** At a steering step of a rollout (``settle``, as the brake's "Settled") whose torque was not
clipped, the rollout may *walk* the rest of the steering instead of stepping it:

1. *plan*: the steering's torque RNEA(q(s), q̇(s), q̈*(s)) is sampled at steps 1, :data:`WALK_EVERY`,
   2·:data:`WALK_EVERY`, … and at the last steering step (the switch, the first step at or after t_s,
   within the rollout's horizon): each within β = ``SETTLE_BETA`` (0.8) of τ_max and its change from the
   sample before within β of the rate window times the steps between. A sample that fails refuses the
   walk, to be tried again from the step it failed at (at least :data:`WALK_EVERY` steps on);
2. *clear*: the steps up to the switch are walked in closed form with the rollout's own lazy clearance
   (each step's Σᵢρᵢ|Δqᵢ| and the obstacles' speed bound), every bound lowered by the **stray**
   δ = ε·Σᵢρᵢ·(joint i's travel so far), ε = :data:`WALK_STRAY` × Δt / 1 ms, each joint kept ε × every
   joint's travel so far [rad] inside its limits (the joints' strays are coupled: a joint resting at its
   limit strays with the others — soak-panda-600, where the first version kept each joint ε × its own
   travel inside and a retreat resting at joint 2's limit left it by 5e-7 rad). A step whose clearance less δ is not above the level refuses the walk, to
   be tried again halfway there (the stray starts from zero at each walk's start);
3. *on*: at the switch the rollout goes on stepping the brake from the walked state, with the last
   sampled torque as the one applied before, every clearance, rest test and joint limit lowered by the
   switch's stray ε_s·Σᵢρᵢ(Tᵢ + |q̇ᵢ|/κ) (Tᵢ joint i's travel along the walk, |q̇ᵢ|/κ its brake's; ε_s =
   :data:`WALK_SWITCH_SHARE` × ε: the steering's feedback has pulled part of the lag back by then) —
   to its settle or its rest as any rollout (a few to a few tens of steps: the brake's ramp under the rate limit). A walked rollout that
   does not verify — its rest inside the stray of an obstacle, say — is stepped again from the walk's
   start without walks: a walk may vouch for a retreat (under the assumption below), never refute one
   the steps would verify.

A refused walk costs its samples and its walked steps (no ABA) and the rollout goes on from its pending
step exactly as it would have; the certificate of a walked rollout counts the walked steps in its steps
(they are its time; the budget of ``check_steps`` is in steps, so a budget shorter than a retreat's
steering leaves no room for a walk).

**What is assumed** (as the brake's settle assumes its decay): the simulator's RK4 steps with the torque
held over each step follow the continuous steering within the stray, and the limits never clip the
torque between samples. The deviation is a lag of the held torque — the commanded acceleration's and
the dynamics' change over a step, corrected by the steering's own feedback —, so it grows with the
step and with the path; ε was set from 300 random unclipped steerings of both arms measured before the
walk was written (Σᵢρᵢ|q − q_walk| at most 0.0151 × the travel so far at Δt = 2 ms, 0.0123 at 1 ms;
at the switch Σᵢρᵢ(|Δqᵢ| + |Δq̇ᵢ|/κ) at most 0.22 of ε·Σᵢρᵢ(Tᵢ + |q̇ᵢ|/κ), which ε_s halves).
Measured, not proved: ``tests/test_walk.py`` rolls walked retreats on in the simulator from random
states of the soak's heavy planar arm (500 Hz) and the Panda (1 kHz) and holds every walked step within
the stray with no torque clipped, the oracle verifying each retreat (``make soak``: 160 walks of 300
planar states, 82 of 150 Panda states, every 4th with a joint resting at a limit: the path at most 0.43
of its stray, the switch 0.50 of its own, every joint 0.28 of its own).
"""

from __future__ import annotations

from collections.abc import Generator
from typing import Any

import numpy as np
import pinocchio as pin

import qpctl.native
from qpctl.kernels import walk as KW
from qpctl.safety.retreat import Retreat, finish

#: The steering's torque is sampled every this many steps (and at the first and the last steering step).
WALK_EVERY = 10
#: The stray's share of the travel per millisecond of step (module docstring): the walked path's allowance for
#: the stepped one.
WALK_STRAY = 0.02
#: The switch's stray, as a share of the path's at the end (module docstring, step 3).
WALK_SWITCH_SHARE = 0.5


class Walk:
    """The walks of one :class:`~qpctl.safety.rollout.BrakeRollout` (module docstring), natively where
    the rollout's loop is native, else in Python and :mod:`qpctl.kernels.walk` (the same operations)."""

    def __init__(self, owner: Any) -> None:
        self.owner = owner
        n = owner.robot.nv
        self.wio = np.zeros(KW.W_SIZE)
        self.T, self.q, self.v, self.prev, self.tau = (np.zeros(n) for _ in range(5))
        self.target, self.q0, self.v0 = np.zeros(n), np.zeros(n), np.zeros(n)
        self._ptr: tuple[Any, tuple[int, ...], tuple[int, ...]] | None = None  # (handle, plan's, clear's)
        self.refused: str | None = None  # what refused the last walk (None: it walked)

    def _native(self) -> tuple[Any, tuple[int, ...], tuple[int, ...]] | None:
        """(the owner's native handle, the plan's and the clear's array addresses), or None where the owner's
        loop is Python's. The addresses once per handle (numpy's ``.ctypes.data`` costs ~1 µs an array and a
        walk calls clear tens of times); the limits are the handle's, copied at each of its runs."""
        nb = self.owner.native
        if nb is None:
            return None
        if self._ptr is None or self._ptr[0] is not nb:
            if nb.lib.qpb_walk_size() != KW.W_SIZE:
                raise qpctl.native.NativeBuildError("the native walk's layout is not this module's")
            tau_max, window, q_min, q_max, rho = nb.ptr[3:8]
            q0, v0, tg, T, wq, wv, tau, io = (a.ctypes.data for a in (self.q0, self.v0, self.target, self.T,
                                                                        self.q, self.v, self.tau, self.wio))
            self._ptr = (nb, (q0, v0, tg, tau_max, window, T, wq, wv, tau, io),
                         (q0, v0, tg, q_min, q_max, rho, T, wq, wv, io))
        return self._ptr

    def attempt(self, q: np.ndarray, v: np.ndarray, retreat: Retreat, gain: float, t0: float, k: int, steps: int,
                lazy_state: tuple[float, float, float], level: float, lazy: bool) -> tuple[bool, float]:
        """:meth:`attempt_iter` without pauses."""
        return finish(self.attempt_iter(q, v, retreat, gain, t0, k, steps, lazy_state, level, lazy, None))

    def attempt_iter(self, q: np.ndarray, v: np.ndarray, retreat: Retreat, gain: float, t0: float, k: int,
                     steps: int, lazy_state: tuple[float, float, float], level: float, lazy: bool,
                     budget: Any) -> Generator[None, None, tuple[bool, float]]:
        """A walk from step k of a rollout from t0 [s] at (q, q̇) — the step's torque, unclipped, in
        ``self.tau`` (the native handle's pending one where the loop is native) —, the lazy bound
        (last, drift, worst) [m]: (walked, the step from which a walk may be tried again). Walked: the
        switch's state in (``self.q``, ``self.v``), the last steering torque in ``self.tau``, the bound
        in :meth:`bound`, the stray in :attr:`stray` and :attr:`joint_stray`."""
        o, wio = self.owner, self.wio
        self.q0[:], self.v0[:], self.target[:] = q, v, retreat.target
        wio[:] = 0.0
        wio[KW.W_K], wio[KW.W_T0], wio[KW.W_DT], wio[KW.W_UNTIL] = k, t0, o.dt, retreat.until
        wio[KW.W_OMEGA], wio[KW.W_GAIN], wio[KW.W_BETA], wio[KW.W_EVERY] = retreat.omega, gain, o.beta, WALK_EVERY
        rate = WALK_STRAY * o.dt / 1e-3  # ε: the stray's share of the travel at this step
        wio[KW.W_STRAY], wio[KW.W_SWITCH_STRAY], wio[KW.W_STEPS] = rate, WALK_SWITCH_SHARE * rate, steps
        wio[KW.W_LAST], wio[KW.W_DRIFT], wio[KW.W_WORST] = lazy_state
        wio[KW.W_LEVEL], wio[KW.W_LAZY], wio[KW.W_MOVE] = level, float(lazy), o.obstacle_speed * o.dt
        if not self._plan():
            self.refused = "a torque sample" if np.isfinite(wio[KW.W_RETRY]) else "the horizon"
            return False, float(wio[KW.W_RETRY])
        while True:
            answer = self._clear()
            if answer != KW.NEED_CLEARANCE:
                break
            while budget is not None and budget.evaluations() < 1:  # paused before an evaluation (run_iter)
                yield
            wio[KW.W_LAST] = o.world(self.q, t0 + (k + int(wio[KW.W_J])) * o.dt)
            wio[KW.W_DRIFT], wio[KW.W_EVALUATED] = 0.0, 1.0
        self.refused = None if answer == KW.WALKED else "the clearance or a joint limit"
        return answer == KW.WALKED, float(wio[KW.W_RETRY])

    @property
    def steps(self) -> int:
        """The steps a walk covered (to the switch)."""
        return int(self.wio[KW.W_NSW])

    @property
    def bound(self) -> tuple[float, float, float]:
        """(last, drift, worst) [m] at the switch, the lazy bound the rollout goes on with (worst less the stray)."""
        return float(self.wio[KW.W_LAST]), float(self.wio[KW.W_DRIFT]), float(self.wio[KW.W_WORST])

    @property
    def stray(self) -> float:
        """The stray the rollout goes on with after a walk [m]: ε_s·ΣᵢρᵢTᵢ, Tᵢ joint i's travel along the
        walk plus its |q̇ᵢ|/κ at the switch (module docstring, step 3)."""
        return float(self.wio[KW.W_DEV])

    @property
    def joint_stray(self) -> np.ndarray:
        """ε_s·ΣⱼTⱼ [rad] for every joint: how far inside its limits each joint is kept after a walk (every
        joint's travel: the dynamics couple the joints' strays — a joint resting at its limit strays with
        the others)."""
        return np.full(self.T.size, float(self.wio[KW.W_SWITCH_STRAY]) * float(np.sum(self.T)))

    def _plan(self) -> bool:
        native = self._native()
        if native is not None:
            nb, ptr, _ = native
            return bool(nb.lib.qpb_walk_plan(nb.handle, *ptr))
        return self._plan_python()

    def _plan_python(self) -> bool:
        """brake_rollout.cpp's ``qpb_walk_plan``, the same operations (the step's torque in ``self.tau``)."""
        o, wio = self.owner, self.wio
        model, data = o.model, o.data
        q0, v0, target, wq, wv = self.q0, self.v0, self.target, self.q, self.v
        k, steps, every = int(wio[KW.W_K]), int(wio[KW.W_STEPS]), int(wio[KW.W_EVERY])
        t0, dt, until, w = (float(wio[i]) for i in (KW.W_T0, KW.W_DT, KW.W_UNTIL, KW.W_OMEGA))
        beta = float(wio[KW.W_BETA])
        w2, w1 = w * w, 2.0 * w
        nsw = 1
        while t0 + float(k + nsw) * dt < until:
            nsw += 1
        wio[KW.W_NSW] = nsw
        if k + nsw >= steps:
            wio[KW.W_RETRY] = np.inf
            return False
        before = self.tau
        j, jprev = 1, 0
        while j < nsw:
            KW.steer_state(q0, v0, target, w, float(j) * dt, wq, wv)
            tau = pin.rnea(model, data, wq, wv, (target - wq) * w2 - w1 * wv)
            if not KW.sample_ok(tau, before, o.tau_max, o.window, beta, beta * float(j - jprev)):
                wio[KW.W_RETRY] = k + max(j, every)
                return False
            before[:] = tau
            jprev = j
            if j == nsw - 1:
                break
            j = min(every if j < every else j + every, nsw - 1)
        self.T[:] = 0.0
        self.prev[:] = q0
        wio[KW.W_PROG] = 0.0
        return True

    def _clear(self) -> int:
        native = self._native()
        if native is not None:
            nb, _, ptr = native
            return int(nb.lib.qpb_walk_clear(nb.handle, *ptr))
        o = self.owner
        return int(KW.walk_clear(self.q0, self.v0, self.target, o.q_min, o.q_max, o._rho, self.T, self.q, self.v,
                                 self.prev, self.wio))


__all__ = ["WALK_EVERY", "WALK_STRAY", "WALK_SWITCH_SHARE", "Walk"]
