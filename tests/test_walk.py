"""A settled retreat's walk (qpctl.safety.walk): the steering walked in closed form instead of stepped.

* the closed form against scipy's ODE solver on the steering's linear ODE;
* the native walk against the Python one: the same certificates and the same clearance evaluations,
  bit for bit, over random retreats of the soak's heavy planar arm and the Panda — with walks taken,
  refused at a torque sample and refused at a clearance among them;
* the assumption, measured: every walk a verified rollout took is held against the simulator's own
  steps (the oracle's loop: Simulator and oracle.brake_torque, none of the rollout's code) — each
  step's link points within the stray of the closed form's, no torque clipped while it walked — and
  the oracle verifies the retreat the rollout vouched for.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
from scipy.integrate import solve_ivp
from test_settle import franka, heavy_planar

from qpctl.kernels import walk as KW
from qpctl.safety import walk as W
from qpctl.safety.oracle import brake_torque, rollout
from qpctl.safety.retreat import Retreat, switch_time
from qpctl.safety.rollout import BrakeRollout
from qpctl.simulation import Simulator


def test_the_closed_form_is_the_steerings_ode(rng):
    """q̈ = ω²(q* − q) − 2ωq̇ integrated by scipy (RK45, tight tolerances) from random states: the closed
    form's (q, q̇) at 20 times within 1e-8."""
    for _ in range(20):
        n, w = 4, float(rng.choice([3.0, 6.0]))
        q0, v0, target = rng.normal(0, 1, n), rng.normal(0, 2, n), rng.normal(0, 1, n)
        times = np.sort(rng.uniform(0, 1.5, 20))

        def rhs(_, y, n=n, w=w, target=target):
            return np.concatenate([y[n:], w * w * (target - y[:n]) - 2 * w * y[n:]])

        sol = solve_ivp(rhs, (0, 1.5), np.concatenate([q0, v0]), t_eval=times, rtol=1e-12, atol=1e-12)
        q, v = np.zeros(n), np.zeros(n)
        for i, s in enumerate(times):
            KW.steer_state(q0, v0, target, w, float(s), q, v)
            np.testing.assert_allclose(q, sol.y[:n, i], atol=1e-8)
            np.testing.assert_allclose(v, sol.y[n:, i], atol=1e-8)


def retreat_case(make, rng, at_limit=False):
    """A random state of ``make``'s arm, a retreat from it (a random target up to 0.6 rad a joint away, ω
    3 or 6 rad/s, from t = 0.3 s) and the torque applied before (gravity, perturbed). ``at_limit``: one
    joint resting at a limit in the state and the target (the search keeps a joint it does not move where
    it is: soak-panda-600's retreat rested at joint 2's lower limit)."""
    ctrl, q, v, dt = make(rng)
    v = v * rng.uniform(0.0, 0.6)
    robot = ctrl.robot
    target = np.clip(q + rng.uniform(-0.6, 0.6, q.size), robot.q_min + 0.05, robot.q_max - 0.05)
    if at_limit:
        i = int(rng.integers(q.size))
        q[i] = target[i] = robot.q_min[i] if rng.random() < 0.5 else robot.q_max[i]
        v[i] = 0.0
    omega = float(rng.choice([3.0, 6.0]))
    retreat = Retreat(tuple(float(x) for x in target), omega, switch_time(0.3, dt, omega))
    tau_prev = pin.computeGeneralizedGravity(robot.model, robot.model.createData(), q) + rng.normal(0, 5, q.size)
    return ctrl, q, v, dt, retreat, tau_prev


def walks_recorded(brake, monkeypatch):
    """Each walk ``brake`` tries — (k, walked, steps walked, the stray, its start (q, q̇), what refused it)
    — recorded."""
    seen: list[tuple[int, bool, int, float, np.ndarray, np.ndarray, str | None]] = []
    attempt = brake.walk.attempt

    def recording(q, v, retreat, gain, t0, k, *a):
        walked, after = attempt(q, v, retreat, gain, t0, k, *a)
        seen.append((k, walked, brake.walk.steps, brake.walk.stray, np.array(q), np.array(v), brake.walk.refused))
        return walked, after

    monkeypatch.setattr(brake.walk, "attempt", recording)
    return seen


def test_native_walks_equal_the_python_ones(monkeypatch):
    """30 random retreats of each arm × lazy/exact clearance × margin 0 and 0.05 m: the native loop's
    certificates, clearance evaluation times and walks equal the Python loop's; walks are taken, refused
    at a torque sample (to be tried again later) and refused at a clearance among them."""
    rng = np.random.default_rng(5)
    answers = set()
    for make in [heavy_planar, franka] * 30:
        ctrl, q, v, dt, retreat, tau_prev = retreat_case(make, rng)
        sim = Simulator(ctrl, dt=dt, duration=dt)
        fast, slow = BrakeRollout(ctrl.robot, sim.world, dt), BrakeRollout(ctrl.robot, sim.world, dt)
        slow.native = None
        assert fast.native is not None
        for exact in (False, True):
            for margin in (0.0, 0.05):
                times: dict[str, list[float]] = {"fast": [], "slow": []}
                for name, b in (("fast", fast), ("slow", slow)):
                    world = b.world
                    monkeypatch.setattr(b, "world", lambda x, t, w=world, r=times[name]: r.append(t) or w(x, t))
                wf, ws = walks_recorded(fast, monkeypatch), walks_recorded(slow, monkeypatch)
                kw = dict(margin=margin, stop_below=margin, exact=exact, retreat=retreat, settle=True)
                a, b = fast.run(q, v, tau_prev, 0.3, 25.0, **kw), slow.run(q, v, tau_prev, 0.3, 25.0, **kw)
                monkeypatch.undo()
                assert a == b
                assert times["fast"] == times["slow"]
                assert [(k, ok, n, s) for k, ok, n, s, *_ in wf] == [(k, ok, n, s) for k, ok, n, s, *_ in ws]
                answers |= {refused for *_, refused in wf}
    assert {None, "a torque sample", "the clearance or a joint limit"} <= answers


def test_a_walk_changes_no_verdict(monkeypatch):
    """80 random retreats of both arms (20 with a joint resting at a limit) × margin 0 and 0.05 m: the
    verdict with walks is the verdict with
    every walk refused (the rollout stepped throughout) — a walked rollout that does not verify is stepped
    again from the walk's start — and walks are taken in a third of the verified rollouts at least."""
    rng = np.random.default_rng(8)
    verified, taken = 0, 0
    for i, make in enumerate([heavy_planar, franka] * 40):
        ctrl, q, v, dt, retreat, tau_prev = retreat_case(make, rng, at_limit=i >= 60)
        brake = BrakeRollout(ctrl.robot, Simulator(ctrl, dt=dt, duration=dt).world, dt)
        for margin in (0.0, 0.05):
            kw = dict(margin=margin, stop_below=margin, exact=False, retreat=retreat, settle=True)
            seen = walks_recorded(brake, monkeypatch)
            walked = brake.run(q, v, tau_prev, 0.3, 25.0, **kw)
            monkeypatch.undo()
            monkeypatch.setattr(brake.walk, "attempt", lambda *a: (False, np.inf))
            stepped = brake.run(q, v, tau_prev, 0.3, 25.0, **kw)
            monkeypatch.undo()
            assert walked.viable == stepped.viable
            verified += stepped.viable
            taken += walked.viable and any(w[1] for w in seen)
    assert verified >= 20 and taken >= verified // 3


def sim_retreat(sim, q, v, tau_prev, t, gain, retreat, steps):
    """The retreat in the simulator, step by step (the oracle's torque, Simulator's steps): the
    configurations, the velocities and whether each step's torque was clipped."""
    robot, dt = sim.robot, sim.dt
    data = robot.model.createData()
    sim.reset(q, v)
    qq, vv, tau = np.array(q, float), np.array(v, float), np.array(tau_prev, float)
    qs, vs, clipped = [qq], [vv], []
    for k in range(steps):
        tk = t + k * dt
        qdd = retreat.accel(qq, vv, np.empty_like(vv)) if retreat.steering(tk) else -gain * vv
        raw = pin.rnea(robot.model, data, qq, vv, qdd)
        tau = brake_torque(robot, data, qq, vv, tau, gain, dt, retreat=retreat, t=tk)
        clipped.append(not np.array_equal(raw, tau))
        sim.apply(tau)
        sim.step(tk)
        qq, vv = (a.copy() for a in sim.read())
        qs.append(qq)
        vs.append(vv)
    return np.array(qs), np.array(vs), np.array(clipped)


@pytest.mark.parametrize("make,samples,seed", [
    (heavy_planar, 60, 11), (franka, 40, 11),
    pytest.param(heavy_planar, 300, 3, marks=pytest.mark.slow),
    pytest.param(franka, 150, 3, marks=pytest.mark.slow)],
    ids=["planar", "panda", "planar-300", "panda-150"])
def test_a_walked_retreat_is_one_the_simulator_follows(make, samples, seed, monkeypatch):
    """``samples`` random retreats (with make soak: 300 planar, 150 Panda; every 4th with a joint resting at
    a limit) rolled out with walks (κ = 25,
    lazy, margin 0): for each walk of a verified certificate, the simulator's own steps from the rollout's
    start stay within the stray of the closed form at every walked step (Σᵢρᵢ|q − q_walk| ≤ stray ×
    Σᵢρᵢ × the joints' travel so far) with no torque clipped, the state at the switch within the switch's
    stray (Σᵢρᵢ(|Δqᵢ| + |Δq̇ᵢ|/κ)), and the oracle verifies the retreat."""
    rng = np.random.default_rng(seed)
    walked, worst, at_switch, joints = 0, 0.0, 0.0, 0.0
    for i in range(samples):
        ctrl, q, v, dt, retreat, tau_prev = retreat_case(make, rng, at_limit=i % 4 == 3)
        sim = Simulator(ctrl, dt=dt, duration=dt)
        if sim.clearance(q, 0.3) <= 0.02:
            continue
        brake = BrakeRollout(ctrl.robot, sim.world, dt)
        seen = walks_recorded(brake, monkeypatch)
        cert = brake.run(q, v, tau_prev, 0.3, 25.0, margin=0.0, stop_below=0.0, exact=False, retreat=retreat,
                         settle=True)
        monkeypatch.undo()
        taken = [s for s in seen if s[1]]
        if not cert.viable or not taken:
            continue
        (k, _, steps, switch, q0, v0, _), = taken  # a rollout walks at most once
        walked += 1
        assert rollout(sim, q, v, tau_prev, 0.3, 25.0, margin=0.0, stop_below=0.0, retreat=retreat).viable
        qs, vs, clipped = sim_retreat(sim, q, v, tau_prev, 0.3, 25.0, retreat, k + steps)
        np.testing.assert_allclose(qs[k], q0, atol=1e-12)  # the rollout's state at the walk's start is the simulator's
        assert not clipped[k:].any(), "the torque was clipped while the rollout walked"
        rho, stray = brake.rho, W.WALK_STRAY * dt / 1e-3
        x, xv, prev, prog, turn = np.zeros(q.size), np.zeros(q.size), q0.copy(), 0.0, 0.0
        for j in range(1, steps):
            KW.steer_state(q0, v0, retreat.q, retreat.omega, j * dt, x, xv)
            prog += float(rho @ np.abs(x - prev))
            turn += float(np.sum(np.abs(x - prev)))
            prev[:] = x
            off = float(rho @ np.abs(qs[k + j] - x))
            assert off <= stray * prog + 1e-12
            worst = max(worst, off / (stray * prog))
            joint = float(np.abs(qs[k + j] - x).max())  # each joint within stray × every joint's travel [rad]
            assert joint <= stray * turn + 1e-12
            joints = max(joints, joint / (stray * turn))
        # at the switch the state the rollout steps on from, position and the brake's travel, within the switch's stray
        KW.steer_state(q0, v0, retreat.q, retreat.omega, steps * dt, x, xv)
        off = float(rho @ (np.abs(qs[k + steps] - x) + np.abs(vs[k + steps] - xv) / 25.0))
        assert off <= switch
        at_switch = max(at_switch, off / switch)
    assert walked >= samples // 5
    assert worst < 0.9 and at_switch < 0.9 and joints < 0.9  # the measured path and switch: within 90 % of their strays


class TickBudget:
    """Work allowed per tick for a rollout spread over ticks: a random number of steps (1–40) and clearance
    evaluations (0–3) each tick, drawn anew at each pause; counts the pauses and the steps integrated."""

    def __init__(self, rng, world):
        self.rng, self.world, self.pauses, self.integrated = rng, world, 0, 0
        self.refill()

    def refill(self):
        self.step_left = int(self.rng.integers(1, 41))
        self.eval_end = self.world.evaluations + int(self.rng.integers(0, 4))

    def steps(self):
        return self.step_left

    def evaluations(self):
        return self.eval_end - self.world.evaluations

    def spend_steps(self, n):
        assert 0 <= n <= self.step_left  # a stretch integrates no more than its tick allows
        self.step_left -= n
        self.integrated += n


class CountedWorld:
    """A world clearance counting its evaluations (the carried search's meter, here by hand)."""

    def __init__(self, world):
        self.inner, self.evaluations = world, 0
        self.ws = world.ws

    def __call__(self, q, t):
        self.evaluations += 1
        return self.inner(q, t)


def test_a_rollout_spread_over_ticks_is_the_rollout():
    """``run_iter`` paused wherever a random per-tick allowance of steps (1–40) and evaluations (0–3) runs
    out, resumed a tick later: the same certificate as ``run`` bit for bit (the native loop's state kept
    across the pauses), and each stretch between two pauses within its tick's steps — over 30 random
    retreats and brakes of each arm, lazy clearance, margin 0 and 0.05 m, with walks and settles."""
    rng = np.random.default_rng(57)
    paused = 0
    for make in [heavy_planar, franka] * 15:
        ctrl, q, v, dt, retreat, tau_prev = retreat_case(make, rng)
        sim = Simulator(ctrl, dt=dt, duration=dt)
        world = CountedWorld(sim.world)
        whole, spread = BrakeRollout(ctrl.robot, sim.world, dt), BrakeRollout(ctrl.robot, world, dt)
        for r in (retreat, None):
            for margin in (0.0, 0.05):
                kw = dict(margin=margin, stop_below=margin, exact=False, retreat=r, settle=True)
                want = whole.run(q, v, tau_prev, 0.3, 25.0, **kw)
                budget = TickBudget(rng, world)
                gen = spread.run_iter(q, v, tau_prev, 0.3, 25.0, budget, **kw)
                while True:
                    try:
                        next(gen)
                    except StopIteration as done:
                        got = done.value
                        break
                    assert budget.step_left < 1 or budget.evaluations() < 1  # paused only where the tick's work is spent
                    budget.pauses += 1
                    budget.refill()
                assert got == want
                paused += budget.pauses > 0
    assert paused >= 60  # most of the 120 rollouts paused at least once
