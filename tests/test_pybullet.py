"""The PyBullet adapter: the model PyBullet loads is the controller's robot, PyBullet's defaults that
would fight a torque controller are undone, and a controller behaves in PyBullet as in the built-in
simulator with the same integrator.

* Dynamics: M(q) (``calculateMassMatrix``) and the bias forces (``calculateInverseDynamics`` at
  q̈ = 0) against Pinocchio's CRBA and ``nonLinearEffects``, computed here, on random states: the
  generated URDF of the planar arm (measured 5e-16 relative) and the Panda's own URDF as
  example-robot-data ships it (fingers fixed: 3e-11, the URDF's printed digits); bound 1e-9.
* Whole runs: PyBullet steps with semi-implicit Euler, so on the paper arm it agrees with the
  built-in ``integrator = "euler"`` to round-off (measured 1.1e-16 rad over 1 s; bound 1e-12) and
  differs from the built-in RK4 by the method's error (1.1e-3 rad).
* The Panda's URDF declares joint damping (0.003 N·m·s/rad) that Pinocchio does not read. Left in,
  PyBullet's q̈ differs from ABA's by 1.8e-2 relative on random states (|v| ≤ 1 rad/s) — it did
  while ``jointDamping=0`` shared a ``changeDynamics`` call with ``maxJointVelocity``, which PyBullet
  3.2.7 then ignores. Set to 0, the forward step agrees with ABA to 2.6e-10 relative (bound 1e-8),
  and the adapter says it removed the damping.
"""

from __future__ import annotations

import json

import numpy as np
import pinocchio as pin
import pytest

pybullet = pytest.importorskip("pybullet")

from qpctl import ConfigError, Obstacle, Scenario, Simulator, WaypointPath
from qpctl.adapters import simulator_class
from qpctl.adapters.pybullet import PybulletSimulator, robot_urdf
from qpctl.run import simulate, write_outputs


def _paper_controller(planar, obstacles=(), duration=0.2):
    from baselines.paper import PaperController

    return PaperController(planar, WaypointPath([[-1.0, -2.0], [-0.5, -1.5]], duration=duration), list(obstacles))


def _assert_pinocchio_dynamics(sim, robot, states, rtol):
    data = robot.model.createData()
    for q, v in states:
        M = pin.crba(robot.model, data, q)
        M = np.triu(M) + np.triu(M, 1).T
        N = pin.nonLinearEffects(robot.model, data, q, v)
        M_pb, N_pb = sim._terms(q, v)
        np.testing.assert_allclose(M_pb, M, rtol=0, atol=rtol * np.abs(M).max())
        np.testing.assert_allclose(N_pb, N, rtol=0, atol=rtol * max(1.0, np.abs(N).max()))


def test_registry_resolves_pybullet():
    assert simulator_class("pybullet") is PybulletSimulator
    with pytest.raises(ConfigError, match="one of builtin, mujoco, pybullet"):
        simulator_class("gazebo")


@pytest.mark.parametrize("robot_name", ["planar", "panda_robot"])
def test_loaded_model_has_pinocchios_dynamics(robot_name, request, random_states):
    robot = request.getfixturevalue(robot_name)
    from baselines.hsu import HsuController

    m = len(robot.task_axes)
    ctrl = HsuController(robot, WaypointPath([np.full(m, 0.1), np.full(m, 0.2)], duration=1.0))
    sim = PybulletSimulator(ctrl, duration=0.01)
    assert sim.dynamics.same
    _assert_pinocchio_dynamics(sim, robot, random_states(robot, 6), 1e-9)
    if robot_name == "panda_robot":  # the URDF's own file, fingers fixed, its joint damping removed
        assert robot.urdf is not None and sim.joint_ids == list(range(7))
        assert "<dynamics" in robot.urdf.read_text()
        assert sim.forward_rel <= 1e-8 and any("joint damping set to 0" in n for n in sim.notes)
    else:
        assert sim.forward_rel < 1e-12 and not sim.notes
    # the forward check itself, independently: one PyBullet step from a random state against ABA + Euler
    data = robot.model.createData()
    for q, v in random_states(robot, 3):
        sim.reset(q, v)
        sim.apply(np.zeros(robot.nv))
        sim.step(0.0)
        a = pin.aba(robot.model, data, q, v, np.zeros(robot.nv))
        np.testing.assert_allclose((sim.read()[1] - v) / sim.dt, a, rtol=0, atol=1e-7 * max(1.0, np.abs(a).max()))


def test_zero_torque_run_is_the_builtin_euler_run(planar):
    """Velocity motors off, damping off: with no torque at all the arm falls exactly as ABA + semi-implicit
    Euler says (a default velocity motor would hold it, default damping would slow it)."""
    q0 = np.array([0.3, -0.5, 0.8])
    sim = PybulletSimulator(_paper_controller(planar), dt=1e-3, duration=0.3)
    sim.reset(q0)
    data = planar.model.createData()
    q, v = q0.copy(), np.zeros(3)
    for k in range(300):
        sim.apply(np.zeros(3))
        sim.step(k * 1e-3)
        v = v + 1e-3 * pin.aba(planar.model, data, q, v, np.zeros(3))
        q = q + 1e-3 * v
    q_pb, v_pb = sim.read()
    assert np.max(np.abs(v)) > 1.0  # it did fall
    np.testing.assert_allclose(q_pb, q, rtol=0, atol=1e-12)
    np.testing.assert_allclose(v_pb, v, rtol=0, atol=1e-11)


def test_paper_scenario_agrees_with_builtin_euler():
    scenario = Scenario.load("paper", ["sim.duration=1.0", "sim.integrator=euler"])
    ctrl = scenario.build_controller("paper")
    q0 = scenario.q0(ctrl.robot)
    euler = Simulator(ctrl, dt=1e-3, duration=1.0, integrator="euler").run(q0)
    rk4 = Simulator(scenario.build_controller("paper"), dt=1e-3, duration=1.0).run(q0)
    pb = PybulletSimulator(scenario.build_controller("paper"), dt=1e-3, duration=1.0).run(q0)
    np.testing.assert_array_equal(pb.t, euler.t)
    for key, bound in (("q", 1e-12), ("v", 1e-10), ("tau", 1e-8), ("x", 1e-12)):
        assert np.max(np.abs(getattr(pb, key) - getattr(euler, key))) <= bound, key
    assert np.max(np.abs(pb.q - rk4.q)) > 1e-5  # the integrators do differ: the comparison can fail


def test_panda_canopy_qp_keeps_clearance_and_tracks(tmp_path):
    """The issue's target on a shortened run (the README's table has the full 6 s): clearance
    ≥ d_safe − 1 mm, tracking within 1 mm, as in the built-in run; same outputs written."""
    pytest.importorskip("qpctl.controllers.qp")
    scenario = Scenario.load("panda_canopy", ["sim.duration=0.6"])
    runs = {}
    for which in ("builtin", "pybullet"):
        result = simulate(scenario, kind="qp", simulator=which)
        write_outputs(result, tmp_path / which, figures=False)
        runs[which] = json.loads((tmp_path / which / "metrics.json").read_text())
    d_safe = scenario.data["controller"]["d_safe"]
    b, p = runs["builtin"], runs["pybullet"]
    assert p["simulator"] == "pybullet" and not p["collided"]
    assert p["min_clearance"] >= d_safe - 1e-3 and b["min_clearance"] >= d_safe - 1e-3
    assert p["max_tracking_error"] <= 1e-3 and abs(p["max_tracking_error"] - b["max_tracking_error"]) <= 1e-3
    assert not any("forward dynamics" in n for n in p["simulator_notes"])
    npz_b, npz_p = np.load(tmp_path / "builtin" / "trajectory.npz"), np.load(tmp_path / "pybullet" / "trajectory.npz")
    assert sorted(npz_b.files) == sorted(npz_p.files)


def test_users_urdf_with_own_joint_names(planar, tmp_path):
    text = robot_urdf(planar)
    for i, name in enumerate(["shoulder", "elbow", "wrist"]):
        text = text.replace(f'name="joint{i + 1}"', f'name="{name}"')
    (tmp_path / "arm.urdf").write_text(text)
    ref = PybulletSimulator(_paper_controller(planar), duration=0.2).run(planar.q_home)
    named = PybulletSimulator(_paper_controller(planar), duration=0.2, model=tmp_path / "arm.urdf",
                              joint_names=["shoulder", "elbow", "wrist"])
    np.testing.assert_array_equal(named.run(planar.q_home).q, ref.q)
    by_order = PybulletSimulator(_paper_controller(planar), duration=0.2, model=tmp_path / "arm.urdf")
    assert any("matched by order" in n for n in by_order.notes)
    np.testing.assert_array_equal(by_order.run(planar.q_home).q, ref.q)
    # a heavier forearm: named joints run with the mismatch reported; matched by order, refused
    (tmp_path / "heavy.urdf").write_text(text.replace('<mass value="10"', '<mass value="12"', 1))
    heavy = PybulletSimulator(_paper_controller(planar), duration=0.2, model=tmp_path / "heavy.urdf",
                              joint_names=["shoulder", "elbow", "wrist"])
    assert not heavy.dynamics.same and heavy.dynamics.m_abs > 0.1
    assert any("DIFFER" in n for n in heavy.notes)
    with pytest.raises(ConfigError, match="sim.joint_names"):
        PybulletSimulator(_paper_controller(planar), duration=0.2, model=tmp_path / "heavy.urdf")
    with pytest.raises(ConfigError, match="sim.joint_names"):
        PybulletSimulator(_paper_controller(planar), duration=0.2, model=tmp_path / "arm.urdf", joint_names=["a"])
    with pytest.raises(ConfigError, match="sim.model"):
        PybulletSimulator(_paper_controller(planar), duration=0.2, model=tmp_path / "missing.urdf")


def test_obstacles_are_ghost_bodies_and_moving_ones_follow(planar):
    obstacles = [Obstacle("sphere", np.array([0.0, -1.2, 0.0]), radius=0.15, name="A"),
                 Obstacle("capsule", np.array([0.6, -0.6, 0.0]), radius=0.05, length=0.4, name="B",
                          axis=np.array([1.0, 0.0, 0.0]), amplitude=np.array([0.1, 0.0, 0.0]), frequency=2.0),
                 Obstacle("box", np.array([2.0, 0.0, 0.0]), size=np.array([0.2, 0.4, 0.6]))]
    sim = PybulletSimulator(_paper_controller(planar, obstacles, 0.1), duration=0.1)
    for body, _ in sim._obstacle_bodies:
        assert pybullet.getCollisionShapeData(body, -1, physicsClientId=sim.client) == ()
    traj = sim.run(planar.q_home)
    expected = np.array([o.position_at(traj.t[-1]) for o in obstacles])
    np.testing.assert_allclose(sim.obstacle_positions(), expected, atol=1e-12)
    assert abs(expected[1, 0] - 0.6) > 1e-3  # B did move
