"""Where a stopped arm may rest: clear of the static obstacles by its creep, and of the swaying
obstacles' whole sweeps (issue 22, items 2 and 4).

An obstacle that sways without drifting — velocity 0, amplitude A ≠ 0 at frequency f > 0, so that
its centre is p₀ + A sin(2πft) — passes every point p₀ + sA, s ∈ [−1, 1], of its segment once a
period, for ever. A brake that brings the arm to rest within reach of that sweep has not avoided the
obstacle, only postponed it: the oracle's rollout ends 50 ms after rest, and the obstacle comes later
(four of the five contacts at rest of the soak's 60 scenes before this check). So a rollout that ends at rest
is verified only if the arm at rest clears every swaying obstacle at every s by more than the margin:
:class:`RestClearance` decides it. Obstacles that drift (velocity ≠ 0) go on for ever: with ``hold`` H > 0
(the guard's ``backup_hold``) the arm at rest from t must clear each over [t, t + H] (the same decision
over time, the clearance being Lipschitz in t with the obstacle's speed bound |v| + 2πf|A|), else they
are followed over the rollout only and an arm at rest in a drifting obstacle's path is struck later.
:func:`fixed_part` is where no rest can be: the part of space every configuration fills.

**The decision** (:meth:`RestClearance.clear`, :func:`above`): g(s), the world clearance between the arm at rest at q
and the obstacle at p₀ + sA (:class:`qpctl.tick.WorldClearance` at the time arcsin(s)/(2πf)), is
|A|-Lipschitz in s (the clearance is 1-Lipschitz in the obstacle's position). On an interval [a, b]
with g(a), g(b) known, g ≥ (g(a) + g(b))/2 − |A|(b − a)/2 (the two cones' meeting point); intervals
whose bound is above the margin are done, the others are halved. A sample at or below the margin
refutes; an interval narrower than ``TOLERANCE`` [m] (|A|(b − a)) whose bound is still below refutes
too (a refusal is always safe). So "clear" is proved, not sampled: the least clearance over the sweep
exceeds the margin.

**Creep.** At the oracle's rest the joints still move (|q̇ᵢ| ≤ 0.01 rad/s) and the brake goes on; the
rest is tested against the static obstacles and the sweeps with the margin raised by :func:`creep`,
Σᵢρᵢ|q̇ᵢ|/κ — what is left of the stop if it decays at κ (exactly so for the continuous, unsaturated
brake; an assumption for the simulator's steps, docs/reliability.md) — so that the arm still clears
them where the stop ends (the rollout watches the clearance only until the rest), and so that a
rollout started later on the same stop (the oracle's, from a visited state) comes to the same verdict.
Drifting obstacles are in the test only over the hold (above). The joint limits get the same test in joint space (:func:`stops_within`: each joint's end q + q̇/κ within
its limits; soak-panda-600 of the fresh set crept past one after its rest).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import pinocchio as pin

from qpctl.geometry.obstacles import Obstacle
from qpctl.kernels import rollout as K
from qpctl.tick import WorldClearance

REVOLUTE = ("JointModelRX", "JointModelRY", "JointModelRZ", "JointModelRevoluteUnaligned")


def lever_arms(robot: Any) -> np.ndarray | None:
    """ρᵢ [m] per degree of freedom: an upper bound, for every configuration, on the distance between
    joint i's origin and any capsule point of the links it moves (the joint placements' translation
    lengths from joint i to the capsule's joint, plus the farther capsule end); None unless every
    joint is a one-degree-of-freedom revolute one (then ρᵢ|θ̇ᵢ| bounds joint i's share of a point's speed)."""
    model = robot.model
    if model.nq != model.nv or any(model.joints[j].shortname() not in REVOLUTE for j in range(1, model.njoints)):
        return None
    rho = np.zeros(model.nv)
    for c in robot.capsules:
        reach = max(float(np.linalg.norm(c.p0)), float(np.linalg.norm(c.p1)))
        j = c.joint_id
        while j > 0:  # joint j's origin is within `reach` of the capsule; walk up the chain
            idx = model.joints[j].idx_v
            rho[idx] = max(rho[idx], reach)
            reach += float(np.linalg.norm(model.jointPlacements[j].translation))
            j = model.parents[j]
    return rho


def creep(rho: np.ndarray | None, v: np.ndarray, gain: float) -> float:
    """How far [m] a link point still moves after the oracle's rest at joint speeds q̇ [rad/s] if the
    brake of gain κ [1/s] goes on decaying as q̇e^{−κt}: Σᵢ ρᵢ|q̇ᵢ|/κ (ρ: :func:`lever_arms`;
    0 where it is None). Under that decay the bound at a later state is the bound now less the way
    travelled, so a rest cleared by its creep stays cleared from every later state of the same stop."""
    if rho is None:
        return 0.0
    return float(np.dot(rho, np.abs(v))) / gain


def stops_within(q: np.ndarray, v: np.ndarray, gain: float, q_min: np.ndarray, q_max: np.ndarray) -> bool:
    """True if the stop's end, q + q̇/κ (where each joint comes to rest if the brake of gain κ [1/s] goes
    on decaying as q̇e^{−κt}), lies within the joint limits [rad]: the joint-space form of :func:`creep`."""
    return bool(K.stops_within(np.asarray(q, float), np.asarray(v, float), float(gain), q_min, q_max))


#: The narrowest interval of the sweep [m of the obstacle's travel] the decision halves before refusing.
TOLERANCE = 1e-4


def swaying(o: Obstacle) -> bool:
    """True if the obstacle sways about a fixed centre (amplitude and frequency, no velocity)."""
    return bool(np.any(o.amplitude) and o.frequency > 0 and not np.any(o.velocity))


def above(at: Callable[[float], float], a: float, b: float, lipschitz: float, margin: float) -> bool:
    """True if g = ``at`` stays above ``margin`` over [a, b], proved with g's Lipschitz constant L (module
    docstring): g ≥ (g(a) + g(b))/2 − L(b − a)/2 on an interval; intervals above are done, the others
    halved; a sample at or below refutes, and so does an interval whose bound is still below once
    L(b − a) ≤ :data:`TOLERANCE`."""
    lo, hi = at(a), at(b)
    if min(lo, hi) <= margin:
        return False
    stack = [(a, lo, b, hi)]
    while stack:
        a, ga, b, gb = stack.pop()
        if 0.5 * (ga + gb) - 0.5 * lipschitz * (b - a) > margin:
            continue
        if lipschitz * (b - a) <= TOLERANCE:
            return False
        m = 0.5 * (a + b)
        gm = at(m)
        if gm <= margin:
            return False
        stack += [(a, ga, m, gm), (m, gm, b, gb)]
    return True


class RestClearance:
    """The rest test of a robot in a world (module docstring): each joint's stop within its limits, and
    the static obstacles and the swaying obstacles' whole sweeps cleared by the stop's creep; with
    ``hold`` [s] > 0 the drifting obstacles too, over the ``hold`` seconds after the rest."""

    def __init__(self, robot: Any, obstacles: Sequence[Obstacle], hold: float = 0.0) -> None:
        self.rho = lever_arms(robot)  # None: no creep bound (joints that are not revolute)
        self.q_min, self.q_max = robot.q_min, robot.q_max
        static = [o for o in obstacles if not o.moving]
        self.static = WorldClearance(robot, static) if static else None
        self.sweeps = [(WorldClearance(robot, [o]), float(np.linalg.norm(o.amplitude)), 2 * math.pi * o.frequency)
                       for o in obstacles if swaying(o)]
        self.hold = float(hold)
        self.drifts = [(WorldClearance(robot, [o]), o.speed_bound)
                       for o in obstacles if o.moving and not swaying(o)] if self.hold > 0 else []

    def __bool__(self) -> bool:
        return self.static is not None or bool(self.sweeps) or bool(self.drifts)

    def worlds(self) -> list[WorldClearance]:
        """Every world clearance the rest test evaluates (the static obstacles', each sweep's, each drift's)."""
        return ([self.static] if self.static is not None else []) + [w for w, _, _ in self.sweeps] + \
            [w for w, _ in self.drifts]

    def verifies(self, q: np.ndarray, v: np.ndarray, gain: float, margin: float, t: float = 0.0,
                 until: float | None = None) -> bool:
        """True if a brake of gain κ [1/s] at rest at (q [rad], q̇ [rad/s]) at t [s] may end there: on a
        robot of revolute joints each joint's stop within its limits (:func:`stops_within`), and the arm
        clear of the static obstacles, the sweeps and (``hold`` > 0) the drifting obstacles' next
        ``hold`` seconds (or until ``until`` [s]) by ``margin`` [m] plus its creep (:meth:`clear`)."""
        if self.rho is not None and not stops_within(q, v, gain, self.q_min, self.q_max):
            return False
        return not self or self.clear(q, margin + creep(self.rho, v, gain), t, until)

    def clear(self, q: np.ndarray, margin: float, t: float = 0.0, until: float | None = None) -> bool:
        """True if the arm at rest at q [rad] from t [s] on clears the static obstacles, every swaying
        obstacle's whole sweep and (``hold`` > 0) every drifting obstacle over [t, t + hold] (or [t,
        ``until``]) by more than ``margin`` [m] (the moving ones proved by the Lipschitz bound: :func:`above`)."""
        end = t + self.hold if until is None else until
        if self.static is not None and self.static(q, 0.0) <= margin:
            return False
        for world, amp, omega in self.sweeps:
            world.pose(q)  # the arm is still: its kinematics once, the obstacle at each s

            def at(s: float, world: WorldClearance = world, omega: float = omega) -> float:
                return world.at(math.asin(s) / omega)

            if not above(at, -1.0, 1.0, amp, margin):
                return False
        for world, speed in self.drifts:  # the clearance changes at most at the obstacle's speed bound
            world.pose(q)
            if not above(world.at, t, end, speed, margin):
                return False
        return True


def fixed_part(robot: Any) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """Part of the space the arm occupies in *every* configuration, as world-frame capsules (p0, p1 [m],
    radius [m]): the capsules on the fixed base, and for each capsule the first joint (revolute, on the
    base) moves, the ball that stays inside it whatever the joint's angle — centred on the joint's
    axis at the foot of the capsule's segment point nearest the axis, of radius r − that distance. An
    obstacle that reaches it strikes the arm whatever any controller does (issue 22 item 4: a contact
    certified unavoidable by any control)."""
    model = robot.model
    data = model.createData()
    q = pin.neutral(model)
    pin.computeJointJacobians(model, data, q)
    out: list[tuple[np.ndarray, np.ndarray, float]] = []
    for c in robot.capsules:
        if c.joint_id == 0:
            out.append((np.asarray(c.p0, float), np.asarray(c.p1, float), float(c.radius)))
    if model.njoints < 2 or model.parents[1] != 0 or model.joints[1].shortname() not in REVOLUTE:
        return out
    axis = pin.getJointJacobian(model, data, 1, pin.LOCAL)[3:, model.joints[1].idx_v]
    axis = axis / np.linalg.norm(axis)
    frame = data.oMi[1]
    for c in robot.capsules:
        if c.joint_id != 1:
            continue
        p0, p1 = np.asarray(c.p0, float), np.asarray(c.p1, float)
        off0, off1 = p0 - (p0 @ axis) * axis, p1 - (p1 @ axis) * axis  # the parts across the axis
        d = off1 - off0
        s = float(np.clip(-(off0 @ d) / (d @ d), 0.0, 1.0)) if d @ d > 0 else 0.0
        point = p0 + s * (p1 - p0)
        across = float(np.linalg.norm(off0 + s * d))
        if across < c.radius:
            foot = frame.act((point @ axis) * axis)
            out.append((foot, foot, float(c.radius) - across))
    return out
