"""A brake rollout that ends where the brake has settled (qpctl.safety.rollout, "Settled") against the
full stop in the built-in simulator (the oracle's own loop: Simulator steps and oracle.brake_torque,
none of the rollout module's code): from random states of the soak's heavy planar arm (τ_max 600–1500
N·m, τ̇_max 1–5 kN·m/s) and the Panda (Franka's limits) among obstacles, every settled certificate is
a stop the simulator brings to rest without contact — the oracle verifies it — and after the settle
step the torque is never clipped again and every link point moves less than the creep bound the
rollout used (1.25 Σᵢρᵢ|q̇ᵢ|/κ). The settle also ends most rollouts well before the rest (what it is for)."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from qpctl import LawGains, Obstacle, WaypointPath, panda, planar_arm
from qpctl.controllers.qp import QPConfig, QPController
from qpctl.safety.oracle import REST_SPEED, REST_TIME, brake_torque, rollout
from qpctl.safety.rollout import SETTLE_GAMMA, BrakeRollout
from qpctl.simulation import Simulator


def heavy_planar(rng):
    robot = planar_arm(tau_max=float(rng.uniform(600, 1500))).with_limits(tau_rate_max=float(rng.uniform(1000, 5000)))
    obstacles = [Obstacle("sphere", rng.uniform(-1.8, 1.8, 2).tolist(), radius=float(rng.uniform(0.08, 0.2))),
                 Obstacle("box", rng.uniform(-1.8, 1.8, 2).tolist(), size=[0.2, 0.3, 0.2])]
    path = WaypointPath([[-1.0, -2.0], [1.0, -1.5]], duration=2.0)
    ctrl = QPController(robot, path, obstacles, LawGains(d_influence=0.3, d_safe=0.05), QPConfig())
    q = rng.uniform(-np.pi, np.pi, 3)
    v = rng.uniform(-2.5, 2.5, 3)
    return ctrl, q, v, 2e-3


def franka(rng):
    robot = panda()
    data = robot.model.createData()
    pin.framesForwardKinematics(robot.model, data, robot.q_home)
    x = data.oMf[robot.ee_frame_id].translation.copy()
    obstacles = [Obstacle("sphere", (x + rng.uniform(-0.4, 0.4, 3)).tolist(), radius=0.06),
                 Obstacle("sphere", (x + rng.uniform(-0.4, 0.4, 3)).tolist(), radius=0.08)]
    path = WaypointPath([x.tolist(), (x + 0.1).tolist()], duration=2.0)
    ctrl = QPController(robot, path, obstacles, LawGains(d_influence=0.3, d_safe=0.03), QPConfig())
    q = robot.q_home + rng.uniform(-0.5, 0.5, 7)
    v = rng.uniform(-1.2, 1.2, 7)
    return ctrl, q, v, 1e-3


def full_stop(sim, q, v, tau_prev, t, gain):
    """The brake to rest in the simulator, step by step: (configurations, velocities, clipped per step,
    least clearance per step)."""
    robot, dt = sim.robot, sim.dt
    data = robot.model.createData()
    sim.reset(q, v)
    qq, vv, tau = np.array(q, float), np.array(v, float), np.array(tau_prev, float)
    qs, vs, clipped, clear = [qq], [vv], [], []
    still = 0.0
    for k in range(round(3.0 / dt)):
        clear.append(sim.clearance(qq, t + k * dt))
        still = still + dt if np.all(np.abs(vv) <= REST_SPEED) else 0.0
        if still >= REST_TIME:
            break
        raw = pin.rnea(robot.model, data, qq, vv, -gain * vv)
        tau = brake_torque(robot, data, qq, vv, tau, gain, dt)
        clipped.append(not np.array_equal(raw, tau))
        sim.apply(tau)
        sim.step(t + k * dt)
        qq, vv = (a.copy() for a in sim.read())
        qs.append(qq)
        vs.append(vv)
    return np.array(qs), np.array(vs), np.array(clipped), np.array(clear)


@pytest.mark.parametrize("make,samples,seed,gains", [
    (heavy_planar, 80, 22, (10.0, 25.0)), (franka, 25, 22, (10.0, 25.0)),
    pytest.param(heavy_planar, 400, 7, (4.0, 10.0, 25.0, 60.0), marks=pytest.mark.slow),
    pytest.param(franka, 100, 7, (4.0, 10.0, 25.0, 60.0), marks=pytest.mark.slow)],
    ids=["planar", "panda", "planar-400", "panda-100"])
def test_a_settled_rollout_is_a_stop_the_simulator_verifies(make, samples, seed, gains):
    """``samples`` random states (with make soak: 400 planar and 100 Panda states, the whole family)."""
    rng = np.random.default_rng(seed)
    settled, early, worst_ratio = 0, 0, 0.0
    for _ in range(samples):
        ctrl, q, v, dt = make(rng)
        sim = Simulator(ctrl, dt=dt, duration=dt)
        if sim.clearance(q, 0.0) <= 0.05:
            continue
        tau_prev = pin.computeGeneralizedGravity(ctrl.robot.model, ctrl.robot.model.createData(), q)
        tau_prev = tau_prev + rng.normal(0, 20, q.size)
        brake = BrakeRollout(ctrl.robot, sim.world, dt)
        for gain in gains:
            cert = brake.run(q, v, tau_prev, 0.0, gain, margin=0.0, stop_below=0.0, exact=False, settle=True)
            full = brake.run(q, v, tau_prev, 0.0, gain, margin=0.0, stop_below=0.0, exact=False, settle=False)
            if not cert.viable:
                continue
            settled += 1
            # the oracle (the simulator's own loop) verifies the stop the settled rollout vouched for
            assert rollout(sim, q, v, tau_prev, 0.0, gain, margin=0.0, stop_below=0.0).viable
            qs, vs, clipped, clear = full_stop(sim, q, v, tau_prev, 0.0, gain)
            k = cert.steps
            assert not clipped[k:].any(), "the torque was clipped after the settle"
            assert clear[k:].min() > 0.0
            bound = float(brake.rho @ np.abs(vs[k])) / gain  # Σρ|q̇|/κ at the settle
            tail = float(np.sum(np.abs(np.diff(qs[k:], axis=0)) @ brake.rho))  # Σρ|Δq| over the rest of the stop
            assert tail <= SETTLE_GAMMA * bound + 1e-12
            worst_ratio = max(worst_ratio, tail / bound if bound > 0 else 0.0)
            early += full.viable and k <= full.steps / 2
    assert settled >= samples // 2
    assert early >= 0.4 * settled  # many settled rollouts end before half the full one's steps (49 % on the 400)
    assert worst_ratio < 1.1  # the measured tail: the decay's bound holds within 10 %
