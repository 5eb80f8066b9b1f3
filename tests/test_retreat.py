"""The evasive backup (qpctl.safety.retreat, issue 22 items 2 and 4): a start inside a swaying obstacle's
sweep, where every brake of the family stops the arm in the swing's way, is left by a retreat that the
guard's rollout and the oracle's verify.

References: the critically damped approach e(t) = e₀(1 + ωt)e^{−ωt} (the retreat's law, the drives
unlimited); python-fcl's distance from the links to the capsule a swaying sphere sweeps (where the
retreat's rest lies); the oracle's Simulator-based rollout (independent of the guard's lean one); the
arm held at its start, which the sphere strikes."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
from test_native_rollout import lib_or_skip

from qpctl import LawGains, Obstacle, Scenario, WaypointPath, panda, planar_arm
from qpctl.constraints.constraints import TorqueLimit
from qpctl.controllers.qp import QPConfig, QPController
from qpctl.errors import ConfigError
from qpctl.geometry.distance import DistanceEngine
from qpctl.safety import BackupGuard, certify, oracle, rollout
from qpctl.safety.backup import GuardedOutput
from qpctl.safety.oracle import BRAKE_GAINS, REST_SPEED
from qpctl.safety.retreat import (
    INSIDE,
    OMEGAS,
    RETRY_TICKS,
    SETTLE,
    Retreat,
    candidates,
    shown,
    switch_time,
    targets,
)
from qpctl.safety.rollout import BrakeRollout
from qpctl.safety.sweep import RestClearance, lever_arms
from qpctl.simulation import Simulator
from qpctl.simulation.metrics import compute_metrics, contact_onsets

DT = 2e-3
Q = np.array([np.pi, np.pi / 2, 0.0])  # the last link hangs along −y, its tip at (−1, −2)


def arm():
    return planar_arm(tau_max=1500.0).with_limits(tau_rate_max=3000.0)


def tip(robot, q):
    data = robot.model.createData()
    pin.forwardKinematics(robot.model, data, q)
    return data.oMi[3].act(robot.capsules[2].p1)


def swing(robot, overlap=0.03):
    """A sphere swinging (0.5 Hz, ±0.3 m along y) up to the tip of the arm at Q, its end overlapping the
    tip's capsule by ``overlap`` [m] at t = 0.5 s: the start lies inside its sweep."""
    r = 0.1
    end = tip(robot, Q)[:2] + np.array([0.0, -(robot.capsules[2].radius + r - overlap)])
    return Obstacle("sphere", end - [0.0, 0.3], radius=r, amplitude=[0.0, 0.3, 0.0], frequency=0.5)


class Hold:
    """A QP controller whose torque is replaced by gravity's, within the drives' torque and rate limits:
    a controller that proposes to hold the arm where it is, which the guard alone must keep out of the
    swing (every other attribute the QP controller's, so the simulator runs it as it runs that)."""

    def __init__(self, robot, obstacles):
        path = WaypointPath([[-1.0, -2.0], [1.0, -1.5]], duration=2.0)
        self.inner = QPController(robot, path, obstacles, LawGains(d_influence=0.3, d_safe=0.05), QPConfig())
        self.limit = next(c for c in self.inner.constraints if isinstance(c, TorqueLimit))
        self.data = robot.model.createData()

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def wanted(self, q, v):
        """The torque [N·m] this controller would apply before the drives' limits: gravity's."""
        return pin.computeGeneralizedGravity(self.robot.model, self.data, q)

    def step(self, q, v, t):
        out = self.inner.step(q, v, t)
        lo, hi = self.limit.window(t)
        tau = np.clip(self.wanted(q, v), lo, hi)
        self.limit.remember(tau, t)  # the guard remembers its brake's torque over this
        return GuardedOutput(out, tau, dict(out.info), float(out.compute_us))


def capsule_distance(robot, q, o, t):
    """python-fcl's distance [m] from the links at q to obstacle o at time t [s]."""
    data = robot.model.createData()
    pin.forwardKinematics(robot.model, data, q)
    seg = np.array([[data.oMi[c.joint_id].act(c.p0), data.oMi[c.joint_id].act(c.p1)] for c in robot.capsules])
    engine = DistanceEngine([c.radius for c in robot.capsules], [o], broadphase=False)
    engine.update(seg, t)
    return engine.min_distance()


def capsule_clearance(robot, q, o):
    """python-fcl's distance [m] from the links at q to the capsule a swaying sphere sweeps."""
    a = float(np.linalg.norm(o.amplitude))
    swept = Obstacle("capsule", o.position, radius=o.radius, length=2 * a, axis=np.asarray(o.amplitude) / a)
    data = robot.model.createData()
    pin.forwardKinematics(robot.model, data, q)
    seg = np.array([[data.oMi[c.joint_id].act(c.p0), data.oMi[c.joint_id].act(c.p1)] for c in robot.capsules])
    engine = DistanceEngine([c.radius for c in robot.capsules], [swept], broadphase=False)
    engine.update(seg, 0.0)
    return engine.min_distance()


def test_the_retreat_steers_as_a_critically_damped_approach():
    """Drives without limits, no obstacle: from rest at Q toward q* = Q + (0.2, −0.3, 0.4) at ω = 6 rad/s,
    the rollout at the switch time is where e(t) = e₀(1 + ωt)e^{−ωt} puts it, up to the torque held over
    each step (the error shrinks with the step: under 1e-4 rad at 0.2 ms, and ≥ 5× below 2 ms's); from
    the switch on it brakes (at rest within 1 s of it)."""
    robot = planar_arm(tau_max=1e9)
    ctrl = QPController(robot, WaypointPath([[-1.0, -2.0], [1.0, -1.5]], duration=2.0), [],
                        LawGains(d_influence=0.3, d_safe=0.05), QPConfig())
    e0, omega = np.array([0.2, -0.3, 0.4]), 6.0
    err = {}
    for dt in (DT, DT / 10):
        r = Retreat(tuple(Q + e0), omega, switch_time(0.0, dt, omega))
        assert (r.until / dt) % 1 == pytest.approx(0.5)  # between two ticks
        n = round(SETTLE / omega / dt)  # the last step that steers
        assert r.steering(n * dt) and not r.steering((n + 1) * dt)
        lean = BrakeRollout(robot, Simulator(ctrl, dt=dt, duration=dt).world, dt)
        q, v, tau = Q.copy(), np.zeros(3), np.full(3, np.nan)
        for k in range(n + 1):
            tau = lean.torque(q, v, tau, 25.0, r, k * dt).copy()
            lean.step(q, v)
        t = (n + 1) * dt
        err[dt] = float(np.max(np.abs(q - (Q + e0 - e0 * (1 + omega * t) * np.exp(-omega * t)))))
    assert err[DT / 10] < 1e-4 and err[DT / 10] < err[DT] / 5, err
    r = Retreat(tuple(Q + e0), omega, switch_time(0.0, DT, omega))
    cert = rollout(Simulator(ctrl, dt=DT, duration=DT), Q, np.zeros(3), np.full(3, np.nan), 0.0, 25.0, retreat=r)
    assert cert.viable and r.until < cert.t_rest < r.until + 1.0


def test_targets_are_the_nearest_rests_clear_of_the_sweeps():
    """The search's targets: one or two joints moved, nearest first by Σρ|Δq|, each one python-fcl puts
    clear of the sphere's swept capsule; the start itself is not clear."""
    robot = arm()
    o = swing(robot)
    rest = RestClearance(robot, [o])
    rho = lever_arms(robot)
    assert capsule_clearance(robot, Q, o) < 0 and not rest.clear(Q, 0.0)
    found = targets(robot, Q, rho, lambda x: rest.clear(x, 0.0))
    assert len(found) >= 3
    moved = [float(rho @ np.abs(x - Q)) for x in found]
    assert np.all(np.diff(moved) >= -1e-12), moved
    assert {np.count_nonzero(x - Q) for x in found} == {1, 2}
    for x in found:
        assert capsule_clearance(robot, x, o) > 0


def test_targets_keep_every_joint_inside_the_limits():
    """The Panda with joints at (or past) their limits: every target lies INSIDE within every limit —
    the joints the move leaves alone taken inside, not kept where they are — and differs from the
    start taken inside in the move's one or two joints only."""
    robot = panda()
    lo, hi = robot.q_min + INSIDE, robot.q_max - INSIDE
    home = robot.q_home.copy()
    starts = [home.copy() for _ in range(3)]
    starts[0][1] = robot.q_min[1]  # joint 2 at its lower limit
    starts[1][3], starts[1][5] = robot.q_max[3] - 0.01, robot.q_min[5] - 1e-3  # one within INSIDE, one past
    starts[2][6] = robot.q_max[6]
    for q in starts:
        near = (q < lo) | (q > hi)
        assert near.any()
        found = candidates(robot, q, lever_arms(robot))
        assert len(found) > 50
        for x in found:
            assert np.all(x >= lo - 1e-12) and np.all(x <= hi + 1e-12), (q, x)
            assert 1 <= np.count_nonzero(np.abs(x - np.clip(q, lo, hi)) > 1e-12) <= 2  # the move's joints only


def looped_candidates(robot, q, rho):
    """The search's targets by a loop over the moves, one dict each (the module docstring's recipe
    written out; what ``candidates`` was before it took arrays): the reference for the arrays."""
    lo, hi = np.asarray(robot.q_min, float) + INSIDE, np.asarray(robot.q_max, float) - INSIDE
    weight = rho if rho is not None else np.ones(robot.nv)
    moves = [{i: sign * step} for i in range(robot.nv) for step in (0.3, 0.6, 1.2) for sign in (1.0, -1.0)]
    moves += [{i: si * a, j: sj * b} for i in range(robot.nv) for j in range(i + 1, robot.nv)
              for a in (0.3, 0.6) for b in (0.3, 0.6) for si in (1.0, -1.0) for sj in (1.0, -1.0)]
    base = np.clip(np.asarray(q, float), lo, np.maximum(lo, hi))
    taken = {int(i): float(weight[i] * abs(base[i] - q[i])) for i in np.flatnonzero(base != q)}
    found = []
    for move in moves:
        x = base.copy()
        for i, d in move.items():
            x[i] = q[i] + d
        if all(lo[i] <= x[i] <= hi[i] for i in move):
            key = sum(weight[i] * abs(d) for i, d in move.items()) + sum(w for i, w in taken.items() if i not in move)
            found.append((float(key), len(found), x))
    found.sort(key=lambda f: (f[0], f[1]))
    return [x for _, _, x in found]


def test_the_targets_are_the_looped_recipes_bit_for_bit():
    """``candidates`` (arrays) gives the targets of the recipe looped move by move, in the same order,
    bit for bit: the Panda at random states — some joints at, near or past a limit (taken inside), some
    moves out of the limits — and the planar arm (no limits: every move, ties in the moves' order)."""
    rng = np.random.default_rng(57)
    robot = panda()
    for k in range(40):
        q = rng.uniform(robot.q_min, robot.q_max)
        near = rng.choice(robot.nv, size=k % 4, replace=False)
        q[near] = np.where(rng.random(near.size) < 0.5, robot.q_min[near], robot.q_max[near]) + \
            rng.uniform(-0.06, 0.06, near.size)
        for rho in (lever_arms(robot), None):
            got, want = candidates(robot, q, rho), looped_candidates(robot, q, rho)
            assert len(got) == len(want) > 0
            assert all(np.array_equal(a, b) for a, b in zip(got, want, strict=True)), k
    flat = arm()
    q = Q + rng.normal(0.0, 0.3, 3)
    got, want = candidates(flat, q, lever_arms(flat)), looped_candidates(flat, q, lever_arms(flat))
    assert len(got) == 3 * 6 + 3 * 16 and all(np.array_equal(a, b) for a, b in zip(got, want, strict=True))


@pytest.mark.parametrize("retreats", [True, False])
def test_a_start_inside_a_sweep_is_left_by_a_verified_retreat(retreats):
    """The arm at rest at Q, the sphere's swing reaching it at 0.36 s (held there, it is struck): no
    brake of the family is certified from the start (the oracle), so the guard searches a retreat; the
    one it stores is certified by the oracle's own rollout, every tick is verified, and the arm held by
    a controller that proposes to stay is never struck. Without retreats (``retreats=False``) the same
    run's ticks are unverified and the sphere strikes the held arm."""
    robot = arm()
    o = swing(robot)
    hold = Hold(robot, [o])
    held = Simulator(hold, dt=DT, duration=2.0).run(Q)
    assert held.clearance.min() < 0 and 0.3 < held.t[contact_onsets(held.clearance)[0]] < 0.45
    gravity = hold.step(Q, np.zeros(3), 0.0).tau
    assert not certify(hold, Q, np.zeros(3), np.full(3, np.nan), 0.0, DT).viable
    guard = BackupGuard(hold, DT, retreats=retreats, retreat_proposals=False)  # step 3's search (the next test: step 1's)
    guard.warmup()
    tr = Simulator(guard, dt=DT, duration=2.0).run(Q)
    m = compute_metrics(tr)
    if not retreats:
        assert m["backup_unverified_ticks"] > 0 and m["collided"]
        return
    assert m["backup_unverified_ticks"] == 0 and not m["collided"] and guard.stats["retreats_found"] >= 1
    [(r, gain)] = shown(tr.infos[0])
    assert r.omega in OMEGAS and capsule_clearance(robot, r.q, o) > 0
    assert certify(hold, Q, np.zeros(3), gravity * np.nan, 0.0, DT, retreats=[(r, gain)]).viable
    # every 10th visited state certified by the oracle, shown the retreat the guard held (if any)
    for k in range(10, len(tr.t), 10):
        assert certify(hold, tr.q[k], tr.v[k], tr.tau[k - 1], float(tr.t[k]), DT,
                       retreats=shown(tr.infos[k - 1])).viable, tr.t[k]


def test_a_hopeless_start_is_searched_every_tenth_tick():
    """A sphere swaying across the planar arm's base (the part every configuration fills): no rest
    clears its sweep, so no retreat is found; over 0.2 s the guard searches on ticks 0, 10, 20, …
    (RETRY_TICKS apart) and counts every tick unverified."""
    robot = arm()
    o = Obstacle("sphere", [0.0, 0.6], radius=0.1, amplitude=[0.0, 0.55, 0.0], frequency=0.1)
    hold = Hold(robot, [o])
    guard = BackupGuard(hold, DT)
    guard.warmup()
    tr = Simulator(guard, dt=DT, duration=0.2).run(Q)
    m = compute_metrics(tr)
    n = m["ticks"]
    assert n >= 100 and m["backup_unverified_ticks"] == n
    assert guard.stats["retreat_searches"] == -(-n // RETRY_TICKS) and guard.stats["retreats_found"] == 0


def test_native_and_python_loops_agree_on_a_retreat():
    """The same retreats rolled out by the native loop and the Python loop: the same certificates —
    four targets of the search, and the start itself (the arm still while it steers: its rest comes only
    once it brakes, in both)."""
    robot = arm()
    o = swing(robot)
    hold = Hold(robot, [o])
    sim = Simulator(hold, dt=DT, duration=DT)
    lib_or_skip()
    fast, slow = BrakeRollout(robot, sim.world, DT), BrakeRollout(robot, sim.world, DT)
    assert fast.native is not None
    slow.native = None
    for x in [Q, *targets(robot, Q, lever_arms(robot), lambda x: True)[:4]]:
        for omega in OMEGAS:
            r = Retreat(tuple(x), omega, switch_time(0.1, DT, omega))
            for exact in (True, False):
                a = fast.run(Q, np.zeros(3), np.full(3, np.nan), 0.1, 25.0, retreat=r, exact=exact, stop_below=0.0)
                b = slow.run(Q, np.zeros(3), np.full(3, np.nan), 0.1, 25.0, retreat=r, exact=exact, stop_below=0.0)
                assert a == b
                if x is Q:
                    assert a.t_rest > r.until - 0.1  # at rest only after the switch


def test_backup_retreats_and_hold_are_scenario_keys():
    on = ["controller.backup=true"]
    assert Scenario.load("paper", overrides=on).build_controller().retreats
    assert not Scenario.load("paper", overrides=[*on, "controller.backup_retreats=false"]).build_controller().retreats
    with pytest.raises(ConfigError) as exc:
        Scenario.load("paper", overrides=[*on, "controller.backup_retreats=3"])
    assert exc.value.key == "controller.backup_retreats"
    assert Scenario.load("paper", overrides=on).build_controller().hold == 2.0
    assert Scenario.load("paper", overrides=[*on, "controller.backup_hold=2.5"]).build_controller().hold == 2.5
    with pytest.raises(ConfigError) as exc:
        Scenario.load("paper", overrides=[*on, "controller.backup_hold=-1"])
    assert exc.value.key == "controller.backup_hold"


def closing_sphere(robot, speed=0.2, gap=0.5):
    """A sphere beside the tip of the arm at Q, ``gap`` [m] from its capsule across the link, drifting
    straight at it at ``speed`` [m/s] (along the line of nearest points: the clearance is gap − speed·t)."""
    cap = robot.capsules[2]
    centre = tip(robot, Q)[:2] + [-(cap.radius + 0.1 + gap), 0.0]
    return Obstacle("sphere", centre.tolist(), radius=0.1, velocity=[speed, 0.0])


def test_a_rest_must_clear_a_drifting_obstacle_for_its_hold():
    """The rest test with hold H against a sphere closing at 0.2 m/s from 0.5 m (it arrives at 2.5 s): the
    arm resting from t is clear while t + H ends 5 mm or more before the arrival and not once it ends
    after it (the clearance gap − 0.2·t by python-fcl); with H = 0 the drifting sphere is not tested."""
    robot = arm()
    o = closing_sphere(robot)
    assert capsule_distance(robot, Q, o, 0.0) == pytest.approx(0.5, abs=1e-6)
    assert capsule_distance(robot, Q, o, 2.4) == pytest.approx(0.02, abs=1e-6)
    for hold in (0.5, 1.5):
        rest = RestClearance(robot, [o], hold)
        for t in np.arange(0.0, 2.5, 0.05):
            end = 0.5 - 0.2 * (t + hold)
            if end >= 5e-3:
                assert rest.clear(Q, 0.0, t), (hold, t)
            elif end < 0:
                assert not rest.clear(Q, 0.0, t), (hold, t)
    assert RestClearance(robot, [o], 0.0).clear(Q, 0.0, 2.4) and not RestClearance(robot, [o], 0.0)


def test_check_steps_bound_a_stops_re_verification_at_rest():
    """At rest at t = 0.6 s with a stop stored and a sphere drifting at the arm, whose rest there it
    reaches within the hold (0.5 − 0.2·(0.6 + 2) < 0): the proposal (gravity's hold) is refused (no
    retreat searched from its successor here), step 4
    refutes the stop and step 3 searches a retreat — hundreds of steps. Within one step the check
    spends at most that step: the re-verification and step 3 cut short, the stop is kept as lapsed
    and the stored brake continues."""
    robot = arm()
    guard = BackupGuard(Hold(robot, [closing_sphere(robot)]), DT, retreat_proposals=False)
    guard.warmup()
    data = robot.model.createData()
    gravity = pin.computeGeneralizedGravity(robot.model, data, Q)
    for steps in (np.inf, 1):
        guard._reset_backup()
        guard._gain, guard._tau_prev, guard.check_steps = 25.0, gravity.copy(), steps
        info: dict = {}
        guard.check(Q, np.zeros(3), gravity, 0.6, info)
        spent = guard.stats["check_steps"][-1]
        assert info["backup_rest_refuted"]
        if steps == np.inf:
            assert spent > 100 and "backup_out_of_steps" not in info
        else:
            assert spent <= 1 and info["backup_out_of_steps"] and info["backup_rest_refuted"]
            assert info["backup_hold_lapsed"] and info["backup"] == 25.0 and guard._gain == 25.0


def test_check_evaluations_bound_the_whole_check(monkeypatch):
    """``check_evaluations``: the world-clearance evaluations one check may spend, its rollouts' and its
    rest tests' together. The state of the test above (at rest, the stored stop refuted by the drifting
    sphere's hold, a retreat searched): every evaluation of the check, counted at
    :meth:`WorldClearance.at` itself, is the meter's — the rest tests' worlds carry it too —, N of them
    with no limit, most of them rest tests. N allowed: the same retreat stored. N − 1 and 5: the
    evaluation past them ends the search, at most that many are made, the tick says so and the stop is
    kept as lapsed."""
    from qpctl.tick import WorldClearance

    made = []
    evaluate = WorldClearance.at

    def counted(self, t):
        d = evaluate(self, t)
        made.append(self)  # an evaluation made (not the one the meter refuses)
        return d

    monkeypatch.setattr(WorldClearance, "at", counted)
    robot = arm()
    # the search within the tick (carry=False: under a limit it is otherwise carried over the ticks)
    guard = BackupGuard(Hold(robot, [closing_sphere(robot)]), DT, retreat_proposals=False, carry=False)
    guard.warmup()
    gravity = pin.computeGeneralizedGravity(robot.model, robot.model.createData(), Q)
    kept, spent = None, {}
    for limit in (np.inf, "N", "N-1", 5):
        budget = {"N": spent.get(np.inf, 0), "N-1": spent.get(np.inf, 0) - 1}.get(limit, limit)
        guard._reset_backup()
        guard._gain, guard._tau_prev, guard.check_evaluations = 25.0, gravity.copy(), budget
        info: dict = {}
        made.clear()
        guard.check(Q, np.zeros(3), gravity, 0.6, info)
        spent[limit] = len(made)
        assert guard.stats["check_evaluations"][-1] == len(made) <= budget
        assert info["backup_rest_refuted"]
        if limit in (np.inf, "N"):
            assert guard._retreat is not None and "backup_out_of_steps" not in info
            assert sum(w is not guard.world for w in made) > len(made) // 2  # mostly the rest tests'
            kept = kept or (guard._gain, guard._retreat)
            assert (guard._gain, guard._retreat) == kept and len(made) == spent[np.inf] > 50
        else:
            assert info["backup_out_of_steps"] and info["backup_hold_lapsed"]
            assert guard._gain == 25.0 and guard._retreat is None
    assert guard.meter.limit == np.inf  # the screen's evaluations outside a check are not limited


@pytest.mark.parametrize("hold", [0.0, 2.0])
def test_a_drifting_obstacle_is_left_when_the_rest_must_clear_it_for_a_hold(hold):
    """The sphere closing on the tip of the arm held by a controller that proposes to stay: without a
    hold the guard lets it rest and the sphere strikes the arm at rest (2.5 s); with a 2 s hold, re-verified
    every tick the arm rests, the rest stops being verified as the sphere comes within 2 s, a retreat takes
    the arm out of its way, nothing touches and every 10th state is certified by the oracle (its hold one
    tick shorter)."""
    robot = arm()
    o = closing_sphere(robot)
    hold_ctrl = Hold(robot, [o])
    # the re-verification at rest (with step 1's search a retreat from a proposal's successor comes first)
    guard = BackupGuard(hold_ctrl, DT, hold=hold, retreat_proposals=False)
    guard.warmup()
    tr = Simulator(guard, dt=DT, duration=3.0).run(Q)
    m = compute_metrics(tr)
    assert m["backup_unverified_ticks"] == 0
    if hold == 0.0:
        assert m["collided"] and m["collisions_at_rest"] == 1
        return
    assert not m["collided"] and m["backup_retreat_ticks"] > 0
    assert any(i.get("backup_rest_refuted") for i in tr.infos)
    for k in range(10, len(tr.t), 10):
        assert certify(hold_ctrl, tr.q[k], tr.v[k], tr.tau[k - 1], float(tr.t[k]), DT,
                       retreats=shown(tr.infos[k - 1]), hold=hold - DT).viable, tr.t[k]


def test_under_a_limit_the_states_search_is_carried_over_the_ticks():
    """The start inside the swing's sweep (the test above: the sphere strikes the held arm at 0.36 s), the
    check limited to 60 steps and 30 evaluations a tick. Searched within each tick (``carry=False``) the
    retreat search never ends: every tick unverified, the arm struck. Carried (the default under a
    limit): the arm follows its stop for CARRY_TICKS ticks to the anchor while the search runs on what the
    ticks leave, the retreat found is stored at exactly that tick — the oracle's Simulator-based rollout
    verifies it from that state —, no tick after it is unverified, nothing touches, and no tick spends
    more than its steps, nor more evaluations than its limit and one rest test (the carried search takes
    a rest test whole once it has begun it: counted here at the rest test itself)."""
    from qpctl.safety.backup import CARRY_TICKS

    robot = arm()
    o = swing(robot)
    hold = Hold(robot, [o])
    runs, rest_tests = {}, [0]
    clear = RestClearance.clear

    def counted(self, *args, **kw):  # the most evaluations one rest test made
        meter = self.worlds()[0].meter
        before = meter.used
        out = clear(self, *args, **kw)
        rest_tests[0] = max(rest_tests[0], meter.used - before)
        return out

    for carry in (False, True):
        guard = BackupGuard(hold, DT, retreat_proposals=False, check_steps=60, check_evaluations=30, carry=carry)
        guard.warmup()
        RestClearance.clear = counted
        try:
            tr = Simulator(guard, dt=DT, duration=1.0).run(Q)
        finally:
            RestClearance.clear = clear
        runs[carry] = guard, tr, compute_metrics(tr)
        assert max(guard.stats["check_steps"]) <= 60
        assert max(guard.stats["check_evaluations"]) <= 30 + (rest_tests[0] if carry else 0)
    _, _, m = runs[False]
    assert m["collided"] and m["backup_unverified_ticks"] > 400
    guard, tr, m = runs[True]
    assert not m["collided"] and guard.stats["carried_adopted"] == 1
    [k] = [k for k, i in enumerate(tr.infos) if i.get("backup_carried_adopted")]
    unverified = [j for j, i in enumerate(tr.infos) if i.get("backup_unverified")]
    assert k == CARRY_TICKS and unverified == list(range(CARRY_TICKS))  # on its stop to the anchor, then verified
    assert all(i.get("backup_carried") for i in tr.infos[:k])
    assert m["backup_carried_ticks"] == CARRY_TICKS and m["backup_carried_adopted"] == 1
    r, gain = shown(tr.infos[k])[0]
    assert certify(hold, tr.q[k], tr.v[k], tr.tau[k - 1], float(tr.t[k]), DT, gains=(), retreats=[(r, gain)]).viable


def test_where_no_retreat_escapes_a_drifting_obstacle_the_arm_keeps_its_stop():
    """A sphere drifting at the planar arm's base at 0.2 m/s (it reaches the ball every configuration fills
    at about 3.3 s): with a 2 s hold the resting arm's stop is refuted from about 1.3 s on and no retreat
    clears the sphere's path, so the guard keeps the arm on its stop — verified as it is without a hold —
    and says so (``backup_hold_lapsed``) rather than applying the proposal unverified."""
    robot = arm()
    o = Obstacle("sphere", [0.0, 0.8], radius=0.1, velocity=[0.0, -0.2])
    hold_ctrl = Hold(robot, [o])
    guard = BackupGuard(hold_ctrl, DT, hold=2.0)
    guard.warmup()
    tr = Simulator(guard, dt=DT, duration=1.6).run(Q)
    m = compute_metrics(tr)
    assert m["backup_unverified_ticks"] == 0 and not m["collided"]
    lapsed = [t for t, i in zip(tr.t, tr.infos, strict=False) if i.get("backup_hold_lapsed")]
    assert m["backup_hold_lapsed_ticks"] == len(lapsed) > 0 and 1.0 < lapsed[0] < 1.5
    assert guard.stats["retreat_searches"] > 0 and guard.stats["retreats_found"] == 0


class Push(Hold):
    """A controller that proposes to drive the arm toward ``target`` (a critically damped approach at
    ``stiffness`` [1/s²], within the drives' torque and rate limits): its way runs through the swing."""

    def __init__(self, robot, obstacles, target, stiffness):
        super().__init__(robot, obstacles)
        self.target, self.stiffness = np.asarray(target, float), float(stiffness)

    def wanted(self, q, v):
        a = self.stiffness * (self.target - q) - 2.0 * np.sqrt(self.stiffness) * v
        return pin.rnea(self.robot.model, self.data, q, v, a)


@pytest.mark.parametrize("unverified", ["stop", "proposal"])
def test_where_nothing_verifies_every_contact_begins_at_rest(unverified):
    """A sphere swaying down onto the planar arm's base (no rest clears its sweep: no tick verifies, no
    retreat exists) and a controller that drives the first link up into its way. With the guard's
    default (``unverified = "stop"``) the proposal is applied only while a brake from its successor
    still comes to rest before a contact; every visited state before the contact is at rest or has
    such a brake by the oracle's own Simulator-based rollout, and the sphere reaches the arm at rest.
    Applying the proposal all the same (``"proposal"``, the guard before) the first link runs into the
    sphere at over 0.5 rad/s, from states no brake stops in time."""
    robot = arm()
    o = Obstacle("sphere", [0.0, 0.6], radius=0.1, amplitude=[0.0, -0.55, 0.0], frequency=0.1)
    ctrl = Push(robot, [o], [np.pi / 2, np.pi / 2, 0.0], stiffness=2.0)
    guard = BackupGuard(ctrl, DT, unverified=unverified)
    guard.warmup()
    tr = Simulator(guard, dt=DT, duration=2.0).run(Q)
    m = compute_metrics(tr)
    onsets = contact_onsets(tr.clearance)
    assert m["backup_unverified_ticks"] == m["ticks"] and guard.stats["retreats_found"] == 0
    assert onsets.size >= 1
    sim = Simulator(ctrl, dt=DT, duration=DT)

    def stops(k):  # at rest, or a brake of the family comes to rest before any contact (the oracle's rollout)
        if np.all(np.abs(tr.v[k]) <= REST_SPEED):
            return True
        return any(np.isfinite(c.t_rest) and c.min_clearance > 0.0
                   for c in (rollout(sim, tr.q[k], tr.v[k], tr.tau[k - 1], float(tr.t[k]), g, stop_below=0.0)
                             for g in BRAKE_GAINS))

    states = range(5, onsets[0] + 1, 5)
    if unverified == "proposal":
        assert m["backup_stop_ticks"] == 0 and m["collisions_at_rest"] == 0
        assert np.abs(tr.v[onsets[0]]).max() > 0.5
        assert not all(stops(k) for k in states)
        return
    moved = [k for k, i in enumerate(tr.infos) if "backup_stop" not in i]
    assert m["backup_stop_ticks"] > 0 and len(moved) > 200  # the proposal applied for a while, then the stop
    assert m["collisions_at_rest"] == onsets.size
    assert all(stops(k) for k in states)

    # the stop the arm keeps is the one it is on, not a default brake: at the first tick on the stop, with a
    # remembered stop of another gain, the guard applies that brake's torque (the oracle's own brake_torque)
    k = next(k for k, i in enumerate(tr.infos) if "backup_stop" in i)
    data = robot.model.createData()
    for gain in (60.0, 10.0):
        guard._gain, guard._stop, guard._tau_prev = None, (gain, None), tr.tau[k - 1]
        guard._wait = {"state": 10**6, "proposal": 10**6}  # no retreat search
        proposal = ctrl.step(tr.q[k], tr.v[k], float(tr.t[k])).tau
        info: dict = {}
        tau = guard.check(tr.q[k], tr.v[k], proposal, float(tr.t[k]), info)
        assert info["backup_stop"] == gain
        expected = oracle.brake_torque(robot, data, tr.q[k], tr.v[k], tr.tau[k - 1], gain, DT)
        np.testing.assert_allclose(tau, expected, rtol=0, atol=1e-9)
        assert np.abs(tau - proposal).max() > 1.0


@pytest.mark.parametrize("retreat_proposals", [True, False])
def test_a_proposal_into_a_sweep_is_let_in_with_a_verified_retreat(retreat_proposals):
    """A controller driving the arm from outside the swinging sphere's sweep to Q, inside it: once its
    stops end in the sweep the rest test refuses them. With ``retreat_proposals`` the guard
    searches a retreat from such a successor; the one it finds lets the proposal in (that tick applies the
    controller's own torque), the oracle's Simulator rollout certifies the successor with it and every
    10th visited state, no tick is unverified, no contact, and the guard brakes on a tenth of the ticks
    it brakes on without the search (where it holds the arm out of the sweep's rests)."""
    robot = arm()
    o = swing(robot)
    start = Q + np.array([0.0, 0.0, 0.6])
    rest = RestClearance(robot, [o])
    assert rest.clear(start, 0.0) and not rest.clear(Q, 0.0)
    ctrl = Push(robot, [o], Q, stiffness=4.0)
    guard = BackupGuard(ctrl, DT, retreat_proposals=retreat_proposals)
    guard.warmup()
    tr = Simulator(guard, dt=DT, duration=3.0).run(start)
    m = compute_metrics(tr)
    assert m["backup_unverified_ticks"] == 0 and not m["collided"]
    if not retreat_proposals:
        assert guard.stats["proposal_searches"] == 0 and m["backup_ticks"] > 200
        return
    assert guard.stats["proposal_retreats_found"] >= 1 and m["backup_ticks"] < 60
    # the first tick whose successor a retreat from the search let in: the controller's torque applied
    k = next(k for k, i in enumerate(tr.infos) if "backup_retreat" in i and "backup" not in i)
    [(r, gain)] = shown(tr.infos[k])
    assert capsule_clearance(robot, r.q, o) > 0
    successor = (ctrl, tr.q[k + 1], tr.v[k + 1], tr.tau[k], float(tr.t[k + 1]), DT)
    assert not certify(*successor).viable  # no brake of the family: each stop ends in the sweep
    assert certify(*successor, gains=(), retreats=[(r, gain)]).viable
    for j in range(10, len(tr.t), 10):
        assert certify(ctrl, tr.q[j], tr.v[j], tr.tau[j - 1], float(tr.t[j]), DT,
                       retreats=shown(tr.infos[j - 1])).viable, tr.t[j]


def test_the_search_from_a_proposals_successor_keeps_to_the_checks_steps():
    """``check_steps`` bounds the retreat search from a proposal's successor too: from the successor the
    search let in above (S steps spent finding its retreat), a budget of S + 1 + the rest tests (each
    counted as a step; fewer than the 400 allowed here) finds the same retreat in S steps (the verdict
    is taken at the step after the last one integrated, as a proposal's rollouts'), S − 1 finds none and
    spends at most S − 1, and so does a budget of a tenth; S + 1 alone, the rest tests counted in it,
    finds none."""
    robot = arm()
    o = swing(robot)
    ctrl = Push(robot, [o], Q, stiffness=4.0)
    guard = BackupGuard(ctrl, DT)
    guard.warmup()
    tr = Simulator(guard, dt=DT, duration=3.0).run(Q + np.array([0.0, 0.0, 0.6]))
    k = next(k for k, i in enumerate(tr.infos) if "backup_retreat" in i and "backup" not in i)
    successor = (tr.q[k + 1], tr.v[k + 1], tr.tau[k], float(tr.t[k + 1]))
    found, spent, short = guard._retreat_from(*successor)
    assert found is not None and spent > 10 and not short
    assert len(candidates(robot, successor[0], lever_arms(robot))) < 400
    again, cost, short = guard._retreat_from(*successor, steps=spent + 1 + 400)
    assert again == found and cost == spent and not short
    none, _, short = guard._retreat_from(*successor, steps=spent + 1)
    assert none is None and short  # its rest tests counted too; the check is told its steps ran out
    for budget in (spent - 1, spent // 10):
        none, cost, short = guard._retreat_from(*successor, steps=budget)
        assert none is None and cost <= budget and short


def test_backup_unverified_is_a_scenario_key():
    on = ["controller.backup=true"]
    assert Scenario.load("paper", overrides=on).build_controller().unverified == "stop"
    guard = Scenario.load("paper", overrides=[*on, "controller.backup_unverified=proposal"]).build_controller()
    assert guard.unverified == "proposal"
    with pytest.raises(ConfigError) as exc:
        Scenario.load("paper", overrides=[*on, "controller.backup_unverified=brake"])
    assert exc.value.key == "controller.backup_unverified"
    with pytest.raises(ValueError):
        BackupGuard(guard.controller, DT, unverified="brake")
    assert guard.retreat_proposals
    off = [*on, "controller.backup_retreat_proposals=false"]
    assert not Scenario.load("paper", overrides=off).build_controller().retreat_proposals
    assert guard.settle and not Scenario.load("paper", overrides=[*on, "controller.backup_settle=false"]
                                              ).build_controller().settle
    with pytest.raises(ConfigError) as exc:
        Scenario.load("paper", overrides=[*on, "controller.backup_settle=3"])
    assert exc.value.key == "controller.backup_settle"
