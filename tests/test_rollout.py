"""The lean brake rollout (qpctl.safety.rollout) against the Simulator-based oracle
(qpctl.safety.oracle.rollout, the independent reference: the built-in simulator's own step, with
the brake torque computed by oracle.brake_torque): the same states to 1e-12 step by step, the same
least clearance to 1e-9 m, time to rest and verdict — with the rate window binding, on contact, at a
joint limit, on the Panda and with a moving obstacle."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from qpctl import LawGains, Obstacle, WaypointPath, panda, planar_arm
from qpctl.controllers.qp import QPConfig, QPController
from qpctl.safety.oracle import brake_torque, rollout
from qpctl.safety.rollout import BrakeRollout
from qpctl.simulation import Simulator

DT = 2e-3


def planar_case(rate: float = 3000.0, obstacles: list[Obstacle] | None = None):
    robot = planar_arm(tau_max=1500.0).with_limits(tau_rate_max=rate)
    path = WaypointPath([[-1.0, -2.0], [1.0, -1.5]], duration=2.0)
    obstacles = obstacles if obstacles is not None else [
        Obstacle("box", [-0.4, -1.3], size=[0.2, 0.2, 0.2]), Obstacle("sphere", [1.2, 0.9], radius=0.15)]
    ctrl = QPController(robot, path, obstacles, LawGains(d_influence=0.3, d_safe=0.05), QPConfig())
    q, v = np.array([np.pi, np.pi / 2, 0.0]), np.array([2.5, -1.5, 3.0])
    return ctrl, q, v


def panda_case():
    robot = panda()
    data = robot.model.createData()
    pin.framesForwardKinematics(robot.model, data, robot.q_home)
    x = data.oMf[robot.ee_frame_id].translation.copy()
    path = WaypointPath([x.tolist(), (x + 0.1).tolist()], duration=2.0)
    obstacles = [Obstacle("sphere", (x + [0.25, 0.0, 0.0]).tolist(), radius=0.05),
                 Obstacle("cylinder", (x + [0.0, 0.3, -0.2]).tolist(), radius=0.04, length=0.4, axis=[0, 0, 1])]
    ctrl = QPController(robot, path, obstacles, LawGains(d_influence=0.3, d_safe=0.03), QPConfig())
    return ctrl, robot.q_home.copy(), np.linspace(-0.8, 0.8, 7)


def gravity(robot, q):
    return pin.computeGeneralizedGravity(robot.model, robot.model.createData(), q)


@pytest.mark.parametrize("case", ["planar", "panda"])
def test_lean_states_equal_the_simulators(case):
    """Step by step for 300 steps of the brake (κ = 25, the rate window binding on the first steps):
    the lean torque and step against oracle.brake_torque applied through Simulator.step."""
    ctrl, q, v = planar_case() if case == "planar" else panda_case()
    robot = ctrl.robot
    sim = Simulator(ctrl, dt=DT, duration=DT)
    lean = BrakeRollout(robot, sim.world, DT)
    data = robot.model.createData()
    sim.reset(q, v)
    tau_ref = gravity(robot, q)
    prev = tau_ref.copy()
    qq, vv = q.copy(), v.copy()
    clipped = 0
    for k in range(300):
        qs, vs = sim.read()
        free = pin.rnea(robot.model, data, qs, vs, -25.0 * vs)
        tau_ref = brake_torque(robot, data, qs, vs, tau_ref, 25.0, DT)
        clipped += not np.allclose(free, tau_ref)
        tau = lean.torque(qq, vv, prev, 25.0).copy()
        assert np.allclose(tau, tau_ref, rtol=0, atol=1e-12)
        prev = tau
        sim.apply(tau_ref)
        sim.step(k * DT)
        lean.step(qq, vv)
        qs, vs = sim.read()
        assert np.allclose(qq, qs, rtol=0, atol=1e-12) and np.allclose(vv, vs, rtol=0, atol=1e-12), k
    assert clipped > 5  # the window and the torque limit were exercised, not only the free brake


@pytest.mark.parametrize("case", ["planar", "panda"])
def test_fused_stages_equal_the_step_by_operation_bit_for_bit(case):
    """The RK4 stages in two kernel calls (``fused``, the default) against one call per operation (the
    path robots with continuous joints take): the same states bit for bit over 200 brake steps, and
    the step's travel Σᵢρᵢ|Δqᵢ| equals the lever arms times the step's |Δq| to rounding."""
    ctrl, q, v = planar_case() if case == "planar" else panda_case()
    sim = Simulator(ctrl, dt=DT, duration=DT)
    fused, plain = BrakeRollout(ctrl.robot, sim.world, DT), BrakeRollout(ctrl.robot, sim.world, DT)
    plain.fused = False
    assert fused.fused
    prev = gravity(ctrl.robot, q)
    qa, va, qb, vb = q.copy(), v.copy(), q.copy(), v.copy()
    for _ in range(200):
        tau = fused.torque(qa, va, prev, 25.0).copy()
        plain.tau[:] = tau
        before = qa.copy()
        fused.step(qa, va)
        plain.step(qb, vb)
        assert np.array_equal(qa, qb) and np.array_equal(va, vb)
        assert fused.travel == pytest.approx(float(fused.rho @ np.abs(qa - before)), rel=1e-9, abs=1e-15)
        prev = tau


@pytest.mark.parametrize("case,gain,stop", [("planar", 4.0, -np.inf), ("planar", 25.0, -np.inf),
                                            ("planar", 60.0, 0.0), ("panda", 10.0, -np.inf), ("panda", 60.0, 0.0)])
def test_lean_certificate_equals_the_oracles(case, gain, stop):
    ctrl, q, v = planar_case() if case == "planar" else panda_case()
    sim = Simulator(ctrl, dt=DT, duration=DT)
    lean = BrakeRollout(ctrl.robot, sim.world, DT)
    tau_prev = gravity(ctrl.robot, q)
    want = rollout(sim, q, v, tau_prev, 0.0, gain, stop_below=stop)
    got = lean.run(q, v, tau_prev, 0.0, gain, stop_below=stop)
    assert got.min_clearance == pytest.approx(want.min_clearance, abs=1e-9)
    assert (got.viable, got.steps, got.t_rest) == (want.viable, want.steps, want.t_rest)


def test_lean_stops_on_contact_and_at_a_joint_limit_as_the_oracle():
    """A sphere in the way (the soft brake runs into it: not viable, stopped at the contact step), and
    joint 2 with a limit just beyond the start (not viable, stopped at the step it is crossed)."""
    ctrl, q, v = planar_case(obstacles=[Obstacle("sphere", [-0.72, -1.45], radius=0.1)])
    sim = Simulator(ctrl, dt=DT, duration=DT)
    lean = BrakeRollout(ctrl.robot, sim.world, DT)
    tau_prev = gravity(ctrl.robot, q)
    want = rollout(sim, q, v, tau_prev, 0.0, 4.0, stop_below=0.0)
    got = lean.run(q, v, tau_prev, 0.0, 4.0, stop_below=0.0)
    assert not want.viable and want.min_clearance < 0 and want.steps > 1
    assert (got.viable, got.steps) == (want.viable, want.steps)
    assert got.min_clearance == pytest.approx(want.min_clearance, abs=1e-9)
    ctrl, q, v = planar_case(obstacles=[])
    ctrl.robot.q_min[1] = q[1] - 0.05  # joint 2 turns at −1.5 rad/s: past it within ~35 ms
    sim = Simulator(ctrl, dt=DT, duration=DT)
    lean = BrakeRollout(ctrl.robot, sim.world, DT)
    want = rollout(sim, q, v, tau_prev, 0.0, 10.0)
    got = lean.run(q, v, tau_prev, 0.0, 10.0)
    assert not want.viable and np.isinf(want.t_rest) and 0 < want.steps < 100
    assert (got.viable, got.steps) == (want.viable, want.steps)


def test_lean_with_a_moving_obstacle_reads_it_at_each_steps_time():
    """An obstacle drifting towards the arm: the clearance along the brake is the oracle's, at the same
    times (from t = 0.7 s: a rollout at another time would see it elsewhere)."""
    moving = Obstacle("sphere", [-1.6, -1.0], radius=0.1, velocity=[0.3, -0.4])
    ctrl, q, v = planar_case(obstacles=[moving])
    sim = Simulator(ctrl, dt=DT, duration=DT)
    lean = BrakeRollout(ctrl.robot, sim.world, DT)
    tau_prev = gravity(ctrl.robot, q)
    want = rollout(sim, q, v, tau_prev, 0.7, 25.0)
    got = lean.run(q, v, tau_prev, 0.7, 25.0)
    assert got.min_clearance == pytest.approx(want.min_clearance, abs=1e-9)
    assert got.min_clearance != pytest.approx(lean.run(q, v, tau_prev, 0.0, 25.0).min_clearance, abs=1e-3)
    assert (got.viable, got.steps) == (want.viable, want.steps)


@pytest.mark.parametrize("which", ["planar", "panda"])
def test_lever_arms_bound_every_capsule_points_motion(which, rng):
    """Σρᵢ|dqᵢ| bounds how far any capsule point moves between two configurations (Pinocchio's
    forward kinematics at 200 random pairs, each capsule's ends and midpoint), and is not loose by
    more than 3× on the worst pair of a small step."""
    from qpctl.safety.sweep import lever_arms

    robot = planar_arm() if which == "planar" else panda()
    rho = lever_arms(robot)
    assert rho is not None and np.all(rho > 0)
    data = robot.model.createData()

    def points(q):
        pin.forwardKinematics(robot.model, data, q)
        return np.array([data.oMi[c.joint_id].act(p) for c in robot.capsules for p in (c.p0, c.p1, (c.p0 + c.p1) / 2)])

    lo = np.where(np.isfinite(robot.q_min), robot.q_min, -np.pi)
    hi = np.where(np.isfinite(robot.q_max), robot.q_max, np.pi)
    tight = 0.0
    for k in range(200):
        q = rng.uniform(lo, hi)
        dq = rng.normal(0.0, 0.5 if k % 2 else 1e-3, robot.nv)
        moved = np.linalg.norm(points(q + dq) - points(q), axis=1).max()
        bound = float(rho @ np.abs(dq))
        assert moved <= bound * (1 + 1e-12)
        if k % 2 == 0:
            tight = max(tight, moved / bound)
    assert tight > 1 / 3


@pytest.mark.parametrize("case,gain,stop", [("planar", 4.0, 0.0), ("planar", 25.0, 0.0), ("panda", 10.0, 0.0),
                                            ("contact", 4.0, 0.0), ("moving", 25.0, 0.0)])
def test_lazy_clearance_keeps_the_verdict_and_bounds_the_least_clearance(case, gain, stop, monkeypatch):
    """exact=False: the same verdict and steps as the exact rollout, the least clearance reported ≤
    the exact one (a lower bound), and fewer clearance evaluations (counted)."""
    if case == "panda":
        ctrl, q, v = panda_case()
    elif case == "contact":
        ctrl, q, v = planar_case(obstacles=[Obstacle("sphere", [-0.72, -1.45], radius=0.1)])
    elif case == "moving":
        ctrl, q, v = planar_case(obstacles=[Obstacle("sphere", [-1.6, -1.0], radius=0.1, velocity=[0.3, -0.4])])
    else:
        ctrl, q, v = planar_case()
    sim = Simulator(ctrl, dt=DT, duration=DT)
    lean = BrakeRollout(ctrl.robot, sim.world, DT)
    tau_prev = gravity(ctrl.robot, q)
    exact = lean.run(q, v, tau_prev, 0.3, gain, stop_below=stop)
    calls = []
    world = lean.world
    monkeypatch.setattr(lean, "world", lambda qq, t: calls.append(t) or world(qq, t))
    lazy = lean.run(q, v, tau_prev, 0.3, gain, stop_below=stop, exact=False)
    assert (lazy.viable, lazy.steps, lazy.t_rest) == (exact.viable, exact.steps, exact.t_rest)
    assert lazy.min_clearance <= exact.min_clearance + 1e-12
    assert len(calls) < exact.steps


@pytest.mark.parametrize("case,gain", [("planar", 4.0), ("contact", 4.0), ("moving", 25.0)])
def test_lazy_clearance_skips_only_the_steps_its_bound_clears(case, gain, monkeypatch):
    """Step by step along the lazy rollout (every state recorded): a step whose clearance is not
    evaluated has the last evaluated clearance minus the travel since — Σᵢρᵢ|Δqᵢ| over the recorded
    states' differences plus the obstacles' speed bound × Δt, computed here — above the level (0), and
    the true clearance at that step is above that bound."""
    obstacles = {"contact": [Obstacle("sphere", [-0.72, -1.45], radius=0.1)],
                 "moving": [Obstacle("sphere", [-1.6, -1.0], radius=0.1, velocity=[0.3, -0.4])]}.get(case)
    ctrl, q, v = planar_case(obstacles=obstacles)
    sim = Simulator(ctrl, dt=DT, duration=DT)
    lean = BrakeRollout(ctrl.robot, sim.world, DT)
    lean.native = None  # the Python loop, whose steps can be recorded (the native one equals it: test_native_rollout)
    world, step = lean.world, lean.step
    states, evaluated = [q.copy()], set()

    def recorded_world(qq, t):
        evaluated.add(len(states) - 1)
        return world(qq, t)

    def recorded_step(qq, vv):
        step(qq, vv)
        states.append(qq.copy())

    monkeypatch.setattr(lean, "world", recorded_world)
    monkeypatch.setattr(lean, "step", recorded_step)
    c = lean.run(q, v, gravity(ctrl.robot, q), 0.3, gain, stop_below=0.0, exact=False)
    speed = max((np.linalg.norm(o.velocity) + 2 * np.pi * o.frequency * np.linalg.norm(o.amplitude)
                 for o in ctrl.obstacles), default=0.0)
    last = drift = np.nan
    skipped = 0
    for k in range(min(len(states), c.steps + 1)):
        true = world(states[k], 0.3 + k * DT)
        if k in evaluated:
            last, drift = true, 0.0
        else:
            skipped += 1
            assert last - drift > -1e-12, k
            assert true >= last - drift - 1e-12, k
        if k + 1 < len(states):
            drift += float(lean.rho @ np.abs(states[k + 1] - states[k])) + speed * DT
    assert skipped > 10 and 0 in evaluated
