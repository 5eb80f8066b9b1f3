"""Faults (issue 12): each fault the simulator applies, checked against an independent computation.

A scripted controller (a :class:`~qpctl.Controller` whose law replays given torques and records the
state it was handed) separates what the controller measured from what the simulator recorded as
the truth. Rigid-body quantities come from Pinocchio, computed here on models built independently
of the fault machinery (one body at a time, or the payload's gravity from the task frame's
Jacobian).
"""

from __future__ import annotations

import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from qpctl import ConfigError, Controller, ControlOutput, Faults, Obstacle, Scenario, Simulator, WaypointPath
from qpctl.run import simulate
from qpctl.simulation.faults import FaultState
from qpctl.tick import WorldClearance

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


class _Scripted(Controller):
    """τ_k = script(k) (default: a damped gravity hold on the measured state); records what it saw."""

    kind = "scripted"

    def __init__(self, robot, path, obstacles=(), script=None):
        super().__init__(robot, path, obstacles)
        self.script = script
        self.seen: list[tuple[np.ndarray, np.ndarray, float]] = []
        self._data = robot.model.createData()

    def control(self, state):
        k = len(self.seen)
        self.seen.append((state.q.copy(), state.v.copy(), state.t))
        if self.script is not None:
            tau = np.asarray(self.script(k), float)
        else:
            tau = -5.0 * state.v + 0.9 * pin.computeGeneralizedGravity(self.robot.model, self._data, state.q)
        return ControlOutput(tau=tau, qdd=np.zeros(self.n), ref=self.path(state.t), x=state.x,
                             e_null=np.zeros(self.n), clearance=state.clearance, singular=False)

    def reset(self):
        super().reset()
        self.seen = []


PATH = WaypointPath([[-1.0, -2.0], [-0.6, -1.8]], duration=0.5)


def _run(robot, faults, *, duration=0.2, dt=1e-3, script=None, obstacles=(), world=None, v0=None):
    ctrl = _Scripted(robot, PATH if robot.m == 2 else WaypointPath([[0.3, 0.0, 0.5]] * 2, duration=1.0),
                     obstacles, script)
    sim = Simulator(ctrl, dt=dt, duration=duration, faults=faults, obstacles=world)
    traj = sim.run(robot.q_home, v0)
    return ctrl, sim, traj


# -- sensing ----------------------------------------------------------------------------------------
def test_quantised_q_is_on_the_encoder_grid_and_within_half_a_step(planar):
    quantum = 1e-3
    ctrl, _, traj = _run(planar, Faults(q_quantum=quantum), v0=np.array([0.5, -0.7, 0.9]))
    seen = np.array([s[0] for s in ctrl.seen])
    steps = seen / quantum
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-9)  # multiples of the quantum
    err = seen - traj.q
    assert np.max(np.abs(err)) <= quantum / 2 + 1e-12
    assert np.max(np.abs(err)) > quantum / 4  # it really quantised (the arm moved across the grid)
    np.testing.assert_array_equal(np.array([s[1] for s in ctrl.seen]), traj.v)  # q̇ untouched


def test_noise_has_the_stated_deviation_and_its_own_stream(planar):
    sq, sv = 1e-3, 2e-2
    ctrl, _, traj = _run(planar, Faults(q_noise=sq, v_noise=sv, seed=7), duration=1.0)
    dq = np.array([s[0] for s in ctrl.seen]) - traj.q
    dv = np.array([s[1] for s in ctrl.seen]) - traj.v
    N = dq.size  # 3003 draws each: the sample deviation is within 4/√(2N) ≈ 5 % of σ
    assert np.std(dq) == pytest.approx(sq, rel=4 / math.sqrt(2 * N))
    assert np.std(dv) == pytest.approx(sv, rel=4 / math.sqrt(2 * N))
    assert abs(np.mean(dq)) < 4 * sq / math.sqrt(N) and abs(np.mean(dv)) < 4 * sv / math.sqrt(N)
    assert abs(np.corrcoef(dq[1:, 0], dq[:-1, 0])[0, 1]) < 4 / math.sqrt(len(dq))  # white
    # The q noise is the same draw whether or not v noise is on (one stream per fault), and another seed differs.
    ctrl2, _, traj2 = _run(planar, Faults(q_noise=sq, seed=7), duration=1.0)
    np.testing.assert_allclose(np.array([s[0] for s in ctrl2.seen]) - traj2.q, dq, atol=1e-12)
    ctrl3, _, traj3 = _run(planar, Faults(q_noise=sq, seed=8), duration=1.0)
    assert np.max(np.abs(np.array([s[0] for s in ctrl3.seen]) - traj3.q - dq)) > sq


# -- actuation --------------------------------------------------------------------------------------
def _script(n, seed=3):
    rng = np.random.default_rng(seed)
    table = rng.uniform(-50.0, 50.0, (1000, n)) + np.array([0.0, 150.0, 50.0][:n])
    return lambda k: table[k]


def _replay(robot, traj, dt, models=None, switch=math.inf):
    """RK4 on the recorded applied torques, on the given (before, after) models: the recorded states."""
    before, after = models or (robot.model, robot.model)
    q, v = traj.q[0].copy(), traj.v[0].copy()
    from qpctl.simulation.simulator import rk4_step

    for k in range(len(traj.t) - 1):
        model = after if k * dt >= switch else before
        data = model.createData()
        q, v = rk4_step(lambda qq, vv, tau=traj.tau[k], m=model, d=data: pin.aba(m, d, qq, vv, tau), q, v, dt)
        np.testing.assert_allclose(traj.q[k + 1], q, rtol=0, atol=1e-12)
        np.testing.assert_allclose(traj.v[k + 1], v, rtol=0, atol=1e-10)


@pytest.mark.parametrize("k", [1, 3])
def test_delay_shifts_the_applied_torque_by_k_ticks(planar, k):
    script = _script(3)
    _, _, traj = _run(planar, Faults(delay_ticks=k), duration=0.05, script=script)
    cmd = np.array([script(j) for j in range(len(traj.t))])
    np.testing.assert_array_equal(traj.tau_command, cmd)
    np.testing.assert_array_equal(traj.tau[k:], cmd[:-k])
    np.testing.assert_array_equal(traj.tau[:k], np.repeat(cmd[:1], k, axis=0))  # the first command, held
    _replay(planar, traj, 1e-3)  # the dynamics felt the applied torque, not the command


def test_a_missed_tick_holds_the_last_torque(planar):
    script, rate = _script(3), 0.3
    _, sim, traj = _run(planar, Faults(miss_rate=rate, seed=5), duration=0.5, script=script)
    cmd = np.array([script(j) for j in range(len(traj.t))])
    fresh = np.all(traj.tau == cmd, axis=1)
    held = np.all(traj.tau[1:] == traj.tau[:-1], axis=1)
    assert fresh[0] and np.all(fresh[1:] | held)  # every tick: this tick's command, or the last one held
    missed = int(np.count_nonzero(~fresh))
    assert sim.fault_counts["missed_commands"] == missed
    N = len(traj.t) - 1
    assert abs(missed - rate * N) < 4 * math.sqrt(N * rate * (1 - rate))
    _replay(planar, traj, 1e-3)


def test_lag_follows_the_first_order_step_response(planar):
    T, dt, u = 0.01, 1e-3, np.array([40.0, 180.0, 60.0])
    _, _, traj = _run(planar, Faults(torque_lag=T), duration=0.05, dt=dt,
                      script=lambda k: np.zeros(3) if k == 0 else u)
    assert np.array_equal(traj.tau[0], np.zeros(3))  # the drive starts at the first command
    for j in range(1, len(traj.t)):
        # the torque held over step j is the mean of T τ̇ = u − τ, τ(t₁) = 0, over [t_j, t_j + dt]:
        # independently, by Gauss–Legendre quadrature of the analytic response u (1 − e^(−(t − t₁)/T))
        nodes, weights = np.polynomial.legendre.leggauss(8)
        s = (j - 1) * dt + 0.5 * dt * (nodes + 1)
        mean = 0.5 * np.sum(weights * (1 - np.exp(-s / T))) * u
        np.testing.assert_allclose(traj.tau[j], mean, rtol=1e-12)
    # and the drive's state at the ticks is the sampled response
    state = FaultState(Faults(torque_lag=T), 3, dt)
    state.actuate(np.zeros(3))
    for j in range(1, 20):
        state.actuate(u)
        np.testing.assert_allclose(state.drive_torque, u * (1 - math.exp(-j * dt / T)), rtol=1e-12)
    _replay(planar, traj, dt)


def test_saturation_clips_what_the_drives_deliver(planar):
    script, sat = _script(3), np.array([100.0, 160.0, 30.0])
    _, sim, traj = _run(planar, Faults(torque_saturation=sat.tolist()), duration=0.05, script=script)
    cmd = np.array([script(j) for j in range(len(traj.t))])
    np.testing.assert_array_equal(traj.tau, np.clip(cmd, -sat, sat))
    assert sim.fault_counts["saturated_ticks"] == int(np.count_nonzero(np.any(np.abs(cmd) > sat, axis=1))) > 0


# -- the robot ----------------------------------------------------------------------------------------
def _one_body(model, i):
    """A copy of ``model`` whose only inertia is body i's."""
    out = model.copy()
    for j in range(1, out.njoints):
        if j != i:
            out.inertias[j] = pin.Inertia.Zero()
    return out


@pytest.mark.parametrize("robot_name", ["planar", "panda_robot"])
def test_mass_error_scales_each_body_of_the_simulated_model_only(robot_name, request, random_states):
    robot = request.getfixturevalue(robot_name)
    nominal = [pin.Inertia(robot.model.inertias[i]) for i in range(robot.model.njoints)]
    faults = Faults(mass_error=0.1, seed=4)
    sim_model, _ = faults.simulated_models(robot)
    eps = faults.mass_factors(robot.model)[1:] - 1.0
    assert np.all(np.abs(eps) <= 0.1) and np.std(eps) > 0.01  # drawn in (−e, e), not all equal
    data = sim_model.createData()
    for q, _ in random_states(robot, 3):
        # crba is linear in the inertias: M_sim = Σ_i (1 + ε_i) M_i, M_i the inertia of body i alone
        expected = sum((1 + e) * pin.crba(_one_body(robot.model, i), _one_body(robot.model, i).createData(), q)
                       for i, e in enumerate(eps, start=1))
        np.testing.assert_allclose(pin.crba(sim_model, data, q), expected, rtol=1e-12, atol=1e-12)
    for i in range(robot.model.njoints):  # the controller's model is left nominal
        assert robot.model.inertias[i] == nominal[i]


@pytest.mark.parametrize("robot_name", ["planar", "panda_robot"])
def test_payload_gravity_is_its_weight_through_the_task_jacobian(robot_name, request, random_states):
    robot = request.getfixturevalue(robot_name)
    mass = 0.5
    before, after = Faults(payload_mass=mass, payload_time=1.0).simulated_models(robot)
    jid = robot.model.frames[robot.ee_frame_id].parentJoint
    assert after.inertias[jid].mass == pytest.approx(before.inertias[jid].mass + mass)
    g = robot.model.gravity.linear
    db, da, dj = before.createData(), after.createData(), robot.model.createData()
    for q, _ in random_states(robot, 4):
        J = pin.computeFrameJacobian(robot.model, dj, q, robot.ee_frame_id, pin.LOCAL_WORLD_ALIGNED)[:3]
        extra = pin.computeGeneralizedGravity(after, da, q) - pin.computeGeneralizedGravity(before, db, q)
        np.testing.assert_allclose(extra, -J.T @ (mass * g), atol=1e-10)  # m·g times each joint's lever


def test_a_declared_payload_is_in_the_controllers_model_and_the_simulated_one():
    plain = Scenario.load("panda_canopy").build_robot()
    declared = Scenario.load("panda_canopy", ["robot.payload_mass=0.5", "robot.payload_radius=0.05"]).build_robot()
    _, unknown = Faults(payload_mass=0.5, payload_radius=0.05).simulated_models(plain)
    for i in range(plain.model.njoints):  # the same body as the unknown payload's
        assert declared.model.inertias[i].isApprox(unknown.inertias[i], 1e-14)
    jid = plain.model.frames[plain.ee_frame_id].parentJoint
    assert declared.model.inertias[jid].mass == pytest.approx(plain.model.inertias[jid].mass + 0.5)
    assert plain.model.inertias[jid].mass != declared.model.inertias[jid].mass  # the plain model untouched
    ctrl = Scenario.load("panda_canopy", ["robot.payload_mass=0.5"]).build_controller("qp")
    assert ctrl.robot.model.inertias[jid].mass == pytest.approx(plain.model.inertias[jid].mass + 0.5)


def test_the_simulation_integrates_the_true_robot_and_takes_the_payload_on_time(planar):
    faults = Faults(mass_error=0.2, payload_mass=2.0, payload_time=0.03, seed=2)
    script = _script(3)
    _, _, traj = _run(planar, faults, duration=0.06, script=script)
    _replay(planar, traj, 1e-3, faults.simulated_models(planar), switch=0.03)
    with pytest.raises(AssertionError):  # the nominal model does not reproduce the run
        _replay(planar, traj, 1e-3)


# -- the scene -----------------------------------------------------------------------------------------
def test_obstacle_noise_moves_only_the_controllers_map(planar):
    truth = [Obstacle("sphere", np.array([-0.4, -1.3, 0.0]), radius=0.12, name="a"),
             Obstacle("sphere", np.array([0.3, -0.9, 0.0]), radius=0.1, name="b")]
    faults = Faults(obstacle_noise=0.02, seed=9)
    seen = faults.perceived(truth, planar.task_axes)
    offsets = np.array([s.position - t.position for s, t in zip(seen, truth, strict=True)])
    assert np.all(offsets[:, 2] == 0) and np.all(np.abs(offsets[:, :2]) > 0)  # in the arm's plane only
    np.testing.assert_allclose(offsets, faults.obstacle_offsets(2, planar.task_axes), rtol=0, atol=1e-15)
    many = faults.obstacle_offsets(4000, (0, 1, 2))
    assert np.std(many) == pytest.approx(0.02, rel=4 / math.sqrt(2 * many.size))
    ctrl, _, traj = _run(planar, faults, duration=0.1, obstacles=seen, world=truth, v0=np.array([0.5, -0.5, 0.5]))
    assert [o.position.tolist() for o in ctrl.obstacles] == [o.position.tolist() for o in seen]
    world, mapped = WorldClearance(planar, truth), WorldClearance(planar, seen)
    for k in range(0, len(traj.t), 10):
        assert traj.clearance[k] == world(traj.q[k], traj.t[k])  # recorded: the true obstacles
        assert abs(traj.clearance[k] - mapped(traj.q[k], traj.t[k])) > 1e-4
    with pytest.raises(ConfigError) as exc:  # the truth must be given when the map is wrong
        Simulator(ctrl, dt=1e-3, duration=0.01, faults=faults)
    assert exc.value.key == "faults.obstacle_noise"


def test_unknown_obstacle_velocity_moves_the_true_obstacles_only(planar):
    truth = [Obstacle("sphere", np.array([-0.4, -1.3, 0.0]), radius=0.12)]
    faults = Faults(obstacle_velocity=0.5, seed=1)
    ctrl, sim, traj = _run(planar, faults, duration=0.2, obstacles=truth)
    drift = sim.obstacles[0].velocity
    assert np.linalg.norm(drift) == pytest.approx(0.5) and drift[2] == 0.0
    assert not ctrl.obstacles[0].moving  # the controller's map: still
    moved = [Obstacle("sphere", truth[0].position + drift * t, radius=0.12) for t in (0.0, 0.1, 0.2)]
    for t, obs in zip((0.0, 0.1, 0.2), moved, strict=True):
        k = round(t / 1e-3)
        assert traj.clearance[k] == pytest.approx(WorldClearance(planar, [obs])(traj.q[k], 0.0), abs=1e-12)


# -- whole runs through the scenario -----------------------------------------------------------------------
MODERATE = ["faults.q_noise=1e-4", "faults.v_noise=1e-2", "faults.delay_ticks=1", "faults.mass_error=0.1",
            "faults.payload_mass=0.5", "faults.payload_time=0.1", "faults.obstacle_noise=0.01",
            "sim.duration=0.3"]


def test_same_seed_same_run_other_seed_other_run():
    runs = [simulate(Scenario.load("paper", MODERATE + [f"faults.seed={s}"]), kind="qp").trajectory
            for s in (1, 1, 2)]
    for name in ("q", "tau", "tau_command", "clearance"):
        np.testing.assert_array_equal(getattr(runs[0], name), getattr(runs[1], name))
    assert np.max(np.abs(runs[0].tau - runs[2].tau)) > 1e-3


def test_a_fault_free_run_is_the_ideal_one_bit_for_bit(planar):
    """Faults all off: the ideal loop; and the faulty loop with a fault that does nothing (drives that
    saturate at inf) reproduces it bit for bit: the same states, torques and clearances."""
    assert not Faults().active and not Faults(torque_saturation=float("inf"), seed=3).sensing
    obstacle = [Obstacle("sphere", np.array([-0.3, -1.2, 0.0]), radius=0.15)]
    runs = [_run(planar, f, duration=0.1, obstacles=obstacle, v0=np.array([0.4, -0.2, 0.3]))[2]
            for f in (None, Faults(), Faults(torque_saturation=float("inf")))]
    assert runs[0].tau_command is None and runs[1].tau_command is None and runs[2].tau_command is not None
    for run in runs[1:]:
        for name in ("q", "v", "tau", "clearance", "x_ref"):
            np.testing.assert_array_equal(getattr(run, name), getattr(runs[0], name))
        np.testing.assert_allclose(run.x, runs[0].x, rtol=0, atol=1e-14)


def test_scenario_runs_are_judged_by_the_true_world_and_the_nominal_d_safe():
    scen = Scenario.load("paper", ["faults.obstacle_noise=0.02", "faults.seed=3", "controller.d_safe_margin=\"auto\"",
                                   "sim.duration=0.2"])
    res = simulate(scen, kind="qp")
    truth = scen.build_obstacles()
    assert [o.position.tolist() for o in res.controller.obstacles] != [o.position.tolist() for o in truth]
    world = WorldClearance(res.controller.robot, truth)
    for k in (0, 100, 200):
        assert res.trajectory.clearance[k] == world(res.trajectory.q[k], res.trajectory.t[k])
    assert res.metrics["d_safe_margin"] == pytest.approx(0.06)  # 3σ of the map; no joint noise
    assert res.controller.gains.d_safe == pytest.approx(0.05 + 0.06)
    assert res.metrics["safety_violated"] == bool(res.metrics["min_clearance"] < 0.05 - 1e-9)
    assert res.metrics["faults"] == {"obstacle_noise": 0.02, "seed": 3}


# -- the margin ----------------------------------------------------------------------------------------------
def test_auto_margin_is_three_sigma_of_the_map_and_the_joint_noise_through_the_reach(planar):
    scen = Scenario.load("paper", ["faults.obstacle_noise=0.01", "faults.q_noise=1e-4", "faults.q_quantum=2e-4",
                                   'controller.d_safe_margin="auto"'])
    # the paper arm reaches 3 m from its base; 3 joints, each off by at most 3σ + Δ/2
    expected = 3 * 0.01 + (3 * 1e-4 + 1e-4) * 3.0 * 3
    assert scen.d_safe_margin() == pytest.approx(expected)
    assert scen.gains().d_safe == pytest.approx(0.05 + expected)
    assert Scenario.load("paper", ['controller.d_safe_margin="auto"']).gains().d_safe == 0.05  # no faults: none
    assert Scenario.load("paper", ["controller.d_safe_margin=0.02"]).gains().d_safe == pytest.approx(0.07)
    assert Scenario.load("paper").gains().d_safe == 0.05


# -- validation ----------------------------------------------------------------------------------------------
BAD = [
    ("faults.q_nois=1e-3", "faults.q_nois"),
    ("faults.q_noise=-1e-3", "faults.q_noise"),
    ('faults.q_noise="a"', "faults.q_noise"),
    ("faults.q_noise=nan", "faults.q_noise"),
    ("faults.q_quantum=inf", "faults.q_quantum"),
    ("faults.v_noise=-0.1", "faults.v_noise"),
    ("faults.delay_ticks=-1", "faults.delay_ticks"),
    ("faults.delay_ticks=1.5", "faults.delay_ticks"),
    ("faults.miss_rate=1.0", "faults.miss_rate"),
    ("faults.miss_rate=-0.1", "faults.miss_rate"),
    ("faults.torque_lag=-0.01", "faults.torque_lag"),
    ("faults.torque_saturation=0", "faults.torque_saturation"),
    ("faults.torque_saturation=[100.0, 100.0]", "faults.torque_saturation"),
    ("faults.mass_error=1.0", "faults.mass_error"),
    ("faults.payload_mass=-0.5", "faults.payload_mass"),
    ("faults.payload_time=-1", "faults.payload_time"),
    ("faults.payload_radius=0", "faults.payload_radius"),
    ("faults.obstacle_noise=-0.01", "faults.obstacle_noise"),
    ("faults.obstacle_velocity=nan", "faults.obstacle_velocity"),
    ("faults.seed=1.5", "faults.seed"),
    ("robot.payload_mass=-0.5", "robot.payload_mass"),
    ("robot.payload_radius=0", "robot.payload_radius"),
    ("controller.d_safe_margin=-0.01", "controller.d_safe_margin"),
    ('controller.d_safe_margin="big"', "controller.d_safe_margin"),
    ("controller.d_safe_margin=0.3", "controller.d_safe_margin"),  # d_safe + margin ≥ d_influence
]


@pytest.mark.parametrize("override, key", BAD, ids=[b[0] for b in BAD])
def test_bad_faults_are_named(override, key):
    with pytest.raises(ConfigError) as exc:
        Scenario.load("paper", [override])
    assert exc.value.key == key, str(exc.value)


def test_faults_refused_by_mujoco_and_reported_on_the_command_line(tmp_path):
    with pytest.raises(ConfigError) as exc:
        Scenario.load("paper", ["faults.q_noise=1e-4", 'sim.simulator="mujoco"'])
    assert exc.value.key == "faults"
    with pytest.raises(ConfigError) as exc:
        simulate(Scenario.load("paper", ["faults.q_noise=1e-4"]), simulator="mujoco")
    assert exc.value.key == "faults"
    cmd = [sys.executable, "-m", "qpctl.cli", "simulate", "paper", "--set", "faults.miss_rate=2", "--out",
           str(tmp_path / "x")]
    proc = subprocess.run(cmd, check=False, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "faults.miss_rate" in proc.stderr


def test_the_readmes_faults_example_is_a_valid_table():
    readme = (Path(__file__).resolve().parents[1] / "docs" / "reliability.md").read_text()  # Faults and robustness
    block = next(b for b in re.findall(r"```toml\n(.*?)```", readme, flags=re.DOTALL) if b.startswith("[faults]"))
    raw = tomllib.loads(block)
    scen = Scenario.from_dict({**tomllib.loads((Path(__file__).resolve().parents[1] / "qpctl" / "scenarios"
                                                / "paper.toml").read_text()), **raw})
    assert scen.faults() == Faults(**raw["faults"]) and scen.faults().active


def test_an_orientation_task_with_self_collision_rows_is_recorded_alike_through_the_faulty_loop():
    """panda_harvest (position + approach axis, self-collision rows): drives that saturate at inf switch
    the faulty loop on and change nothing, so it records what the ideal loop does — x as the position
    columns, the quaternions, the orientation error and the self clearance."""
    runs = [simulate(Scenario.load("panda_harvest", ["sim.duration=0.3"] + extra), kind="qp").trajectory
            for extra in ([], ["faults.torque_saturation=inf"])]
    ideal, faulty = runs
    assert ideal.tau_command is None and faulty.tau_command is not None
    assert faulty.x.shape == (301, 3) and faulty.quat is not None and faulty.self_clearance is not None
    for name in ("q", "tau", "clearance", "self_clearance", "quat", "quat_ref", "orientation_error_deg", "x_ref"):
        np.testing.assert_array_equal(getattr(faulty, name), getattr(ideal, name))
    np.testing.assert_allclose(faulty.x, ideal.x, rtol=0, atol=1e-14)
