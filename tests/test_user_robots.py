"""Robots and files qpctl does not ship, as a new user brings them (issue 12's defects).

A planar N-link URDF written here (links of 0.5 m along x, revolute about z, the task frame a
``tip`` link fixed at the far end of the last link), example-robot-data's Z1 (a link and a joint
both named ``gripperStator``), and scenario files in a folder other than the working one. The
clearance check is against the analytic point–segment distance, not against qpctl's own code.
"""

from __future__ import annotations

import builtins
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from qpctl import ConfigError, Scenario
from qpctl.cli import main
from qpctl.robot.model import RobotModel, example_robot_data_path
from qpctl.simulation.simulator import Simulator

LINK = 0.5      # [m]
RADIUS = 0.05   # capsule radius [m]


def planar_urdf(n: int) -> str:
    """A planar n-link arm in the xy plane: 1 kg rods of LINK m, the task frame ``tip`` at the end."""
    parts = ['<?xml version="1.0"?>', '<robot name="planar_user">', '<link name="base"/>']
    parent = "base"
    for i in range(1, n + 1):
        origin = "0 0 0" if i == 1 else f"{LINK} 0 0"
        inertia = 1.0 * LINK ** 2 / 12
        parts += [
            (f'<joint name="j{i}" type="revolute"><parent link="{parent}"/><child link="l{i}"/>'
            f'<origin xyz="{origin}"/><axis xyz="0 0 1"/><limit lower="-3.2" upper="3.2" effort="500" velocity="10"/>'
            "</joint>"),
            (f'<link name="l{i}"><inertial><origin xyz="{LINK / 2} 0 0"/><mass value="1.0"/>'
            f'<inertia ixx="1e-4" iyy="{inertia}" izz="{inertia}" ixy="0" ixz="0" iyz="0"/></inertial></link>'),
        ]
        parent = f"l{i}"
    parts += [(f'<joint name="tip_joint" type="fixed"><parent link="{parent}"/><child link="tip"/>'
              f'<origin xyz="{LINK} 0 0"/></joint>'), '<link name="tip"/>', "</robot>"]
    return "\n".join(parts)


def scenario_text(urdf: str, *, ee_frame: str = "tip", obstacle: tuple[float, float] = (0.5, 1.2),
                  planar: bool = True) -> str:
    """A scenario for the planar URDF; ``planar``: a task in x–y (else the default, x–y–z)."""
    lines = ["[robot]", 'kind = "urdf"', f'urdf = "{urdf}"']
    if ee_frame:
        lines.append(f'ee_frame = "{ee_frame}"')
    if planar:
        lines.append('task_axes = ["x", "y"]')
    lines += [f"radius = {RADIUS}", "gravity = [0.0, 0.0, 0.0]", "q0 = [0.3, 0.3, 0.3, 0.3]",
              "[path]", f"waypoints = [{'[1.2, 1.0]' if planar else '[1.2, 1.0, 0.0]'}]", "duration = 0.2",
              "[[obstacles]]", 'shape = "sphere"', f"position = [{obstacle[0]}, {obstacle[1]}, 0.0]", "radius = 0.1",
              "[sim]", "duration = 0.05"]
    return "\n".join(lines) + "\n"


@pytest.fixture
def user_folder(tmp_path, monkeypatch) -> Path:
    """A scenario folder holding ``planar4.urdf``, while the working folder is elsewhere."""
    folder = tmp_path / "cell"
    folder.mkdir()
    (folder / "planar4.urdf").write_text(planar_urdf(4))
    elsewhere = tmp_path / "cwd"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    return folder


def test_relative_urdf_named_planar_resolves_from_the_scenario_folder(user_folder):
    """`urdf = "planar4.urdf"` is a file beside the TOML, not the built-in arm, and not the cwd's."""
    toml = user_folder / "scene.toml"
    toml.write_text(scenario_text("planar4.urdf"))
    robot = Scenario.load(toml).build_robot()
    assert robot.nv == 4 and robot.model.frames[robot.ee_frame_id].name == "tip"
    assert main(["simulate", str(toml), "--controller", "qp", "--out", str(user_folder / "run"), "--quiet"]) == 0
    assert (user_folder / "run" / "trajectory.npz").is_file()


def test_uppercase_urdf_suffix_is_accepted(user_folder):
    (user_folder / "planar4.urdf").rename(user_folder / "ARM.URDF")
    toml = user_folder / "scene.toml"
    toml.write_text(scenario_text("ARM.URDF"))
    assert Scenario.load(toml).build_robot().nv == 4


@pytest.mark.parametrize("key", ["urdf", "ee_frame"])
def test_missing_urdf_keys_are_named(user_folder, key, capsys):
    toml = user_folder / "scene.toml"
    toml.write_text(scenario_text("" if key == "urdf" else "planar4.urdf", ee_frame="" if key == "ee_frame" else "tip"))
    with pytest.raises(ConfigError) as info:
        Scenario.load(toml).build_robot()
    assert f"robot.{key}" in str(info.value)
    assert main(["simulate", str(toml), "--out", str(user_folder / "run"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"robot.{key}" in err
    assert not (user_folder / "run").exists()


def _point_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    ab = b - a
    s = np.clip(np.dot(p - a, ab) / np.dot(ab, ab), 0.0, 1.0)
    return float(np.linalg.norm(p - (a + s * ab)))


def test_last_link_is_covered_to_the_task_frame_and_clearance_is_real(user_folder):
    """The obstacle sits beside the middle of the last link: the reported clearance is the distance
    to that link's segment (joint 4 to the tip), which a capsule ending at joint 4 would overstate."""
    toml = user_folder / "scene.toml"
    centre = np.array([3 * LINK + LINK / 2, 0.2, 0.0])   # q = 0: the arm lies along x, 0 … 2 m
    toml.write_text(scenario_text("planar4.urdf", obstacle=(float(centre[0]), float(centre[1]))))
    scen = Scenario.load(toml)
    robot = scen.build_robot()
    last = robot.capsules[-1]
    np.testing.assert_allclose(last.p1, [LINK, 0.0, 0.0], atol=1e-12)   # to the tip frame
    ctrl = scen.build_controller("paper")
    sim = Simulator(ctrl, dt=1e-3, duration=0.01)
    q = np.zeros(4)
    links = [(np.array([i * LINK, 0, 0]), np.array([(i + 1) * LINK, 0, 0])) for i in range(4)]
    expected = min(_point_segment(centre, a, b) for a, b in links) - RADIUS - 0.1
    assert expected == pytest.approx(0.05)
    assert sim.clearance(q, 0.0) == pytest.approx(expected, abs=1e-12)
    # A bent pose: the same, with the link ends from the thin-rod kinematics.
    q = np.array([0.4, -0.3, 0.5, -0.6])
    angles = np.cumsum(q)
    joints = np.vstack([np.zeros(2), np.cumsum(LINK * np.c_[np.cos(angles), np.sin(angles)], axis=0)])
    joints = np.c_[joints, np.zeros(5)]
    expected = min(_point_segment(centre, joints[i], joints[i + 1]) for i in range(4)) - RADIUS - 0.1
    assert sim.clearance(q, 0.0) == pytest.approx(expected, abs=1e-12)


def test_z1_with_link_and_joint_of_one_name_loads(tmp_path):
    """Z1's URDF names a link and a joint "gripperStator": the task frame is the link's frame."""
    urdf = example_robot_data_path("z1_description/urdf/z1.urdf")
    robot = RobotModel.from_urdf(urdf, "gripperStator")
    frame = robot.model.frames[robot.ee_frame_id]
    assert frame.name == "gripperStator" and str(frame.type) == "BODY"
    toml = tmp_path / "z1.toml"
    toml.write_text("\n".join([
        "[robot]", 'kind = "urdf"', f'urdf = "{urdf}"', 'ee_frame = "gripperStator"', "radius = 0.04",
        "[path]", "waypoints = [[0.3, 0.0, 0.3]]", "duration = 0.5", "[sim]", "duration = 0.02", ""]))
    assert main(["simulate", str(toml), "--controller", "qp", "--out", str(tmp_path / "run"), "--quiet"]) == 0


def test_mujoco_missing_is_a_config_error(monkeypatch, capsys, tmp_path):
    real_import = builtins.__import__

    def no_mujoco(name, *args, **kwargs):  # type: ignore[no-untyped-def]
        if name == "mujoco" or name.startswith("qpctl.adapters.mujoco"):
            raise ImportError(f"No module named {name!r}")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_mujoco)
    monkeypatch.delitem(__import__("sys").modules, "qpctl.adapters.mujoco", raising=False)
    code = main(["simulate", "paper", "--sim", "mujoco", "--set", "sim.duration=0.01", "--out",
                 str(tmp_path / "run"), "--quiet"])
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "MuJoCo" in err and "sim.simulator" in err


def test_a_task_axis_the_arm_cannot_move_along_is_refused(user_folder):
    """The planar URDF in the default x–y–z task: the z row of its Jacobian is zero everywhere, so
    every tick was flagged singular (issue 12); now the scenario is refused, naming the key."""
    toml = user_folder / "scene.toml"
    toml.write_text(scenario_text("planar4.urdf", planar=False))
    with pytest.raises(ConfigError) as info:
        Scenario.load(toml).build_robot()
    assert info.value.key == "robot.task_axes" and '["x", "y"]' in str(info.value)


def test_planar_urdf_in_its_plane_is_not_singular(user_folder):
    """With task_axes = ["x", "y"] the 2×4 task Jacobian has full rank along the run: no tick is
    flagged singular by any law (its smallest singular value, from numpy, is well above zero)."""
    toml = user_folder / "scene.toml"
    toml.write_text(scenario_text("planar4.urdf").replace("duration = 0.05", "duration = 0.3"))
    scen = Scenario.load(toml)
    for kind in ("paper", "hsu", "qp"):
        ctrl = scen.build_controller(kind)
        traj = Simulator(ctrl, dt=1e-3, duration=0.3).run(scen.q0(ctrl.robot))
        assert not traj.singular.any(), kind
        robot = ctrl.robot
        data = robot.model.createData()
        J = pin.computeFrameJacobian(robot.model, data, traj.q[-1], robot.ee_frame_id, pin.LOCAL_WORLD_ALIGNED)[:2]
        assert np.linalg.svd(J, compute_uv=False).min() > 0.05


@pytest.mark.parametrize("axes", [["x", "x"], ["y", "x"], ["w"], []])
def test_bad_task_axes_name_the_key(user_folder, axes):
    toml = user_folder / "scene.toml"
    toml.write_text(scenario_text("planar4.urdf").replace('task_axes = ["x", "y"]', f"task_axes = {axes}".replace("'", '"')))
    with pytest.raises(ConfigError) as info:
        Scenario.load(toml).build_robot()
    assert info.value.key == "robot.task_axes"
