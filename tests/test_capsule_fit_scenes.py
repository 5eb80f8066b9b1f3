"""Robots described by their own files, run: the mobile harvester (URDF + capsules file + SRDF), the
fitted Panda on panda_canopy, and ``qpctl fit-capsules`` from the command line.

The fruits' positions come from the scenario file; where the arm is comes from Pinocchio's
kinematics of the recorded joint positions (not from the controller's own task error)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from qpctl import Scenario
from qpctl.cli import main
from qpctl.run import simulate

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def test_mobile_harvester_reaches_every_fruit_along_the_row():
    scenario = Scenario.load(EXAMPLES / "mobile_harvester.toml")
    robot = scenario.build_robot()
    assert robot.nv == 10 and robot.srdf is not None and robot.srdf.name == "mobile_harvester.srdf"
    assert [c.name for c in robot.capsules][:2] == ["cart", "panda_link1"]
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
    # the arm alone could not: the cart travelled along the row
    assert np.ptp(traj.q[:, 0]) > 2.0
    # the arm's reach from its base at the start is < 0.86 m; the last fruit is ~2.9 m away from there
    pin.framesForwardKinematics(robot.model, data, traj.q[0])
    base = data.oMf[robot.model.getFrameId("panda_link0")].translation
    assert np.linalg.norm(fruits[-1] - base) > 2.5


@pytest.mark.slow
def test_fitted_panda_runs_panda_canopy_collision_free(tmp_path):
    out = tmp_path / "panda.toml"
    subprocess.run([sys.executable, "-m", "qpctl.cli", "fit-capsules", "panda", "--out", str(out)], check=True,
                   capture_output=True)
    # the paper law collides on this scene with the hand-made capsules too (-0.095 m; fitted: -0.092 m)
    for kind in ("qp", "hsu"):
        result = simulate(Scenario.load("panda_canopy", [f"robot.capsules={out}"]), kind=kind, progress=False)
        assert not result.metrics["collided"], kind


def test_fit_capsules_command(tmp_path, capsys):
    urdf = tmp_path / "arm.urdf"
    urdf.write_text("""<robot name="arm"><link name="base"/>
  <link name="l1"><inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial>
    <collision><origin xyz="0 0 0.2"/><geometry><box size="0.05 0.05 0.4"/></geometry></collision></link>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/><axis xyz="0 0 1"/>
    <limit lower="-3" upper="3" effort="10" velocity="2"/></joint></robot>""")
    out = tmp_path / "caps.toml"
    assert main(["fit-capsules", str(urdf), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "l1: 1 capsule from 8 collision vertices" in printed and f"-> {out}" in printed
    assert '[[capsule]]\nlink = "l1"' in out.read_text()
    assert main(["fit-capsules", str(tmp_path / "nope.urdf"), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "ROBOT: robot file not found" in err
    assert main(["fit-capsules", str(urdf), "--out", str(out), "--skip", "l9"]) == 2
    assert "--skip: no link 'l9'" in capsys.readouterr().err
