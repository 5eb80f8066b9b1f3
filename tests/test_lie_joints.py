"""Configurations on a Lie group (issue 24, part B item 1): continuous and planar joints.

Each check against an independent computation: the group operations against finite differences of
Pinocchio's Jacobians and plain angle arithmetic; runs on a continuous-joint robot against the same
robot written with bounded revolute joints (nq == nv, the code path of every other robot); a planar
base against the same base written as two slides and a hinge.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from qpctl import Scenario
from qpctl.errors import ConfigError
from qpctl.robot.model import LinkCapsule, RobotModel
from qpctl.simulation.faults import Faults, FaultState
from qpctl.simulation.simulator import Simulator

KINOVA = "package://example-robot-data/robots/kinova_description/robots/kinova.urdf"


def _kinova(**robot_keys: object) -> RobotModel:
    raw = {"robot": {"kind": "urdf", "urdf": KINOVA, "ee_frame": "j2s6s200_end_effector", "srdf": "none",
                     **robot_keys},
           "path": {"waypoints": [[0.2, -0.3, 0.5]], "durations": [1.0]}, "sim": {"duration": 0.01}}
    return Scenario.from_dict(raw).build_robot()


def _twin(robot: RobotModel, replace: dict[str, pin.JointModel]) -> RobotModel:
    """The same robot with the joints of kind ``k`` in ``replace`` rebuilt as ``replace[k]``: the same
    bodies, frames, capsules and limits, another configuration space."""
    src = robot.model
    model = pin.Model()
    model.name = src.name
    model.gravity = src.gravity
    for j in range(1, src.njoints):
        jm = replace.get(src.joints[j].shortname(), src.joints[j])
        jid = model.addJoint(int(src.parents[j]), jm, src.jointPlacements[j], src.names[j])
        model.appendBodyToJoint(jid, src.inertias[j], pin.SE3.Identity())
    for f in list(src.frames)[1:]:
        model.addFrame(pin.Frame(f.name, f.parentJoint, f.parentFrame, f.placement, f.type, f.inertia), False)
    return RobotModel(name=robot.name + "-twin", model=model, ee_frame=robot.ee_frame, task_axes=robot.task_axes,
                      capsules=list(robot.capsules), q_min=robot.q_min, q_max=robot.q_max, v_max=robot.v_max,
                      tau_max=robot.tau_max, q_home=robot.angles(robot.q_home))


def _wrap(a: np.ndarray) -> np.ndarray:
    return np.angle(np.exp(1j * np.asarray(a)))


def test_kinova_loads_with_continuous_joints() -> None:
    robot = _kinova()
    assert (robot.nq, robot.nv) == (9, 6)
    assert robot.lie and robot.q_home.shape == (9,)
    # continuous joints are unlimited, the bounded ones keep their URDF limits
    assert list(np.isinf(robot.q_min)) == [True, False, False, True, False, True]
    assert robot.q_min[1] == pytest.approx(0.8203047, abs=1e-6)


def test_angles_and_configuration_are_inverse() -> None:
    robot = _kinova()
    rng = np.random.default_rng(1)
    a = rng.uniform(-np.pi, np.pi, (20, robot.nv))
    a[:, 1:3] = rng.uniform(1.0, 5.0, (20, 2))
    q = robot.configuration(a)
    assert q.shape == (20, 9)
    assert np.allclose(robot.angles(q), a, atol=1e-14)
    # each continuous joint's (cos, sin) is a unit vector
    assert np.allclose(q[:, 0] ** 2 + q[:, 1] ** 2, 1.0)


def test_integrate_and_difference_against_jacobian_finite_differences() -> None:
    """d/dε p(q ⊕ εv) at 0 equals J(q) v (central differences, every frame's position and rotation),
    difference inverts integrate, and the angles of q ⊕ dv are the angles of q plus dv (mod 2π)."""
    robot = _kinova()
    model, data = robot.model, robot.model.createData()
    rng = np.random.default_rng(2)
    eps = 1e-6
    fid = robot.ee_frame_id
    for _ in range(5):
        a = rng.uniform(-np.pi, np.pi, robot.nv)
        a[1:3] = rng.uniform(1.0, 5.0, 2)
        q, v = robot.configuration(a), rng.normal(size=robot.nv)
        J = pin.computeFrameJacobian(model, data, q, fid, pin.LOCAL_WORLD_ALIGNED)
        poses = []
        for s in (eps, -eps):
            pin.framesForwardKinematics(model, data, robot.integrate(q, s * v))
            poses.append(data.oMf[fid].copy())
        lin = (poses[0].translation - poses[1].translation) / (2 * eps)
        ang = pin.log3(poses[0].rotation @ poses[1].rotation.T) / (2 * eps)
        assert np.allclose(lin, J[:3] @ v, atol=1e-7)
        assert np.allclose(ang, J[3:] @ v, atol=1e-7)
        dv = rng.uniform(-3, 3, robot.nv)
        q1 = robot.integrate(q, dv)
        assert np.allclose(robot.difference(q, q1), dv, atol=1e-12)
        assert np.allclose(_wrap(robot.angles(q1) - (a + dv)), 0.0, atol=1e-12)


def _planar_arm() -> RobotModel:
    """A planar base (x, y, θ) carrying a two-link arm (hinges about y, then z), gravity along −z."""
    model = pin.Model()
    base = model.addJoint(0, pin.JointModelPlanar(), pin.SE3.Identity(), "base")
    model.appendBodyToJoint(base, pin.Inertia(20.0, np.array([0.1, 0.0, 0.1]), np.diag([0.5, 0.6, 0.8])),
                            pin.SE3.Identity())
    j1 = model.addJoint(base, pin.JointModelRY(), pin.SE3(np.eye(3), np.array([0.2, 0.0, 0.3])), "shoulder")
    model.appendBodyToJoint(j1, pin.Inertia(3.0, np.array([0.0, 0.0, 0.25]), np.diag([0.06, 0.06, 0.01])),
                            pin.SE3.Identity())
    j2 = model.addJoint(j1, pin.JointModelRZ(), pin.SE3(np.eye(3), np.array([0.0, 0.0, 0.5])), "elbow")
    model.appendBodyToJoint(j2, pin.Inertia(2.0, np.array([0.2, 0.0, 0.0]), np.diag([0.01, 0.03, 0.03])),
                            pin.SE3.Identity())
    model.addFrame(pin.Frame("tool", j2, 0, pin.SE3(np.eye(3), np.array([0.4, 0.0, 0.0])), pin.FrameType.OP_FRAME))
    caps = [LinkCapsule("base", base, np.zeros(3), np.array([0.2, 0.0, 0.0]), 0.1),
            LinkCapsule("upper", j1, np.zeros(3), np.array([0.0, 0.0, 0.5]), 0.05),
            LinkCapsule("fore", j2, np.zeros(3), np.array([0.4, 0.0, 0.0]), 0.04)]
    inf = np.full(5, np.inf)
    return RobotModel(name="planar-base", model=model, ee_frame="tool", task_axes=(0, 1, 2), capsules=caps,
                      q_min=-inf, q_max=inf, v_max=inf, tau_max=np.array([200.0, 200.0, 100.0, 80.0, 40.0]),
                      q_home=np.array([0.0, 0.0, 0.3, 0.6, 0.4]))


def test_planar_base_integrate_against_jacobian() -> None:
    robot = _planar_arm()
    assert (robot.nq, robot.nv) == (6, 5) and robot.dof_names[:3] == ["base.x", "base.y", "base.theta"]
    model, data = robot.model, robot.model.createData()
    rng = np.random.default_rng(3)
    eps = 1e-6
    for _ in range(5):
        q, v = robot.configuration(rng.uniform(-2, 2, 5)), rng.normal(size=5)
        J = pin.computeFrameJacobian(model, data, q, robot.ee_frame_id, pin.LOCAL_WORLD_ALIGNED)
        p = []
        for s in (eps, -eps):
            pin.framesForwardKinematics(model, data, robot.integrate(q, s * v))
            p.append(data.oMf[robot.ee_frame_id].translation.copy())
        assert np.allclose((p[0] - p[1]) / (2 * eps), J[:3] @ v, atol=1e-7)
        dv = rng.uniform(-1, 1, 5)
        assert np.allclose(robot.difference(q, robot.integrate(q, dv)), dv, atol=1e-12)


def test_planar_base_free_motion_matches_slides_and_hinge() -> None:
    """No torque, a moving start: the planar base's RK4 run and the same robot written as slides along
    x, y and a hinge about z (velocities in the world frame: ẋ, ẏ = R(θ) v_xy) follow the same motion."""
    robot = _planar_arm()
    src = robot.model
    model = pin.Model()
    px = model.addJoint(0, pin.JointModelPX(), pin.SE3.Identity(), "base_x")
    model.appendBodyToJoint(px, pin.Inertia.Zero(), pin.SE3.Identity())
    py = model.addJoint(px, pin.JointModelPY(), pin.SE3.Identity(), "base_y")
    model.appendBodyToJoint(py, pin.Inertia.Zero(), pin.SE3.Identity())
    ids = {1: model.addJoint(py, pin.JointModelRZ(), pin.SE3.Identity(), "base_theta")}
    model.appendBodyToJoint(ids[1], src.inertias[1], pin.SE3.Identity())
    for j in range(2, src.njoints):
        ids[j] = model.addJoint(ids[int(src.parents[j])], src.joints[j], src.jointPlacements[j], src.names[j])
        model.appendBodyToJoint(ids[j], src.inertias[j], pin.SE3.Identity())
    a0, v0 = np.array([0.3, -0.2, 0.7, 0.5, -0.4]), np.array([0.4, -0.3, 0.8, 1.0, -0.6])
    q, v = robot.configuration(a0), v0.copy()
    c, s = np.cos(a0[2]), np.sin(a0[2])
    qs, vs = a0.copy(), np.concatenate([[c * v0[0] - s * v0[1], s * v0[0] + c * v0[1]], v0[2:]])
    d1, d2 = src.createData(), model.createData()
    from qpctl.simulation.simulator import rk4_step

    zero = np.zeros(5)
    for _ in range(500):
        q, v = rk4_step(lambda qq, vv: pin.aba(src, d1, qq, vv, zero), q, v, 1e-3, robot.integrate)
        qs, vs = rk4_step(lambda qq, vv: pin.aba(model, d2, qq, vv, zero), qs, vs, 1e-3)
    assert np.allclose(robot.angles(q), qs, atol=1e-9)
    pin.framesForwardKinematics(src, d1, q)
    pin.forwardKinematics(model, d2, qs)
    assert np.allclose(d1.oMi[3].translation, d2.oMi[ids[3]].translation, atol=1e-9)


def test_free_flyer_is_refused() -> None:
    model = pin.Model()
    root = model.addJoint(0, pin.JointModelFreeFlyer(), pin.SE3.Identity(), "float")
    model.appendBodyToJoint(root, pin.Inertia.Random(), pin.SE3.Identity())
    model.addFrame(pin.Frame("tool", root, 0, pin.SE3.Identity(), pin.FrameType.OP_FRAME))
    inf = np.full(6, np.inf)
    with pytest.raises(ConfigError, match="free-flyer.*contact"):
        RobotModel(name="floating", model=model, ee_frame="tool", task_axes=(0, 1, 2), capsules=[], q_min=-inf,
                   q_max=inf, v_max=inf, tau_max=inf, q_home=np.zeros(6))


@pytest.mark.parametrize("kind", ["qp", "hsu"])
def test_continuous_joints_run_as_their_revolute_twin(kind: str) -> None:
    """The compiled tick on the Kinova (continuous joints 1, 4, 6: nq 9, nv 6) and on its twin with
    bounded-revolute joints there (nq = nv = 6, unlimited), from the same start, with a posture task
    and obstacles: the same torques and motion. Covers the kernels' angle view, the posture's
    pin.difference, the joint-limit rows (none on continuous joints) and RK4 on the group."""
    robot = _kinova()
    twin = _twin(robot, {"JointModelRUBZ": pin.JointModelRZ()})
    assert not twin.lie and np.allclose(twin.q_min, robot.q_min, equal_nan=True)
    a0 = np.array([3.0, 2.9, 1.3, -2.8, 2.0, 3.1])  # near ±π on the continuous joints: wrapping matters
    raw = {"robot": {"kind": "urdf", "urdf": KINOVA, "ee_frame": "j2s6s200_end_effector", "srdf": "none",
                     "q0": a0.tolist()},
           "path": {"waypoints": [[0.15, -0.35, 0.45]], "durations": [0.4]},
           "obstacles": [{"shape": "sphere", "position": [0.1, -0.45, 0.55], "radius": 0.05}],
           "controller": {"kind": kind, "v_ref": 0.3, "d_influence": 0.2, "d_safe": 0.02},
           "sim": {"dt": 1e-3, "duration": 0.4}}
    # the posture across ±π from q0 on joints 4 and 6: the Kinova's pulls the short way round (its error
    # is pin.difference), as the twin's does with those targets moved by ∓2π
    posture = np.array([2.5, 3.0, 1.5, 2.9, 2.2, -3.0])
    postures = (posture, posture + np.array([0, 0, 0, -2, 0, 2]) * np.pi)
    runs = []
    for r, p in zip((robot, twin), postures):
        if kind == "qp":
            raw["controller"].update(posture_weight=5.0, posture=p.tolist())
        ctrl = Scenario.from_dict(raw).build_controller(robot=r)
        sim = Simulator(ctrl, dt=1e-3, duration=0.4)
        runs.append(sim.run(a0))
    lie, plain = runs
    assert lie.q.shape == (401, 9) and plain.q.shape == (401, 6)
    assert np.abs(lie.tau).max() > 1.0  # it did something
    assert np.allclose(lie.tau, plain.tau, atol=1e-6 * np.abs(plain.tau).max())
    assert np.allclose(_wrap(robot.angles(lie.q) - plain.q), 0.0, atol=1e-9)
    assert np.allclose(lie.clearance, plain.clearance, atol=1e-9)


def test_faults_read_angles_on_continuous_joints() -> None:
    robot = _kinova()
    state = FaultState(Faults(q_noise=0.01, q_quantum=0.001, seed=4), robot.nv, 1e-3, robot)
    q = robot.configuration([3.1, 2.0, 1.0, -3.1, 2.0, 0.5])
    qm, _ = state.measure(q, np.zeros(6))
    assert qm.shape == (9,) and np.allclose(qm[[0, 4, 7]] ** 2 + qm[[1, 5, 8]] ** 2, 1.0)
    err = _wrap(robot.angles(qm) - robot.angles(q))
    assert 0 < np.abs(err).max() < 0.06  # noise of 0.01 rad, not a 2π jump at ±π
    assert np.allclose(np.round(robot.angles(qm) / 0.001) * 0.001, robot.angles(qm), atol=1e-9)


def test_scenario_q0_posture_and_trajectory_angles(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from qpctl.run import simulate, write_outputs

    raw = {"name": "kinova-angles",
           "robot": {"kind": "urdf", "urdf": KINOVA, "ee_frame": "j2s6s200_end_effector", "srdf": "none",
                     "q0": [3.0, 2.9, 1.3, -2.8, 2.0, 3.1]},
           "path": {"waypoints": [[0.15, -0.35, 0.45]], "durations": [0.1]},
           "controller": {"kind": "qp"}, "sim": {"duration": 0.1}}
    scenario = Scenario.from_dict(raw)
    robot = scenario.build_robot()
    q0 = scenario.q0(robot)
    assert np.allclose(q0[:2], [np.cos(3.0), np.sin(3.0)])
    result = simulate(scenario)
    write_outputs(result, tmp_path, figures=False, replay=False)
    with np.load(tmp_path / "trajectory.npz") as npz:
        assert npz["q"].shape == (101, 9) and npz["angles"].shape == (101, 6)
        assert np.allclose(npz["angles"][0], raw["robot"]["q0"])
        assert np.allclose(robot.configuration(npz["angles"]), npz["q"], atol=1e-12)
    with pytest.raises(ConfigError, match="robot.q0.*6 joint values"):
        Scenario.from_dict({**raw, "robot": {**raw["robot"], "q0": [0.0] * 9}})


@pytest.mark.parametrize("simulator", ["mujoco", "pybullet", "drake"])
def test_continuous_joints_in_the_adapters_match_the_builtin_simulator(simulator: str) -> None:
    """The adapters map Pinocchio's (cos θ, sin θ) to their hinges' angles and back: the Kinova's run
    in MuJoCo (RK4) and in PyBullet and Drake (semi-implicit Euler; Drake on the URDF qpctl writes, as
    it cannot parse the Kinova's own: a material defined twice) equals the built-in simulator's."""
    import dataclasses

    pytest.importorskip({"mujoco": "mujoco", "pybullet": "pybullet", "drake": "pydrake"}[simulator])
    raw = {"robot": {"kind": "urdf", "urdf": KINOVA, "ee_frame": "j2s6s200_end_effector", "srdf": "none",
                     "q0": [3.0, 2.9, 1.3, -2.8, 2.0, 3.1]},
           "path": {"waypoints": [[0.15, -0.35, 0.45]], "durations": [0.3]},
           "controller": {"kind": "hsu"}, "sim": {"duration": 0.3}}
    scenario = Scenario.from_dict(raw)
    robot = scenario.build_robot()
    q0 = scenario.q0(robot)
    if simulator == "mujoco":
        from qpctl.adapters.mujoco import MujocoSimulator as Sim
    elif simulator == "pybullet":
        from qpctl.adapters.pybullet import PybulletSimulator as Sim  # type: ignore[assignment]
    else:
        from qpctl.adapters.drake import DrakeSimulator as Sim  # type: ignore[assignment]
        robot = dataclasses.replace(robot, urdf=None, capsules=list(robot.capsules))
    integrator = "rk4" if simulator == "mujoco" else "euler"
    ref = Simulator(scenario.build_controller(robot=robot), dt=1e-3, duration=0.3, integrator=integrator).run(q0)
    sim = Sim(scenario.build_controller(robot=robot), dt=1e-3, duration=0.3)
    out = sim.run(q0)
    assert out.q.shape == (301, 9)
    assert np.abs(out.q - ref.q).max() < 1e-12
    assert np.abs(out.tau - ref.tau).max() < 1e-9 * np.abs(ref.tau).max()
    assert np.abs(robot.angles(out.q[-1]) - robot.angles(q0)).max() > 0.01  # it moved


def test_planar_base_is_refused_by_the_adapters() -> None:
    pytest.importorskip("mujoco")
    from qpctl.adapters.mujoco import MujocoSimulator
    from qpctl.controllers.closed_form import HsuController

    robot = _planar_arm()
    from qpctl.paths import WaypointPath

    ctrl = HsuController(robot, WaypointPath([[0.6, 0.0, 0.8], [0.8, 0.2, 0.8]], duration=1.0))
    with pytest.raises(ConfigError, match="sim.simulator.*planar"):
        MujocoSimulator(ctrl, duration=0.01)


def test_planar_base_qp_reaches_beyond_the_arm() -> None:
    """The QP on the planar base (x, y, θ): a target 1.5 m away, beyond the arm's 0.9 m, reached by
    moving the base, past a sphere; checked by forward kinematics of the recorded configuration."""
    from qpctl.controllers.qp import QPController
    from qpctl.geometry.obstacles import Obstacle
    from qpctl.paths import WaypointPath

    robot = _planar_arm()
    data = robot.model.createData()
    pin.framesForwardKinematics(robot.model, data, robot.q_home)
    start = data.oMf[robot.ee_frame_id].translation.copy()
    goal = start + np.array([1.2, 0.9, -0.1])
    path = WaypointPath([start, goal], duration=3.0)
    sphere = Obstacle("sphere", np.array([0.9, 0.0, 0.3]), radius=0.1)
    ctrl = QPController(robot, path, [sphere])
    traj = Simulator(ctrl, dt=1e-3, duration=3.5).run(robot.q_home)
    pin.framesForwardKinematics(robot.model, data, traj.q[-1])
    assert np.linalg.norm(data.oMf[robot.ee_frame_id].translation - goal) < 5e-3
    assert traj.clearance.min() > 0
    assert np.linalg.norm(traj.angles[-1, :2] - traj.angles[0, :2]) > 0.5  # the base carried the arm there


def test_kinova_picks_three_fruits_among_branches() -> None:
    """examples/kinova_branches.toml: the QP on the Kinova with its fitted capsules and SRDF pairs; each
    fruit within 5 mm at the end of its dwell (forward kinematics of the recorded configuration), no
    collision, and joint 1 through ±π (its angle wraps, the motion does not jump)."""
    from pathlib import Path

    from qpctl.run import simulate

    scenario = Scenario.load(Path(__file__).parent.parent / "examples" / "kinova_branches.toml")
    robot = scenario.build_robot()
    assert robot.lie and robot.srdf is not None and robot.srdf.name == "kinova.srdf"
    result = simulate(scenario, progress=False)
    m, traj = result.metrics, result.trajectory
    assert not m["collided"] and m["min_clearance"] > 0.0
    path = scenario.data["path"]
    fruits = np.array(path["waypoints"])
    arrive = np.cumsum(path["durations"]) + path["dwell"] * np.arange(len(fruits))
    data = robot.model.createData()
    for fruit, t_arrive in zip(fruits, arrive):
        k = int(np.searchsorted(traj.t, min(t_arrive + path["dwell"], traj.t[-1]) - 1e-9))
        pin.framesForwardKinematics(robot.model, data, traj.q[k])
        assert np.linalg.norm(data.oMf[robot.ee_frame_id].translation - fruit) <= 5e-3
    theta = traj.angles[:, 0]
    assert theta.max() > 3.0 and theta.min() < -3.0  # both sides of ±π
    assert np.abs(_wrap(np.diff(theta))).max() < 2e-3  # 1 ms steps at ≤ 0.63 rad/s: no jump in the motion


def test_a_runs_scenario_toml_reads_back_with_its_robot_files(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """scenario.toml beside a run (Scenario.to_toml) names robot.capsules by an absolute path, so that
    `qpctl replay RUN_DIR` reads it back from anywhere (the examples' capsules files are relative)."""
    from pathlib import Path

    src = Scenario.load(Path(__file__).parent.parent / "examples" / "kinova_branches.toml")
    (tmp_path / "scenario.toml").write_text(src.to_toml())
    back = Scenario.load(tmp_path / "scenario.toml")
    assert Path(back.data["robot"]["capsules"]).is_absolute()
    assert [c.name for c in back.build_robot().capsules] == [c.name for c in src.build_robot().capsules]


def test_the_kernels_angle_view_is_robot_angles() -> None:
    """qpctl.kernels.lie.joint_angles (the compiled tick's per-tick view) against RobotModel.angles, on
    the Kinova's continuous joints and a planar base."""
    from qpctl.kernels.lie import joint_angles

    rng = np.random.default_rng(5)
    for robot in (_kinova(), _planar_arm()):
        out = np.empty(robot.nv)
        for _ in range(10):
            q = robot.configuration(rng.uniform(-np.pi, np.pi, robot.nv))
            joint_angles(q, robot._plain_q, robot._plain_v, robot._rot_q, robot._rot_v, out)
            assert np.array_equal(out, robot.angles(q))
