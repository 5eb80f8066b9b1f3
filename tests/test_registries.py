"""Issue 15: adding an obstacle shape, a controller kind or a solver fast path is one class plus one
registry line, a scenario key is declared once (its dataclass field), and an unregistered name is a
clear error."""

from __future__ import annotations

import dataclasses
from typing import Any

import fcl
import numpy as np
import pytest

from qpctl.config import REQUIRED, schema_of
from qpctl.controllers.base import Controller, ControlOutput
from qpctl.controllers.config import ControllerConfig
from qpctl.controllers.factory import CONTROLLERS
from qpctl.controllers.qp import QPConfig
from qpctl.errors import ConfigError, UnknownSolverError
from qpctl.geometry.shapes import SHAPES, Geom, Shape, register_shape
from qpctl.law import LawGains
from qpctl.run import simulate
from qpctl.scenario import ARRAYS, SCHEMA, Scenario
from qpctl.solvers.base import FAST_PATH_SOLVERS, GenericSolver, make_solver
from qpctl.state import TickState

PLANAR = {"robot": {"kind": "planar3", "gravity": [0.0, -9.81, 0.0], "q0": [3.14159265358979, 1.5707963267949, 0.0]},
          "path": {"waypoints": [[-0.9, -1.9]], "duration": 1.0}, "sim": {"duration": 0.05}}


# -- an obstacle shape defined here: its geometry, its MuJoCo geom and its plot ---------------------
class Ellipsoid(Shape):
    """``size`` = the three semi-axes [m], axis-aligned."""

    name = "ellipsoid"

    def check(self, obs: Any, key: str) -> None:
        if obs.size is None or len(obs.size) != 3 or not np.all(np.asarray(obs.size) > 0):
            raise ConfigError(f"needs 3 positive semi-axes, got {obs.size}", key=f"{key}.size")
        obs.size = np.asarray(obs.size, float)

    def geometry(self, obs: Any) -> fcl.CollisionGeometry:
        return fcl.Ellipsoid(*obs.size)

    def bounding_radius(self, obs: Any) -> float:
        return float(np.max(obs.size))

    def mujoco_geom(self, obs: Any) -> Geom:
        return Geom("ellipsoid", tuple(float(s) for s in obs.size))

    def patch(self, obs: Any, centre: np.ndarray, **style: Any) -> Any:
        from matplotlib.patches import Ellipse

        return Ellipse((centre[0], centre[1]), 2 * obs.size[0], 2 * obs.size[1], **style)


def _with_ellipsoid(shape: str = "ellipsoid") -> dict[str, Any]:
    return dict(PLANAR, obstacles=[{"shape": shape, "position": [-0.3, -1.6], "size": [0.1, 0.05, 0.1]}],
                controller={"kind": "qp", "d_influence": 0.5})


def test_a_shape_defined_outside_the_package_runs_end_to_end(monkeypatch):
    monkeypatch.setitem(SHAPES, "ellipsoid", Ellipsoid())
    scen = Scenario.from_dict(_with_ellipsoid())
    (obs,) = scen.build_obstacles()
    assert obs.kind.name == "ellipsoid" and obs.bounding_radius() == 0.1
    result = simulate(scen)  # the QP's compiled tick: distances by python-fcl
    c = result.trajectory.clearance
    assert np.all(np.isfinite(c)) and c.min() > 0

    # python-fcl's ellipsoid distance, in the controller's engine, against a direct query
    from qpctl.geometry.distance import DistanceEngine

    seg = np.array([[[0.0, -1.3, 0.0], [0.0, -1.0, 0.0]]])
    engine = DistanceEngine([0.05], [obs], broadphase=False)
    engine.update(seg, 0.0)
    link = fcl.CollisionObject(fcl.Capsule(0.05, 0.3), fcl.Transform(rotation_to_y(), np.array([0.0, -1.15, 0.0])))
    other = fcl.CollisionObject(obs.geometry(), obs.transform(0.0))
    ref = fcl.distance(link, other, fcl.DistanceRequest(enable_nearest_points=True), fcl.DistanceResult())
    assert engine.pair(0, 0)[0] == pytest.approx(ref, abs=1e-6)

    # its MuJoCo geom (the MJCF of the built-in adapter) and its plot patch
    from matplotlib.patches import Ellipse

    from qpctl.plots import draw_obstacles

    pytest.importorskip("mujoco")
    from qpctl.adapters.mujoco import robot_mjcf

    assert 'type="ellipsoid"' in robot_mjcf(result.controller.robot, [obs])

    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    draw_obstacles(ax, [obs])
    assert [type(p) for p in ax.patches] == [Ellipse]
    plt.close(fig)


def rotation_to_y() -> np.ndarray:
    return np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # z → y


def test_an_unregistered_or_incomplete_shape_is_an_error():
    with pytest.raises(ConfigError, match=r"obstacles\[0\]\.shape.*unknown shape 'ellipsoid'; one of sphere, box"):
        Scenario.from_dict(_with_ellipsoid())

    class NoPlot(Shape):  # no MuJoCo geom, no patch: cannot be made, so cannot be registered
        name = "noplot"

        def check(self, obs: Any, key: str) -> None: ...

        def geometry(self, obs: Any) -> fcl.CollisionGeometry:
            return fcl.Sphere(1.0)

        def bounding_radius(self, obs: Any) -> float:
            return 1.0

    with pytest.raises(TypeError, match="abstract"):
        register_shape(NoPlot())  # type: ignore[abstract]
    with pytest.raises(ConfigError, match="must be a Shape"):
        register_shape("torus")  # type: ignore[arg-type]
    assert "noplot" not in SHAPES


# -- a controller kind defined here ----------------------------------------------------------------
class ComputedTorque(Controller):
    """Unweighted resolved acceleration with joint damping in the null space (no obstacle sensor)."""

    kind = "computed-torque"

    def control(self, state: TickState) -> ControlOutput:
        ref = self.reference(state)
        a = ref.xdd + self.gains.kv * (ref.xd - state.xdot) + self.gains.kp * (ref.x - state.x) - state.drift
        Jp = np.linalg.pinv(state.J)
        qdd = Jp @ a - self.gains.kn * (state.v - Jp @ (state.J @ state.v))
        return ControlOutput(state.M @ qdd + state.N, qdd, ref, state.x, np.zeros(state.n), state.clearance, False)


def test_a_controller_kind_defined_outside_the_package_runs_end_to_end(monkeypatch):
    monkeypatch.setitem(CONTROLLERS, "computed-torque", ComputedTorque)
    scen = Scenario.from_dict(dict(PLANAR, controller={"kind": "computed-torque", "kp": 50.0}))
    result = simulate(scen)
    assert isinstance(result.controller, ComputedTorque) and result.controller.gains.kp == 50.0
    assert result.metrics["controller"] == "computed-torque" and result.metrics["max_tracking_error"] < 1e-3
    # the built-in kinds are still there, through the same registry
    assert [type(scen.build_controller(k)).kind for k in ("paper", "hsu", "qp")] == ["paper", "hsu", "qp"]


def test_an_unregistered_controller_kind_is_an_error():
    with pytest.raises(ConfigError, match=r"<dict>: controller\.kind: unknown controller 'computed-torque'; "
                                          "one of paper, hsu, qp"):
        Scenario.from_dict(dict(PLANAR, controller={"kind": "computed-torque"}))
    with pytest.raises(ConfigError, match="unknown controller 'nope'"):
        Scenario.from_dict(PLANAR).build_controller("nope")


# -- each [controller] key declared once ------------------------------------------------------------
def test_every_key_is_one_dataclass_field_and_its_default_is_the_fields():
    from qpctl.paths import PathConfig
    from qpctl.robot.config import RobotConfig
    from qpctl.simulation.camera import CameraConfig
    from qpctl.simulation.faults import Faults
    from qpctl.simulation.loop import SimConfig

    tables = {"robot": (RobotConfig,), "path": (PathConfig,), "controller": (ControllerConfig, LawGains, QPConfig),
              "faults": (Faults,), "sim": (SimConfig,)}
    from qpctl.scenes.canopy import CanopyConfig

    tables["camera"], tables["canopy"] = (CameraConfig,), (CanopyConfig,)
    from qpctl.perception.config import PerceptionConfig

    tables["perception"] = (PerceptionConfig,)
    assert sorted(tables) == sorted(k for k, v in SCHEMA.items() if isinstance(v, dict) and k not in ARRAYS)
    for table, classes in tables.items():
        fields = [f for c in classes for f in dataclasses.fields(c) if f.name != "obstacle_v_ref"]
        assert len(fields) == len({f.name for f in fields}) and sorted(f.name for f in fields) == sorted(SCHEMA[table])
        for f in fields:
            default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
            assert SCHEMA[table][f.name][1] == (REQUIRED if default is dataclasses.MISSING else default), f.name
    from qpctl.geometry.obstacles import Obstacle
    from qpctl.scenario import OBSTACLE_SCHEMA

    assert sorted(OBSTACLE_SCHEMA) == sorted([f.name for f in dataclasses.fields(Obstacle)] + ["area"])
    from qpctl.paths import TaskConfig
    from qpctl.scenario import TASK_SCHEMA

    assert sorted(ARRAYS) == ["obstacles", "tasks"] and ARRAYS["tasks"] is TASK_SCHEMA
    assert sorted(TASK_SCHEMA) == sorted(f.name for f in dataclasses.fields(TaskConfig))
    assert OBSTACLE_SCHEMA["axis"][1] == Obstacle("sphere", np.zeros(3), radius=1.0).axis.tolist()


def test_a_new_key_is_one_field_with_its_rule():
    """What a contributor writes: a field; the schema reads its type and the rule is checked at
    construction, naming the key."""
    from qpctl.config import check_fields, setting

    @dataclasses.dataclass
    class Extra:
        needed: float = setting()
        horizon: float = setting(0.5, valid="positive", unit="s")
        label: str = "x"

        def __post_init__(self) -> None:
            check_fields(self, "controller")

    schema = schema_of(Extra)
    assert schema["horizon"][0](2) == 2.0 and schema["horizon"][1] == 0.5 and schema["needed"][1] is REQUIRED
    with pytest.raises(TypeError):
        schema["label"][0](3)
    with pytest.raises(ConfigError, match=r"controller\.horizon: must be a positive number, got -1"):
        Extra(1.0, horizon=-1)
    with pytest.raises(TypeError, match="declared twice"):
        schema_of(Extra, Extra)


def test_a_broken_qp_setting_is_refused_at_construction_naming_the_key():
    with pytest.raises(ConfigError, match=r"controller\.barrier_k1: must be a positive number, got 0"):
        QPConfig(barrier_k1=0.0)
    with pytest.raises(ConfigError, match=r"x\.toml: controller\.joint_k0: must be a positive number, got -3"):
        Scenario.from_dict(dict(PLANAR, controller={"joint_k0": -3.0}), source="x.toml")


# -- a solver fast path --------------------------------------------------------------------------------
class CountingQuadprog(GenericSolver):
    """quadprog through the generic path, counting its solves: stands in for a new fast path."""

    fast_path = True

    def __init__(self, settings: dict[str, Any] | None = None) -> None:
        super().__init__("quadprog", settings)
        self.solves = 0

    def solve(self, problem: Any) -> Any:
        self.solves += 1
        return super().solve(problem)


def test_a_solver_fast_path_is_one_registry_line(monkeypatch):
    pytest.importorskip("quadprog")
    monkeypatch.setitem(FAST_PATH_SOLVERS, "quadprog", (f"{__name__}:CountingQuadprog", "counts its solves"))
    scen = Scenario.from_dict(dict(PLANAR, controller={"kind": "qp", "solver": "quadprog"}))
    ctrl = scen.build_controller()
    assert isinstance(make_solver("quadprog"), CountingQuadprog)
    assert type(make_solver("qpsolvers:quadprog")) is GenericSolver  # the generic path can still be forced
    out = ctrl.step(scen.q0(ctrl.robot), np.zeros(3), 0.0)
    solvers = (ctrl._solver, ctrl._solver_soft)  # the task hard, and with its slack
    assert all(isinstance(s, CountingQuadprog) for s in solvers)
    assert out.info["status"] == "solved" and sum(s.solves for s in solvers) == 1
    with pytest.raises(UnknownSolverError, match="no-such-solver"):
        make_solver("no-such-solver")


def test_a_choice_is_checked_on_load_naming_the_key():
    """ControllerConfig's and SimConfig's choices hold on load (broadphase used to wait for the build)."""
    with pytest.raises(ConfigError, match=r"x\.toml: controller\.broadphase: must be auto, on or off, got 'x'"):
        Scenario.from_dict(dict(PLANAR, controller={"broadphase": "x"}), source="x.toml")
    with pytest.raises(ConfigError, match=r"x\.toml: sim\.integrator: must be rk4 or euler, got 'rk45'"):
        Scenario.from_dict(dict(PLANAR, sim={"integrator": "rk45"}), source="x.toml")
