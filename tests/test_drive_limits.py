"""The drives' limits in the QP (issue #16): torque rate |τ_k − τ_k−1| ≤ τ̇_max dt and joint
acceleration |q̈| ≤ q̈_max, held every tick, by the solved QP and by every fallback.

The reference for each check is the trajectory itself (torques differenced tick to tick) or the
limits' definition, never the controller's own bookkeeping.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from qpctl import ConfigError, Scenario
from qpctl.constraints import TorqueLimit
from qpctl.controllers.qp import FALLBACK_BRAKE, QPController
from qpctl.qp import Solution
from qpctl.run import simulate
from qpctl.solvers.daqp_ import DAQPSolver
from qpctl.tasks import AccelerationTask, EndEffectorTask

RATE = 1000.0  # [N·m/s]
# The paper's cost alone (no damping task), so that the unlimited QP changes its torques faster than
# the drives allow and the rows, not the damping, hold the limit.
DRIVES = ["robot.tau_max=1000.0", f"robot.tau_rate_max={RATE}", "sim.duration=1.5", "controller.damping=0.0"]


def torque_rates(traj) -> np.ndarray:
    """(T − 1, n) |τ_k − τ_k−1| / (t_k − t_k−1) [N·m/s] of a recorded run."""
    return np.abs(np.diff(traj.tau, axis=0)) / np.diff(traj.t)[:, None]


def test_window_is_the_torque_limit_and_the_rate_about_the_last_command():
    limit = TorqueLimit(np.array([10.0, 10.0]), np.array([1000.0, 100.0]))
    lo, hi = limit.window(0.5)  # nothing commanded yet: the torque limits alone
    np.testing.assert_array_equal(lo, [-10.0, -10.0])
    np.testing.assert_array_equal(hi, [10.0, 10.0])
    limit.remember(np.array([9.5, -2.0]), 0.5)
    lo, hi = limit.window(0.501)  # 1 ms later: ±1 and ±0.1 N·m about the last command, within ±10
    np.testing.assert_allclose(lo, [8.5, -2.1])
    np.testing.assert_allclose(hi, [10.0, -1.9])
    lo, hi = limit.window(0.5)  # no time has passed (a repeated tick): no rate window
    np.testing.assert_array_equal(hi, [10.0, 10.0])
    limit.remember(np.array([20.0, 0.0]), 1.0)  # beyond the limit (the limit was changed): it wins
    lo, hi = limit.window(1.001)
    assert lo[0] == -10.0 and hi[0] == 10.0
    limit.forget()
    assert np.all(np.isnan(limit.previous)) and np.isnan(limit.t_previous[0])


def test_the_rate_limit_holds_on_every_tick_of_a_run_and_binds():
    """The paper scenario with 1000 N·m and 1000 N·m/s drives (the issue's setting on the planar
    arm): no tick changes a torque faster than the limit, and the limit is met with equality at
    ticks where the unlimited QP goes faster (so the rows, not luck, hold it)."""
    free = simulate(Scenario.load("paper", DRIVES[:1] + DRIVES[2:]), kind="qp")
    assert torque_rates(free.trajectory).max() > 5 * RATE  # without the limit the QP goes faster
    run = simulate(Scenario.load("paper", DRIVES), kind="qp")
    rates = torque_rates(run.trajectory)
    assert rates.max() <= RATE * (1 + 1e-6), rates.max()
    assert np.all(np.abs(run.trajectory.tau) <= 1000.0 + 1e-9)
    hits = sum(1 for info in run.trajectory.infos if info.get("rate_limited"))
    assert hits >= 10 and np.count_nonzero(rates >= RATE * (1 - 1e-6)) >= 10
    assert run.metrics["min_clearance"] >= run.controller.gains.d_safe - 1e-3


class _Acceleration(AccelerationTask):
    """Any subclass takes the Python formulation."""


class _EndEffector(EndEffectorTask):
    pass


def test_compiled_and_python_paths_hold_the_same_window():
    """Consecutive ticks of the drive-limited paper scenario on the compiled path and on the Python
    path (the same tasks under subclasses): the same torques, to 1e-8 relative, while the rate
    window binds — both read and update the same remembered torque."""
    sc = Scenario.load("paper", DRIVES)
    run = simulate(sc, kind="qp")
    fast = sc.build_controller("qp")
    slow = sc.build_controller("qp")
    ee = next(t for t in slow.tasks if isinstance(t, EndEffectorTask))
    slow.tasks = [_Acceleration(), _EndEffector(ee.slack_l1, ee.slack_l2)]
    slow._formulation = slow._ws = None
    assert fast.workspace().spec is not None and slow.workspace().spec is None
    traj = run.trajectory
    first = next(k for k, info in enumerate(traj.infos) if info.get("rate_limited"))  # where it binds
    binding = 0
    for k in range(max(first - 100, 0), first + 200):
        a = fast.step(traj.q[k], traj.v[k], float(traj.t[k]))
        b = slow.step(traj.q[k], traj.v[k], float(traj.t[k]))
        np.testing.assert_allclose(a.tau, b.tau, rtol=1e-8, atol=1e-8 * np.abs(b.tau).max())
        binding += bool(a.info.get("rate_limited"))
    assert binding >= 5


def test_acceleration_limits_bound_every_commanded_acceleration():
    """The Panda (Franka's q̈_max by default) among the canopy: every commanded q̈ — checked from τ by
    Pinocchio's forward dynamics, not the controller's own q̈ — within ±q̈_max on every tick."""
    sc = Scenario.load("panda_canopy", ["sim.duration=1.0", "controller.damping=0.0"])
    run = simulate(sc, kind="qp")
    robot = run.controller.robot
    assert np.all(np.isfinite(robot.qdd_max)) and np.all(robot.tau_rate_max == 1000.0)
    data = robot.model.createData()
    traj = run.trajectory
    worst = 0.0
    for k in range(len(traj.t)):
        qdd = pin.aba(robot.model, data, traj.q[k], traj.v[k], traj.tau[k])
        worst = max(worst, float(np.max(np.abs(qdd) / robot.qdd_max)))
    assert worst <= 1 + 1e-6, worst
    assert worst > 0.9  # the bounds are reached in this scene
    assert torque_rates(traj).max() <= 1000.0 * (1 + 1e-6)


def test_a_fallback_holds_the_rate_window(monkeypatch):
    """The solver fails on every tick and the chain ends in the brake: the torques still move no faster
    than the rate limit (the brake's torque is clipped to the window)."""
    run = simulate(Scenario.load("paper", DRIVES), kind="qp")
    traj = run.trajectory

    def failing(self, *args, **kwargs):
        return None, "max_iter", 1000

    monkeypatch.setattr(DAQPSolver, "native", lambda self, buf: None)
    monkeypatch.setattr(DAQPSolver, "solve_buffers", failing)
    monkeypatch.setattr(DAQPSolver, "solve", lambda self, p: Solution(False, np.zeros(p.n_var), "max_iter"))
    ctrl = Scenario.load("paper", DRIVES + ['controller.fallback=["brake"]']).build_controller("qp")
    assert isinstance(ctrl, QPController)
    prev = None
    clipped = 0
    for k in range(1000, 1100):
        out = ctrl.step(traj.q[k], traj.v[k], float(traj.t[k]))
        assert out.info["fallback"] == FALLBACK_BRAKE
        if prev is not None:
            assert np.all(np.abs(out.tau - prev) <= RATE * 1e-3 * (1 + 1e-9) + 1e-12)
        clipped += "clipped" in out.info
        prev = out.tau.copy()
    assert clipped > 0  # the brake alone would have jumped


def test_reset_forgets_the_last_command():
    sc = Scenario.load("paper", DRIVES)
    ctrl = sc.build_controller("qp")
    q0 = sc.q0(ctrl.robot)
    ctrl.step(q0, np.zeros(3), 0.0)
    limit = next(c for c in ctrl.constraints if isinstance(c, TorqueLimit))
    assert np.all(np.isfinite(limit.previous))
    ctrl.reset()
    assert np.all(np.isnan(limit.previous))


@pytest.mark.parametrize("key, value", [("robot.tau_rate_max", "-1.0"), ("robot.qdd_max", "0.0"),
                                        ("robot.tau_rate_max", "[1.0, 2.0]")])
def test_bad_drive_limits_name_their_key(key, value):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        Scenario.load("paper", [f"{key}={value}"]).build_controller("qp")


def test_rms_jerk_is_the_analytic_jerk_of_a_sine_and_of_a_two_tick_chatter():
    """metrics' rms_jerk_per_joint against closed forms: v = A sin ωt has jerk −Aω² sin ωt, RMS Aω²/√2
    over whole periods; a joint whose acceleration flips between +a and −a every tick has |jerk| = 2a/Δt
    on every tick; a joint at constant speed has none."""
    from qpctl.simulation.metrics import compute_metrics
    from qpctl.simulation.trajectory import Trajectory

    dt, A, w = 1e-3, 0.4, 2 * np.pi * 2.0  # 2 Hz, 2 s: four periods
    t = np.arange(2001) * dt
    a = 20.0
    chatter = np.cumsum(np.where(np.arange(t.size) % 2 == 0, a * dt, -a * dt))  # q̈ = +a, −a, +a, …
    v = np.c_[A * np.sin(w * t), chatter, np.full(t.size, 0.3)]
    T, n = t.size, v.shape[1]
    z = np.zeros((T, 2))
    traj = Trajectory(t, np.zeros((T, n)), v, np.zeros((T, n)), z, z, z, z, np.full(T, 0.1),
                      np.zeros((T, n)), np.zeros(T), np.zeros(T, bool), [{} for _ in range(T)])
    jerk = compute_metrics(traj)["rms_jerk_per_joint"]
    assert jerk[0] == pytest.approx(A * w**2 / np.sqrt(2), rel=1e-3)
    assert jerk[1] == pytest.approx(2 * a / dt, rel=1e-9)
    assert jerk[2] == pytest.approx(0.0, abs=1e-6)
