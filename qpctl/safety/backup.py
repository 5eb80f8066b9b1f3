"""The verified backup (issue 22, item 2): a controller's torque is applied only if, from the state it
leads to, a brake of the family (:mod:`qpctl.safety.oracle`) brings the arm to rest without contact in
a rollout on the controller's own model; otherwise the stored verified brake continues.

Each tick at (q, q̇, t) with the torque τ_prev applied last, the controller proposes τ (its ``step``);
then, where the world clearance (exact, every pair: :class:`qpctl.tick.WorldClearance`) is below
``check_distance`` [m] (default: everywhere):

1. the successor (q₁, q̇₁) — τ held over one step, the built-in simulator's RK4 — is rolled out
   (:class:`qpctl.safety.rollout.BrakeRollout`) with the stored brake's gain first, then the others; a
   rollout ends at rest — with ``settle`` (default on) already where the brake has settled into its
   decay and the rest it decays to is bounded (:mod:`qpctl.safety.rollout`, "Settled": 7 steps instead
   of 213 at the median on the Panda at 1 kHz), a retreat's unclipped steering walked in closed form
   (:mod:`qpctl.safety.walk`) —, on the first step below ``margin`` [m] or past a
   joint limit; the first that comes to rest with the clearance above ``margin`` all along is stored
   and τ applied; with ``check_steps`` (default inf) the rollouts of one check — the proposal's, the
   retreat search from its successor, and steps 3 and 4 below — take at most that many steps in
   all — a proposal not verified within them is refuted, which bounds a check's cost (the guarantee is
   untouched: a refuted proposal only means the stored brake continues; step 3 cut short leaves the
   tick unverified and the arm on its stop, step 4's re-verification cut short keeps the stop as
   lapsed: ``info["backup_out_of_steps"]`` on every tick the steps ended a rollout); with
   ``check_evaluations`` (default inf) the check evaluates the world clearance at most that many times
   in all — the rollouts' lazy clearance, the walks' and every rest test's (:class:`Meter`) —, and the
   evaluation past them ends the rollout or search it was in, as the steps do (the same flag): the two
   limits together bound the check's whole cost (steps × a step's time + evaluations × an evaluation's);
   while the last tick applied
   the stored brake, only ``tries_on_brake`` gains are tried (default 2: the stored one and the first
   other) — the checks that refute every gain are the long ones (four rollouts, 2,000–4,000 steps on
   the soak's heavy arm), and they come in runs while the arm brakes; with ``retreat_proposals``
   (default on) a successor none of whose stops verifies but one of which comes to rest without contact
   (refused by the rest test: a rest in a swaying obstacle's sweep or a drifting one's way) gets the
   retreat search of step 3 as well (after a failed one, only ``RETRY_TICKS`` ticks later): a retreat
   found is stored and τ applied — the QP may dodge through a sweep with its escape verified;
2. if none does, the stored brake's torque from (q, q̇, τ_prev) is applied (``info["backup"]``: its
   gain): it was verified from this very state one tick ago, and the rollout is the simulator's own
   integration, so under the exact model following it stays verified;
3. if no brake is stored (the start, or the first tick back within ``check_distance``), a brake is
   rolled out from (q, q̇, τ_prev) itself; if none is verified — every stop from here ends where a
   swaying obstacle's sweep comes back, the start of a scene inside one — a *retreat* is searched
   (``retreats``, default on: :mod:`qpctl.safety.retreat`, a few targets whose rests clear the sweeps,
   steered toward and braked at, each rolled out the same way; after a search that found nothing, the
   next only ``RETRY_TICKS`` ticks later); the first verified is stored and its
   torque applied (``info["backup"]``: its gain; ``info["backup_retreat"]``: the retreat stored after
   the tick, on every tick it stays stored), else the tick is unverified (``info["backup_unverified"]``):
   τ is applied if one of its successor's rollouts came to rest without contact (failing the rest test
   only: the stop is struck later, at rest), else the arm keeps *its stop* — the last such rollout's
   brake (or retreat), from whose trajectory the state has not left (``info["backup_stop"]``: its gain;
   ``unverified = "proposal"``: τ applied all the same, as before). So where no stop is verified the
   arm can still always come to rest before a contact: every contact of a run begins at rest (the
   title of issue 22; speed and separation monitoring's rule for a contact no stop avoids).
   A stored retreat is what a proposal's successor is rolled out with first, as a stored gain is.
4. with ``hold`` [s] (default 2) a rest must also clear every drifting obstacle over the ``hold`` seconds
   after it (:class:`qpctl.safety.sweep.RestClearance`); that window slides with the time, so while the
   arm rests the stored stop is re-verified from each state, and when it is refuted step 3 runs (a
   retreat out of the obstacle's way) — or, where nothing verifies, the stop is kept
   (``info["backup_hold_lapsed"]``: verified as it is with no hold, not for the hold).

**Carried search** (``carry``, default on; only under a limit — ``check_steps`` or ``check_evaluations``
finite —, with retreats, ``unverified = "stop"`` and the native loop): a state whose retreat search
(step 3) does not fit one tick's limits would have it cut every tick, nothing stored, every tick
unverified. Instead the search is carried over the ticks. The arm keeps the stop it is on (the stored
stop whose hold lapsed, or the unverified tick's stop) for the next ``CARRY_TICKS`` ticks — so the state
at that *anchor* tick is known exactly: it is computed from this state as the guard applies the stop,
its torque at each state and the rollout's RK4 step — and the search runs from the anchor on what the
ticks leave (while it runs a tick's own check takes ``1 − CARRY_SHARE`` of the limits; its rollouts and
walks pause where the tick's steps or evaluations are spent and resume the next tick, bit for bit the
rollout run at once: :meth:`BrakeRollout.run_iter`; a rest test, once begun, is taken whole). At the
anchor tick its retreat is stored if the state is the anchor bit for bit (the arm followed the stop)
and nothing else was stored meanwhile: a verified backup from this very state, as step 3's would be. A
search not done by its anchor is dropped and the next looks twice as far ahead (up to ``CARRY_MAX``
ticks). The ticks on the way are unverified (the arm on its stop), as they would be anyway.

Beyond ``check_distance`` τ is applied unchecked and the stored brake forgotten. **What is proved**
(exact model: the built-in simulator's RK4 at the guard's Δt; obstacles static or moving as the scene
says): every state from a verified tick on admits a verified brake, so a run without an unverified tick
has no contact: the states beyond ``check_distance`` are clear by the screen's own test, and at each
return within it step 3 verifies the state before anything else. A screen that is too short can only
cost an unverified tick, which the run counts (``stats["unverified"]``, the metrics'
``backup_unverified_ticks``). With ``unverified = "stop"`` every state of any run (screen at inf) admits
a brake or retreat that comes to rest before any contact — the torque applied is a verified one, a
proposal whose successor has such a stop, or the stop the state lies on —, so a contact can only begin
once a stop has come to rest and an obstacle reaches the arm there (``collisions_at_rest``).
"""

from __future__ import annotations

import time
from collections.abc import Generator
from typing import Any, ClassVar

import numpy as np

from qpctl.constraints.constraints import TorqueLimit
from qpctl.safety.oracle import BRAKE_GAINS, REST_SPEED, Certificate
from qpctl.safety.retreat import OMEGAS, RETRY_TICKS, SETTLE, Retreat, noted, search, search_iter, switch_time
from qpctl.safety.rollout import BrakeRollout
from qpctl.tick import WorldClearance

#: The guard's order of the family [1/s]: after the stored gain, the firm brakes first — they come to
#: rest soonest, so their rollouts are the shortest (κ = 4 from 0.5 rad/s: ~530 steps of 2 ms, κ = 25:
#: ~100 on the planar arm), and the first verified is the one stored and tried first next tick.
GUARD_GAINS = (25.0, 60.0, 10.0, 4.0)
assert sorted(GUARD_GAINS) == sorted(BRAKE_GAINS)  # the oracle's family, in another order


class OutOfEvaluations(Exception):
    """The check's world-clearance evaluations ran out (raised by :meth:`Meter.spend` in the evaluation
    past the limit; the guard ends the rollout or search it was in: never an error of a run)."""


class Meter:
    """The world-clearance evaluations of one check against its limit: every
    :class:`~qpctl.tick.WorldClearance` the guard's rollouts and rest tests evaluate carries it
    (``world.meter``) and calls :meth:`spend` at each evaluation."""

    def __init__(self) -> None:
        self.used, self.limit, self.out = 0, np.inf, False

    def start(self, limit: float) -> None:
        """A check begins with ``limit`` evaluations (inf: no limit)."""
        self.used, self.limit, self.out = 0, float(limit), False

    def spend(self) -> None:
        """One evaluation counted, or :class:`OutOfEvaluations` (and ``out`` from then on) where the limit is spent."""
        if self.used >= self.limit:
            self.out = True
            raise OutOfEvaluations
        self.used += 1


class TickWork:
    """What the check's limits leave a tick for the carried search (:meth:`BackupGuard._carry`): steps to
    integrate and clearance evaluations (counted by ``meter``, the carried search's own worlds'), the
    interface :meth:`qpctl.safety.rollout.BrakeRollout.run_iter` pauses on."""

    def __init__(self, meter: Meter) -> None:
        self.meter, self._steps, self._end, self.spent = meter, 0.0, 0, 0

    def start(self, steps: float, evaluations: float) -> None:
        """A tick's allowance; ``spent`` counts its integrated steps from here."""
        self._steps, self._end, self.spent = max(float(steps), 0.0), self.meter.used + max(evaluations, 0.0), 0

    def steps(self) -> float:
        return self._steps

    def evaluations(self) -> float:
        return self._end - self.meter.used

    def spend_steps(self, n: int) -> None:
        self._steps -= n
        self.spent += n


class Carried:
    """A retreat search carried over the ticks (module docstring, "Carried search"): the stop the arm follows
    meanwhile (gain, retreat), the tick its anchor is reached (``due``), the anchor once computed, the
    search (a generator) and what it found."""

    def __init__(self, follow: tuple[float, Retreat | None], due: int) -> None:
        self.follow, self.due = follow, due
        self.anchor: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # (q, q̇, τ_prev) at the due tick
        self.work: Generator[None, None, None] | None = None
        self.found: tuple[float, Retreat] | None = None
        self.done = False


#: The first carried search's anchor lies this many ticks ahead; each one not done by its anchor doubles it
#: for the next (up to CARRY_MAX), one done resets it.
CARRY_TICKS, CARRY_MAX = 20, 2000
#: While a search is carried, this share of the check's limits is left to it (the tick's own check takes the rest).
CARRY_SHARE = 0.5


class GuardedOutput:
    """A controller's output with the torque the guard applied (every other attribute the output's)."""

    def __init__(self, out: Any, tau: np.ndarray, info: dict[str, Any], compute_us: float) -> None:
        self._out, self.tau, self.info, self.compute_us = out, tau, info, compute_us

    def __getattr__(self, name: str) -> Any:
        return getattr(self._out, name)


class BackupGuard:
    """A controller behind the verified backup (module docstring); every other attribute is the
    controller's, so it runs wherever the controller does. ``dt`` [s]: the control period (the
    simulator's step), ``check_distance`` [m], ``margin`` [m] (kept along the brake), ``horizon`` [s]:
    the longest brake rolled out. A tick's ``compute_us`` is the controller's plus the check's."""

    def __init__(self, controller: Any, dt: float, *, check_distance: float = np.inf, margin: float = 0.0,
                 horizon: float = 3.0, gains: tuple[float, ...] = GUARD_GAINS, check_steps: float = np.inf,
                 check_evaluations: float = np.inf, tries_on_brake: float = 2, retreats: bool = True, hold: float = 2.0,
                 unverified: str = "stop", retreat_proposals: bool = True, settle: bool = True,
                 carry: bool = True) -> None:
        self.controller = controller
        self.dt, self.check_distance, self.margin, self.horizon = float(dt), float(check_distance), float(margin), \
            float(horizon)
        self.check_steps = float(check_steps)  # rollout steps a proposal's check may spend (module docstring)
        self.check_evaluations = float(check_evaluations)  # world-clearance evaluations a check may spend
        self.gains = tuple(gains)
        self.exact = False  # the lazy clearance (True: every step's clearance evaluated; the same verdicts)
        self.tries = np.inf  # gains tried from a proposal's successor (inf: the whole family)
        self.tries_on_brake = float(tries_on_brake)  # the same while the last tick applied the stored brake
        self.retreats = bool(retreats)  # step 3 searches a retreat where no brake verifies
        self.world = WorldClearance(controller.robot, controller.obstacles)  # obstacles only: no self pairs
        self.hold = float(hold)  # [s] a rest must stay clear of the drifting obstacles this long (0: not tested)
        if unverified not in ("stop", "proposal"):
            raise ValueError(f"unverified must be 'stop' or 'proposal', not {unverified!r}")
        self.unverified = unverified  # what an unverified tick applies (module docstring, step 3)
        # step 1 also searches a retreat from a refused proposal's successor whose stop is refused by the rest test
        self.retreat_proposals = bool(retreat_proposals) and self.retreats
        self.brake = BrakeRollout(controller.robot, self.world, self.dt, self.hold)
        self.meter = Meter()  # the check's evaluations: every world the rollouts and the rest tests evaluate
        for world in (self.world, *self.brake.rest.worlds()):
            world.meter = self.meter
        # the carried search's own rollout (its native state kept across ticks) and the count of its evaluations
        self.ahead: BrakeRollout | None = None
        self.ahead_meter = Meter()
        self._work = TickWork(self.ahead_meter)
        self.settle = bool(settle)  # a rollout ends where its brake settles (qpctl.safety.rollout, "Settled")
        self.carry = bool(carry)  # under a limit, step 3's retreat search is carried over the ticks
        self._limit = next((c for c in getattr(controller, "constraints", []) if isinstance(c, TorqueLimit)), None)
        self.stats: dict[str, Any] = {"checked": 0, "backup": 0, "unverified": 0, "out_of_steps": 0, "check_us": [],
                                      "check_steps": [], "check_evaluations": [], "retreat_searches": 0,
                                      "retreats_found": 0, "hold_lapsed": 0,
                                      "stops": 0, "proposal_searches": 0, "proposal_retreats_found": 0,
                                      "carried_searches": 0, "carried_found": 0, "carried_adopted": 0}
        self._reset_backup()

    def __getattr__(self, name: str) -> Any:
        return getattr(self.controller, name)

    def _reset_backup(self) -> None:
        self._gain: float | None = None
        self._retreat: Retreat | None = None  # the stored backup is this retreat, braking at _gain
        self._wait = {"state": 0, "proposal": 0}  # ticks until a failed retreat search of each kind may be repeated
        # while nothing is stored (once a backup is, it stays stored): a rollout from the state the last torque
        # leads to that comes to rest without contact, verified or not — the arm's stop where nothing verifies
        self._stop: tuple[float, Retreat | None] | None = None
        self._on_brake = False  # the last tick applied the stored brake
        self._tau_prev = np.full(self.controller.robot.nv, np.nan)
        self._carried: Carried | None = None  # a retreat search carried over the ticks
        self._carry_ticks = CARRY_TICKS
        self._ticks = 0  # the checks so far (the carried search's clock)

    def reset(self) -> None:
        self.controller.reset()
        self._reset_backup()

    def warmup(self) -> float:
        """The controller's warmup, then every kernel the check calls compiled or loaded (numba's cache) —
        without it, the first tick that applies the stored brake, settles a stop or walks a retreat loads
        its kernel mid-loop (5 ms each on the 2-core EPYC): the native loop's and the Python loop's (robots
        with continuous joints; a machine without the native build), each with a settled brake and a walked
        retreat. Returns the controller's warmup's."""
        out = self.controller.warmup()
        robot, b, gain = self.controller.robot, self.brake, self.gains[0]
        q, v, prev = robot.q_home.astype(float), np.full(robot.nv, 0.05), np.zeros(robot.nv)
        sway = Retreat(tuple(robot.q_home), OMEGAS[0], switch_time(0.0, self.dt, OMEGAS[0]))
        native = b.native
        for loop in ((native, None) if native is not None else (None,)):
            b.native = loop
            try:
                for retreat in (None, sway):
                    b.run(q, v, prev, 0.0, gain, horizon=1.0 + SETTLE / OMEGAS[0], exact=False, retreat=retreat,
                          settle=True, margin=-np.inf)
            finally:
                b.native = native
        b.torque(q, v, prev, gain)  # the stored brake applied (outside the loops)
        b.successor(q, v, prev)
        if self._carries():  # the carried search's rollout made now (its native handle: milliseconds)
            self._ahead_rollout()
        self._reset_backup()
        return float(out)

    def _roll(self, q: np.ndarray, v: np.ndarray, tau_prev: np.ndarray, t: float, gain: float,
              retreat: Retreat | None, steps: int | None = None) -> Any:
        """The guard's rollout of the brake of gain κ (or ``retreat``) from (q, q̇) after τ_prev at t: ended
        below ``margin``, kept above it, settled where ``settle``, in at most ``steps`` steps (default: the
        horizon's) — the rest of a settled stop still due within the horizon, not the steps."""
        horizon = self.horizon if steps is None else steps * self.dt
        try:
            return self.brake.run(q, v, tau_prev, t, gain, horizon=horizon, margin=self.margin,
                                  stop_below=self.margin, exact=self.exact, retreat=retreat, settle=self.settle,
                                  rest_within=self.horizon)
        except OutOfEvaluations:  # not verified; the check does no more work (every rollout after it ends at its
            return Certificate(False, gain, -np.inf, np.inf, 0)  # first evaluation): its steps are not counted

    def _first_verified(self, q: np.ndarray, v: np.ndarray, tau_prev: np.ndarray, t: float,
                        tries: float = np.inf, steps: float = np.inf
                        ) -> tuple[tuple[float, Retreat | None] | None, int, bool, tuple[float, Retreat | None] | None]:
        """(The first backup (gain, retreat or None) verified from (q, q̇) after τ_prev at t — the stored
        one first, then the family's brakes —, or None; the rollout steps spent; whether ``steps`` ran
        out; the first of the rollouts tried that came to rest without contact, verified or not — a stop —,
        or None), trying at most ``tries`` (inf: all) in at most ``steps`` rollout steps over all of them (a
        rollout they cut short is not verified)."""
        stored = [(self._gain, self._retreat)] if self._gain is not None else []
        order = stored + [(g, None) for g in self.gains if (g, None) not in stored]
        full = round(self.horizon / self.dt)
        left, spent, stop = steps, 0, None
        for g, r in order[:int(min(tries, len(order)))]:
            n = full if left >= full else int(left)
            if n < 1:
                return None, spent, True, stop
            cert = self._roll(q, v, tau_prev, t, g, r, n)
            spent += cert.steps
            if cert.viable:
                return (g, r), spent, False, (g, r)
            if stop is None and np.isfinite(cert.t_rest) and cert.min_clearance > self.margin:
                stop = g, r  # at rest without contact, its rest refuted by the rest test
            if (n < full and cert.steps >= n) or self.meter.out:  # a limit ended this rollout, not the brake
                return None, spent, True, stop
            left -= max(cert.steps, 1)
        return None, spent, False, stop

    def _retreat_from(self, q: np.ndarray, v: np.ndarray, tau_prev: np.ndarray, t: float,
                      steps: float = np.inf) -> tuple[tuple[float, Retreat] | None, int, bool]:
        """A retreat verified from (q, q̇) after τ_prev at t (step 3; :func:`qpctl.safety.retreat.search`,
        braking at the first gain of the family once it stops steering) in at most ``steps`` rollout steps
        (a rollout they cut short is not verified; each target's rest test counts as one step against
        them — where most targets fail it, as beside two drifting obstacles, a search is hundreds of rest
        tests), or None; the rollout steps spent; whether the steps ended the search."""
        spent, tested, gain = 0, 0, self.gains[0]
        full = round(self.horizon / self.dt)
        ran_out = steps < 1
        if ran_out:
            return None, 0, True  # no steps left: not searched (nor its targets' rest tests taken)

        def run(r: Retreat) -> Any:
            nonlocal spent, ran_out
            n = int(min(full, steps - spent - tested))
            if n < 1:
                ran_out = True
                return None  # out of steps: the search ends here
            cert = self._roll(q, v, tau_prev, t, gain, r, n)
            spent += max(cert.steps, 1)
            if self.meter.out:
                ran_out = True
                return None  # out of evaluations: the search ends here
            return cert  # (one cut short by the steps left is not verified: its horizon ended it)

        rest = self.brake.rest

        def clear(x: np.ndarray) -> bool | None:
            nonlocal tested, ran_out
            if spent + tested >= steps or self.meter.out:
                ran_out = True
                return None  # out of steps or evaluations: the search ends here
            tested += 1
            try:
                return bool(rest.clear(x, self.margin, t))
            except OutOfEvaluations:
                ran_out = True
                return None

        found = search(run, self.controller.robot, q, t, self.dt, rest.rho, clear)
        return ((gain, found[0]) if found is not None else None), spent, ran_out

    #: the stats each kind of search counts in: (searches, retreats found)
    SEARCH_STATS: ClassVar[dict[str, tuple[str, str]]] = {"state": ("retreat_searches", "retreats_found"),
                                                          "proposal": ("proposal_searches",
                                                                       "proposal_retreats_found")}

    def _throttled_retreat(self, kind: str, wanted: bool, q: np.ndarray, v: np.ndarray, tau_prev: np.ndarray,
                           t: float, steps: float = np.inf) -> tuple[tuple[float, Retreat] | None, int, bool]:
        """:meth:`_retreat_from` (in at most ``steps`` rollout steps) if ``wanted`` and no search of this
        ``kind`` ("state": step 3, "proposal": from a proposal's successor) found nothing within the last
        ``RETRY_TICKS`` calls; every call counts one tick of the wait. (The retreat or None, the steps spent,
        whether the steps ended the search.)"""
        found, spent, ran_out = None, 0, False
        if wanted and self._wait[kind] <= 0:
            found, spent, ran_out = self._retreat_from(q, v, tau_prev, t, steps)
            self._wait[kind] = RETRY_TICKS if found is None else 0
            searches, hits = self.SEARCH_STATS[kind]
            self.stats[searches] += 1
            self.stats[hits] += found is not None
        self._wait[kind] -= 1
        return found, spent, ran_out

    def check(self, q: np.ndarray, v: np.ndarray, tau: np.ndarray, t: float, info: dict[str, Any]) -> np.ndarray:
        """The check of one tick (module docstring, steps 1–3): the torque to apply [N·m] given the
        proposal ``tau`` at (q, q̇, t), the stored gain and the torque applied last; ``info`` gets
        ``backup`` / ``backup_unverified`` / ``backup_out_of_steps`` where they apply; ``stats["check_steps"]``
        the rollout steps the check spent, ``stats["check_evaluations"]`` its world-clearance evaluations."""
        self._ticks += 1
        self._adopt(q, v, info)
        # while a search is carried, the tick's own check takes CARRY_SHARE less of the limits: the rest is the
        # carried search's at least (else the proposals' rollouts spend them all and the search never ends)
        c = self._carried
        steps, evaluations = self.check_steps, self.check_evaluations
        if c is not None and not c.done:
            steps, evaluations = np.floor((1.0 - CARRY_SHARE) * steps), np.floor((1.0 - CARRY_SHARE) * evaluations)
        self.meter.start(evaluations)
        extra = 0
        try:
            tau = self._check(q, v, tau, t, info, steps)
            extra = self._carry_on()
            return tau
        finally:
            self.stats["check_evaluations"].append(self.meter.used + extra)
            self.meter.limit = np.inf  # the screen's evaluations (check_distance) are not the check's

    def _carries(self) -> bool:
        """True where step 3's retreat search is carried over the ticks (module docstring, "Carried search"):
        a limit on the check, retreats on, the arm kept on its stop where nothing verifies, the native loop."""
        return (self.carry and self.retreats and self.unverified == "stop" and self.brake.native is not None
                and (self.check_steps < np.inf or self.check_evaluations < np.inf))

    def _ahead_rollout(self) -> BrakeRollout:
        """The carried search's own rollout (made once: its native state lives across the ticks)."""
        if self.ahead is None:
            robot = self.controller.robot
            self.ahead = BrakeRollout(robot, WorldClearance(robot, self.controller.obstacles), self.dt, self.hold)
            for world in (self.ahead.world, *self.ahead.rest.worlds()):
                world.meter = self.ahead_meter
        return self.ahead

    def _carry(self, q: np.ndarray, v: np.ndarray, t: float, follow: tuple[float, Retreat | None]) -> None:
        """A carried search from this tick: the arm follows ``follow`` for the next ``_carry_ticks`` ticks to
        the anchor, from which the search runs on what the ticks' limits leave."""
        c = Carried(follow, self._ticks + self._carry_ticks)
        c.work = self._carry_work(c, q.copy(), v.copy(), self._tau_prev.copy(), t)
        self._carried = c
        self.stats["carried_searches"] += 1

    def _carry_work(self, c: Carried, q: np.ndarray, v: np.ndarray, prev: np.ndarray,
                    t: float) -> Generator[None, None, None]:
        """The carried search's work, paused wherever the tick's work is spent: the anchor — the state the
        follow's torque leads to at the due tick, step by step as the guard applies it (its torque at each
        state, the rollout's RK4 step) —, then :func:`qpctl.safety.retreat.search_iter` from there."""
        b, work = self._ahead_rollout(), self._work
        g, r = c.follow
        ahead = c.due - self._ticks
        for i in range(ahead):
            while work.steps() < 1:
                yield
            tau = b.torque(q, v, prev, g, r, t + i * self.dt).copy()
            q, v = b.successor(q, v, tau)
            prev = tau
            work.spend_steps(1)
        ta = t + ahead * self.dt
        c.anchor = (q, v, prev)
        gain = self.gains[0]

        def run(retreat: Retreat) -> Generator[None, None, Any]:
            return b.run_iter(q, v, prev, ta, gain, work, horizon=self.horizon, margin=self.margin,
                              stop_below=self.margin, exact=self.exact, retreat=retreat, settle=self.settle,
                              rest_within=self.horizon)

        found = yield from search_iter(run, self.controller.robot, q, ta, self.dt, b.rest.rho,
                                       lambda x: bool(b.rest.clear(x, self.margin, ta)),
                                       lambda: work.evaluations() >= 1)
        c.found = (gain, found[0]) if found is not None else None
        c.done = True
        self.stats["carried_found"] += c.found is not None

    def _carry_on(self) -> int:
        """The carried search resumed on what this tick's limits left (its steps added to the tick's
        ``check_steps``); returns its evaluations."""
        c = self._carried
        if c is None or c.done or c.work is None:
            return 0
        spent = self.stats["check_steps"][-1]
        self._work.start(self.check_steps - spent, self.check_evaluations - self.meter.used)
        used = self.ahead_meter.used
        try:
            next(c.work)
        except StopIteration:
            pass
        self.stats["check_steps"][-1] = spent + self._work.spent
        return self.ahead_meter.used - used

    def _adopt(self, q: np.ndarray, v: np.ndarray, info: dict[str, Any]) -> None:
        """At its due tick a carried search ends: its retreat is stored if it verified one from this very state
        (the anchor: the arm followed the stop to it) and the stored backup is none or that stop. One that
        ended without a retreat ends at once (the next may begin this tick)."""
        c = self._carried
        if c is None or (self._ticks < c.due and not (c.done and c.found is None)):
            return
        self._carried = None
        if not c.done:  # the ticks' work did not finish it: the next one looks further ahead
            self._carry_ticks = min(2 * self._carry_ticks, CARRY_MAX)
            return
        self._carry_ticks = CARRY_TICKS
        if c.found is None:
            return
        assert c.anchor is not None and self._ticks == c.due  # (a search is done only from its anchor)
        aq, av, ap = c.anchor
        stored = None if self._gain is None else (self._gain, self._retreat)
        if (stored in (None, c.follow) and np.array_equal(q, aq) and np.array_equal(v, av)
                and np.array_equal(self._tau_prev, ap)):
            self._gain, self._retreat = c.found
            self.stats["carried_adopted"] += 1
            info["backup_carried_adopted"] = True

    def _check(self, q: np.ndarray, v: np.ndarray, tau: np.ndarray, t: float, info: dict[str, Any],
               limit: float) -> np.ndarray:
        """:meth:`check`'s work within ``limit`` rollout steps."""
        q1, v1 = self.brake.successor(q, v, tau)
        tries = min(self.tries, self.tries_on_brake) if self._on_brake else self.tries
        found, spent, cut, stop = self._first_verified(q1, v1, tau, t + self.dt, tries, limit)
        # a stop from the successor comes to rest without contact but not clear of the sweeps (or the hold): a
        # retreat from the successor out of their way lets the proposal in (a dodge through a swing's sweep)
        escape, more, short = self._throttled_retreat("proposal", found is None and stop is not None and
                                                      self.retreat_proposals, q1, v1, tau, t + self.dt,
                                                      limit - spent)
        found, spent, cut = found or escape, spent + more, cut or short
        self._on_brake = False
        if found is not None:
            self._count_cut(cut, info)
            self.stats["check_steps"].append(spent)
            self._gain, self._retreat = found
            self._carried = None  # a verified backup: the carried search is moot
            self._note_retreat(info)
            return tau
        lapsed: tuple[float, Retreat | None] | None = None
        if self._gain is not None and self.brake.rest.drifts and np.all(np.abs(v) <= REST_SPEED):
            # at rest the stored stop's rest moves on with the time, and so does the window over which it must
            # clear the drifting obstacles (hold): re-verified from this very state (the stored one alone), else
            # forgotten (step 3); within the check's steps left (cut short: refuted, the stop then kept as lapsed)
            kept, more, short, _ = self._first_verified(q, v, self._tau_prev, t, 1, limit - spent)
            spent, cut = spent + more, cut or short
            if kept is None:
                lapsed = self._gain, self._retreat
                self._gain, self._retreat = None, None
                info["backup_rest_refuted"] = True
        if self._gain is None:  # nothing stored: is the state itself verified? (step 3, in the check's steps left)
            found, more, short, here = self._first_verified(q, v, self._tau_prev, t, steps=limit - spent)
            spent, cut = spent + more, cut or short
            self._stop = self._stop or here  # (the start: no torque applied before it)
            if self._carries():  # the state's retreat search carried over the ticks (module docstring)
                escape, more, short = None, 0, False
                if found is None and self._carried is None:
                    self._carry(q, v, t, lapsed or self._stop or (self.gains[0], None))
            else:
                escape, more, short = self._throttled_retreat("state", found is None and self.retreats, q, v,
                                                              self._tau_prev, t, limit - spent)
            found, spent, cut = found or escape, spent + more, cut or short
            if found is not None:
                self._gain, self._retreat = found
                self._carried = None
            elif lapsed is not None:  # no retreat either: the arm stays on its stop, verified as with no hold
                self._gain, self._retreat = lapsed
                info["backup_hold_lapsed"] = True
                self.stats["hold_lapsed"] += 1
        self._count_cut(cut, info)
        self.stats["check_steps"].append(spent)
        if self._gain is None:
            self.stats["unverified"] += 1
            info["backup_unverified"] = True
            if self._carried is not None:  # the arm follows the carried search's stop to its anchor
                g, r = self._carried.follow
                info["backup_stop"], info["backup_carried"] = g, True
                self.stats["stops"] += 1
                return self._apply(self.brake.torque(q, v, self._tau_prev, g, r, t), t)
            if self.unverified == "proposal" or stop is not None:
                self._stop = stop
                return tau
            # no rollout from the proposal's successor comes to rest before a contact: the arm keeps its stop
            # (the state lies on it: the last tick's torque is its, or a proposal whose successor it is from)
            g, r = self._stop if self._stop is not None else (self.gains[0], None)
            info["backup_stop"] = g
            self.stats["stops"] += 1
            return self._apply(self.brake.torque(q, v, self._tau_prev, g, r, t), t)
        # the stored backup continues
        info["backup"] = self._gain
        self._note_retreat(info)
        self._on_brake = True
        self.stats["backup"] += 1
        return self._apply(self.brake.torque(q, v, self._tau_prev, self._gain, self._retreat, t), t)

    def _count_cut(self, cut: bool, info: dict[str, Any]) -> None:
        """``info["backup_out_of_steps"]`` and its count where ``check_steps`` or ``check_evaluations`` ended a
        rollout or search of the check."""
        if cut or self.meter.out:
            info["backup_out_of_steps"] = True
            self.stats["out_of_steps"] += 1

    def _apply(self, tau: np.ndarray, t: float) -> np.ndarray:
        """A copy of the backup's torque ``tau`` [N·m], remembered by the torque limit: the rate window
        of the next tick is about the torque applied."""
        tau = tau.copy()
        if self._limit is not None:
            self._limit.remember(tau, t)
        return tau

    def _note_retreat(self, info: dict[str, Any]) -> None:
        """``info["backup_retreat"]`` = (target [rad], ω [rad/s], t_s [s], gain [1/s]) while the stored
        backup is a retreat (what the state the tick leads to lies on: the oracle may be shown it)."""
        if self._retreat is not None and self._gain is not None:
            info["backup_retreat"] = noted(self._retreat, self._gain)

    def step(self, q: np.ndarray, v: np.ndarray, t: float) -> Any:
        out = self.controller.step(q, v, t)
        tau = np.array(out.tau, float)
        info = dict(out.info)
        t0 = time.perf_counter()
        q, v = np.asarray(q, float), np.asarray(v, float)
        # every tick is checked by default: the world clearance is only needed for a finite check distance
        near = self.check_distance == np.inf or self.world(q, t) < self.check_distance
        info["backup_checked"] = near
        if near:
            tau = self.check(q, v, tau, t, info)
        else:
            self._gain, self._retreat, self._on_brake, self._stop, self._carried = None, None, False, None, None
        us = (time.perf_counter() - t0) * 1e6
        if near:
            self.stats["check_us"].append(us)
            self.stats["checked"] += 1
            info["backup_check_us"] = us
        self._tau_prev = tau
        return GuardedOutput(out, tau, info, float(getattr(out, "compute_us", 0.0)) + us)

    def torque(self, q: np.ndarray, v: np.ndarray, t: float) -> np.ndarray:
        return np.asarray(self.step(q, v, t).tau)
