"""MJCF robots (qpctl.robot.mjcf; ``robot.kind = "mjcf"``) and MuJoCo on their own files.

Independent references: MuJoCo's own compilation of the same file (``mj_fullM``, ``qfrc_bias``,
body poses), python-fcl distances from the geoms' points to the fitted capsules, the actuators as
written in the file.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import trimesh

mujoco = pytest.importorskip("mujoco")

from test_capsule_fit import FCL_TOL, fcl_signed_distance

from qpctl import Scenario
from qpctl.adapters.mujoco import MujocoSimulator, full_inertia
from qpctl.errors import ConfigError
from qpctl.robot.mjcf import from_mjcf
from qpctl.robot.model import example_robot_data_path
from qpctl.simulation.simulator import Simulator

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
ARM = EXAMPLES / "mjcf_arm.xml"


@pytest.fixture(scope="module")
def panda_mjcf(tmp_path_factory) -> Path:
    """example-robot-data's Panda URDF compiled by MuJoCo and saved as MJCF: mesh geoms, boxes, armature-free."""
    folder = tmp_path_factory.mktemp("panda_mjcf")
    urdf = example_robot_data_path("panda_description/urdf/panda.urdf")
    text = re.sub(r"<visual>.*?</visual>", "", urdf.read_text(), flags=re.DOTALL)
    text = text.replace("package://example-robot-data/robots/panda_description/meshes/", "")
    text = re.sub(r"(<robot name=\"panda\"[^>]*>)", rf'\1<mujoco><compiler meshdir="{urdf.parents[1] / "meshes"}" '
                  r'fusestatic="false"/></mujoco>', text)
    (folder / "panda.urdf").write_text(text)
    model = mujoco.MjModel.from_xml_path(str(folder / "panda.urdf"))
    mujoco.mj_saveLastXML(str(folder / "panda.xml"), model)
    return folder / "panda.xml"


def mujoco_terms(mj, names, q, v):
    data = mujoco.MjData(mj)
    qadr = [mj.jnt_qposadr[mj.joint(n).id] for n in names]
    vadr = [mj.jnt_dofadr[mj.joint(n).id] for n in names]
    data.qpos[qadr], data.qvel[vadr] = q, v
    mujoco.mj_forward(mj, data)
    return full_inertia(mj, data)[np.ix_(vadr, vadr)], data.qfrc_bias[vadr].copy()


@pytest.mark.parametrize("which", ["arm", "panda"])
def test_mass_matrix_and_bias_forces_match_mujoco(which, panda_mjcf, random_states):
    path = ARM if which == "arm" else panda_mjcf
    robot = from_mjcf(path, "link5" if which == "arm" else "panda_hand", capsules=False)
    mj = mujoco.MjModel.from_xml_path(str(path))
    data = robot.model.createData()
    for q, v in random_states(robot, 6):
        M_mj, N_mj = mujoco_terms(mj, robot.joint_names, q, v)
        M = pin.crba(robot.model, data, q)
        M = np.triu(M) + np.triu(M, 1).T
        N = pin.nonLinearEffects(robot.model, data, q, v)
        assert np.max(np.abs(M - M_mj)) <= 1e-10 * max(1.0, np.abs(M_mj).max())
        assert np.max(np.abs(N - N_mj)) <= 1e-10 * max(1.0, np.abs(N_mj).max())
    if which == "arm":  # the file's armature is in both
        assert np.allclose(robot.model.armature, [0.05, 0.05, 0.05, 0.01, 0.01])


def test_links_are_placed_as_mujoco_places_its_bodies(rng):
    robot = from_mjcf(ARM, "tcp", capsules=False)
    mj = mujoco.MjModel.from_xml_path(str(ARM))
    mdata = mujoco.MjData(mj)
    data = robot.model.createData()
    q = rng.uniform(robot.q_min, robot.q_max)
    mdata.qpos[:] = q
    mujoco.mj_kinematics(mj, mdata)
    pin.framesForwardKinematics(robot.model, data, q)
    for b in range(1, mj.nbody):
        frame = data.oMf[robot.model.getFrameId(mj.body(b).name)]
        assert np.allclose(frame.translation, mdata.xpos[b], atol=1e-12)
        assert np.allclose(frame.rotation, mdata.xmat[b].reshape(3, 3), atol=1e-12)
    assert np.allclose(data.oMf[robot.ee_frame_id].translation, mdata.site_xpos[0], atol=1e-12)


def test_capsules_come_from_the_collision_geoms(rng):
    robot = from_mjcf(ARM, "tcp")
    caps = {c.name: c for c in robot.capsules}
    # link1's one geom is a capsule from (0, 0, 0) to (0, 0, 0.2), r 0.06: kept as it is
    c = caps["link1"]
    assert np.allclose(sorted([c.p0[2], c.p1[2]]), [0.0, 0.2]) and c.radius == pytest.approx(0.06)
    # link5's box (half sizes 0.05, 0.035, 0.02 at x = 0.05): its corners inside its capsules (python-fcl)
    corners = np.array([[0.05 + sx * 0.05, sy * 0.035, sz * 0.02] for sx in (-1, 1) for sy in (-1, 1)
                        for sz in (-1, 1)])
    mine = [c for c in robot.capsules if c.links == ("link5",)]
    assert np.min([fcl_signed_distance(corners, c.p0, c.p1, c.radius) for c in mine], axis=0).max() <= FCL_TOL
    # the visual-only geoms are not used: every capsule lies on a body with collision geoms
    assert {c.links[0] for c in robot.capsules} == {"base", "link1", "link2", "link3", "link4", "link5"}


def test_mesh_geoms_are_fitted(tmp_path):
    part = trimesh.creation.box(extents=[0.05, 0.06, 0.3])
    part.export(tmp_path / "part.stl")
    (tmp_path / "one.xml").write_text("""<mujoco><compiler meshdir="."/>
  <asset><mesh name="part" file="part.stl"/></asset>
  <worldbody><body name="b" pos="0 0 0.1"><joint name="j" axis="1 0 0"/><inertial pos="0 0 0" mass="1" diaginertia="0.01 0.01 0.01"/>
    <geom type="mesh" mesh="part" pos="0 0 0.15"/><site name="tip" pos="0 0 0.3"/></body></worldbody></mujoco>""")
    robot = from_mjcf(tmp_path / "one.xml", "tip")
    verts = np.asarray(part.vertices) + [0, 0, 0.15]
    d = np.min([fcl_signed_distance(verts, c.p0, c.p1, c.radius) for c in robot.capsules], axis=0)
    assert d.max() <= FCL_TOL
    assert all(c.joint_id == 1 for c in robot.capsules)


def test_torque_limits_from_the_actuators(tmp_path):
    (tmp_path / "acts.xml").write_text("""<mujoco><worldbody>
  <body name="a"><joint name="j1" axis="0 0 1"/><geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.04" mass="1"/>
   <body name="b" pos="0.3 0 0"><joint name="j2" axis="0 0 1" actuatorfrcrange="-20 20"/>
     <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.04" mass="1"/>
     <body name="c" pos="0.3 0 0"><joint name="j3" axis="0 0 1"/><geom type="sphere" size="0.03" mass="0.5"/>
      <body name="d" pos="0.1 0 0"><joint name="j4" axis="0 0 1"/><geom type="sphere" size="0.02" mass="0.2"/></body>
     </body></body></body></worldbody>
  <actuator>
    <motor joint="j1" gear="50" ctrlrange="-2 2"/>
    <position joint="j2" kp="100" gear="2" forcerange="-30 30" ctrlrange="-3 3"/>
    <position joint="j3" kp="100" ctrlrange="-3 3"/>
  </actuator></mujoco>""")
    robot = from_mjcf(tmp_path / "acts.xml", "d")
    # motor: ctrlrange 2 × gear 50; servo: forcerange 30 × gear 2 = 60, tighter joint actuatorfrcrange 20;
    # a servo's ctrlrange is a position, not a torque; no actuator: no limit
    assert list(robot.tau_max) == [100.0, 20.0, np.inf, np.inf]


def test_mujoco_runs_the_same_file_with_its_servos_as_motors(tmp_path):
    """Damping off (the controller's model has none): MuJoCo on the MJCF follows the built-in RK4 to
    round-off, with the servos turned into motors (torque through ctrl) and a one-line note."""
    xml = tmp_path / "arm.xml"
    xml.write_text(re.sub(r'damping="[0-9.]+"', 'damping="0"', ARM.read_text()))
    toml = tmp_path / "arm.toml"
    toml.write_text((EXAMPLES / "mjcf_arm.toml").read_text().replace('mjcf = "mjcf_arm.xml"', 'mjcf = "arm.xml"'))
    scenario = Scenario.load(toml, ["sim.duration=0.3", "controller.kind=paper"])
    robot = scenario.build_robot()
    assert robot.mjcf == xml.resolve() and robot.q_home[2] == pytest.approx(1.2)  # the "home" keyframe
    q0 = scenario.q0(robot)
    sim = MujocoSimulator.from_scenario(scenario.build_controller(), scenario)
    note = [n for n in sim.notes if "turned into motors" in n]
    assert len(note) == 1 and "5 servos" in note[0] and "act4 (kp 200, kv 20)" in note[0]
    assert len(sim.actuation.motor_ids) == 5 and sim.dynamics.same
    traj = sim.run(q0)
    ref = Simulator(scenario.build_controller(), dt=1e-3, duration=0.3).run(q0)
    assert np.max(np.abs(traj.q - ref.q)) <= 1e-9
    assert np.max(np.abs(ref.q[-1] - ref.q[0])) > 0.05  # it did move


def test_bad_mjcf_files_name_the_key(tmp_path):
    (tmp_path / "broken.xml").write_text("<mujoco><worldbody><body name='a'>")
    with pytest.raises(ConfigError, match=r"^robot\.mjcf: cannot parse broken\.xml"):
        from_mjcf(tmp_path / "broken.xml", "a")
    (tmp_path / "ball.xml").write_text("""<mujoco><worldbody><body name="a"><joint name="j" type="ball"/>
      <geom type="sphere" size="0.1" mass="1"/></body></worldbody></mujoco>""")
    with pytest.raises(ConfigError, match=r"robot\.mjcf: ball\.xml has joints .*nq 4 ≠ nv 3"):
        from_mjcf(tmp_path / "ball.xml", "a")
    (tmp_path / "mesh.xml").write_text("""<mujoco><asset><mesh name="m" file="gone.stl"/></asset><worldbody>
      <body name="a"><joint name="j"/><geom type="mesh" mesh="m" mass="1"/></body></worldbody></mujoco>""")
    with pytest.raises(ConfigError, match=r"^robot\.mjcf: .*gone\.stl"):
        from_mjcf(tmp_path / "mesh.xml", "a")
    raw = {"robot": {"kind": "mjcf", "ee_frame": "tcp"}, "path": {"waypoints": [[0.4, 0.0, 0.3]], "duration": 1.0}}
    with pytest.raises(ConfigError, match=r"robot\.mjcf: is required"):
        Scenario.from_dict(raw)
