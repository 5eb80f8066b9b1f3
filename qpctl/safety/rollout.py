"""The lean brake rollout (issue 22, item 2): the oracle's brake and the built-in simulator's RK4,
with Pinocchio called directly on preallocated arrays, the step's arithmetic in compiled kernels
(:mod:`qpctl.kernels.rollout`) and the world clearance of the simulator's own
:class:`qpctl.tick.WorldClearance` — no :class:`~qpctl.simulation.Simulator` object stepped.

Per step at (q, q̇, t) after τ_prev, exactly as :func:`qpctl.safety.oracle.rollout` does it:

    clearance(q, t);  τ = clip(clip(RNEA(q, q̇, −κq̇), ±τ_max), τ_prev ± τ̇_max Δt)
    (q, q̇) ← RK4 of q̇ = v, v̇ = ABA(q, v, τ) over Δt          (simulation.simulator.rk4_step's stages)

A rollout that comes to rest is verified only if the rest passes the rest test as the oracle's does
(:class:`qpctl.safety.sweep.RestClearance`): each joint's stop within its limits, the static obstacles
and every swaying obstacle's whole sweep cleared by the stop's creep.

The arithmetic is rk4_step's operations in the same order, so the states equal the simulator's (the
tests hold them to 1e-12 against the oracle); a robot with continuous or planar joints integrates on
its configuration space through ``robot.integrate`` as the simulator does.

**Lazy clearance** (``exact=False``, the guard's): the world clearance is a 1-Lipschitz function of
every link point's and every obstacle's position, and over a step dq no point of a link moves farther
than Σᵢ ρᵢ|dqᵢ| (revolute joints: ρᵢ bounds the distance of joint i's origin to any capsule point it
carries, the joint placements' lengths along the chain plus the capsule's end, configuration-free)
and no obstacle farther than its speed bound |v| + 2πf|amplitude| times Δt. So after a clearance c
was evaluated, c minus the bounds accumulated since is a lower bound on the clearance; while it stays
above the level the rollout tests (``margin``, ``stop_below``) the evaluation is skipped and the bound
stands in for it. The verdict is then sound (the least clearance reported is a lower bound, not the
exact value); robots with other joints evaluate every step.

**Settled** (``settle=True``, the guard's): most of a stop's steps are its tail, the speed decaying
toward rest (on the Panda at 1 kHz a median 213 steps to rest, 50 of them the rest time). Where the
brake's torque τ = RNEA(q, q̇, −κq̇) was clipped by neither limit, the continuous brake gives q̈ = −κq̇,
so q̇ decays as q̇e^{−κt}, each joint moves |q̇ᵢ|/κ more and a link point Σᵢρᵢ|q̇ᵢ|/κ more (the creep of
:mod:`qpctl.safety.sweep`) — *as long as the limits never clip it again*. A step's brake has
**settled** when its torque was not clipped and the torque one step ahead along that decay,
RNEA(q + Δt·q̇, e·q̇, −κe·q̇) with e = e^{−κΔt}, changes by d ≤ β·τ̇_maxΔt per joint and leaves
|τ| + d/(κΔt) ≤ β·τ_max (the whole change if the rate decays with the speed), β = :data:`SETTLE_BETA`.
The rollout then ends, verified, if the decay reaches rest (REST_SPEED for REST_TIME) within the
horizon and the rest test passes at the current configuration with the creep raised by
γ = :data:`SETTLE_GAMMA` (the drifting obstacles over the window from now to the hold after that rest);
else it goes on, and the next settled step is tested only once its creep is half the refused one's.
This is an assumption about the simulator's steps, as the creep at rest already was (the continuous,
unclipped decay is exact; the RK4 steps with the torque held are not), and it is **measured, not
proved**: ``tests/test_settle.py`` rolls settled stops on to rest in the simulator (with ``make soak``
1,167 of them from random states of the soak's heavy planar arm and the Panda, four gains) — none
clipped again, each verified by the oracle, the tail at most 0.997 of Σᵢρᵢ|q̇ᵢ|/κ (γ leaves 25 %). The soak's oracle certifies the guard's
states with full rollouts, so a settle that vouched for a bad stop would show there.

**Walked retreats** (with ``settle``): a retreat's steering whose torque was not clipped is walked in
closed form instead of stepped, every clearance and limit lowered by the walk's stray, and the rollout
steps on from the switch — :mod:`qpctl.safety.walk`; a walked rollout that does not verify is stepped
again from the walk's start without walks.

**Native loop** (``native``, the default where :mod:`qpctl.native` builds): the loop of :meth:`run`
— the brake's torque, the RK4 step, the state's checks and the lazy bound's bookkeeping — runs in
C++ on Pinocchio's own ``rnea`` and ``aba`` (libpinocchio, the code the bindings call), returning to
Python only where a clearance must be evaluated. Same operations in the same order: the same
certificates bit for bit (``tests/test_native_rollout.py``); 2–3.5× fewer µs a step (what remains
is Pinocchio's four ABA and one RNEA; docs/reliability.md). Robots whose configuration is not a
vector space (continuous, planar joints) keep the Python loop.
"""

from __future__ import annotations

import math
import weakref
from collections.abc import Generator
from typing import Any

import numpy as np
import pinocchio as pin

import qpctl.native
from qpctl.kernels import rollout as K
from qpctl.safety.oracle import REST_SPEED, REST_TIME, Certificate
from qpctl.safety.retreat import Retreat, finish
from qpctl.safety.sweep import RestClearance, swaying
from qpctl.safety.walk import Walk
from qpctl.tick import WorldClearance

# qpb_advance's io block (brake_rollout.cpp's IO_* order) and answers
(IO_K, IO_STEPS, IO_STILL, IO_LAST, IO_DRIFT, IO_WORST, IO_LEVEL, IO_STOP_BELOW, IO_GAIN, IO_DT,
 IO_OBSTACLE_SPEED, IO_REST_SPEED, IO_REST_TIME, IO_EVALUATED, IO_LAZY, IO_T0, IO_UNTIL, IO_W2, IO_W1,
 IO_SETTLE, IO_SETTLE_BELOW, IO_DECAY, IO_BETA, IO_GAMMA, IO_CREEP, IO_PENDING, IO_WALK_AFTER, IO_STRAY,
 IO_SIZE) = range(29)
NEED_CLEARANCE, AT_REST_END, FAILED, HORIZON, SETTLED, WALK = range(6)

#: A settled brake's torque and rate stay within this share of their limits (module docstring, "Settled").
SETTLE_BETA = 0.8
#: The settled stop's creep bound is Σᵢρᵢ|q̇ᵢ|/κ times this (module docstring, "Settled").
SETTLE_GAMMA = 1.25


class BrakeRollout:
    """Brake rollouts of one robot in one world at step ``dt`` [s] (module docstring).

    Args:
        robot: the controller's :class:`~qpctl.robot.RobotModel` (its model, limits, capsules).
        world: the exact world clearance (a simulator's ``world``; its obstacles move with t).
        dt: the step [s] (the run's: the guarantee is about the simulator's own integration).
        hold: [s] how long after its rest a stop must stay clear of the drifting obstacles
            (:class:`~qpctl.safety.sweep.RestClearance`; 0: not tested).
    """

    #: the settle's shares (module docstring, "Settled"), read by the walk (:mod:`qpctl.safety.walk`)
    beta, gamma = SETTLE_BETA, SETTLE_GAMMA

    def __init__(self, robot: Any, world: WorldClearance, dt: float, hold: float = 0.0) -> None:
        self.robot, self.world, self.dt = robot, world, float(dt)
        model = robot.model
        self.model, self.data = model, model.createData()
        n = robot.nv
        self.tau_max = np.asarray(robot.tau_max, float)
        rate = robot.tau_rate_max if robot.tau_rate_max is not None else np.full(n, np.inf)
        self.window = np.asarray(rate, float) * self.dt
        self.q_min, self.q_max = np.asarray(robot.q_min, float), np.asarray(robot.q_max, float)
        self.lie = bool(robot.lie)
        self.tau, self.raw, self.qdd = np.zeros(n), np.zeros(n), np.zeros(n)  # raw: τ before the limits
        self._kq, self._ka = np.zeros((4, n)), np.zeros((4, n))  # the stages' k·q (velocities), k·v
        self._qs, self._vs, self._dq, self._dv = np.zeros(model.nq), np.zeros(n), np.zeros(n), np.zeros(n)
        self._angles = np.zeros(n)
        self._kq_rows = [self._kq[i] for i in range(4)]  # the stages' velocities, as Pinocchio's arguments
        self.travel = 0.0
        self.fused = not self.lie  # the stages in two kernel calls (False: one call per operation, as before)
        self.rest = RestClearance(robot, world.ws.obstacles, hold)  # the rest test (qpctl.safety.sweep)
        self.rho = self.rest.rho  # lever_arms(robot); None: a joint that is not revolute
        self._rho = self.rho if self.rho is not None else np.zeros(n)
        self.obstacle_speed = max((o.speed_bound for o in world.ws.obstacles), default=0.0)
        # a rollout may end where the brake settles (module docstring): its creep needs the lever arms, and a
        # drifting obstacle is in the rest test only over a hold (without one the rollout must follow it)
        drifting = any(o.moving and not swaying(o) for o in world.ws.obstacles)
        self.settles = self.rho is not None and (hold > 0 or not drifting)
        self.native: NativeBrake | None = NativeBrake.create(self) if not self.lie else None
        self.walk = Walk(self)  # a settled retreat's steering walked (qpctl.safety.walk)

    def at_rest(self, q: np.ndarray, v: np.ndarray, gain: float, worst: float, margin: float, t: float,
                k: int, stray: float = 0.0) -> Certificate:
        """The certificate of a rollout from t [s] at rest at step k, (q, q̇), its least clearance ``worst``
        [m]: verified if the clearance stayed above ``margin`` [m] and the rest passes the rest test at its
        time t + k·dt by ``margin`` + ``stray`` (a walk's allowance) (both loops end here)."""
        ok = worst > margin and self.rest.verifies(q, v, gain, margin + stray, t + k * self.dt)
        return Certificate(ok, gain, worst, k * self.dt, k)

    def torque(self, q: np.ndarray, v: np.ndarray, tau_prev: np.ndarray, gain: float, retreat: Retreat | None = None,
               t: float = 0.0) -> np.ndarray:
        """The brake's torque [N·m] at (q, q̇) after τ_prev into ``self.tau`` (oracle.brake_torque); with a
        ``retreat`` steering at t [s], its torque (:mod:`qpctl.safety.retreat`)."""
        if retreat is not None and retreat.steering(t):
            retreat.accel(q, v, self.qdd)
        else:
            np.multiply(v, -gain, out=self.qdd)
        self.tau[:] = pin.rnea(self.model, self.data, q, v, self.qdd)
        self.raw[:] = self.tau
        K.clip_brake(self.tau, self.tau_max, tau_prev, self.window)
        return self.tau

    def settled(self, q: np.ndarray, v: np.ndarray, gain: float, decay: float) -> bool:
        """True if the brake's torque at (q, q̇) — ``self.tau``, just computed by :meth:`torque`, and not
        clipped — settled into its decay (module docstring, "Settled"); ``decay`` = e^{−κΔt}."""
        ahead = v * decay
        nxt = pin.rnea(self.model, self.data, q + self.dt * v, ahead, ahead * -gain)
        return bool(K.settled(self.tau, nxt, self.tau_max, self.window, gain, self.dt, SETTLE_BETA))

    def settled_rest(self, q: np.ndarray, v: np.ndarray, gain: float, worst: float, margin: float,
                     t: float, left: float, stray: float = 0.0) -> bool:
        """True if a settled brake at (q, q̇) at t [s], its least clearance so far ``worst`` [m], may end
        its rollout here: the decay comes to rest (every |q̇ᵢ| ≤ REST_SPEED for REST_TIME) within the
        ``left`` [s] of the horizon — as the full rollout must —, and the rest test passes with the creep
        bound raised by :data:`SETTLE_GAMMA`, the drifting obstacles tested from now until the hold after
        that rest (the full rollout's window: its rest comes later) — by ``margin`` + ``stray`` [m] (a
        walk's allowance: :mod:`qpctl.safety.walk`)."""
        speed = K.max_abs(v)
        to_rest = (math.log(speed / REST_SPEED) / gain if speed > REST_SPEED else 0.0) + REST_TIME
        return (worst > margin and to_rest <= left
                and self.rest.verifies(q, SETTLE_GAMMA * v, gain, margin + stray, t, t + to_rest + self.rest.hold))

    def _stage(self, q: np.ndarray, v: np.ndarray, h: float, i: int) -> None:
        """Stage i + 1 from stage i: its velocity kq[i+1] = v + h·ka[i], its acceleration ABA(q ⊕ h·kq[i], ·)."""
        kq, ka, qs, vs = self._kq, self._ka, self._qs, self._vs
        K.stage(q, v, kq[i], ka[i], h, self._dq, qs, vs)
        if self.lie:
            qs[:] = self.robot.integrate(q, self._dq)
        kq[i + 1] = vs
        ka[i + 1] = pin.aba(self.model, self.data, qs, vs, self.tau)

    def step(self, q: np.ndarray, v: np.ndarray) -> None:
        """One RK4 step of the held ``self.tau`` over dt; (q, v) updated in place (rk4_step's stages);
        ``self.travel`` ← Σᵢρᵢ|Δqᵢ| of the step (vector-space robots; their stages in two kernel calls
        around Pinocchio's aba)."""
        dt = self.dt
        if self.fused:
            model, data, tau, kq, ka, qs = self.model, self.data, self.tau, self._kq, self._ka, self._qs
            ka[0] = pin.aba(model, data, q, v, tau)
            for i, h in ((0, 0.5 * dt), (1, 0.5 * dt), (2, dt)):
                K.stage_into(q, v, kq, ka, i, h, qs)
                ka[i + 1] = pin.aba(model, data, qs, self._kq_rows[i + 1], tau)
            self.travel = K.finish(q, v, kq, ka, dt / 6, self._dq, self._dv, self._rho)
            return
        self._kq[0] = v
        self._ka[0] = pin.aba(self.model, self.data, q, v, self.tau)
        self._stage(q, v, 0.5 * dt, 0)
        self._stage(q, v, 0.5 * dt, 1)
        self._stage(q, v, dt, 2)
        K.combine(self._kq, dt / 6, self._dq)
        K.combine(self._ka, dt / 6, self._dv)
        if self.lie:
            q[:] = self.robot.integrate(q, self._dq)
        else:
            q += self._dq
        v += self._dv

    def successor(self, q: np.ndarray, v: np.ndarray, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(q₁, q̇₁): ``tau`` [N·m] held over one step from (q, q̇), as the simulator steps it (new arrays;
        the native step where there is one, the same operations)."""
        if self.native is not None:
            return self.native.successor(q, v, tau)
        qq, vv = np.array(q, float), np.array(v, float)
        self.tau[:] = tau
        self.step(qq, vv)
        return qq, vv

    def run(self, q: np.ndarray, v: np.ndarray, tau_prev: np.ndarray, t: float, gain: float, *,
            horizon: float = 3.0, margin: float = 0.0, stop_below: float = -np.inf,
            exact: bool = True, retreat: Retreat | None = None, settle: bool = False,
            rest_within: float | None = None) -> Certificate:
        """The brake of gain κ [1/s] from (q, q̇ [rad/s], τ_prev [N·m]) at t [s]: the
        :class:`~qpctl.safety.oracle.Certificate` :func:`qpctl.safety.oracle.rollout` gives (the
        arguments mean the same; a state that is not finite ends it, not viable). Inputs unchanged.
        ``exact=False``: the lazy clearance (module docstring; the least clearance a lower bound).
        ``retreat``: the retreat that brakes at κ once it stops steering (:mod:`qpctl.safety.retreat`).
        ``settle``: the rollout may end where the brake has settled (module docstring, "Settled"; the
        certificate's time and steps are then the settle's), if its decay reaches rest within
        ``rest_within`` [s] of t (default: the horizon; a rollout cut short by a step budget passes the
        horizon the full one would have had)."""
        return finish(self.run_iter(q, v, tau_prev, t, gain, None, horizon=horizon, margin=margin,
                                    stop_below=stop_below, exact=exact, retreat=retreat, settle=settle,
                                    rest_within=rest_within))

    def run_iter(self, q: np.ndarray, v: np.ndarray, tau_prev: np.ndarray, t: float, gain: float, budget: Any, *,
                 horizon: float = 3.0, margin: float = 0.0, stop_below: float = -np.inf, exact: bool = True,
                 retreat: Retreat | None = None, settle: bool = False,
                 rest_within: float | None = None) -> Generator[None, None, Certificate]:
        """:meth:`run` as a generator that pauses (yields) wherever ``budget`` (None: never) has no work left
        for now — before integrating a step (``budget.steps()`` < 1) and before evaluating a clearance,
        testing a rest or trying a walk (``budget.evaluations()`` < 1) — and is resumed where it paused (the
        work spread over several ticks: :class:`qpctl.safety.backup.BackupGuard`'s carried search); the
        certificate is its return value, bit for bit :meth:`run`'s. ``budget.spend_steps(n)`` is told each
        stretch of integrated steps (a walk's steps are not integrated). A budget needs the native loop (a
        ValueError where this robot has none)."""
        lazy = not exact and self.rho is not None
        level = max(margin, stop_below)
        settle = settle and self.settles
        rest_within = horizon if rest_within is None else rest_within
        steps = round(horizon / self.dt)
        if self.native is not None:
            return (yield from self.native.run_iter(q, v, tau_prev, t, gain, steps, margin, stop_below, level, lazy,
                                                    retreat, settle, rest_within, budget))
        if budget is not None:
            raise ValueError("a rollout spread over ticks needs the native loop")
        return self._stepped(q, v, tau_prev, t, gain, steps, margin, stop_below, level, lazy, retreat, settle,
                             rest_within)

    def _stepped(self, q: np.ndarray, v: np.ndarray, tau_prev: np.ndarray, t: float, gain: float, steps: int,
                 margin: float, stop_below: float, level: float, lazy: bool, retreat: Retreat | None, settle: bool,
                 rest_within: float) -> Certificate:
        """:meth:`run`'s loop in Python (robots without the native loop; the arguments prepared by :meth:`run_iter`)."""
        dt, world, rho = self.dt, self.world, self.rho
        qq, vv, prev = np.array(q, float), np.array(v, float), np.array(tau_prev, float)
        worst, still, last, drift = np.inf, 0.0, np.inf, np.inf
        decay, below = math.exp(-gain * dt), np.inf  # below: a settle's creep must be under it (halved on a refusal)
        walk_after = 0.0  # a retreat's walk is tried from this step on (qpctl.safety.walk)
        stray, q_min, q_max = 0.0, self.q_min, self.q_max  # after a walk: its allowance, the limits less it
        walked_from: tuple[Any, ...] | None = None  # the state a walk started from, while the rollout is on from it
        k = 0
        while True:
            end: Certificate | None = None
            if k >= steps:
                end = Certificate(False, gain, worst, np.inf, steps)
            else:
                if lazy and last - drift - stray > level:
                    worst = min(worst, last - drift - stray)
                else:
                    last, drift = world(qq, t + k * dt), 0.0
                    worst = min(worst, last - stray)
                code = K.state_code(self.robot.angles(qq, self._angles) if self.lie else qq, vv, q_min, q_max,
                                    REST_SPEED)
                tk = t + k * dt
                steering = retreat is not None and retreat.steering(tk)  # a retreat's rest is its brake's
                still = still + dt if code == K.AT_REST and not steering else 0.0
                if worst < stop_below or code == K.OUTSIDE:
                    end = Certificate(False, gain, worst, np.inf, k)
                elif still >= REST_TIME:
                    end = self.at_rest(qq, vv, gain, worst, margin, t, k, stray)
            if end is not None:
                if end.viable or walked_from is None:
                    return end
                # a walked rollout that does not verify is stepped again from the walk's start, without walks:
                # a walk may refute nothing the steps would verify
                k, last, drift, worst, q0, v0, p0 = walked_from
                qq[:], vv[:], prev[:] = q0, v0, p0
                stray, q_min, q_max, walk_after, walked_from, below, still = 0.0, self.q_min, self.q_max, np.inf, \
                    None, np.inf, 0.0
                continue
            self.torque(qq, vv, prev, gain, retreat, tk)
            if settle and steering and k >= walk_after and np.array_equal(self.tau, self.raw):
                assert retreat is not None
                walk = self.walk
                walk.tau[:] = self.tau
                walked, walk_after = walk.attempt(qq, vv, retreat, gain, t, k, steps, (last, drift, worst), level, lazy)
                if walked:  # on from the switch's state, every clearance and limit less the walk's stray
                    walked_from = k, last, drift, worst, qq.copy(), vv.copy(), prev.copy()
                    qq[:], vv[:], prev[:] = walk.q, walk.v, walk.tau
                    (last, drift, worst), stray = walk.bound, walk.stray
                    q_min, q_max = self.q_min + walk.joint_stray, self.q_max - walk.joint_stray
                    k += walk.steps
                    continue
            if settle and not steering and np.array_equal(self.tau, self.raw):  # unclipped
                creep = K.travel(vv, rho) * SETTLE_GAMMA / gain
                if creep < below and self.settled(qq, vv, gain, decay):
                    if self.settled_rest(qq, vv, gain, worst, margin, tk, rest_within - k * dt, stray):
                        return Certificate(True, gain, worst, k * dt, k)
                    below = 0.5 * creep
            prev[:] = self.tau
            self.step(qq, vv)
            if lazy:
                drift += (self.travel if self.fused else K.travel(self._dq, rho)) + self.obstacle_speed * dt
            k += 1


class NativeBrake:
    """:meth:`BrakeRollout.run`'s loop in :mod:`qpctl.native`'s C++ (module docstring): one handle on
    a copy of the robot's Pinocchio model (serialized and loaded there) and the rollout's arrays."""

    def __init__(self, owner: BrakeRollout, lib: Any, handle: int) -> None:
        self.owner, self.lib, self.handle = owner, lib, handle
        self.io = np.zeros(IO_SIZE)
        self._free = weakref.finalize(self, lib.qpb_free, handle)
        n = owner.robot.nv
        self.q, self.v, self.prev, self.target = (np.zeros(n) for _ in range(4))
        self.limits = [np.zeros(n) for _ in range(5)]  # τ_max, the rate window, q_min, q_max, ρ: copied each run
        # the arrays' addresses once (numpy's ``.ctypes.data`` costs ~1 µs an array)
        self.ptr = [a.ctypes.data for a in (self.q, self.v, self.prev, *self.limits, self.target, self.io)]

    @classmethod
    def create(cls, owner: BrakeRollout) -> NativeBrake | None:
        """The native loop for ``owner``'s model, or None where :mod:`qpctl.native` is unavailable."""
        lib = qpctl.native.library()
        if lib is None:
            return None
        text = owner.model.saveToString().encode()
        handle = lib.qpb_new(text, len(text))
        if not handle:
            raise qpctl.native.NativeBuildError(f"the native rollout refused the model: {lib.qpb_error().decode()}")
        if lib.qpb_io_size() != IO_SIZE or lib.qpb_nv(handle) != owner.robot.nv:
            lib.qpb_free(handle)
            raise qpctl.native.NativeBuildError("the native rollout's layout is not this module's")
        return cls(owner, lib, handle)

    def successor(self, q: np.ndarray, v: np.ndarray, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`BrakeRollout.successor` in C++ (qpb_step: the rollout's own RK4 step)."""
        self.q[:], self.v[:], self.prev[:], self.limits[4][:] = q, v, tau, self.owner._rho
        ptr = self.ptr
        self.lib.qpb_step(self.handle, ptr[0], ptr[1], ptr[2], self.owner.dt, ptr[7])
        return self.q.copy(), self.v.copy()

    def run_iter(self, q: np.ndarray, v: np.ndarray, tau_prev: np.ndarray, t: float, gain: float, steps: int,
                 margin: float, stop_below: float, level: float, lazy: bool, retreat: Retreat | None,
                 settle: bool, rest_within: float, budget: Any) -> Generator[None, None, Certificate]:
        """:meth:`BrakeRollout.run`'s loop in C++, pausing where ``budget`` (None: never) says so
        (:meth:`BrakeRollout.run_iter`)."""
        io, qq, vv, prev = self.io, self.q, self.v, self.prev
        qq[:], vv[:], prev[:] = q, v, tau_prev
        io[:] = 0.0
        io[IO_STEPS], io[IO_LAST], io[IO_DRIFT], io[IO_WORST] = steps, np.inf, np.inf, np.inf
        io[IO_LEVEL], io[IO_STOP_BELOW], io[IO_GAIN], io[IO_DT] = level, stop_below, gain, self.owner.dt
        io[IO_OBSTACLE_SPEED], io[IO_REST_SPEED], io[IO_REST_TIME] = self.owner.obstacle_speed, REST_SPEED, REST_TIME
        io[IO_LAZY] = float(lazy)
        io[IO_T0], io[IO_UNTIL] = t, -np.inf
        io[IO_SETTLE], io[IO_SETTLE_BELOW], io[IO_DECAY] = float(settle), np.inf, math.exp(-gain * self.owner.dt)
        io[IO_BETA], io[IO_GAMMA] = SETTLE_BETA, SETTLE_GAMMA
        if retreat is not None:
            self.target[:] = retreat.target
            io[IO_UNTIL], io[IO_W2], io[IO_W1] = retreat.until, retreat.omega * retreat.omega, 2.0 * retreat.omega
        o = self.owner  # its limits read at each run, as the Python loop reads them
        for dst, src in zip(self.limits, (o.tau_max, o.window, o.q_min, o.q_max, o._rho), strict=True):
            dst[:] = src
        ptr = self.ptr
        advance, world, dt = self.lib.qpb_advance, self.owner.world, self.owner.dt
        walked_from: tuple[Any, ...] | None = None  # as in BrakeRollout.run
        while True:
            if budget is not None:  # integrate no more steps than the budget has now (the horizon a chunk's end)
                while budget.steps() < 1:
                    yield
                k0 = int(io[IO_K])
                io[IO_STEPS] = min(steps, k0 + budget.steps())  # (the native loop takes its whole part)
            answer = advance(self.handle, *ptr)
            k = int(io[IO_K])
            if budget is not None:
                budget.spend_steps(k - k0)
                io[IO_STEPS] = steps
                if answer == HORIZON and k < steps:
                    continue  # the chunk's end, not the rollout's
                if answer in (WALK, SETTLED, NEED_CLEARANCE, AT_REST_END):
                    while budget.evaluations() < 1:
                        yield
            if answer == WALK:
                assert retreat is not None
                walk = self.owner.walk
                bound = (float(io[IO_LAST]), float(io[IO_DRIFT]), float(io[IO_WORST]))
                if budget is None:
                    walked, io[IO_WALK_AFTER] = walk.attempt(qq, vv, retreat, gain, t, k, steps, bound, level, lazy)
                else:  # its clearance evaluations paused on as the rollout's are
                    walked, io[IO_WALK_AFTER] = yield from walk.attempt_iter(qq, vv, retreat, gain, t, k, steps, bound,
                                                                            level, lazy, budget)
                if walked:  # on from the switch's state, every clearance and limit less the walk's stray
                    walked_from = k, float(io[IO_LAST]), float(io[IO_DRIFT]), float(io[IO_WORST]), qq.copy(), \
                        vv.copy(), prev.copy()
                    qq[:], vv[:], prev[:] = walk.q, walk.v, walk.tau
                    io[IO_LAST], io[IO_DRIFT], io[IO_WORST] = walk.bound
                    io[IO_K], io[IO_STRAY], io[IO_PENDING], io[IO_EVALUATED] = k + walk.steps, walk.stray, 0.0, 0.0
                    self.limits[2] += walk.joint_stray
                    self.limits[3] -= walk.joint_stray
                continue
            if answer == SETTLED:
                if self.owner.settled_rest(qq, vv, gain, float(io[IO_WORST]), margin, t + k * dt,
                                           rest_within - k * dt, float(io[IO_STRAY])):
                    return Certificate(True, gain, float(io[IO_WORST]), k * dt, k)
                io[IO_SETTLE_BELOW] = 0.5 * io[IO_CREEP]
                continue
            if answer == NEED_CLEARANCE:
                last = world(qq, t + k * dt)
                io[IO_LAST], io[IO_DRIFT], io[IO_EVALUATED] = last, 0.0, 1.0
                io[IO_WORST] = min(float(io[IO_WORST]), last - float(io[IO_STRAY]))
                continue
            worst = float(io[IO_WORST])
            if answer == FAILED:
                end = Certificate(False, gain, worst, np.inf, k)
            elif answer == AT_REST_END:
                end = self.owner.at_rest(qq, vv, gain, worst, margin, t, k, float(io[IO_STRAY]))
            else:
                end = Certificate(False, gain, worst, np.inf, steps)
            if end.viable or walked_from is None:
                return end
            # a walked rollout that does not verify is stepped again from the walk's start, without walks
            k0, io[IO_LAST], io[IO_DRIFT], io[IO_WORST], q0, v0, p0 = walked_from
            qq[:], vv[:], prev[:] = q0, v0, p0
            io[IO_K], io[IO_STRAY], io[IO_PENDING], io[IO_EVALUATED], io[IO_STILL] = k0, 0.0, 0.0, 0.0, 0.0
            io[IO_SETTLE_BELOW], io[IO_WALK_AFTER] = np.inf, np.inf
            self.limits[2][:], self.limits[3][:] = o.q_min, o.q_max
            walked_from = None
