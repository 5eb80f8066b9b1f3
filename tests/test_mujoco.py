"""The MuJoCo adapter: the generated MJCF is Pinocchio's robot, and a controller behaves the same in
MuJoCo as in the built-in simulator.

* Dynamics of the generated MJCF: M(q) (``mj_fullM``) and the bias forces C(q, q̇)q̇ + G(q)
  (``qfrc_bias``) against Pinocchio's CRBA and ``nonLinearEffects`` on random states, for the planar
  arm and the Panda. Measured: relative differences ≤ 1.6e-15 (round-off); bound 1e-12. The Panda is
  also compiled by MuJoCo itself from the mesh-stripped URDF (fingers fixed), an independent reading
  of the same file: measured ≤ 2.2e-15; bound 1e-12.
* Agreement of whole runs. Both simulators hold the torque over the step (zero-order hold) and run
  classical RK4 on the same model with the same step, so they differ only by round-off: MuJoCo's
  stage 1 reuses the ``mj_forward`` at the start state and stages 2–4 call ``mj_forwardSkip``, its
  accelerations come from the CRB inertia's LDLᵀ factorisation instead of Pinocchio's ABA. Measured
  on the paper scenario, 1 s (1001 ticks), largest differences over the run, paper law / hsu / QP
  (proxqp): q 4.7e-16 / 6.9e-17 / 3.3e-16 rad, q̇ 4.0e-15 / 2.8e-16 / 6.2e-15 rad/s,
  τ 1.4e-12 / 6.5e-13 / 1.9e-11 N·m, x 6.7e-16 / 2.2e-16 / 6.7e-16 m, clearance 5.6e-16 / 0 / 6.1e-16 m.
  Round-off moves with every change to the laws' arithmetic, so the bounds are about 10× the largest
  figure measured over the versions of the laws seen while writing this (paper law up to
  6.7e-16 rad, 6.7e-15 rad/s, 1.4e-12 N·m, 1.4e-15 m; QP up to 4.4e-16 rad, 7.1e-15 rad/s,
  1.9e-11 N·m). For scale, a real mismatch is many orders larger: MuJoCo's Euler against our RK4
  differs by 1.1e-3 rad in q over the same second. (The full 5 s paper run agrees to 1.8e-15 rad;
  1 s keeps the file fast.)
  On the Panda (panda_canopy, 0.5 s) hsu agrees to 1.1e-16 rad / 9.9e-14 N·m, the paper law to
  2.5e-11 rad / 1.5e-9 N·m — its null-space self-motion under gravity amplifies round-off (see the
  README); bounds about 10×.
"""

from __future__ import annotations

import json
import re

import numpy as np
import pinocchio as pin
import pytest

mujoco = pytest.importorskip("mujoco")

from qpctl import ConfigError, Obstacle, Scenario, Simulator, WaypointPath
from qpctl.adapters import JointMap
from qpctl.adapters.mujoco import (
    MujocoJoints,
    MujocoSimulator,
    build_model,
    full_inertia,
    robot_mjcf,
)
from qpctl.robot.model import example_robot_data_path

# Bounds on max |builtin − MuJoCo| over a run (see module docstring for the measurements).
PAPER_BOUNDS = {"q": 1e-14, "v": 1e-13, "tau": 1e-11, "x": 1e-14, "clearance": 1e-14}
QP_BOUNDS = {"q": 5e-15, "v": 7e-14, "tau": 2e-10, "x": 1e-14}
PANDA_BOUNDS = {"hsu": {"q": 1e-15, "tau": 1e-12}, "paper": {"q": 3e-10, "tau": 2e-8}}


def _pinocchio_terms(robot, q, v):
    data = robot.model.createData()
    M = pin.crba(robot.model, data, q)
    M = np.triu(M) + np.triu(M, 1).T
    return M, pin.nonLinearEffects(robot.model, data, q, v)


def _mujoco_terms(mj_model, robot, q, v):
    data = mujoco.MjData(mj_model)
    joints = MujocoJoints.for_robot(mj_model, robot)
    joints.write_state(data, q, v)
    mujoco.mj_forward(mj_model, data)
    return joints.select(full_inertia(mj_model, data)), data.qfrc_bias[joints.dof_adr].copy()


def _assert_same_dynamics(mj_model, robot, states):
    for q, v in states:
        M_mj, b_mj = _mujoco_terms(mj_model, robot, q, v)
        M_pin, b_pin = _pinocchio_terms(robot, q, v)
        np.testing.assert_allclose(M_mj, M_pin, rtol=0, atol=1e-12 * np.abs(M_pin).max())
        np.testing.assert_allclose(b_mj, b_pin, rtol=0, atol=1e-12 * max(1.0, np.abs(b_pin).max()))


@pytest.mark.parametrize("robot_name", ["planar", "panda_robot"])
def test_generated_mjcf_has_pinocchios_dynamics(robot_name, request, random_states):
    robot = request.getfixturevalue(robot_name)
    mj_model = build_model(robot)
    assert mj_model.nv == robot.nv and np.allclose(mj_model.opt.gravity, robot.model.gravity.linear)
    assert not np.any(mj_model.dof_damping) and not np.any(mj_model.dof_armature)
    np.testing.assert_allclose(mj_model.body_mass[1:], [robot.model.inertias[j].mass
                                                        for j in range(1, robot.model.njoints)])
    _assert_same_dynamics(mj_model, robot, random_states(robot, 10))


def test_panda_urdf_compiled_by_mujoco_matches_pinocchio(panda_robot, random_states):
    """MuJoCo's own reading of the URDF (meshes stripped, fingers fixed) against Pinocchio's reduced model."""
    text = example_robot_data_path("panda_description/urdf/panda.urdf").read_text()
    text = re.sub(r"<(visual|collision)>.*?</\1>", "", text, flags=re.DOTALL)
    text = re.sub(r"<mimic[^>]*/>", "", text)
    text = re.sub(r'(<joint name="panda_finger_joint\d" )type="prismatic"', r'\1type="fixed"', text)
    fuse = '<mujoco><compiler fusestatic="true"/></mujoco>'
    text = re.sub(r"<robot ([^>]*)>", r"<robot \1>" + fuse, text, count=1)
    mj_model = mujoco.MjModel.from_xml_string(text)
    assert mj_model.nv == 7
    _assert_same_dynamics(mj_model, panda_robot, random_states(panda_robot, 10))


def _both(scenario, kind, duration):
    ctrl = scenario.build_controller(kind)
    q0 = scenario.q0(ctrl.robot)
    dt = scenario.data["sim"]["dt"]
    builtin = Simulator(ctrl, dt=dt, duration=duration).run(q0)
    mj = MujocoSimulator(scenario.build_controller(kind), dt=dt, duration=duration).run(q0)
    return builtin, mj


def _max_diff(a, b, key):
    return float(np.max(np.abs(getattr(a, key) - getattr(b, key))))


@pytest.mark.parametrize("kind", ["paper", "hsu"])
def test_paper_scenario_agrees_with_builtin_simulator(kind):
    scenario = Scenario.load("paper", ["sim.duration=1.0"])
    builtin, mj = _both(scenario, kind, 1.0)
    np.testing.assert_array_equal(builtin.t, mj.t)
    for key, bound in PAPER_BOUNDS.items():
        assert _max_diff(builtin, mj, key) <= bound, (key, _max_diff(builtin, mj, key))
    np.testing.assert_allclose(mj.x_ref, builtin.x_ref, rtol=0, atol=0)


def test_qp_agrees_with_builtin_simulator():
    """The QP controller (proxqp) runs unchanged in MuJoCo."""
    pytest.importorskip("qpctl.controllers.qp")
    scenario = Scenario.load("paper", ["sim.duration=1.0", "controller.solver=proxqp"])
    builtin, mj = _both(scenario, "qp", 1.0)
    for key, bound in QP_BOUNDS.items():
        assert _max_diff(builtin, mj, key) <= bound, (key, _max_diff(builtin, mj, key))


@pytest.mark.parametrize("kind", ["hsu", "paper"])
def test_panda_canopy_agrees_with_builtin_simulator(kind):
    scenario = Scenario.load("panda_canopy", ["sim.duration=0.5"])
    builtin, mj = _both(scenario, kind, 0.5)
    for key, bound in PANDA_BOUNDS[kind].items():
        assert _max_diff(builtin, mj, key) <= bound, (key, _max_diff(builtin, mj, key))


def test_simulate_writes_the_same_outputs_under_mujoco(tmp_path):
    from qpctl.run import simulate, write_outputs

    scenario = Scenario.load("paper", ["sim.duration=0.05"])
    written = {}
    for sim in ("builtin", "mujoco"):
        result = simulate(scenario, simulator=sim)
        write_outputs(result, tmp_path / sim, figures=False)
        written[sim] = (np.load(tmp_path / sim / "trajectory.npz"),
                        json.loads((tmp_path / sim / "metrics.json").read_text()))
    (npz_b, met_b), (npz_m, met_m) = written["builtin"], written["mujoco"]
    assert sorted(npz_b.files) == sorted(npz_m.files)
    for key in npz_b.files:
        if key != "tick_us":
            np.testing.assert_allclose(npz_m[key], npz_b[key], rtol=0, atol=1e-10, err_msg=key)
    assert set(met_b) == set(met_m) and met_m["simulator"] == "mujoco"
    assert met_m["max_tracking_error"] == pytest.approx(met_b["max_tracking_error"], abs=1e-12)


# -- joint map ----------------------------------------------------------------------------------
def test_joint_map_permutes_and_round_trips():
    jm = JointMap.from_names(["c", "a", "b"], ["a", "b", "c"])
    np.testing.assert_array_equal(jm.sim_index, [1, 2, 0])
    np.testing.assert_array_equal(jm.to_model(np.array([3.0, 1.0, 2.0])), [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(jm.to_sim(np.array([1.0, 2.0, 3.0])), [3.0, 1.0, 2.0])
    assert not jm.identity and JointMap.from_names(["a", "b"], ["a", "b"]).identity


def test_joint_map_mismatch_names_both_sets():
    with pytest.raises(ConfigError) as exc:
        JointMap.from_names(["joint1", "elbow", "joint3", "gripper"], ["joint1", "joint2", "joint3"])
    msg = str(exc.value)
    for name in ("joint1", "joint2", "joint3", "elbow", "gripper"):
        assert name in msg
    assert "missing from the simulator: joint2" in msg and "unknown to the model: elbow, gripper" in msg
    with pytest.raises(ConfigError, match="missing from the simulator: joint2"):
        JointMap.from_names(["joint1", "elbow", "joint3"], ["joint1", "joint2", "joint3"], allow_extra=True)
    with pytest.raises(ConfigError, match="repeats joint1"):
        JointMap.from_names(["joint1", "joint1", "joint2", "joint3"], ["joint1", "joint2", "joint3"])


def test_mujoco_model_with_other_joint_names_is_refused(planar):
    xml = robot_mjcf(planar).replace('name="joint2"', 'name="elbow"')
    path = WaypointPath([[-1.0, -2.0], [-0.5, -1.5]], duration=1.0)
    from baselines.paper import PaperController

    with pytest.raises(ConfigError) as exc:
        MujocoSimulator(PaperController(planar, path), model=mujoco.MjModel.from_xml_string(xml))
    assert "joint2" in str(exc.value) and "elbow" in str(exc.value)


def test_extra_mujoco_joints_are_mapped_by_address(planar):
    """A free-floating body before the arm shifts qpos by 7 and qvel by 6; the run must not change."""
    from baselines.paper import PaperController

    extra = ('<body name="apple" pos="1 1 0"><freejoint name="apple"/>'
             '<inertial pos="0 0 0" mass="0.1" diaginertia="1e-4 1e-4 1e-4"/></body>')
    xml = re.sub(r"(<worldbody>)", r"\1" + extra, robot_mjcf(planar), count=1)
    model = mujoco.MjModel.from_xml_string(xml)
    path = WaypointPath([[-1.0, -2.0], [-0.5, -1.5]], duration=0.2)
    with pytest.raises(ConfigError, match="unknown to the model: apple"):
        MujocoSimulator(PaperController(planar, path), model=model)
    ref = MujocoSimulator(PaperController(planar, path), dt=1e-3, duration=0.2).run(planar.q_home)
    sim = MujocoSimulator(PaperController(planar, path), dt=1e-3, duration=0.2, model=model,
                          allow_extra_joints=True)
    np.testing.assert_array_equal(sim.joints.qpos_adr, [7, 8, 9])
    np.testing.assert_array_equal(sim.joints.dof_adr, [6, 7, 8])
    out = sim.run(planar.q_home)
    np.testing.assert_allclose(out.q, ref.q, rtol=0, atol=1e-14)


def test_obstacles_are_contact_free_geoms_and_moving_ones_follow_their_motion(planar):
    from baselines.paper import PaperController

    obstacles = [Obstacle("sphere", np.array([0.0, -1.2, 0.0]), radius=0.15, name="A"),
                 Obstacle("capsule", np.array([0.6, -0.6, 0.0]), radius=0.05, length=0.4, name="B",
                          axis=np.array([1.0, 0.0, 0.0]), amplitude=np.array([0.1, 0.0, 0.0]), frequency=2.0),
                 Obstacle("box", np.array([2.0, 0.0, 0.0]), size=np.array([0.2, 0.4, 0.6]))]
    path = WaypointPath([[-1.0, -2.0], [-0.5, -1.5]], duration=0.1)
    sim = MujocoSimulator(PaperController(planar, path, obstacles), dt=1e-3, duration=0.1)
    model = sim.model
    assert not np.any(model.geom_contype) and not np.any(model.geom_conaffinity)
    box = model.geom("obstacle2")
    np.testing.assert_allclose(box.size, [0.1, 0.2, 0.3])
    traj = sim.run(planar.q_home)
    mocap = model.body("B").mocapid[0]
    np.testing.assert_allclose(sim.data.mocap_pos[mocap], obstacles[1].position_at(traj.t[-1]), atol=1e-12)
    assert np.all(np.isfinite(traj.clearance))


def test_bad_arguments_raise_config_errors(planar):
    from baselines.paper import PaperController

    path = WaypointPath([[-1.0, -2.0], [-0.5, -1.5]], duration=1.0)
    with pytest.raises(ConfigError, match="integrator"):
        MujocoSimulator(PaperController(planar, path), integrator="verlet")
    with pytest.raises(ConfigError, match="sim.dt"):
        MujocoSimulator(PaperController(planar, path), dt=0.0)
    with pytest.raises(ConfigError, match="q0"):
        MujocoSimulator(PaperController(planar, path), duration=0.01).run(np.zeros(2))


def test_scenario_integrator_reaches_mujoco():
    """``sim.integrator`` reaches MuJoCo under ``--sim mujoco`` (it used to run RK4 whatever the scenario
    said): for each integrator the MuJoCo run agrees with the built-in simulator's run with the same
    integrator (classical RK4, or semi-implicit Euler in both) to round-off — PAPER_BOUNDS; measured
    over 0.3 s: RK4 4.7e-16 rad / 4.0e-15 rad/s / 8.5e-13 N·m, Euler 3.9e-16 rad / 2.9e-15 rad/s /
    7.7e-13 N·m — while MuJoCo's Euler run differs from the built-in RK4 run by ~1e-3 rad (measured
    1.06e-3), far beyond round-off."""
    from qpctl.run import simulate

    runs = {}
    for integrator in ("rk4", "euler"):
        scenario = Scenario.load("paper", ["sim.duration=0.3", f"sim.integrator={integrator}"])
        for which in ("builtin", "mujoco"):
            result = simulate(scenario, simulator=which)
            assert result.metrics["simulator"] == which
            runs[integrator, which] = result.trajectory
    for integrator in ("rk4", "euler"):
        builtin, mj = runs[integrator, "builtin"], runs[integrator, "mujoco"]
        np.testing.assert_array_equal(builtin.t, mj.t)
        assert builtin.t[-1] == pytest.approx(0.3)
        for key in ("q", "v", "tau", "x"):
            assert np.all(np.isfinite(getattr(mj, key)))
            assert _max_diff(builtin, mj, key) <= PAPER_BOUNDS[key], (integrator, key, _max_diff(builtin, mj, key))
    assert _max_diff(runs["euler", "mujoco"], runs["rk4", "builtin"], "q") > 1e-5


# -- the user's own MJCF: its joint names, its actuators, its inertias ------------------------------
EXAMPLES = __import__("pathlib").Path(__file__).resolve().parents[1] / "examples"
MY_ARM = EXAMPLES / "my_arm.xml"
MY_NAMES = ["shoulder", "elbow", "wrist"]


def test_hand_written_mjcf_with_geared_motors_agrees_over_5_s():
    """examples/my_arm.xml: joints shoulder/elbow/wrist, motor actuators with gear 100: driven through
    the TOML (sim.model relative to examples/my_arm.toml) and through the API, the paper law's 5 s run
    agrees with the built-in simulator to ≤ 1e-8 rad (measured 1.2e-15 rad both ways)."""
    from qpctl.run import simulate

    scenario = Scenario.load(EXAMPLES / "my_arm.toml")
    assert scenario.data["sim"]["duration"] == 5.0
    q0 = scenario.q0(scenario.build_robot())
    builtin = Simulator(scenario.build_controller(), dt=1e-3, duration=5.0).run(q0)
    toml = simulate(scenario)
    assert toml.metrics["simulator"] == "mujoco" and toml.metrics["ctrl_clamped_ticks"] == 0
    assert any("shoulder × 100" in n for n in toml.metrics["simulator_notes"])
    api = MujocoSimulator(scenario.build_controller(), dt=1e-3, duration=5.0, model=MY_ARM, joint_names=MY_NAMES)
    assert api.dynamics.same and list(api.actuation.scale) == [100.0] * 3
    api_traj = api.run(q0)
    for traj in (toml.trajectory, api_traj):
        assert np.max(np.abs(traj.q - builtin.q)) <= 1e-8
        np.testing.assert_allclose(traj.tau, builtin.tau, rtol=0, atol=1e-5)
    assert np.max(np.abs(builtin.q[-1] - builtin.q[0])) > 1.0  # the arm did move


def _my_arm(tmp_path, old, new, name="arm.xml"):
    path = tmp_path / name
    path.write_text(MY_ARM.read_text().replace(old, new))
    return path


def test_servo_actuators_become_motors_with_a_note(tmp_path, planar):
    """Position servos (as in Menagerie's Panda) left in the MJCF would pull the arm toward ctrl = 0:
    in a file, they are turned into motors (MjSpec set_to_motor) and said so in one line, and the run
    is the built-in one."""
    servo = _my_arm(tmp_path, '<motor gear="100" ctrlrange="-5 5"/>', '<position kp="500" kv="50"/>')
    servo.write_text(servo.read_text().replace("<motor ", "<position "))
    ctrl = _paper_controller(planar, 0.5)
    sim = MujocoSimulator(ctrl, duration=0.5, model=servo, joint_names=MY_NAMES)
    notes = [n for n in sim.notes if "turned into motors" in n]
    assert len(notes) == 1 and notes[0].count("kp 500, kv 50") == 3
    assert len(sim.actuation.motor_ids) == 3 and np.all(sim.model.actuator_biasprm == 0)
    assert np.all(sim.model.actuator_ctrllimited == 0)  # a position range is no torque limit
    ref = Simulator(_paper_controller(planar, 0.5), dt=1e-3, duration=0.5).run(planar.q_home)
    assert np.max(np.abs(sim.run(planar.q_home).q - ref.q)) <= 1e-12


def _paper_controller(planar, duration):
    """The paper law on a 1 s reach (torques within the motors' ±500 N·m), for a run of ``duration``."""
    from baselines.paper import PaperController

    assert duration <= 1.0
    return PaperController(planar, WaypointPath([[-1.0, -2.0], [-0.5, -1.5]], duration=1.0))


def test_ctrlrange_clamping_is_counted_and_reported(tmp_path, planar):
    """ctrlrange ±0.5 with gear 100 caps the torque at 50 N·m: the ticks at which it acted are counted —
    the same count as the recorded commands exceeding 50 N·m, computed here — and reported."""
    path = _my_arm(tmp_path, 'ctrlrange="-5 5"', 'ctrlrange="-0.5 0.5"')
    sim = MujocoSimulator(_paper_controller(planar, 0.2), duration=0.2, model=path, joint_names=MY_NAMES)
    traj = sim.run(planar.q_home)
    expected = int(np.count_nonzero(np.any(np.abs(traj.tau[:-1]) > 50.0, axis=1)))
    assert expected > 0 and sim.counts["ctrl_clamped_ticks"] == expected
    assert any("clamped the torque on" in n for n in sim.notes)


def test_inertia_mismatch_is_reported_with_its_size(tmp_path, planar):
    path = _my_arm(tmp_path, 'mass="10"', 'mass="12"')  # every link 20 % heavier
    sim = MujocoSimulator(_paper_controller(planar, 0.1), duration=0.1, model=path, joint_names=MY_NAMES)
    assert not sim.dynamics.same and sim.dynamics.m_rel > 0.1
    note = next(n for n in sim.notes if "DIFFER" in n)
    assert f"{sim.dynamics.m_abs:.2g}" in note
    # matched by order (no names given), a mismatch is refused: the order is not trusted blindly
    with pytest.raises(ConfigError, match="sim.joint_names"):
        MujocoSimulator(_paper_controller(planar, 0.1), duration=0.1, model=path)


def test_joints_matched_by_order_when_no_name_matches(planar):
    sim = MujocoSimulator(_paper_controller(planar, 0.1), duration=0.1, model=MY_ARM)
    assert any("matched by order: joint1 → shoulder" in n for n in sim.notes)
    ref = MujocoSimulator(_paper_controller(planar, 0.1), duration=0.1).run(planar.q_home)
    np.testing.assert_allclose(sim.run(planar.q_home).q, ref.q, rtol=0, atol=1e-14)


@pytest.mark.parametrize(("sets", "key"), [
    (['sim.model="no_such.xml"'], "sim.model"),
    (["sim.model=3"], "sim.model"),
    (['sim.model=""', 'sim.joint_names=["a", "b", "c"]'], "sim.joint_names"),  # without sim.model
    (['sim.model="my_arm.xml"', 'sim.joint_names=["shoulder", "elbow"]'], "sim.joint_names"),
    (['sim.model="my_arm.xml"', "sim.joint_names=5"], "sim.joint_names"),
    (['sim.simulator="gazebo"'], "sim.simulator"),
])
def test_new_sim_keys_are_validated(sets, key):
    with pytest.raises(ConfigError) as exc:
        Scenario.load(EXAMPLES / "my_arm.toml", sets)
    assert exc.value.key == key and (exc.value.source in ("--set", str(EXAMPLES / "my_arm.toml")))


def test_unknown_sim_key_in_file_names_file_and_key(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text((EXAMPLES / "my_arm.toml").read_text().replace("[sim]\n", "[sim]\nmodle = \"x.xml\"\n"))
    with pytest.raises(ConfigError, match="sim.modle") as exc:
        Scenario.load(bad)
    assert str(bad) in str(exc.value)


def test_pybullet_refuses_an_mjcf_naming_the_key(tmp_path):
    pytest.importorskip("pybullet")
    from qpctl.run import simulate

    with pytest.raises(ConfigError, match="sim.model") as exc:
        simulate(Scenario.load(EXAMPLES / "my_arm.toml", ["sim.duration=0.01"]), simulator="pybullet")
    assert "my_arm.toml" in str(exc.value)


def test_panda_with_menagerie_style_position_servos_runs_as_builtin():
    """The Panda's MJCF with a position servo on every joint (kp 4500, kv 450, as MuJoCo Menagerie's
    Panda has them) given as ``model=``: the servos are switched off and the hsu run is the built-in
    one (measured 2.5e-15 rad over 2 s; left on, the same loop diverges within 2 ms)."""
    scenario = Scenario.load("panda_canopy", ["sim.duration=0.5"])
    ctrl = scenario.build_controller("hsu")
    acts = "".join(f'<position joint="{n}" kp="4500" kv="450"/>' for n in ctrl.robot.joint_names)
    xml = robot_mjcf(ctrl.robot, ctrl.obstacles).replace("</mujoco>", f"<actuator>{acts}</actuator></mujoco>")
    model = mujoco.MjModel.from_xml_string(xml)
    q0 = scenario.q0(ctrl.robot)
    sim = MujocoSimulator(ctrl, dt=1e-3, duration=0.5, model=model)
    assert sum("switched off" in n for n in sim.notes) == 7 and sim.dynamics.same
    assert model.actuator_gainprm[0, 0] == 4500  # the user's MjModel is left as it was (a copy is changed)
    builtin = Simulator(scenario.build_controller("hsu"), dt=1e-3, duration=0.5).run(q0)
    assert np.max(np.abs(sim.run(q0).q - builtin.q)) <= 1e-12
