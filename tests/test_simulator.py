"""The simulator: RK4's order and energy behaviour on Pinocchio's ABA, zero-order hold, records.

* Order: free motion of the planar arm under gravity (smooth), state error at T = 0.5 s against a
  step-T/1280 reference for steps T/20, T/40, T/80. The least-squares slope of log error over
  log step must be 4 ± 0.5 (measured 3.86; the pre-asymptotic coarse steps pull it just below 4).
* Energy: without torque or damping E = ½q̇ᵀMq̇ + V is conserved by the physics, so any change is
  integration error, which for RK4 scales as (ω dt)⁴ per unit time; with the arm's fastest motion
  here ω ≲ 10 rad/s and dt = 1e-3 s that is ≲ 1e-8 relative to the kinetic-energy scale — the bound.
  The drift must also shrink by ≈ 10⁴ (10^3.5 … 10^4.5) when dt shrinks tenfold, which separates
  integration error from a modelling error (that would not depend on dt).
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from qpctl import (
    ConfigError,
    Controller,
    ControlOutput,
    Obstacle,
    SimulationError,
    Simulator,
    Trajectory,
    WaypointPath,
)
from qpctl.simulation.simulator import rk4_step


def _free(robot):
    model, data = robot.model, robot.model.createData()
    return lambda q, v: pin.aba(model, data, q, v, np.zeros(robot.nv))


def _integrate(f, q, v, dt, T):
    for _ in range(round(T / dt)):
        q, v = rk4_step(f, q, v, dt)
    return q, v


def test_rk4_is_fourth_order(planar):
    f = _free(planar)
    q0, v0, T = np.array([0.3, -0.4, 0.5]), np.array([0.5, -0.3, 0.2]), 0.5
    q_ref, v_ref = _integrate(f, q0, v0, T / 1280, T)
    steps = np.array([T / 20, T / 40, T / 80])
    errors = []
    for dt in steps:
        q, v = _integrate(f, q0, v0, dt, T)
        errors.append(np.linalg.norm(np.concatenate([q - q_ref, v - v_ref])))
    order = np.polyfit(np.log(steps), np.log(errors), 1)[0]
    assert order == pytest.approx(4.0, abs=0.5)


def test_rk4_on_a_linear_oscillator_matches_the_exact_solution():
    """q̈ = −ω²q: RK4's one-step map is exact to O((ω dt)⁵); after 1 s error ≲ (ω dt)⁴ ω t."""
    w = 5.0
    q, v = np.array([1.0]), np.array([0.0])
    dt = 1e-2
    q, v = _integrate(lambda qq, vv: -w * w * qq, q, v, dt, 1.0)
    assert q[0] == pytest.approx(np.cos(w), abs=(w * dt) ** 4 * w)
    assert v[0] == pytest.approx(-w * np.sin(w), abs=(w * dt) ** 4 * w * w)


def _energy(robot, thin_rod, q, v):
    data = robot.model.createData()
    M = pin.crba(robot.model, data, q)
    M = np.triu(M) + np.triu(M, 1).T
    return 0.5 * v @ M @ v + thin_rod.potential(q), 0.5 * v @ M @ v


def test_potential_energy_agrees_with_pinocchio(planar, thin_rod, random_states):
    data = planar.model.createData()
    for q, _ in random_states(planar, 5):
        assert pin.computePotentialEnergy(planar.model, data, q) == pytest.approx(thin_rod.potential(q), abs=1e-9)


def test_energy_is_conserved_without_torque(planar, thin_rod):
    f = _free(planar)
    q0, v0 = np.array([0.3, -0.4, 0.5]), np.array([0.5, -0.3, 0.2])
    drift = {}
    for dt in (1e-2, 1e-3):
        q, v = q0.copy(), v0.copy()
        E0, _ = _energy(planar, thin_rod, q, v)
        worst, ke_max = 0.0, 0.0
        for _ in range(round(1.0 / dt)):
            q, v = rk4_step(f, q, v, dt)
            E, ke = _energy(planar, thin_rod, q, v)
            worst, ke_max = max(worst, abs(E - E0)), max(ke_max, ke)
        drift[dt] = worst / ke_max
    assert ke_max > 100.0  # the arm really swings (hundreds of joules), so the test has teeth
    assert drift[1e-3] < 1e-8
    assert 10**3.5 < drift[1e-2] / drift[1e-3] < 10**4.5


# -- the Simulator class --------------------------------------------------------------------------
class _Damper(Controller):
    """τ = −D q̇ + G(q)·½: a smooth state feedback, enough to test the simulator's bookkeeping."""

    kind = "damper"

    def control(self, state):
        data = self.robot.model.createData()
        G = pin.computeGeneralizedGravity(self.robot.model, data, state.q)
        tau = -5.0 * state.v + 0.5 * G
        ref = self.path(state.t)
        return ControlOutput(tau=tau, qdd=np.zeros(self.n), ref=ref, x=state.x, e_null=np.full(self.n, state.t),
                             clearance=state.clearance, singular=False)


def _closest(a, b, c):
    s = np.clip(np.dot(c - a, b - a) / np.dot(b - a, b - a), 0.0, 1.0)
    return a + s * (b - a)


def test_simulator_holds_torque_and_records(planar, thin_rod, tmp_path):
    obstacle = Obstacle("sphere", np.array([-0.3, -1.2, 0.0]), radius=0.15)
    path = WaypointPath([[-1.0, -2.0], [-0.5, -1.8]], duration=0.2)
    ctrl = _Damper(planar, path, [obstacle])
    dt, T = 2e-3, 0.1
    traj = Simulator(ctrl, dt=dt, duration=T).run(planar.q_home, np.array([0.4, -0.2, 0.3]))
    steps = round(T / dt) + 1
    assert traj.t.shape == (steps,) and traj.q.shape == (steps, 3) and traj.x.shape == (steps, 2)
    np.testing.assert_allclose(traj.t, np.arange(steps) * dt, atol=1e-12)
    # Independent replay: torque sampled at the start of each step, held over the RK4 step.
    model, data = planar.model, planar.model.createData()
    q, v = planar.q_home.copy(), np.array([0.4, -0.2, 0.3])
    for k in range(steps):
        np.testing.assert_allclose(traj.q[k], q, atol=1e-12)
        np.testing.assert_allclose(traj.v[k], v, atol=1e-12)
        tau = -5.0 * v + 0.5 * pin.computeGeneralizedGravity(model, data, q)
        np.testing.assert_allclose(traj.tau[k], tau, atol=1e-9)
        np.testing.assert_allclose(traj.x[k], thin_rod.ee(q), atol=1e-12)
        ref = path(k * dt)
        np.testing.assert_allclose(traj.x_ref[k], ref.x)
        np.testing.assert_allclose(traj.xd_ref[k], ref.xd)
        np.testing.assert_allclose(traj.xdd_ref[k], ref.xdd)
        # World clearance: closed-form capsule–sphere distance over all links.
        joints = thin_rod.joint_positions(q)
        c = obstacle.position[:2]
        d = min(np.linalg.norm(_closest(joints[i], joints[i + 1], c) - c) for i in range(3)) - 0.05 - 0.15
        assert traj.clearance[k] == pytest.approx(d, abs=1e-9)
        q, v = rk4_step(lambda qq, vv, tau=tau: pin.aba(model, data, qq, vv, tau), q, v, dt)
    np.testing.assert_allclose(traj.e_null[:, 0], traj.t)  # the controller's e_null is what is recorded
    assert np.all(traj.tick_us > 0)
    traj.save(tmp_path / "t.npz")
    back = Trajectory.load(tmp_path / "t.npz")
    for name in Trajectory.ARRAYS:
        np.testing.assert_array_equal(getattr(back, name), getattr(traj, name))


@pytest.mark.parametrize("kwargs, key", [({"dt": -1e-3}, "sim.dt"), ({"dt": 0.0}, "sim.dt"),
                                         ({"duration": float("nan")}, "sim.duration"),
                                         ({"integrator": "leapfrog"}, "sim.integrator")])
def test_simulator_rejects_bad_settings(planar, kwargs, key):
    ctrl = _Damper(planar, WaypointPath([[0.0, 1.0], [0.0, 1.0]], duration=1.0))
    with pytest.raises(ConfigError) as exc:
        Simulator(ctrl, **kwargs)
    assert exc.value.key == key


def test_non_finite_torque_is_a_simulation_error(planar):
    class Broken(_Damper):
        def control(self, state):
            out = super().control(state)
            out.tau = out.tau * np.nan
            return out

    ctrl = Broken(planar, WaypointPath([[0.0, 1.0], [0.0, 1.0]], duration=1.0))
    with pytest.raises(SimulationError):
        Simulator(ctrl, dt=1e-3, duration=0.01).run(planar.q_home)


def test_euler_is_first_order(planar):
    """The alternative integrator: semi-implicit Euler's error halves with the step (slope 1 ± 0.3)."""
    from qpctl.simulation.simulator import euler_step

    f = _free(planar)
    q0, v0, T = np.array([0.3, -0.4, 0.5]), np.array([0.5, -0.3, 0.2]), 0.3
    q_ref, v_ref = _integrate(f, q0, v0, T / 1200, T)
    steps = np.array([T / 150, T / 300, T / 600])
    errors = []
    for dt in steps:
        q, v = q0, v0
        for _ in range(round(T / dt)):
            q, v = euler_step(f, q, v, dt)
        errors.append(np.linalg.norm(np.concatenate([q - q_ref, v - v_ref])))
    assert np.polyfit(np.log(steps), np.log(errors), 1)[0] == pytest.approx(1.0, abs=0.3)
