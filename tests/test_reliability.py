"""Reliability (issue 6): bad input is refused at the boundary with a named error (one line and exit
status 2 on the command line, nothing half-written); a failed solve goes down the configured fallback
chain within the tick budget and says so; singular configurations give bounded torques and are
reported. (Random states, scenes and gains: test_properties.py; the long run: test_soak.py.)
"""

from __future__ import annotations

import copy

import numpy as np
import pinocchio as pin
import pytest

from baselines import PaperController
from qpctl import (
    ConfigError,
    InvalidStateError,
    LawGains,
    Obstacle,
    QpctlError,
    Scenario,
    UnknownFrameError,
    UnknownSolverError,
    WaypointPath,
    planar_arm,
)
from qpctl.cli import main
from qpctl.controllers.qp import (
    BUILT_IN_FALLBACKS,
    FALLBACK_BRAKE,
    FALLBACK_CLOSED_FORM,
    FALLBACK_SAFE_STOP,
    QPConfig,
    QPController,
)
from qpctl.formulation import Formulation
from qpctl.law import law_terms
from qpctl.qp import Solution
from qpctl.robot.model import example_robot_data_path
from qpctl.run import simulate
from qpctl.simulation import Simulator
from qpctl.solvers import available_solvers
from qpctl.solvers.daqp_ import DAQPSolver
from qpctl.solvers.proxqp_ import ProxQPSolver
from qpctl.tasks.tasks import PostureTask

nan, inf = float("nan"), float("inf")

BASE = {
    "name": "reliability",
    "robot": {"kind": "planar3", "radius": 0.05},
    "path": {"waypoints": [[1.0, -1.5]], "duration": 1.0},
    "obstacles": [{"shape": "sphere", "position": [0.6, -0.6], "radius": 0.15}],
    "controller": {"kind": "qp"},
    "sim": {"dt": 0.002, "duration": 0.2},
}


def edited(**edits: object) -> dict:
    """BASE with dotted keys replaced (``obstacles[0].radius`` included)."""
    raw = copy.deepcopy(BASE)
    for dotted, value in edits.items():
        *path, last = dotted.replace("[0]", ".0").split(".")
        node: object = raw
        for part in path:
            node = node[int(part)] if part.isdigit() else node.setdefault(part, {})  # type: ignore[index]
        node[last] = value  # type: ignore[index]
    return raw


def one_line(err: str, *needles: str) -> None:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("qpctl: "), err
    assert "Traceback" not in err
    for needle in needles:
        assert needle in lines[0], (needle, err)


# ------------------------------------------------------------------------------------------------
# 1. Input validation at the boundary
# ------------------------------------------------------------------------------------------------
BAD_SCENARIOS = {
    # edits, the dotted key the error names, a word of its message
    "waypoint out of reach": ({"path.waypoints": [[3.5, 0.0]]}, "path.waypoints", "out of reach"),
    "waypoint out of reach (2nd)": ({"path.waypoints": [[1.0, -1.5], [0.0, 3.01]]}, "path.waypoints", "reach"),
    # link 2 runs from (−1, 0) to (−1, −1) at the start pose (π, π/2, 0)
    "obstacle penetrates a link": ({"obstacles[0].position": [-1.0, -0.5], "obstacles[0].radius": 0.1},
                                   "obstacles[0]", "penetrates"),
    "q0 not finite": ({"robot.q0": [nan, 0.0, 0.0]}, "robot.q0", "finite"),
    # the arm folded back on itself: link 3 lies across link 1 (issue 22, item 5)
    "links overlap at the start": ({"robot.q0": [0.71, 2.74, 3.13]}, "robot.q0", "self_d_safe"),
    "zero link radius": ({"robot.radius": 0.0}, "robot.radius", "positive"),
    "negative link radius": ({"robot.radius": -0.05}, "robot.radius", "positive"),
    "zero obstacle radius": ({"obstacles[0].radius": 0.0}, "obstacles[0].radius", "positive"),
    "zero kp": ({"controller.kp": 0.0}, "controller.kp", "positive"),
    "negative kv": ({"controller.kv": -1.0}, "controller.kv", "positive"),
    "negative kn": ({"controller.kn": -1.0}, "controller.kn", ">= 0"),
    "NaN v_ref": ({"controller.v_ref": nan}, "controller.v_ref", ">= 0"),
    "negative d_safe": ({"controller.d_safe": -0.01}, "controller.d_safe", ">= 0"),
    "zero barrier gain": ({"controller.barrier_k0": 0.0}, "controller.barrier_k0", "positive"),
    "negative joint gain": ({"controller.joint_k1": -1.0}, "controller.joint_k1", "positive"),
    "zero speed gain": ({"controller.velocity_gain": 0.0}, "controller.velocity_gain", "positive"),
    "negative slack weight": ({"controller.slack_l1": -1.0}, "controller.slack_l1", ">= 0"),
    "negative tick budget": ({"controller.tick_budget_us": -1.0}, "controller.tick_budget_us", ">= 0"),
    "infinite tick budget": ({"controller.tick_budget_us": inf}, "controller.tick_budget_us", ">= 0"),
    "unknown fallback": ({"controller.fallback": ["nosuchsolver"]}, "controller.fallback", "nosuchsolver"),
    "fallback not a list": ({"controller.fallback": "closed-form"}, "controller.fallback", "list"),
    "zero time step": ({"sim.dt": 0.0}, "sim.dt", "positive"),
    "NaN time step": ({"sim.dt": nan}, "sim.dt", "positive"),
    "negative duration": ({"sim.duration": -1.0}, "sim.duration", "positive"),
    "zero path duration": ({"path.duration": 0.0}, "path.duration", "positive"),
    "NaN path start": ({"path.start_time": nan}, "path.start_time", "finite"),
    "zero torque limit": ({"robot.tau_max": 0.0}, "robot.tau_max", "positive"),
    "negative torque limit": ({"robot.tau_max": [100.0, -1.0, 100.0]}, "robot.tau_max", "positive"),
    "zero speed limit": ({"robot.v_max": 0.0}, "robot.v_max", "positive"),
}


@pytest.mark.parametrize("case", sorted(BAD_SCENARIOS))
def test_bad_scenario_is_a_named_error_naming_the_key(case):
    edits, key, word = BAD_SCENARIOS[case]
    with pytest.raises(ConfigError) as exc:
        Scenario.from_dict(edited(**edits), source="bad.toml")
    assert exc.value.key == key, str(exc.value)
    assert "bad.toml" in str(exc.value) and word in str(exc.value)
    assert "\n" not in str(exc.value)


def _planar_links(q: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The planar arm's unit links as (start, end) in its plane, by hand (angles summed along the chain)."""
    ends, angle, p = [], 0.0, np.zeros(2)
    for qi in q:
        angle += qi
        nxt = p + np.array([np.cos(angle), np.sin(angle)])
        ends.append((p, nxt))
        p = nxt
    return ends


def _sampled_distance(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> float:
    s = np.linspace(0.0, 1.0, 2001)[:, None]
    pa, pb = a[0] + s * (a[1] - a[0]), b[0] + s * (b[1] - b[0])
    return float(np.min(np.linalg.norm(pa[:, None] - pb[None], axis=2)))


def test_start_with_links_within_self_d_safe_is_refused():
    """Issue 22, item 5: along a fold of joint 3 (link 3 swung towards link 1), the starts whose link 1 –
    link 3 gap (axis distance by a sampled search, less both radii, computed here by hand) is below
    self_d_safe (0.1 m) are refused naming robot.q0; those beyond it load; without the self-collision
    barrier a refused one loads."""
    r, self_d_safe = BASE["robot"]["radius"], 0.1
    refused = accepted = 0
    for q3 in (0.9, 1.1, 1.25, 1.45, 1.7, 2.0):
        q0 = np.array([0.71, 2.74, q3])
        links = _planar_links(q0)
        gap = _sampled_distance(links[0], links[2]) - 2 * r
        raw = edited(**{"robot.q0": q0.tolist(), "controller.self_d_safe": self_d_safe})
        if gap < self_d_safe - 1e-4:
            with pytest.raises(ConfigError) as exc:
                Scenario.from_dict(raw, source="folded.toml")
            assert exc.value.key == "robot.q0" and "link1" in str(exc.value) and "link3" in str(exc.value)
            refused += 1
        elif gap > self_d_safe + 5e-3:
            Scenario.from_dict(raw, source="folded.toml")
            accepted += 1
    Scenario.from_dict(edited(**{"robot.q0": [0.71, 2.74, 2.0], "controller.self_collision": False}), source="t")
    assert refused >= 2 and accepted >= 2, (refused, accepted)


def _leaves(node: object, prefix: str = "") -> dict[str, object]:
    """Dotted key → value of every leaf of a nested dict/list (lists of tables indexed as ``obstacles.0``)."""
    if isinstance(node, dict):
        out: dict[str, object] = {}
        for key, value in node.items():
            out.update(_leaves(value, f"{prefix}.{key}" if prefix else key))
        return out
    if isinstance(node, list) and node and isinstance(node[0], dict):
        out = {}
        for i, value in enumerate(node):
            out.update(_leaves(value, f"{prefix}.{i}"))
        return out
    return {prefix: node}


def test_base_scenario_is_valid():
    """BASE — what every bad case above edits — loads as written (every key it gives kept, nothing
    dropped), builds the QP controller it names over its one obstacle, starts clear of that obstacle,
    and its first tick is solved with a finite torque: so each bad case fails because of its edit."""
    scenario = Scenario.from_dict(edited(), source="base.toml")
    data = _leaves(scenario.data)
    for key, value in _leaves(BASE).items():
        assert data[key] == value, (key, data.get(key), value)
    ctrl = scenario.build_controller()
    assert isinstance(ctrl, QPController) and ctrl.robot.nv == 3
    assert len(ctrl.obstacles) == 1 and ctrl.obstacles[0].shape == "sphere"
    np.testing.assert_array_equal(ctrl.obstacles[0].position, [0.6, -0.6, 0.0])
    assert ctrl.obstacles[0].radius == 0.15
    q0 = scenario.q0(ctrl.robot)
    np.testing.assert_allclose(q0, Q0)
    # the start pose's links: (0, 0)→(−1, 0)→(−1, −1)→(−1, −2); the sphere's centre is 0.6√2 m from the
    # first link's end at the base, so 0.6√2 − 0.15 − 0.05 ≈ 0.65 m clear — beyond d_influence (0.3 m)
    out = ctrl.step(q0, np.zeros(3), 0.0)
    assert out.clearance > ctrl.gains.d_influence
    assert out.info["status"] == "solved" and "fallback" not in out.info
    assert np.all(np.isfinite(out.tau)) and np.all(np.abs(out.tau) < 1e3)


def test_q0_outside_the_joint_limits_names_the_joint():
    raw = {"robot": {"kind": "panda", "q0": [0.0] * 7}, "path": {"waypoints": [[0.4, 0.0, 0.5]], "duration": 1.0}}
    with pytest.raises(ConfigError, match="panda_joint4") as exc:  # joint 4 lives in [−3.07, −0.07] rad
        Scenario.from_dict(raw)
    assert exc.value.key == "robot.q0"


def test_panda_target_out_of_reach():
    raw = {"robot": {"kind": "panda"}, "path": {"waypoints": [[1.5, 0.0, 0.5]], "duration": 1.0}}
    with pytest.raises(ConfigError, match="out of reach") as exc:
        Scenario.from_dict(raw)
    assert exc.value.key == "path.waypoints"


def test_unknown_frame_lists_the_frames_that_exist(tmp_path):
    urdf = example_robot_data_path("panda_description/urdf/panda.urdf")
    raw = {"robot": {"kind": "urdf", "urdf": str(urdf), "ee_frame": "nope"},
           "path": {"waypoints": [[0.4, 0.0, 0.5]], "duration": 1.0}}
    with pytest.raises(UnknownFrameError) as exc:
        Scenario.from_dict(raw)
    assert isinstance(exc.value, QpctlError)
    assert "'nope'" in str(exc.value) and "panda_hand" in str(exc.value) and "panda_link0" in str(exc.value)


BAD_STATES = {
    "NaN q": (np.array([nan, 0.0, 0.0]), np.zeros(3), 0.1),
    "inf v": (np.zeros(3), np.array([0.0, inf, 0.0]), 0.1),
    "NaN t": (np.zeros(3), np.zeros(3), nan),
    "inf t": (np.zeros(3), np.zeros(3), inf),
    "short q": (np.zeros(2), np.zeros(3), 0.1),
    "column q": (np.zeros((3, 1)), np.zeros(3), 0.1),
    "long v": (np.zeros(3), np.zeros(4), 0.1),
    "array t": (np.zeros(3), np.zeros(3), np.array([0.1, 0.2])),
    "text t": (np.zeros(3), np.zeros(3), "0.1"),
    "bool t": (np.zeros(3), np.zeros(3), True),
    "None t": (np.zeros(3), np.zeros(3), None),
    "None q": (None, np.zeros(3), 0.1),
    "complex q": (np.zeros(3, complex), np.zeros(3), 0.1),
    "text q": (["a", "b", "c"], np.zeros(3), 0.1),
    "ragged q": ([1.0, [2.0, 3.0]], np.zeros(3), 0.1),
    "overflowing speeds": (np.zeros(3), np.full(3, 1e200), 0.1),
}


@pytest.fixture(scope="module")
def controllers():
    scen = Scenario.from_dict(edited())
    return {kind: scen.build_controller(kind) for kind in ("paper", "hsu", "qp")}


@pytest.mark.parametrize("kind", ["paper", "hsu", "qp"])
@pytest.mark.parametrize("case", sorted(BAD_STATES))
def test_bad_state_is_an_invalid_state_error(controllers, kind, case):
    q, v, t = BAD_STATES[case]
    with pytest.raises(InvalidStateError):
        controllers[kind].torque(q, v, t)


def test_cli_bad_input_is_one_line_exit_2_and_writes_nothing(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["simulate", "paper", "--set", "path.waypoints=[[3.5, 0.0]]", "--out", str(out), "--quiet"]) == 2
    one_line(capsys.readouterr().err, "path.waypoints", "out of reach")
    bad = tmp_path / "penetrating.toml"
    bad.write_text('[path]\nwaypoints = [[1.0, -1.5]]\nduration = 1.0\n'
                   '[[obstacles]]\nshape = "sphere"\nposition = [-1.0, -0.5]\nradius = 0.1\n')
    assert main(["simulate", str(bad), "--out", str(out), "--quiet"]) == 2
    one_line(capsys.readouterr().err, str(bad), "obstacles[0]", "penetrates")
    urdf = tmp_path / "frame.toml"
    urdf.write_text(f'[robot]\nkind = "urdf"\nurdf = "{example_robot_data_path("panda_description/urdf/panda.urdf")}"\n'
                    'ee_frame = "nope"\n[path]\nwaypoints = [[0.4, 0.0, 0.5]]\nduration = 1.0\n')
    assert main(["simulate", str(urdf), "--out", str(out), "--quiet"]) == 2
    one_line(capsys.readouterr().err, "unknown frame 'nope'", "panda_hand")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frame.toml", "penetrating.toml"]


def test_cli_unexpected_error_is_one_line_exit_3(tmp_path, capsys, monkeypatch):
    import qpctl.run

    def broken(*_args, **_kwargs):
        raise ZeroDivisionError("a bug\nover two lines")

    monkeypatch.setattr(qpctl.run, "simulate", broken)
    monkeypatch.delenv("QPCTL_DEBUG", raising=False)
    out = tmp_path / "out"
    assert main(["simulate", "paper", "--out", str(out), "--quiet"]) == 3
    one_line(capsys.readouterr().err, "internal error", "ZeroDivisionError", "a bug over two lines", "QPCTL_DEBUG")
    assert not out.exists()
    monkeypatch.setenv("QPCTL_DEBUG", "1")
    with pytest.raises(ZeroDivisionError):
        main(["simulate", "paper", "--out", str(out), "--quiet"])


def test_failed_write_into_an_existing_folder_leaves_it_as_it_was(tmp_path, capsys, monkeypatch):
    import qpctl.plots

    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")

    def broken(*_args, **_kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(qpctl.plots, "write_figures", broken)
    assert main(["simulate", "paper", "--out", str(out), "--set", "sim.duration=0.01", "--quiet"]) == 2
    one_line(capsys.readouterr().err, "disk full")
    assert [p.name for p in tmp_path.iterdir()] == ["out"]  # no temporary folder left beside it
    assert [p.name for p in out.iterdir()] == ["notes.txt"]


def test_new_output_folder_appears_whole_with_a_normal_mode(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["simulate", "paper", "--out", str(out), "--set", "sim.duration=0.01", "--quiet",
                 "--no-figures"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["metrics.json", "replay.html", "scenario.toml", "trajectory.npz"]
    assert out.stat().st_mode & 0o077 == (0o777 & ~_umask()) & 0o077  # not mkdtemp's private 0700
    assert [p.name for p in tmp_path.iterdir()] == ["run"]


def _umask() -> int:
    import os

    mask = os.umask(0)
    os.umask(mask)
    return mask


# ------------------------------------------------------------------------------------------------
# 2. Solver failure policy: the fallback chain and the tick budget
# ------------------------------------------------------------------------------------------------
Q0 = np.array([np.pi, np.pi / 2, 0.0])  # links 2 and 3 hang down along x = −1
PATH = WaypointPath([[-1.0, -2.0], [1.0, -1.5]], duration=1.0)


def make_qp(obstacles=(), tau_max=400.0, gains=None, **cfg) -> QPController:
    """A planar-arm QP controller; the primary solver is proxqp unless ``solver`` says otherwise (the
    tests below make it fail by patching ProxQPSolver.solve)."""
    cfg.setdefault("solver", "proxqp")
    return QPController(planar_arm(tau_max=tau_max), PATH, list(obstacles), gains or LawGains(), QPConfig(**cfg))


def failing(status: str = "max_iter"):
    def solve(self, problem):
        return Solution(False, np.zeros(problem.n_var), status, 1000, 0.0, self.name)

    return solve


def test_solver_exception_is_a_failed_tick_not_a_crash(monkeypatch):
    def boom(self, problem):
        raise RuntimeError("backend exploded")

    monkeypatch.setattr(ProxQPSolver, "solve", boom)
    ctrl = make_qp()
    out = ctrl.step(Q0, np.zeros(3), 0.1)
    assert out.info["status"] == "error: RuntimeError"
    assert out.info["fallback"] == FALLBACK_CLOSED_FORM and out.info["fallback_reason"] == "error: RuntimeError"
    paper = PaperController(ctrl.robot, PATH, [], LawGains()).torque(Q0, np.zeros(3), 0.1)
    np.testing.assert_allclose(out.tau, paper, rtol=1e-12)  # within the limits: the paper law itself


class _Posture(PostureTask):
    """A task the compiled assembly does not know (any subclass): the tick takes the Python formulation."""


@pytest.mark.parametrize("path", ["compiled", "formulation"])
def test_non_finite_problem_never_reaches_a_solver(monkeypatch, path):
    """A NaN in the problem's data (poisoned here: a torque limit on the compiled path, the cost after
    Formulation.build on the Python path) is caught before any solver sees it; the chain takes over."""
    monkeypatch.setattr(ProxQPSolver, "solve", lambda self, problem: pytest.fail("solver called"))
    ctrl = make_qp(fallback=["daqp", FALLBACK_CLOSED_FORM])
    if path == "compiled":
        ctrl.workspace().tau_max[0] = nan
    else:
        build = Formulation.build

        def poisoned(self, state, terms, *, relax=True):
            problem = build(self, state, terms, relax=relax)
            problem.c[0] = nan
            return problem

        monkeypatch.setattr(Formulation, "build", poisoned)
        ctrl.add_task(_Posture(Q0, weight=1e-9))
    out = ctrl.step(Q0, np.zeros(3), 0.1)
    assert (ctrl.workspace().spec is None) == (path == "formulation")
    assert out.info["status"] == "nonfinite_problem"
    assert out.info["fallback_tried"] == ["daqp:nonfinite_problem"]
    assert out.info["fallback"] == FALLBACK_CLOSED_FORM and np.all(np.isfinite(out.tau))


def test_fallback_chain_is_tried_in_order(monkeypatch):
    monkeypatch.setattr(ProxQPSolver, "solve", failing("max_iter"))
    obstacles = [Obstacle("sphere", [-0.75, -1.5, 0.0], radius=0.1)]
    ctrl = make_qp(obstacles, fallback=["daqp", FALLBACK_CLOSED_FORM])
    v = np.array([0.0, 0.0, 1.0])
    out = ctrl.step(Q0, v, 0.1)
    assert out.info["status"] == "max_iter" and out.info["fallback"] == "daqp"
    assert "fallback_tried" not in out.info
    direct = make_qp(obstacles, solver="daqp").step(Q0, v, 0.1)
    np.testing.assert_allclose(out.tau, direct.tau, rtol=1e-9, atol=1e-9)  # the same QP, solved by daqp
    # daqp failing too: on to the closed form
    monkeypatch.setattr(DAQPSolver, "solve", failing("failed"))
    out = ctrl.step(Q0, v, 0.1)
    assert out.info["fallback_tried"][0] == "daqp:failed"
    assert out.info["fallback"] in (FALLBACK_CLOSED_FORM, FALLBACK_BRAKE)


@pytest.mark.parametrize("tau_max", [400.0, inf])
def test_chain_without_a_terminal_entry_ends_with_the_brake(monkeypatch, tau_max):
    """The QP fails and the chain is empty: the brake gives the torque (QPConfig's docstring):
    q̈ = k_v (g − q̇), g = 0 with no obstacle, scaled by the largest s ∈ [0, 1] that keeps M s q̈ + N
    within ±τ_max (direction kept), τ = M q̈ + N — checked against Pinocchio's M and N. At this state
    M q̈_brake + N = (−645, −162, −65) N·m: the 400 N·m limits scale it to s ≈ 0.39 (joint 1 at −400)."""
    monkeypatch.setattr(ProxQPSolver, "solve", failing("max_iter"))
    v = np.array([0.5, -0.5, 1.0])
    ctrl = make_qp(tau_max=tau_max, fallback=[])
    out = ctrl.step(Q0, v, 0.1)
    assert out.info["fallback"] == FALLBACK_BRAKE and out.info["fallback_reason"] == "max_iter"
    assert np.all(np.isfinite(out.tau))
    model = ctrl.robot.model
    data = model.createData()
    M = pin.crba(model, data, Q0)
    M = np.triu(M) + np.triu(M, 1).T
    N = pin.nonLinearEffects(model, data, Q0, v)
    brake = ctrl.gains.kv * (np.zeros(3) - v)
    s = float(out.qdd @ brake / (brake @ brake))
    np.testing.assert_allclose(out.qdd, s * brake, rtol=0, atol=1e-9 * np.abs(brake).max())  # the brake's direction
    np.testing.assert_allclose(out.tau, M @ out.qdd + N, rtol=1e-12, atol=1e-9)
    if np.isinf(tau_max):
        assert s == pytest.approx(1.0, rel=1e-12)  # nothing to scale
    else:
        # the largest scale within the limits: one joint exactly at its limit, none beyond
        assert 0.0 < s < 1.0
        assert np.all(np.abs(out.tau) <= tau_max * (1 + 1e-12))
        assert np.max(np.abs(out.tau)) == pytest.approx(tau_max, rel=1e-9)
        d, n0 = M @ brake, N
        s_max = min(((tau_max if di > 0 else -tau_max) - ni) / di for di, ni in zip(d, n0) if di != 0)
        assert s == pytest.approx(s_max, rel=1e-9)


def brake_acceleration(ctrl: QPController, q, v, t) -> np.ndarray:
    state = ctrl.dynamics.compute(q, v, t)
    terms = law_terms(state, ctrl.path(t), ctrl.gains, weighted=True)
    return ctrl.gains.kv * (terms.g - v)


def test_closed_form_brakes_when_a_link_is_within_d_safe(monkeypatch):
    """Link 3 (x = −1) touches the sphere's safety margin: the closed form is not trusted there; the
    brake backs the link away along the obstacle sensor's g."""
    monkeypatch.setattr(ProxQPSolver, "solve", failing("max_iter"))
    sphere = Obstacle("sphere", [-0.88, -1.5, 0.0], radius=0.05)  # 0.12 − 0.05 − 0.05 = 0.02 m < d_safe
    ctrl = make_qp([sphere], tau_max=inf, fallback=[FALLBACK_CLOSED_FORM])
    out = ctrl.step(Q0, np.zeros(3), 0.1)
    assert out.clearance < ctrl.gains.d_safe
    assert out.info["fallback"] == FALLBACK_BRAKE
    assert out.info["fallback_tried"] == ["closed-form:within_d_safe"]
    np.testing.assert_allclose(out.qdd, brake_acceleration(ctrl, Q0, np.zeros(3), 0.1), rtol=1e-9, atol=1e-12)
    state = ctrl.dynamics.compute(Q0, np.zeros(3), 0.1)
    i = int(np.argmin(state.pairs.distance))
    assert state.pairs.normal[i] @ state.pair_jac[i] @ out.qdd > 0  # the link accelerates away


def test_closed_form_brakes_when_it_would_break_a_barrier(monkeypatch):
    """Link 3 swings toward the sphere at 2.5 m/s: the paper law's q̈ violates the barrier row, so
    the brake is used; it decelerates the approach more than the paper law would."""
    monkeypatch.setattr(ProxQPSolver, "solve", failing("max_iter"))
    sphere = Obstacle("sphere", [-0.75, -1.5, 0.0], radius=0.1)  # 0.25 − 0.1 − 0.05 = 0.10 m > d_safe
    ctrl = make_qp([sphere], tau_max=inf, fallback=[FALLBACK_CLOSED_FORM])
    v = np.array([0.0, 0.0, 5.0])
    out = ctrl.step(Q0, v, 0.1)
    assert out.clearance > ctrl.gains.d_safe
    assert out.info["fallback_tried"] == ["closed-form:barrier_violated"] and out.info["fallback"] == FALLBACK_BRAKE
    paper = PaperController(ctrl.robot, PATH, [sphere], LawGains()).step(Q0, v, 0.1)
    state = ctrl.dynamics.compute(Q0, v, 0.1)
    i = int(np.argmin(state.pairs.distance))
    row = state.pairs.normal[i] @ state.pair_jac[i]
    assert row @ out.qdd > row @ paper.qdd


def test_fallback_torque_keeps_its_direction_within_the_limits(monkeypatch):
    """The brake (and the closed form) are scaled toward gravity compensation, not clipped per joint:
    τ − N stays parallel to M q̈ of the unlimited command."""
    monkeypatch.setattr(ProxQPSolver, "solve", failing("max_iter"))
    ctrl = make_qp(tau_max=300.0, fallback=[FALLBACK_BRAKE])
    q, v = np.array([-1.3, 0.3, 0.1]), np.array([2.0, -2.0, 3.0])
    out = ctrl.step(q, v, 0.1)
    assert np.max(np.abs(out.tau)) == pytest.approx(300.0)
    state = ctrl.dynamics.compute(q, v, 0.1)
    assert np.all(np.abs(state.N) < 300.0)
    want = state.M @ brake_acceleration(ctrl, q, v, 0.1)
    got = out.tau - state.N
    scale = (got @ want) / (want @ want)
    assert 0 < scale < 1
    np.testing.assert_allclose(got, scale * want, rtol=1e-9, atol=1e-9)


def barrier_rows(ctrl: QPController, q, v, t, qdd) -> np.ndarray:
    """ḧ + k₁ḣ + k₀h of every pair within d_influence at q̈, from a fresh state (its own Pinocchio data
    and distance queries): ≥ 0 where the barrier holds."""
    from qpctl.dynamics import Dynamics

    state = Dynamics(ctrl.robot, ctrl.obstacles, cutoff=ctrl.gains.d_influence).compute(q, v, t)
    pairs, drift = state.pairs, state.barrier_drift()
    barrier = next(c for c in ctrl.constraints if c.name == "obstacles")
    out = []
    for r in range(len(pairs)):
        n, Jp = pairs.normal[r], state.pair_jac[r]
        hdot = n @ (Jp @ v) - n @ pairs.v_obstacle[r]
        out.append(n @ (Jp @ qdd) + drift[r] + barrier.k1 * hdot + barrier.k0 * (pairs.distance[r] - ctrl.gains.d_safe))
    return np.array(out)


def test_safe_stop_decelerates_the_approach_harder_than_the_brake(monkeypatch):
    """Link 3 swings at 5 rad/s into a sphere with 400 N·m available: no q̈ keeps the barrier (the QP
    is infeasible). The safe stop stays within the torque limits and violates the barrier row less
    than the brake scaled into the same limits; where the barrier can hold, it holds it."""
    monkeypatch.setattr(ProxQPSolver, "solve", failing("primal_infeasible"))
    v = V_RUSH
    outs = {name: make_qp(RUSHING, fallback=[name]).step(Q0, v, 0.1) for name in (FALLBACK_SAFE_STOP, FALLBACK_BRAKE)}
    safe, brake = outs[FALLBACK_SAFE_STOP], outs[FALLBACK_BRAKE]
    assert safe.info["fallback"] == FALLBACK_SAFE_STOP and brake.info["fallback"] == FALLBACK_BRAKE
    assert np.all(np.abs(safe.tau) <= 400.0 + 1e-6) and np.all(np.isfinite(safe.tau))
    ctrl = make_qp(RUSHING)
    rows_safe, rows_brake = barrier_rows(ctrl, Q0, v, 0.1, safe.qdd), barrier_rows(ctrl, Q0, v, 0.1, brake.qdd)
    assert rows_safe.min() < 0  # infeasible indeed
    assert rows_safe.min() > rows_brake.min() + 1.0, (rows_safe, rows_brake)  # [m/s²]
    # a slower approach, which the limits can stop: the safe stop keeps every barrier row
    slow = np.array([0.0, 0.0, 0.5])
    out = make_qp(RUSHING, fallback=[FALLBACK_SAFE_STOP]).step(Q0, slow, 0.1)
    assert out.info["fallback"] == FALLBACK_SAFE_STOP
    assert barrier_rows(ctrl, Q0, slow, 0.1, out.qdd).min() >= -1e-6


# A soak scene (seed 20240611, scene 19) in which an obstacle drifting into the arm made the QP
# infeasible and the brake let a link through the sphere (−0.164 m).
DRIFTING_INTO_THE_ARM = {
    "name": "soak-planar-19",
    "robot": {"kind": "planar3", "q0": [2.5019764496454595, -1.5150506253479943, -1.8180443488793683],
              "tau_max": 791.4939068182964},
    "path": {"waypoints": [[0.43147917578681527, -0.326776354989431], [-1.771750372608427, -0.5553890297043779],
                           [-1.1985889318640504, -1.2269898509944486]], "duration": 2.744890155922677},
    "obstacles": [{"shape": "sphere", "position": [-1.0197062132309942, -0.4771797095878284, 0.0],
                   "radius": 0.1141377817851334, "velocity": [0.29506753811185, 0.037349027167102644, 0.0]}],
    "controller": {"kind": "qp", "solver": "quadprog", "damping": 0.0, "self_collision": False, "kp": 202.44698389719898, "kv": 33.63035195596057,
                   "kn": 1.5424848428808846, "v_ref": 0.5087639820325691, "d_safe": 0.05402102257055946,
                   "d_influence": 0.44134817960398104, "barrier_k1": 20.0, "barrier_k0": 84.45230828951159,
                   "tick_budget_us": 5000.0},
    "sim": {"dt": 0.002, "duration": 3.244890155922677},
}


def test_safe_stop_avoids_a_collision_the_brake_lets_through():
    clearance = {}
    for chain in (["daqp", FALLBACK_CLOSED_FORM], ["daqp", FALLBACK_CLOSED_FORM, FALLBACK_SAFE_STOP]):
        raw = copy.deepcopy(DRIFTING_INTO_THE_ARM)
        raw["controller"]["fallback"] = chain
        result = simulate(Scenario.from_dict(raw))
        assert np.all(np.abs(result.trajectory.tau) <= raw["robot"]["tau_max"] + 1e-6)
        clearance[chain[-1]] = result.metrics["min_clearance"]
        used = result.metrics.get("qp_fallbacks", {})
        assert set(used) <= {"daqp", FALLBACK_CLOSED_FORM, FALLBACK_SAFE_STOP, FALLBACK_BRAKE}
        if chain[-1] == FALLBACK_SAFE_STOP:
            assert used.get(FALLBACK_SAFE_STOP, 0) > 0, used
    assert clearance[FALLBACK_CLOSED_FORM] < -0.1  # the brake: a link through the sphere
    assert clearance[FALLBACK_SAFE_STOP] > 0.0, clearance  # measured: +0.056 m (d_safe 0.054 m)


def test_infeasible_ticks_fall_back_and_are_counted_in_the_metrics():
    """A sphere rushing at 3 m/s into an arm with 400 N·m: many ticks have no feasible q̈. The run goes
    on, every torque is within the limits, and metrics.json counts statuses and fallbacks."""
    raw = {"name": "rush", "robot": {"kind": "planar3", "tau_max": 400.0},
           "path": {"waypoints": [[-1.0, -2.0]], "duration": 1.0},
           "obstacles": [{"shape": "sphere", "position": [0.3, -1.5], "radius": 0.1, "velocity": [-3.0, 0.0]}],
           "controller": {"kind": "qp", "tick_budget_us": 5000.0, "fallback": ["daqp", "closed-form"]},
           "sim": {"dt": 0.002, "duration": 0.6}}
    result = simulate(Scenario.from_dict(raw), solver="osqp")
    m = result.metrics
    assert sum(m["qp_fallbacks"].values()) > 10, m["qp_fallbacks"]
    assert set(m["qp_fallbacks"]) <= {"daqp", FALLBACK_CLOSED_FORM, FALLBACK_BRAKE}
    assert set(m["qp_status_counts"]) - {"solved"}, m["qp_status_counts"]
    assert m["max_abs_torque"] <= 400.0 and np.all(np.isfinite(result.trajectory.tau))
    reasons = {i["fallback_reason"] for i in result.trajectory.infos if "fallback" in i}
    assert reasons and "solved" not in reasons


# -- the tick budget ---------------------------------------------------------------------------------
RUSHING = [Obstacle("sphere", [-0.8, -1.5, 0.0], radius=0.1)]  # link 3 at d_safe, swinging into it
V_RUSH = np.array([0.0, 0.0, 5.0])
PATHOLOGICAL = {  # settings under which each solver, unbounded, spends 0.1–5 s on this tick
    "proxqp": {},  # proxsuite stalls on the infeasible QP: ~1000 inner iterations per outer one
    "osqp": {"eps_abs": 1e-15, "eps_rel": 1e-15, "max_iter": 10**9, "polishing": False},
}


@pytest.mark.parametrize("solver", [s for s in PATHOLOGICAL if s in available_solvers()])
def test_tick_budget_bounds_a_pathological_tick(solver):
    """Unbounded, these ticks take seconds (proxqp: ~5 s); with a 3 ms budget the solver is stopped,
    the fallback acts, and the whole tick stays far below 100 ms (a coarse bound: the machine may be
    busy; the budget's own accuracy is measured by the soak)."""
    ctrl = make_qp(RUSHING, solver=solver, solver_settings=PATHOLOGICAL[solver], tick_budget_us=3000.0,
                   task_relaxation="always")
    for _ in range(3):
        out = ctrl.step(Q0, V_RUSH, 0.1)
        assert out.info["status"] in ("time_limit", "stalled", "primal_infeasible", "primal_infeasible_inaccurate"), out.info
        assert out.info["fallback"] in BUILT_IN_FALLBACKS
        assert out.compute_us < 50_000, out.compute_us
        assert np.all(np.abs(out.tau) <= 400.0)


def test_spent_budget_skips_every_further_solver():
    ctrl = make_qp(RUSHING, tick_budget_us=1e-3, fallback=["daqp", "osqp", FALLBACK_CLOSED_FORM])
    out = ctrl.step(Q0, V_RUSH, 0.1)
    assert out.info["status"] == "time_limit" and out.info["budget_exhausted"]
    assert out.info["fallback_tried"][:2] == ["daqp:time_limit", "osqp:time_limit"]
    assert out.info["fallback"] in (FALLBACK_CLOSED_FORM, FALLBACK_BRAKE)


def test_generous_budget_changes_nothing_on_a_normal_run():
    """The budget binds only when a tick would exceed it: on the paper scenario (1 s) a 50 ms budget
    gives the same torques as none, every tick solved."""
    taus = []
    for budget in (0.0, 50_000.0):
        scen = Scenario.load("paper", [f"controller.tick_budget_us={budget}", "sim.duration=1.0", "sim.dt=0.002"])
        ctrl = scen.build_controller("qp")
        traj = Simulator(ctrl, dt=0.002, duration=1.0).run(scen.q0(ctrl.robot))
        assert all(i["status"] == "solved" for i in traj.infos)
        taus.append(traj.tau)
    np.testing.assert_allclose(taus[0], taus[1], rtol=1e-8, atol=1e-8)


def test_fallback_configuration_is_checked_at_construction():
    with pytest.raises(ConfigError, match="list"):
        QPConfig(fallback="closed-form")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="tick_budget_us"):
        QPConfig(tick_budget_us=-5.0)
    with pytest.raises(UnknownSolverError):
        make_qp(fallback=["nosuchsolver"])


# ------------------------------------------------------------------------------------------------
# 3. Singularities, end to end (paper, hsu, qp)
# ------------------------------------------------------------------------------------------------
def run_singular(kind: str, q0, waypoints, duration: float, robot: dict | None = None,
                 controller: dict | None = None):
    raw = {"name": "singular", "robot": {"kind": "planar3", "q0": list(q0), **(robot or {})},
           "path": {"waypoints": waypoints, "duration": duration},
           "controller": {"kind": kind, **(controller or {})}, "sim": {"dt": 0.002, "duration": duration + 0.3}}
    return simulate(Scenario.from_dict(raw))


@pytest.mark.parametrize("kind", ["paper", "hsu", "qp"])
@pytest.mark.parametrize("start", ["outstretched", "hanging"])
def test_starting_at_a_singular_configuration(kind, start):
    """q = (0, 0, 0) (arm stretched along x: J has rank 1) and q = (−π/2, 0, 0) (stretched down, under
    gravity): finite, bounded torques; the damped ticks are flagged and counted in the metrics."""
    q0, target = ((0.0, 0.0, 0.0), [[1.5, -1.5]]) if start == "outstretched" else ((-np.pi / 2, 0.0, 0.0), [[1.0, -2.0]])
    result = run_singular(kind, q0, target, 1.2)
    traj, m = result.trajectory, result.metrics
    assert np.all(np.isfinite(traj.tau))
    # Bounded by the damping (‖J⁺‖ ≤ 1/(2 pinv_eps σ_max)); measured peaks: paper and qp 360–615 N·m,
    # hsu 4.8–6.2 kN·m (no inertia weighting: its null-space motion fights gravity at full speed).
    assert m["max_abs_torque"] < 2e4, m["max_abs_torque"]
    assert traj.singular[0] and m["singular_ticks"] == int(np.count_nonzero(traj.singular)) > 0
    assert m["final_tracking_error"] < 1e-2


@pytest.mark.parametrize("kind", ["hsu", "qp", "paper"])
def test_passing_near_the_outstretched_configuration(kind):
    """The path touches the workspace boundary (0, −3) — the arm stretched straight down — and comes
    back: bounded torque and finite state throughout, and within the QP's torque limits.

    The paper law runs with pinv_eps = 3e-2: at the default 1e-3 it passes the pose undamped
    (σ_min/σ_max ≈ 5e-3 there) and diverges — the README's "Reliability" section says so."""
    extra = {"qp": {"robot": {"tau_max": 1000.0}}, "paper": {"controller": {"pinv_eps": 3e-2}}}.get(kind, {})
    result = run_singular(kind, (np.pi, np.pi / 2, 0.0), [[0.0, -3.0], [1.5, -1.5]], 2.0, **extra)
    m = result.metrics
    assert np.all(np.isfinite(result.trajectory.tau)) and np.all(np.isfinite(result.trajectory.q))
    assert m["max_abs_torque"] < 2e4, m["max_abs_torque"]
    if kind == "qp":
        assert m["max_abs_torque"] <= 1000.0
    assert m["final_tracking_error"] < 1e-2
