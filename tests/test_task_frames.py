"""Several task frames (issue 24, part B item 3): ``[[tasks]]``, stacked rows, two arms on one torso.

Against independent computations: the stacked rows against Pinocchio's frame Jacobians and classical
accelerations of each frame; the dual-arm law (closed form and QP, the compiled tick) against the
single-task law run on each arm alone (Baxter's arms share a fixed torso, so its M, J and W_b are
block-diagonal and the stacked law must split into the two single-arm laws).
"""

from __future__ import annotations

import copy
import functools
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from qpctl import Scenario
from qpctl.errors import ConfigError
from qpctl.simulation.simulator import Simulator
from qpctl.tick import Workspace

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
BAXTER = "package://example-robot-data/robots/baxter_description/urdf/baxter.urdf"
SRDF = "package://example-robot-data/robots/baxter_description/srdf/baxter_manipulation.srdf"  # no sampled pairs
HEAD_AND_FINGERS = ["head_pan", "l_gripper_l_finger_joint", "l_gripper_r_finger_joint", "r_gripper_l_finger_joint",
                    "r_gripper_r_finger_joint"]
ARM = [0.0, -0.55, 0.0, 0.75, 0.0, 1.26, 0.0]
SIDES = {"left": ("left_gripper", [[0.85, 0.40, 0.30]]), "right": ("right_gripper", [[0.80, -0.35, 0.40]])}


def _raw(sides: tuple[str, ...], kind: str, **controller: object) -> dict:
    locked = list(HEAD_AND_FINGERS)
    for other in ("left", "right"):
        if other not in sides:
            locked += [f"{other}_{j}" for j in ("s0", "s1", "e0", "e1", "w0", "w1", "w2")]
    return {"robot": {"kind": "urdf", "urdf": BAXTER, "locked_joints": locked, "q0": ARM * len(sides), "srdf": SRDF},
            "tasks": [{"frame": SIDES[s][0], "waypoints": SIDES[s][1]} for s in sides],
            "obstacles": [{"shape": "sphere", "position": [0.95, 0.45, 0.36], "radius": 0.04},
                          {"shape": "capsule", "position": [0.9, -0.3, 0.55], "axis": [0.0, 1.0, 0.2],
                           "length": 0.4, "radius": 0.025}],
            "path": {"durations": [1.5]},
            "controller": {"kind": kind, "self_collision": False, **controller}, "sim": {"duration": 1.5}}


def test_stacked_rows_are_each_frames_jacobian_and_drift() -> None:
    scenario = Scenario.from_dict(_raw(("left", "right"), "qp"))
    robot = scenario.build_robot()
    assert robot.frames == ("left_gripper", "right_gripper") and robot.m == 6 and robot.nv == 14
    ws = Workspace(robot, [], None, None, np.inf)
    model, data = robot.model, robot.model.createData()
    rng = np.random.default_rng(0)
    for _ in range(4):
        q, v = rng.uniform(-1, 1, 14), rng.uniform(-1, 1, 14)
        assert ws.state(q, v, 0.0) == 0
        pin.forwardKinematics(model, data, q, v, np.zeros(14))
        pin.computeJointJacobians(model, data, q)
        pin.updateFramePlacements(model, data)
        for i, f in enumerate(robot.task_frame_ids):
            rows = slice(3 * i, 3 * i + 3)
            J = pin.getFrameJacobian(model, data, f, pin.LOCAL_WORLD_ALIGNED)[:3]
            acc = pin.getFrameClassicalAcceleration(model, data, f, pin.LOCAL_WORLD_ALIGNED).linear
            assert np.allclose(ws.x[rows], data.oMf[f].translation, atol=1e-12)
            assert np.allclose(ws.J[rows], J, atol=1e-12)
            assert np.allclose(ws.xdot[rows], J @ v, atol=1e-12)
            assert np.allclose(ws.drift[rows], acc, atol=1e-10)


@pytest.mark.parametrize("kind", ["paper", "hsu", "qp"])
def test_dual_arm_law_splits_into_each_arm_alone(kind: str) -> None:
    """The two-task law on Baxter, on the states of its own closed-loop run (a leaf near the left
    gripper, a branch near the right one), gives each arm the torque the one-task law gives that
    arm alone (the other locked) on the same states: the stacked Jacobian, stacked rows and the
    barrier rows of each arm's links. Hsu's law (W = W_b = I) splits bit for bit; the paper's and the
    QP's (q̈₀ from Ryu's W_b) to 5e-5 of the torque: W_b's ridge, 1e-9·tr(W_b)·I (kernels.small.
    add_trace_ridge), is the whole robot's, and on W_b's smallest eigenvalues (a wrist roll barely
    moves the links' mid-points) it shows at ~1e-5 (measured: 8e-6 paper, 2.7e-5 QP)."""
    extra = {"damping": 0.0} if kind == "qp" else {}  # DampingTask's weight scales with the whole robot's M
    dual_sc = Scenario.from_dict(_raw(("left", "right"), kind, **extra))
    dual = dual_sc.build_controller()
    traj = Simulator(dual, dt=1e-3, duration=1.5).run(dual_sc.q0(dual.robot))
    _assert_each_arm_alone(traj, kind, lambda side: _raw((side,), kind, **extra))


def _assert_each_arm_alone(traj, kind: str, single_raw) -> None:  # type: ignore[no-untyped-def]
    """Each arm's torques in ``traj`` (Baxter's two-task run) are what the one-task controller of
    ``single_raw(side)`` gives that arm alone on the same states: Hsu's law bit for bit, the others
    to 5e-5 of the torque."""
    assert np.abs(traj.tau).max() > 1.0
    for side, cols in (("left", slice(0, 7)), ("right", slice(7, 14))):
        single = Scenario.from_dict(single_raw(side)).build_controller()
        single.reset()
        tau = np.array([single.torque(q[cols].copy(), v[cols].copy(), float(t))
                        for t, q, v in zip(traj.t, traj.q, traj.v)])
        scale = np.abs(traj.tau[:, cols]).max()
        assert np.abs(tau - traj.tau[:, cols]).max() <= (0.0 if kind == "hsu" else 5e-5 * scale), side


def test_baxter_picks_two_fruits_at_once() -> None:
    """examples/baxter_two_fruits.toml: both grippers within 5 mm of their fruits at the end of the
    dwell (forward kinematics of the recorded configuration), no collision."""
    from qpctl.run import simulate

    scenario = Scenario.load(EXAMPLES / "baxter_two_fruits.toml")
    robot = scenario.build_robot()
    result = simulate(scenario, progress=False)
    m, traj = result.metrics, result.trajectory
    assert not m["collided"] and m["min_clearance"] > 0.0
    right = np.linalg.norm(traj.x[:, 3:] - traj.x_ref[:, 3:], axis=1)  # the second frame's rows
    assert m["max_tracking_error_per_task"][1] == pytest.approx(right.max())
    assert m["max_tracking_error"] >= max(m["max_tracking_error_per_task"])
    t_end = scenario.data["path"]["durations"][0] + scenario.data["path"]["dwell"]
    k = int(np.searchsorted(traj.t, t_end - 1e-9))
    data = robot.model.createData()
    pin.framesForwardKinematics(robot.model, data, traj.q[k])
    for i, task in enumerate(scenario.data["tasks"]):
        fruit = np.array(task["waypoints"][0])
        assert np.linalg.norm(data.oMf[robot.task_frame_ids[i]].translation - fruit) <= 5e-3, task["frame"]


def _edited(change) -> dict:  # type: ignore[no-untyped-def]
    raw = copy.deepcopy(_raw(("left", "right"), "qp"))
    change(raw)
    return raw


@pytest.mark.parametrize("change, key, text", [
    (lambda r: r["tasks"][1].update(frame="right_hand_nope"), "tasks[1].frame", "right_hand_nope"),
    (lambda r: r["tasks"][1].update(frame="left_gripper"), "tasks[1].frame", "two tasks on frame"),
    (lambda r: r["tasks"][1].update(waypoints=[[0.8, -0.3, 0.4], [0.7, -0.5, 0.3]]), "tasks[1].waypoints", "points"),
    (lambda r: r["tasks"][0].pop("frame"), "tasks[0].frame", "missing"),
    (lambda r: r["path"].update(waypoints=[[0.8, 0.4, 0.3]]), "path.waypoints", "[[tasks]]"),
    (lambda r: r["robot"].update(ee_frame="right_gripper"), "robot.ee_frame", "first task"),
    (lambda r: r["tasks"][0].update(weights=[1.0, -2.0, 1.0]), "tasks[0].weights", "positive"),
    (lambda r: r["tasks"][0].update(waypoints=[[0.8, 0.4]]), "tasks[0].waypoints", "3 coordinates"),
])
def test_bad_tasks_are_one_line_errors_naming_the_key(change, key, text) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ConfigError) as err:
        Scenario.from_dict(_edited(change), source="dual.toml")
    assert err.value.key == key and text in str(err.value) and "\n" not in str(err.value)


def test_task_weights_reach_the_qp_rows() -> None:
    raw = _edited(lambda r: r["tasks"][1].update(weights=4.0))
    scenario = Scenario.from_dict(raw)
    ctrl = scenario.build_controller()
    assert scenario.task_weights(ctrl.robot) == [1.0, 1.0, 1.0, 4.0, 4.0, 4.0]
    assert np.array_equal(ctrl.workspace().task_w, [1.0, 1.0, 1.0, 4.0, 4.0, 4.0])


def test_single_frame_keys_still_work() -> None:
    """No [[tasks]]: robot.ee_frame and [path] as before; one [[tasks]] table is the same task."""
    one = _raw(("left",), "hsu")
    old = copy.deepcopy(one)
    old["robot"]["ee_frame"] = "left_gripper"
    old["path"]["waypoints"] = old.pop("tasks")[0]["waypoints"]
    runs = []
    for raw in (one, old):
        sc = Scenario.from_dict(raw)
        runs.append(Simulator(sc.build_controller(), dt=1e-3, duration=0.3).run(sc.q0(sc.build_robot())))
    assert np.array_equal(runs[0].tau, runs[1].tau)


def test_cli_reports_a_bad_task_frame_in_one_line(tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    import tomli_w

    from qpctl.cli import main

    bad = tmp_path / "dual.toml"
    bad.write_text(tomli_w.dumps(_edited(lambda r: r["tasks"][1].update(frame="left_gripper"))))
    assert main(["simulate", str(bad), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "tasks[1].frame" in err and str(bad) in err


def test_orientation_rows_ride_on_the_first_task_frame() -> None:
    """controller.task = "approach" with two task frames: 6 position rows, then the first frame's 2
    approach rows. Hsu's law on Baxter then gives the left arm (first frame) exactly what the one-task
    approach law gives the left arm alone, on the same states."""
    def raw(sides: tuple[str, ...]) -> dict:
        r = _raw(sides, "hsu", task="approach", approach_axis=[0.0, 0.0, 1.0])
        r["path"]["approach"] = [[1.0, 0.0, -0.3]]
        return r

    dual_sc = Scenario.from_dict(raw(("left", "right")))
    dual = dual_sc.build_controller()
    assert (dual.robot.m, dual.robot.m_orientation) == (8, 2)
    traj = Simulator(dual, dt=1e-3, duration=1.0).run(dual_sc.q0(dual.robot))
    assert traj.orientation_error_deg[-1] < 0.5  # [deg] the approach tracked (1 s run)
    single = Scenario.from_dict(raw(("left",))).build_controller()
    single.reset()
    tau = np.array([single.torque(q[:7].copy(), v[:7].copy(), float(t)) for t, q, v in zip(traj.t, traj.q, traj.v)])
    assert np.abs(traj.tau[:, :7]).max() > 1.0
    assert np.array_equal(tau, traj.tau[:, :7])


# -- an orientation task per task frame ------------------------------------------------------------
# the left gripper approaches along a tilted axis, the right one holds a pose turned about z
LEFT_APPROACH = [[1.0, 0.0, -0.3]]
RIGHT_TURN = np.array([0.0, 0.15, 0.4])  # [rad] the right gripper's pose: turned by this (world) from its start


@functools.cache
def _right_quat() -> tuple[float, ...]:
    """The right gripper's pose target (x, y, z, w): its rotation at q0 turned by RIGHT_TURN."""
    robot = Scenario.from_dict(_raw(("right",), "hsu")).build_robot()
    data = robot.model.createData()
    pin.framesForwardKinematics(robot.model, data, Scenario.from_dict(_raw(("right",), "hsu")).q0(robot))
    return tuple(pin.Quaternion(pin.exp3(RIGHT_TURN) @ data.oMf[robot.ee_frame_id].rotation).coeffs().tolist())


RIGHT_APPROACH = [[0.8, -0.3, -0.6]]


def _oriented(sides: tuple[str, ...], kind: str, *, own: bool = True, right: str = "pose") -> dict:
    """Each arm's orientation task: in its [[tasks]] table (``own``), or with the single frame's keys
    (controller.task, controller.approach_axis, path.approach / path.orientations) on one arm; the
    right arm's a pose (``right``) or an approach."""
    r = _raw(sides, kind, **({"damping": 0.0} if kind == "qp" else {}))
    spec = {"left": {"task": "approach", "approach_axis": [0.0, 0.0, 1.0], "approach": LEFT_APPROACH},
            "right": ({"task": "pose", "orientations": [list(_right_quat())]} if right == "pose" else
                      {"task": "approach", "approach_axis": [0.0, 0.0, 1.0], "approach": RIGHT_APPROACH})}
    if own:
        for t, s in zip(r["tasks"], sides):
            t.update(spec[s])
        return r
    (side,) = sides
    s = dict(spec[side])
    r["controller"]["task"] = s.pop("task")
    if "approach_axis" in s:
        r["controller"]["approach_axis"] = s.pop("approach_axis")
    r["path"].update(s)
    return r


def test_each_task_frame_takes_its_own_orientation_task() -> None:
    robot = Scenario.from_dict(_oriented(("left", "right"), "qp")).build_robot()
    assert robot.oriented_frames == (0, 1) and (robot.m_position, robot.m_orientation, robot.m) == (6, 5, 11)
    assert [robot.frame_orientation(i).kind for i in (0, 1)] == ["approach", "pose"]
    right_only = _oriented(("left", "right"), "qp")
    for key in ("task", "approach_axis", "approach"):
        right_only["tasks"][0].pop(key)
    robot = Scenario.from_dict(right_only).build_robot()
    assert robot.oriented_frames == (1,) and robot.m == 9 and robot.orientation == "none"


def test_compiled_rows_of_two_oriented_frames_match_the_python_ones() -> None:
    """The compiled tick's orientation rows (x, ẋ, J, J̇q̇, x_d, ẋ_d, ẍ_d), frame after frame after the
    six position rows, against qpctl.orientation on Pinocchio's frame functions of each frame."""
    from qpctl.orientation import frame_terms, orientation_reference, orientation_rows

    scenario = Scenario.from_dict(_oriented(("left", "right"), "qp"))
    ctrl = scenario.build_controller()
    robot, path, ws = ctrl.robot, ctrl.path, ctrl.workspace()
    rng = np.random.default_rng(1)
    for _ in range(6):
        q, v, t = rng.uniform(-1, 1, 14), rng.uniform(-1, 1, 14), float(rng.uniform(0.1, 1.4))
        assert ws.state(q, v, t) == 0
        r0 = robot.m_position
        for j, f in enumerate(robot.oriented_frames):
            R, w, a, J = frame_terms(robot, q, v, frame=f)
            Rd, wd, ad = path.orientation(t, j)
            want = (orientation_rows(robot, R, w, a, J, Rd, wd, frame=f)
                    + orientation_reference(robot, R, Rd, wd, ad, frame=f))
            rows = slice(r0, r0 + robot.frame_orientation(f).rows)
            got = (ws.x[rows], ws.xdot[rows], ws.J[rows], ws.drift[rows], ws.ref[0, rows], ws.ref[1, rows],
                   ws.ref[2, rows])
            for mine, theirs in zip(got, want):
                np.testing.assert_allclose(mine, theirs, atol=1e-11)
            np.testing.assert_allclose(ws.ee_R[j], R, atol=1e-14)
            r0 = rows.stop
        assert np.abs(ws.J[6:]).max() > 0.1 and np.count_nonzero(ws.J[6:8, 7:]) == 0  # the left's rows: left joints


@pytest.mark.parametrize("kind, right", [("hsu", "pose"), ("paper", "approach"), ("qp", "approach")])
def test_two_orientation_tasks_split_into_each_arm_alone(kind: str, right: str) -> None:
    """Both arms with their own orientation task ([[tasks]] keys) against the single-task law on each
    arm alone (the single frame's keys: controller.task, path.approach / path.orientations), on the
    states of the dual run: Hsu's law bit for bit, the paper's and the QP's (compiled tick) to 5e-5 of
    the torque (W_b's ridge is the whole robot's, test_dual_arm_law_splits_into_each_arm_alone).

    The paper's and the QP's with an approach on each arm, not a pose on the right: Ryu's W_b barely
    weights Baxter's wrist roll, so with a full pose J_b⁺ is damped on every tick (σ_min/σ_max <
    pinv_eps, the right arm alone too), and the damping's threshold is the whole stacked Jacobian's
    (eps·σ_max over both arms): a damped stacked law does not split into the arms' (measured: 18 N·m
    on the left arm). Here no tick is damped, which the test checks."""
    dual_sc = Scenario.from_dict(_oriented(("left", "right"), kind, right=right))
    dual = dual_sc.build_controller()
    traj = Simulator(dual, dt=1e-3, duration=1.0).run(dual_sc.q0(dual.robot))
    assert dual.robot.m == (11 if right == "pose" else 10)
    if kind != "hsu":
        assert not traj.singular.any()
    _assert_each_arm_alone(traj, kind, lambda side: _oriented((side,), kind, own=False, right=right))


def test_two_orientation_tasks_are_tracked_and_reported_per_task() -> None:
    """The QP run of both orientation tasks: each frame's angle in trajectory.npz and metrics.json,
    the largest of them as orientation_error_deg, each against the frames' own rotations."""
    from qpctl.orientation import orientation_error_deg
    from qpctl.simulation.metrics import compute_metrics
    from qpctl.simulation.trajectory import finish_trajectory

    scenario = Scenario.from_dict(_oriented(("left", "right"), "qp"))
    ctrl = scenario.build_controller()
    traj = finish_trajectory(Simulator(ctrl, dt=1e-3, duration=1.5).run(scenario.q0(ctrl.robot)), ctrl)
    per = traj.orientation_error_deg_per_task
    assert per is not None and per.shape == (traj.t.size, 2)
    assert np.array_equal(traj.orientation_error_deg, per.max(axis=1))
    robot, data = ctrl.robot, ctrl.robot.model.createData()
    pin.framesForwardKinematics(robot.model, data, traj.q[-1])
    R_right = data.oMf[robot.task_frame_ids[1]].rotation
    x, y, z, w = _right_quat()
    want = pin.Quaternion(w, x, y, z).matrix()
    assert per[-1, 1] == pytest.approx(orientation_error_deg(robot, R_right, want, frame=1), abs=1e-9)
    assert per[-1, 1] < 0.5  # [deg] the right gripper turned to its pose, 24.5° from where it started:
    start = robot.model.createData()
    pin.framesForwardKinematics(robot.model, start, traj.q[0])
    assert np.degrees(np.linalg.norm(pin.log3(start.oMf[robot.task_frame_ids[1]].rotation.T @ R_right))) > 20.0
    z = data.oMf[robot.task_frame_ids[0]].rotation[:, 2]
    d = np.array(LEFT_APPROACH[0]) / np.linalg.norm(LEFT_APPROACH[0])
    assert per[-1, 0] == pytest.approx(np.degrees(np.arccos(np.clip(z @ d, -1, 1))), abs=1e-6) and per[-1, 0] < 0.5
    m = compute_metrics(traj, frames=2)
    assert m["final_orientation_error_deg_per_task"] == per[-1].tolist()
    assert m["max_orientation_error_deg"] == pytest.approx(per.max())


@pytest.mark.parametrize("change, key, text", [
    (lambda r: r["tasks"][1].update(orientations=[[0.0, 0.0, 0.0, 1.0]]), "tasks[1].orientations", "pose only"),
    (lambda r: r["tasks"][1].update(task="pose", approach_axis=[1.0, 0.0, 0.0]), "tasks[1].approach_axis",
     "approach only"),
    (lambda r: r["tasks"][1].update(task="approach", task_mask=[1, 1, 1, 1, 1, 0]), "tasks[1].task_mask", "pose only"),
    (lambda r: r["tasks"][1].update(task="pose", task_mask=[1, 1, 0, 1, 1, 1]), "tasks[1].task_mask",
     "position axes"),
    (lambda r: r["tasks"][1].update(task="twist"), "tasks[1].task", "twist"),
    (lambda r: r["tasks"][1].update(task="approach", approach_axis=[0.0, 0.0, 0.0]), "tasks[1].approach_axis",
     "non-zero"),
    (lambda r: r["tasks"][1].update(task="pose", orientations=[[0.0, 0.0, 0.0, 1.0]] * 2), "tasks[1].orientations",
     "one entry per waypoint"),
    (lambda r: (r["tasks"][0].update(task="pose"), r["controller"].update(task="approach")), "tasks[0].task",
     "give one of them"),
    (lambda r: r["tasks"][0].update(start_orientation=[0.0, 0.0, 0.0, 1.0]), "tasks[0].start_orientation",
     "pose or approach only"),
])
def test_bad_orientation_keys_of_a_task_name_the_key(change, key, text) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ConfigError) as err:
        Scenario.from_dict(_edited(change), source="dual.toml")
    assert err.value.key == key and text in str(err.value) and "\n" not in str(err.value)
    assert "dual.toml" in str(err.value)


def test_a_path_without_each_oriented_frames_rotations_is_refused() -> None:
    from qpctl.controllers.qp import QPController
    from qpctl.paths import PosePath

    ctrl = Scenario.from_dict(_oriented(("left", "right"), "qp")).build_controller()
    one = PosePath(ctrl.path.points, ctrl.path.frame_rotations[0], durations=[1.5])
    with pytest.raises(ConfigError) as err:
        QPController(ctrl.robot, one, [])
    assert err.value.key == "path.orientations" and "2 task frames" in str(err.value)
