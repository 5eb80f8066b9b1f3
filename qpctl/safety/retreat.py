"""The evasive backup (issue 22, items 2 and 4): where no brake verifies — the start, or a stretch, inside
a swaying obstacle's sweep, where every stop ends in the swing's way — a *retreat* takes the arm to a
rest that clears every sweep, then brakes.

A retreat toward the target q* [rad] at natural frequency ω [rad/s] until the time t_s [s] is

    q̈* = ω²(q* − q) − 2ω q̇     while t < t_s   (critically damped toward q*),
    q̈* = −κ q̇                   from t_s on      (the brake of gain κ, :mod:`qpctl.safety.oracle`),

made a torque as the brake's is: RNEA at q̈*, clipped to ±τ_max and the rate window. Nothing about it is
assumed: a retreat counts only where a rollout on the controller's own model — the guard's
(:class:`qpctl.safety.rollout.BrakeRollout`) or the oracle's Simulator-based one — brings the arm to
rest without contact and the rest passes the rest test of its brake (joint limits, static obstacles and
sweeps cleared by the creep: :class:`qpctl.safety.sweep.RestClearance`). The target and ω are only the
recipe; the rollout is the proof.

t_s is absolute and set half a step between two ticks (:func:`switch_time`), so that the guard applying
a stored retreat at its own tick times and a rollout from any state on it take the same law at every
step whatever the rounding of t.

**The search** (:func:`search`): the targets are the configuration moved by one joint by ±0.3, ±0.6 or
±1.2 rad, or by two joints by ±0.3 or ±0.6 rad each (within the limits, 0.05 rad inside; the other
joints, where nearer a limit than that, moved to 0.05 rad inside it), in order of
how far they move the links (Σᵢρᵢ|Δqᵢ|, :func:`qpctl.safety.sweep.lever_arms`), kept where the arm at
rest there clears the static obstacles and every sweep by the margin (:meth:`RestClearance.clear`);
the first :data:`TRIES` of them are rolled out at each ω of :data:`OMEGAS`, switching to the brake
after :data:`SETTLE` / ω. A rollout that meets an obstacle ends there, so a failed search is cheap
next to a verified stop; the guard repeats a failed search only every :data:`RETRY_TICKS` ticks.
"""

from __future__ import annotations

from collections.abc import Callable, Generator, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

#: The retreat's natural frequencies tried [rad/s], brisk first.
OMEGAS = (6.0, 3.0)
#: How long a retreat steers toward its target before it brakes, in units of 1/ω (a critically damped
#: approach is within 5 % of its step after 4.7/ω).
SETTLE = 5.0
#: The joint steps of the targets searched [rad]: one joint, and two together; how far inside the joint
#: limits a target lies [rad]; how many targets whose rests are clear are rolled out (each at every ω).
STEPS = (0.3, 0.6, 1.2)
PAIR_STEPS = (0.3, 0.6)
INSIDE = 0.05
TRIES = 24
#: After a search that found nothing, the guard searches again only this many ticks later (the ticks
#: between stay unverified, as they would be anyway: a bound on what a hopeless start costs a tick).
RETRY_TICKS = 10


@dataclass(frozen=True)
class Retreat:
    """A retreat (module docstring): target q* [rad], natural frequency ω [rad/s], switch time t_s [s]."""

    target: tuple[float, ...]
    omega: float
    until: float

    @property
    def q(self) -> np.ndarray:
        return np.asarray(self.target, float)

    def steering(self, t: float) -> bool:
        """True while the retreat steers toward its target (t < t_s), False once it brakes."""
        return t < self.until

    def accel(self, q: np.ndarray, v: np.ndarray, out: np.ndarray) -> np.ndarray:
        """q̈* = ω²(q* − q) − 2ωq̇ into ``out`` (the operations in the native loop's order)."""
        w2, w1 = self.omega * self.omega, 2.0 * self.omega
        np.subtract(self.q, q, out=out)
        out *= w2
        out -= w1 * v
        return out


def noted(retreat: Retreat, gain: float) -> tuple[list[float], float, float, float]:
    """The retreat braking at ``gain`` [1/s] as a tick's ``info["backup_retreat"]``: (target, ω, t_s, gain)."""
    return list(retreat.target), retreat.omega, retreat.until, gain


def shown(info: dict[str, Any]) -> list[tuple[Retreat, float]]:
    """The retreat a tick's ``info`` notes (:func:`noted`), as the oracle's proposal ``[(retreat, gain)]``
    for the state the tick led to; [] where the tick held none."""
    r = info.get("backup_retreat")
    return [(Retreat(tuple(r[0]), r[1], r[2]), r[3])] if r is not None else []


def switch_time(t: float, dt: float, omega: float) -> float:
    """t_s for a retreat started at t [s] with ticks every dt [s]: SETTLE/ω later, moved to the middle
    between two ticks (module docstring)."""
    return t + (round(SETTLE / omega / dt) + 0.5) * dt


def _moves(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The search's moves of an n-joint arm in their order (module docstring): each joint by ±STEPS, then
    each pair by ±PAIR_STEPS each — as (first joint, second joint (= the first for a one-joint move), the
    first's step, the second's (0 for one joint)) arrays."""
    one = [(i, i, sign * step, 0.0) for i in range(n) for step in STEPS for sign in (1.0, -1.0)]
    two = [(i, j, si * a, sj * b) for i in range(n) for j in range(i + 1, n)
           for a in PAIR_STEPS for b in PAIR_STEPS for si in (1.0, -1.0) for sj in (1.0, -1.0)]
    m = np.array(one + two)
    return m[:, 0].astype(int), m[:, 1].astype(int), m[:, 2:]


_MOVES: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}


def candidates(robot: Any, q: np.ndarray, rho: np.ndarray | None) -> list[np.ndarray]:
    """The search's targets from q [rad] before the rest test (module docstring), nearest first: each
    joint moved by ±:data:`STEPS`, each pair of joints by ±:data:`PAIR_STEPS` each, within the limits
    (:data:`INSIDE` inside them; a joint not moved that lies nearer a limit than that is moved to
    :data:`INSIDE` inside it), ordered by Σᵢρᵢ|Δqᵢ| (ρ: the lever arms; 1 where None), ties in the moves'
    order. In arrays (the Panda's 376 targets in 0.16 ms; a loop over the moves took 1.06 ms, a search's
    cost the check's limits do not count): the keys' sums in the loop's order of additions, so the
    same floats and the same order."""
    n = robot.nv
    q = np.asarray(q, float)
    lo, hi = np.asarray(robot.q_min, float) + INSIDE, np.asarray(robot.q_max, float) - INSIDE
    weight = np.asarray(rho, float) if rho is not None else np.ones(n)
    if n not in _MOVES:
        _MOVES[n] = _moves(n)
    i, j, d = _MOVES[n]
    pair = i != j
    # the joints a move leaves are kept INSIDE the limits too: a rest at a limit leaves a walk
    # (qpctl.safety.walk) no room for its stray, and the whole steering is then stepped
    base = np.clip(q, lo, np.maximum(lo, hi))
    xi, xj = q[i] + d[:, 0], q[j] + d[:, 1]
    ok = (lo[i] <= xi) & (xi <= hi[i]) & (~pair | ((lo[j] <= xj) & (xj <= hi[j])))
    key = weight[i] * np.abs(d[:, 0]) + np.where(pair, weight[j] * np.abs(d[:, 1]), 0.0)
    taken = np.zeros(key.size)  # the joints taken inside and left by the move: Σρ|Δq| each, summed in order
    for t in np.flatnonzero(base != q):
        taken = taken + np.where((i != t) & (j != t), float(weight[t] * abs(base[t] - q[t])), 0.0)
    key = key + taken
    keep = np.flatnonzero(ok)
    order = keep[np.argsort(key[keep], kind="stable")]
    x = np.repeat(base[None, :], order.size, axis=0)
    rows = np.arange(order.size)
    x[rows, i[order]] = xi[order]
    x[rows, j[order]] = np.where(pair[order], xj[order], xi[order])
    return list(x)


def clear_targets(robot: Any, q: np.ndarray, rho: np.ndarray | None, clear: Callable[[np.ndarray], bool | None],
                  count: float = np.inf, ready: Callable[[], bool] | None = None) -> Iterator[np.ndarray | None]:
    """The first ``count`` of :func:`candidates` that the rest test ``clear`` accepts (the arm at rest
    there clear of the static obstacles and the sweeps), nearest first, each tested as it is asked for;
    none after ``clear`` answers None (its caller's work ran out). With ``ready``, a None is yielded
    before a rest test for as long as ``ready()`` is False (a pause: :func:`search_iter`)."""
    found = 0
    for x in candidates(robot, q, rho):
        if found >= count:
            return
        while ready is not None and not ready():
            yield None
        ok = clear(x)
        if ok is None:
            return
        if ok:
            found += 1
            yield x


def targets(robot: Any, q: np.ndarray, rho: np.ndarray | None, clear: Callable[[np.ndarray], bool | None],
            count: float = np.inf) -> list[np.ndarray]:
    """:func:`clear_targets` as a list."""
    return [x for x in clear_targets(robot, q, rho, clear, count) if x is not None]


def search_iter(run: Callable[[Retreat], Generator[None, None, Any]], robot: Any, q: np.ndarray, t: float, dt: float,
                rho: np.ndarray | None, clear: Callable[[np.ndarray], bool | None],
                ready: Callable[[], bool] | None = None, tries: int = TRIES) -> Generator[None, None, Any | None]:
    """:func:`search` as a generator: ``run(r)`` is itself a generator rollout (its pauses passed on), and
    the search pauses (yields) before each rest test while ``ready()`` is False — a search spread over the
    ticks (:class:`qpctl.safety.backup.BackupGuard`'s carried search). Its return value is :func:`search`'s."""
    for x in clear_targets(robot, q, rho, clear, tries, ready):
        if x is None:
            yield  # paused before a rest test
            continue
        for omega in OMEGAS:
            r = Retreat(tuple(float(a) for a in x), omega, switch_time(t, dt, omega))
            cert = yield from run(r)
            if cert is None:
                return None
            if cert.viable:
                return r, cert
    return None


def finish(gen: Generator[None, None, Any]) -> Any:
    """The return value of a generator run to its end (every pause passed over)."""
    while True:
        try:
            next(gen)
        except StopIteration as done:
            return done.value


def _at_once(value: Any) -> Generator[None, None, Any]:
    """A generator that returns ``value`` without pausing."""
    return value
    yield  # pragma: no cover (makes this a generator)


def search(run: Callable[[Retreat], Any], robot: Any, q: np.ndarray, t: float, dt: float, rho: np.ndarray | None,
           clear: Callable[[np.ndarray], bool | None], tries: int = TRIES) -> Any | None:
    """The first retreat from (q, t) that ``run`` (a rollout: Retreat → certificate with ``viable``, or
    None where the caller's steps ran out: the search ends there) verifies, as (retreat, certificate), or
    None: the first ``tries`` of :func:`clear_targets`, each at every ω of :data:`OMEGAS` — the rest
    test of each candidate taken as the search comes to it (``clear`` answering None ends the search), so
    a search its steps end costs only the tests before that. (:func:`search_iter` without pauses.)"""
    return finish(search_iter(lambda r: _at_once(run(r)), robot, q, t, dt, rho, clear, tries=tries))
