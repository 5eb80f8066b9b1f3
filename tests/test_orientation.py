"""Orientation tasks (issue 11): the gripper's pose and approach direction, for every law.

Checked against independent computations: the compiled SO(3) exponential and logarithm against
Pinocchio's ``exp3``/``log3``; the slerp path's angular velocity and acceleration against finite
differences of its rotations; the task rows' error rates against finite differences on SO(3) along
the motion (exact for the approach rows; for the pose rows at zero error, where the log map's
Jacobian is the identity); the compiled rows against the Python ones (:mod:`qpctl.orientation`),
which use Pinocchio's frame functions; the QP against the closed form it generalises.
"""

from __future__ import annotations

import json

import numpy as np
import pinocchio as pin
import pytest

from qpctl import ConfigError, Scenario, Simulator, panda
from qpctl.cli import main
from qpctl.controllers.qp import QPConfig, QPController
from qpctl.kernels.rotation import exp3, log3
from qpctl.law import LawGains
from qpctl.orientation import (
    approach_rotations,
    frame_terms,
    orientation_reference,
    orientation_rows,
    rotation_error,
)
from qpctl.paths import PosePath

RNG = np.random.default_rng(11)


def _random_axis(rng: np.random.Generator) -> np.ndarray:
    a = rng.normal(size=3)
    return a / np.linalg.norm(a)


@pytest.mark.parametrize("regime", ["any", "small", "near_pi", "pi"])
def test_exp_and_log_kernels_match_pinocchio(regime):
    rng = np.random.default_rng({"any": 0, "small": 1, "near_pi": 2, "pi": 3}[regime])
    for _ in range(200):
        th = {"any": rng.uniform(0, np.pi), "small": 10 ** rng.uniform(-12, -2),
              "near_pi": np.pi - 10 ** rng.uniform(-9, -2), "pi": np.pi}[regime]
        w = th * _random_axis(rng)
        R = np.empty((3, 3))
        exp3(w, R)
        np.testing.assert_allclose(R, pin.exp3(w), atol=1e-15)
        out = np.empty(3)
        assert log3(pin.exp3(w), out) == pytest.approx(th, abs=1e-9)
        ref = pin.log3(pin.exp3(w))
        # at exactly a half turn ±w are the same rotation: compare the rotations then
        if regime == "pi":
            np.testing.assert_allclose(pin.exp3(out), pin.exp3(ref), atol=1e-12)
        else:
            np.testing.assert_allclose(out, ref, atol=1e-8 if regime == "near_pi" else 1e-14)


def _pose_path() -> PosePath:
    R0 = pin.exp3(np.array([0.2, -0.4, 0.1]))
    R1 = pin.exp3(np.array([1.0, 0.3, -0.5])) @ R0
    R2 = pin.exp3(np.array([-0.2, 0.9, 0.4])) @ R1
    return PosePath([[0.0, 0.0, 0.0], [0.2, 0.0, 0.1], [0.2, 0.0, 0.1]], [R0, R1, R2], duration=3.0, dwell=0.2)


def test_slerp_path_rates_are_its_rotations_derivatives():
    """ω_d = vee(Ṙ_d R_dᵀ) and ω̇_d by central differences of the path's own rotations; the rotations
    at the waypoints are the given ones; at rest at every waypoint; a pure turn gets time."""
    path = _pose_path()
    assert path.durations[1] == pytest.approx(0.1 * np.linalg.norm(path.theta[1]) / (
        0.1 * np.linalg.norm(path.theta[1]) + max(np.linalg.norm([0.2, 0, 0.1]), 0.1 * np.linalg.norm(path.theta[0])))
        * 3.0)
    h = 1e-5
    for t in np.linspace(0.05, path.end_time - 0.05, 40):
        R, w, a = path.orientation(t)
        Rp, Rm = path.orientation(t + h)[0], path.orientation(t - h)[0]
        w_fd = pin.log3(Rp @ Rm.T) / (2 * h)
        np.testing.assert_allclose(w, w_fd, atol=1e-7)
        a_fd = (path.orientation(t + h)[1] - path.orientation(t - h)[1]) / (2 * h)
        np.testing.assert_allclose(a, a_fd, atol=1e-5)
    for k, t in enumerate([path.starts[0], path.starts[1], path.end_time]):
        R, w, a = path.orientation(t)
        np.testing.assert_allclose(R, path.rotations[k], atol=1e-12)
        np.testing.assert_allclose(w, 0.0, atol=1e-12)


def _state(robot, rng):
    q = robot.q_home + rng.normal(size=robot.nv) * 0.3
    return np.clip(q, robot.q_min + 0.05, robot.q_max - 0.05), rng.normal(size=robot.nv)


def _rows(robot, path, q, v, t):
    """e, ė and ë at q̈ = 0, as the law sees them: x_d − x, ẋ_d − J q̇, ẍ_d − J̇q̇."""
    R, w, a, J = frame_terms(robot, q, v)
    Rd, wd, ad = path.orientation(t)
    x, xdot, _, drift = orientation_rows(robot, R, w, a, J, Rd, wd)
    xd, xdd, xddd = orientation_reference(robot, R, Rd, wd, ad)
    return xd - x, xdd - xdot, xddd - drift


def _along(robot, path, q, v, t, s):
    """The rows at time t + s, the joints having moved at constant q̇ (q̈ = 0)."""
    return _rows(robot, path, pin.integrate(robot.model, q, v * s), v, t + s)


def test_approach_rows_are_exact_derivatives():
    """ė and ë of the approach rows equal central differences along the motion at random states and
    errors of up to ~30° (the rows are exact, not linearised)."""
    robot = panda().with_orientation("approach")
    h = 1e-5
    for _ in range(10):
        q, v = _state(robot, RNG)
        R0 = frame_terms(robot, q, v)[0] @ pin.exp3(0.5 * RNG.normal(size=3))
        path = PosePath([[0.3, 0, 0.5], [0.4, 0, 0.5]], approach_rotations(R0, robot.approach_axis, [_random_axis(RNG)]),
                        duration=2.0)
        t = float(RNG.uniform(0.2, 1.8))
        e, ed, edd = _rows(robot, path, q, v, t)
        fd1 = (_along(robot, path, q, v, t, h)[0] - _along(robot, path, q, v, t, -h)[0]) / (2 * h)
        fd2 = (_along(robot, path, q, v, t, h)[1] - _along(robot, path, q, v, t, -h)[1]) / (2 * h)
        np.testing.assert_allclose(ed, fd1, atol=1e-6 * max(1.0, np.abs(ed).max()))
        np.testing.assert_allclose(edd, fd2, atol=1e-5 * max(1.0, np.abs(edd).max()))
        # e = 0 exactly when the approach axis points along the reference's (and not before)
        R, *_ = frame_terms(robot, q, v)
        assert np.linalg.norm(e) > 0 and np.linalg.norm(rotation_error(robot, R, path.orientation(t)[0])) > 0


def test_pose_rows_at_zero_error_are_exact():
    """The pose rows' ė = ω_d − ω is exact where the error is zero (the log map's Jacobian is the
    identity there): checked by central differences along the motion, on a reference that passes
    through the frame's orientation at t while turning at its own rate."""
    robot = panda().with_orientation("pose")
    h = 1e-6
    t, duration = 0.9, 2.0
    s = PosePath([[0, 0, 0], [0.1, 0, 0]], [np.eye(3), np.eye(3)], duration=duration).timing(t)[1]
    for _ in range(10):
        q, v = _state(robot, RNG)
        R = frame_terms(robot, q, v)[0]
        turn = 0.8 * _random_axis(RNG)
        R0 = pin.exp3(-s * turn) @ R  # so that R_d(t) = exp(s θ) R0 = R
        path = PosePath([[0, 0, 0], [0.1, 0, 0]], [R0, pin.exp3(turn) @ R0], duration=duration)
        np.testing.assert_allclose(path.orientation(t)[0], R, atol=1e-12)
        e, ed, _ = _rows(robot, path, q, v, t)
        np.testing.assert_allclose(e, 0.0, atol=1e-12)
        fd1 = (_along(robot, path, q, v, t, h)[0] - _along(robot, path, q, v, t, -h)[0]) / (2 * h)
        np.testing.assert_allclose(ed, fd1, atol=1e-6 * max(1.0, np.abs(ed).max()))
        assert np.abs(ed).max() > 0.1  # the frame and the reference do turn at different rates


@pytest.mark.parametrize("kind", ["pose", "approach"])
def test_compiled_rows_match_the_python_ones(kind):
    """The compiled tick's rows (x, ẋ, J, J̇q̇ and x_d, ẋ_d, ẍ_d after the position's) against
    :mod:`qpctl.orientation` on Pinocchio's frame functions, at random states and times."""
    robot = panda().with_orientation(kind)
    q0, _ = _state(robot, RNG)
    R0 = frame_terms(robot, q0, np.zeros(7))[0]
    rots = (approach_rotations(R0, robot.approach_axis, [[0.5, 0.2, -1.0]]) if kind == "approach"
            else [R0, pin.exp3(np.array([0.4, -0.6, 0.3])) @ R0])
    path = PosePath([[0.3, 0.0, 0.5], [0.4, 0.1, 0.4]], rots, duration=2.0)
    ws = QPController(robot, path, []).workspace()
    m_p = robot.m_position
    for _ in range(10):
        q, v = _state(robot, RNG)
        t = float(RNG.uniform(0, 2.2))
        assert ws.state(q, v, t) == 0
        R, w, a, J = frame_terms(robot, q, v)
        Rd, wd, ad = path.orientation(t)
        rows = orientation_rows(robot, R, w, a, J, Rd, wd) + orientation_reference(robot, R, Rd, wd, ad)
        mine = (ws.x[m_p:], ws.xdot[m_p:], ws.J[m_p:], ws.drift[m_p:], ws.ref[0, m_p:], ws.ref[1, m_p:],
                ws.ref[2, m_p:])
        for got, want in zip(mine, rows):
            np.testing.assert_allclose(got, want, atol=1e-12)
        np.testing.assert_allclose(ws.ee_R[0], R, atol=1e-14)


@pytest.mark.parametrize("kind", ["pose", "approach"])
def test_qp_reduces_to_the_closed_form_with_orientation_rows(kind):
    """No constraints, no damping: the QP's torque is the paper law's on random states (the 6- or
    5-row task generalises both the same way)."""
    from baselines import PaperController

    robot = panda().with_orientation(kind)
    q0 = robot.q_home
    R0 = frame_terms(robot, q0, np.zeros(7))[0]
    rots = (approach_rotations(R0, robot.approach_axis, [[0.3, 0.0, -1.0]]) if kind == "approach"
            else [R0, pin.exp3(np.array([0.2, 0.3, -0.1])) @ R0])
    path = PosePath([[0.3, 0.0, 0.5], [0.4, 0.1, 0.4]], rots, duration=2.0)
    cfg = QPConfig(damping=0.0, torque_limits=False, joint_limits=False, self_collision=False)
    # J M⁻¹ of the Panda's 6-row task has σ_min/σ_max ≈ 1.7e-3 near home (M's own spread, not a
    # singularity): pinv_eps 1e-4 keeps the law undamped there (README, "Orientation tasks")
    gains = LawGains(pinv_eps=1e-4)
    qp, paper = QPController(robot, path, [], gains, config=cfg), PaperController(robot, path, [], gains)
    assert qp.constraints == []
    data = robot.model.createData()
    checked = 0
    for _ in range(15):
        q, v = _state(robot, RNG)
        t = float(RNG.uniform(0, 2))
        tp = paper.step(q, v, t).tau
        # the law's task inverse J_M⁺ undamped (σ_min/σ_max of J M⁻¹ above pinv_eps, from numpy): then
        # the QP's optimum is the law's exactly, whatever the damping of Ryu's J_b⁺ inside e_N
        J = np.vstack([pin.computeFrameJacobian(robot.model, data, q, robot.ee_frame_id, pin.LOCAL_WORLD_ALIGNED)[:3],
                       paper.workspace().J[3:]])
        M = pin.crba(robot.model, data, q)
        sv = np.linalg.svd(J @ np.linalg.inv(np.triu(M) + np.triu(M, 1).T), compute_uv=False)
        if sv.min() / sv.max() < 2 * paper.gains.pinv_eps:
            continue
        checked += 1
        assert np.linalg.norm(qp.step(q, v, t).tau - tp) <= 1e-6 * np.linalg.norm(tp)
    assert checked >= 10


PANDA_POSE = """
[robot]
kind = "panda"
[path]
waypoints = [[0.35, 0.15, 0.45]]
orientations = [[0.9238795, -0.3826834, 0.0, 0.0]]
start_orientation = [1.0, 0.0, 0.0, 0.0]
duration = 1.5
[controller]
kind = "qp"
task = "pose"
[sim]
duration = 2.0
"""


@pytest.fixture(scope="module")
def pose_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("pose")
    (out / "pose.toml").write_text(PANDA_POSE)
    return out


@pytest.mark.parametrize("kind", ["qp", "paper", "hsu"])
def test_panda_reaches_a_pose(pose_run, kind):
    """Every law turns the gripper to the given quaternion while it moves (from the start quaternion
    given, which the arm's home is): at the end within 0.05° and 0.1 mm; trajectory.npz's quaternions
    are Pinocchio's frame rotation at the recorded q; metrics.json has the angles."""
    out = pose_run / kind
    assert main(["simulate", str(pose_run / "pose.toml"), "--controller", kind, "--out", str(out), "--quiet",
                 "--no-figures"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["final_orientation_error_deg"] < 0.05 and metrics["final_tracking_error"] < 1e-4
    assert metrics["max_orientation_error_deg"] < 2.0
    with np.load(out / "trajectory.npz") as data:
        q, quat, quat_ref, err = data["q"], data["quat"], data["quat_ref"], data["orientation_error_deg"]
        assert data["x"].shape[1] == 3 and quat.shape == (q.shape[0], 4)
    robot = panda()
    rdata = robot.model.createData()
    for k in (0, q.shape[0] // 2, q.shape[0] - 1):
        pin.framesForwardKinematics(robot.model, rdata, q[k])
        R = rdata.oMf[robot.ee_frame_id].rotation
        np.testing.assert_allclose(pin.Quaternion(quat[k]).matrix(), R, atol=1e-12)
        angle = np.degrees(np.linalg.norm(pin.log3(pin.Quaternion(quat_ref[k]).matrix() @ R.T)))
        assert err[k] == pytest.approx(angle, abs=1e-9)
    target = pin.Quaternion(0.0, 0.9238795, -0.3826834, 0.0).normalized()  # (w, x, y, z): the file's (x, y, z, w)
    np.testing.assert_allclose(np.abs(quat_ref[-1] @ target.coeffs()), 1.0, atol=1e-9)


def _load(text: str, tmp_path, *sets: str) -> Scenario:
    p = tmp_path / "s.toml"
    p.write_text(text)
    return Scenario.load(p, list(sets))


APPROACH = PANDA_POSE.replace('orientations = [[0.9238795, -0.3826834, 0.0, 0.0]]', "approach = [[0.0, 0.3, -1.0]]"
                               ).replace('task = "pose"', 'task = "approach"')


@pytest.mark.parametrize("text, sets, key", [
    (PANDA_POSE, ['controller.task="twist"'], "controller.task"),
    (PANDA_POSE, ["controller.task_mask=[1,1,1,1,1]"], "controller.task_mask"),
    (PANDA_POSE, ["controller.task_mask=[0,0,0,1,1,1]"], "controller.task_mask"),
    (PANDA_POSE, ["controller.task_mask=[1,1,1,1,1,1]", 'robot.task_axes=["x","y","z"]'], "controller.task_mask"),
    (PANDA_POSE, ['controller.task="position"'], "path.orientations"),
    (PANDA_POSE, ['controller.task="approach"'], "path.orientations"),
    (PANDA_POSE, ["path.orientations=[[0.0,0.0,0.0,0.0]]"], "path.orientations"),
    (PANDA_POSE, ["path.orientations=[[0.0,0.0,0.0,1.0],[0.0,0.0,0.0,1.0]]"], "path.orientations"),
    (PANDA_POSE, ["path.start_orientation=[1.0,0.0]"], "path.start_orientation"),
    (APPROACH, ["controller.approach_axis=[0.0,0.0,0.0]"], "controller.approach_axis"),
    (APPROACH, ["path.approach=[[0.0,0.0,0.0]]"], "path.approach"),
    (APPROACH, ["path.approach=[[0.0,1.0]]"], "path.approach"),
    (APPROACH, ["controller.task_mask=[1,1,1,1,1,1]"], "controller.task_mask"),
])
def test_bad_orientation_keys_are_named(tmp_path, text, sets, key):
    with pytest.raises(ConfigError) as info:
        _load(text, tmp_path, *sets)
    assert info.value.key == key, (info.value.key, str(info.value))


def test_approach_scenario_turns_the_axis_only(tmp_path):
    """The approach task from the file: the gripper's z axis ends along the given direction (within
    0.05°, the angle from Pinocchio's frame rotation), its roll about that axis left to the law."""
    scen = _load(APPROACH, tmp_path)
    ctrl = scen.build_controller("qp")
    assert ctrl.robot.m == 5
    traj = Simulator(ctrl, dt=1e-3, duration=2.0).run(scen.q0(ctrl.robot))
    robot = ctrl.robot
    data = robot.model.createData()
    pin.framesForwardKinematics(robot.model, data, traj.q[-1])
    z = data.oMf[robot.ee_frame_id].rotation[:, 2]
    d = np.array([0.0, 0.3, -1.0]) / np.linalg.norm([0.0, 0.3, -1.0])
    assert np.degrees(np.arccos(np.clip(z @ d, -1, 1))) < 0.05
    assert traj.orientation_error_deg[-1] == pytest.approx(np.degrees(np.arccos(np.clip(z @ d, -1, 1))), abs=1e-6)


def test_jdot_term_is_refused_with_orientation_rows(tmp_path):
    scen = _load(PANDA_POSE, tmp_path, "controller.jdot_en=true")
    for kind in ("paper", "hsu", "qp"):
        with pytest.raises(ConfigError) as info:
            scen.build_controller(kind)
        assert info.value.key == "controller.jdot_en"


def test_pose_mask_drops_rows(tmp_path):
    """task_mask = x, y, z, rz: 4 rows; the path's points keep 3 coordinates."""
    scen = _load(PANDA_POSE, tmp_path, "controller.task_mask=[1,1,1,0,0,1]")
    robot = scen.build_robot()
    assert robot.m == 4 and robot.m_position == 3 and robot.orientation_axes == (2,)
    ctrl = scen.build_controller("qp")
    traj = Simulator(ctrl, dt=1e-3, duration=0.05).run(scen.q0(robot))
    assert traj.x.shape == (51, 3) and np.all(np.isfinite(traj.tau))


INFEASIBLE_APPROACH = """
[robot]
kind = "panda"
[path]
waypoints = [[0.45, 0.1, 0.4], [0.5, 0.0, 0.3]]
approach = [[0.3, 0.0, -1.0], [1.0, 0.0, 0.0]]
duration = 3.0
[controller]
kind = "qp"
task = "approach"
[sim]
duration = 3.5
"""


def test_task_weights_choose_which_rows_give_way(tmp_path):
    """The last approach is out of the Panda's reach within its joint limits (paper and hsu exceed
    them): the QP gives way. Weighting the position rows 100× over the axis rows moves the error
    from the position to the axis; on a reachable task the weights change nothing."""
    def final(sets):
        from qpctl.run import simulate

        run = simulate(_load(INFEASIBLE_APPROACH, tmp_path, *sets), kind="qp")
        return run.metrics["final_tracking_error"], run.metrics["final_orientation_error_deg"], run.trajectory.tau
    pos1, ang1, _ = final([])
    pos2, ang2, _ = final(["controller.task_weights=[100.0, 100.0, 100.0, 1.0, 1.0]"])
    assert pos1 > 0.05 and ang1 < 1.0  # equal weights: the position gave way
    assert pos2 < 0.2 * pos1 and ang2 > 10 * ang1, (pos1, ang1, pos2, ang2)
    reachable = PANDA_POSE.replace("duration = 2.0", "duration = 0.3")
    base = Simulator(_load(reachable, tmp_path).build_controller("qp"), dt=1e-3, duration=0.3).run(panda().q_home)
    scen = _load(reachable, tmp_path, "controller.task_weights=[3.0, 1.0, 2.0, 0.5, 1.0, 4.0]")
    weighted = Simulator(scen.build_controller("qp"), dt=1e-3, duration=0.3).run(panda().q_home)
    np.testing.assert_allclose(weighted.tau, base.tau, rtol=0, atol=1e-6 * np.abs(base.tau).max())
    with pytest.raises(ConfigError) as info:
        _load(reachable, tmp_path, "controller.task_weights=[1.0, 1.0]")
    assert info.value.key == "controller.task_weights"


def test_weighted_rows_compiled_and_python_agree(tmp_path):
    """The weights in the compiled assembly and in EndEffectorTask (the Python formulation, taken by
    a subclass): the same torques to 1e-8 on ticks where the task gives way."""
    from qpctl.tasks import AccelerationTask, EndEffectorTask

    class _Acc(AccelerationTask):
        pass

    class _EE(EndEffectorTask):
        pass

    sets = ["controller.task_weights=[100.0, 100.0, 100.0, 1.0, 1.0]"]
    scen = _load(INFEASIBLE_APPROACH, tmp_path, *sets)
    fast, slow = scen.build_controller("qp"), scen.build_controller("qp")
    ee = next(t for t in slow.tasks if isinstance(t, EndEffectorTask))
    slow.tasks = [_Acc(), _EE(ee.slack_l1, ee.slack_l2, ee.weights)] + [
        t for t in slow.tasks if not isinstance(t, (AccelerationTask, EndEffectorTask))]
    slow._formulation = slow._ws = None
    assert fast.workspace().spec is not None and slow.workspace().spec is None
    traj = Simulator(scen.build_controller("qp"), dt=1e-3, duration=3.5).run(scen.q0(fast.robot))
    gave_way = 0
    for k in range(2000, 3500, 10):
        a = fast.step(traj.q[k], traj.v[k], float(traj.t[k]))
        b = slow.step(traj.q[k], traj.v[k], float(traj.t[k]))
        np.testing.assert_allclose(a.tau, b.tau, rtol=1e-8, atol=1e-8 * np.abs(b.tau).max())
        gave_way += a.info.get("slack_norm", 0.0) > 1e-6
    assert gave_way >= 50, gave_way
