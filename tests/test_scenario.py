"""Scenario files: validation on load (one-line ConfigError naming file and key), overrides, builders."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

import qpctl
from qpctl import ConfigError, Scenario, packaged_scenarios
from qpctl.run import simulate

BASE = """\
name = "t"
[path]
waypoints = [[1.0, -1.5]]
duration = 1.0
[[obstacles]]
shape = "sphere"
position = [0.0, -1.2]
radius = 0.15
[sim]
dt = 0.001
duration = 0.2
"""


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "scenario.toml"
    path.write_text(text)
    return path


# Each bad file: the edit to BASE and the dotted key the error must name.
BAD_FILES = {
    "unknown key": (BASE.replace("[sim]", "[sim]\nfoo = 1"), "sim.foo"),
    "unknown top-level key": ("bogus = 1\n" + BASE, "bogus"),
    "unknown obstacle key": (BASE.replace("radius = 0.15", "radius = 0.15\ncolour = 'red'"), "obstacles[0].colour"),
    "wrong type": (BASE.replace("dt = 0.001", 'dt = "fast"'), "sim.dt"),
    "wrong type (bool for number)": (BASE.replace("duration = 1.0", "duration = true"), "path.duration"),
    "missing waypoints": (BASE.replace("waypoints = [[1.0, -1.5]]\n", ""), "path.waypoints"),
    "missing path duration": (BASE.replace("duration = 1.0\n", ""), "path.duration"),
    "negative dt": (BASE.replace("dt = 0.001", "dt = -0.001"), "sim.dt"),
    "bad obstacle radius": (BASE.replace("radius = 0.15", "radius = -0.15"), "obstacles[0].radius"),
    "bad obstacle shape": (BASE.replace('"sphere"', '"blob"'), "obstacles[0].shape"),
    "missing obstacle position": (BASE.replace("position = [0.0, -1.2]\n", ""), "obstacles[0].position"),
    "obstacles not an array": (BASE.replace("[[obstacles]]", "[obstacles]"), "obstacles"),
    "waypoint dimension": (BASE.replace("[[1.0, -1.5]]", "[[1.0, -1.5, 0.3]]"), "path.waypoints"),
    "unknown controller": (BASE + '[controller]\nkind = "pid"\n', "controller.kind"),
    "negative gain": (BASE + "[controller]\nkp = -1.0\n", "controller.kp"),
    "d_influence below d_safe": (BASE + "[controller]\nd_influence = 0.01\n", "controller.d_influence"),
    "unknown robot": (BASE + '[robot]\nkind = "kuka"\n', "robot.kind"),
    "q0 length": (BASE + "[robot]\nq0 = [1.0, 2.0]\n", "robot.q0"),
    "unknown integrator": (BASE.replace("[sim]", '[sim]\nintegrator = "leapfrog"'), "sim.integrator"),
}


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_bad_file_is_a_one_line_error_naming_file_and_key(tmp_path, case):
    text, key = BAD_FILES[case]
    path = _write(tmp_path, text)
    with pytest.raises(ConfigError) as exc:
        Scenario.load(path)
    assert exc.value.key == key
    message = str(exc.value)
    assert "\n" not in message
    assert str(path) in message and key in message


def test_base_file_is_valid(tmp_path):
    s = Scenario.load(_write(tmp_path, BASE))
    assert s.name == "t" and s.data["sim"]["dt"] == 0.001
    assert s.data["controller"]["kind"] == "paper"  # defaults filled in


def test_invalid_toml_and_missing_file(tmp_path):
    with pytest.raises(ConfigError) as exc:
        Scenario.load(_write(tmp_path, BASE.replace("dt = 0.001", "dt = = 1")))
    assert "not valid TOML" in str(exc.value) and "\n" not in str(exc.value)
    with pytest.raises(ConfigError, match="not found"):
        Scenario.load(tmp_path / "nope.toml")
    with pytest.raises(ConfigError, match="paper"):  # an unknown name lists the packaged ones
        Scenario.load("no-such-scenario")


BAD_SETS = {
    "controller.foo=1": "controller.foo",
    "sim=3": "sim",
    "sim.dt=abc": "sim.dt",
    "sim.dt=-1": "sim.dt",
    "controller.kp=-2": "controller.kp",
    "obstacles.radius=1": "obstacles.radius",
    "nosuch.key=1": "nosuch.key",
}


@pytest.mark.parametrize("item", sorted(BAD_SETS))
def test_bad_override_names_the_key(item):
    with pytest.raises(ConfigError) as exc:
        Scenario.load("paper", [item])
    assert exc.value.key == BAD_SETS[item]
    assert BAD_SETS[item] in str(exc.value) and "\n" not in str(exc.value)


@pytest.mark.parametrize("item", ["nokey", "=3"])
def test_malformed_override(item):
    with pytest.raises(ConfigError, match="--set"):
        Scenario.load("paper", [item])


def test_overrides_apply(paper_scenario):
    s = Scenario.load("paper", ["controller.v_ref=0.4", "sim.duration=0.3", 'controller.kind="hsu"', "controller.kind=qp"])
    assert s.data["controller"]["v_ref"] == 0.4
    assert s.data["sim"]["duration"] == 0.3
    assert s.data["controller"]["kind"] == "qp"  # last one wins; bare words are read as text
    # the packaged file is untouched by the overrides
    assert Scenario.load("paper").data["controller"]["v_ref"] == paper_scenario.data["controller"]["v_ref"] != 0.4


PACKAGED_RUN_S = 0.5  # [s] of each packaged scenario run with the QP (about 1 s of wall time in all)


def test_every_packaged_scenario_loads():
    """Every .toml file shipped in qpctl/scenarios is listed and loads under its own name, and a short
    run of it with the QP (built-in RK4) is finite, tracks the path, and is collision-free: the
    simulator's own clearance (every link against every obstacle) never goes negative, nor below d_safe
    by more than a millimetre (the barriers keep h = d − d_safe ≥ 0)."""
    folder = Path(qpctl.__file__).parent / "scenarios"
    names = packaged_scenarios()
    assert names == sorted(p.stem for p in folder.glob("*.toml")) and "paper" in names
    for name in names:
        scenario = Scenario.load(name, [f"sim.duration={PACKAGED_RUN_S}"])
        assert scenario.name == name
        result = simulate(scenario, kind="qp")
        traj, metrics = result.trajectory, result.metrics
        assert metrics["controller"] == "qp" and metrics["collided"] is False, (name, metrics)
        assert traj.t[-1] == pytest.approx(PACKAGED_RUN_S) and len(traj.t) == round(PACKAGED_RUN_S / traj.t[1]) + 1
        for key in ("q", "v", "tau", "x", "e_null", "clearance"):
            assert np.all(np.isfinite(getattr(traj, key))), (name, key)
        assert np.min(traj.clearance) >= 0.0, name
        assert np.min(traj.clearance) >= scenario.data["controller"]["d_safe"] - 1e-3, (name, np.min(traj.clearance))
        assert metrics["min_clearance"] == pytest.approx(np.min(traj.clearance))
        assert metrics["max_tracking_error"] < 0.01, (name, metrics["max_tracking_error"])  # [m]
        assert not metrics.get("qp_fallbacks") and set(metrics["qp_status_counts"]) == {"solved"}, (name, metrics)


def test_paper_scenario_matches_design(paper_scenario):
    """DESIGN.md §3: 3 unit 10 kg rods, vertical plane, g = 9.81 along −y, start at rest at (π, π/2, 0), RK4 1 ms."""
    s = paper_scenario
    robot = s.build_robot()
    assert robot.nv == 3 and robot.m == 2
    np.testing.assert_allclose(robot.model.gravity.linear, [0.0, -9.81, 0.0])
    assert pin.computeTotalMass(robot.model) == pytest.approx(30.0)
    q0 = s.q0(robot)
    np.testing.assert_allclose(q0, [np.pi, np.pi / 2, 0.0])
    path = s.build_path(robot, q0)
    np.testing.assert_allclose(path(0.0).x, [-1.0, -2.0], atol=1e-12)  # starts where the arm is
    assert not np.any(path(0.0).xd) and not np.any(path(path.end_time).xd)
    assert s.data["sim"]["dt"] == 0.001 and s.data["sim"]["integrator"] == "rk4"
    obstacles = s.build_obstacles()
    assert len(obstacles) >= 2
    for kind in ("paper", "hsu"):
        ctrl = s.build_controller(kind)
        assert ctrl.kind == kind
        tau = ctrl.torque(q0, np.zeros(3), 0.0)
        assert tau.shape == (3,) and np.all(np.isfinite(tau))
