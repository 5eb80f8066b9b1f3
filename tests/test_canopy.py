"""The seeded canopy: what it grows, the promises it keeps, its reachability report, its scenario keys.

Independent references: Pinocchio's frame placement (a reachable fruit's configuration puts the task
point on it), python-fcl (clearances the generator kept with its own closed forms: branches off the
path and the arm, nothing at the start arm, no leaf in a fruit), the depth camera (the occluding leaves
hide part of each fruit from the scenario's camera).
"""

from __future__ import annotations

import itertools

import fcl
import numpy as np
import pinocchio as pin
import pytest

from qpctl import ConfigError, Obstacle, Scenario
from qpctl.scenario import depth_canopies
from qpctl.scenes.canopy import CanopyConfig, generate_canopy, link_capsules
from qpctl.simulation.camera import DepthCamera


@pytest.fixture(scope="module")
def scenario() -> Scenario:
    return Scenario.load("panda_canopy_depth")


def _capsule(a, b, r) -> fcl.CollisionObject:
    """A python-fcl capsule with the axis a–b (a sphere when a = b)."""
    axis = np.asarray(b, float) - np.asarray(a, float)
    length = float(np.linalg.norm(axis))
    if length < 1e-12:
        return fcl.CollisionObject(fcl.Sphere(r), fcl.Transform(np.asarray(a, float)))
    o = Obstacle("capsule", 0.5 * (np.asarray(a) + np.asarray(b)), radius=r, length=length, axis=axis)
    return fcl.CollisionObject(o.geometry(), o.transform(0.0))


def _fcl(o: Obstacle) -> fcl.CollisionObject:
    return fcl.CollisionObject(o.geometry(), o.transform(0.0))


def _distance(x, y) -> float:
    return float(fcl.distance(x, y, fcl.DistanceRequest(enable_signed_distance=True), fcl.DistanceResult()))


def test_what_it_grows(scenario):
    canopy = scenario.canopy()
    obs = canopy.obstacles
    assert canopy.count("leaf") == 300 and canopy.count("branch") == 12 and canopy.count("wire") == 3
    kinds = {(o.name.rstrip("0123456789"), o.shape, o.material, o.perceived) for o in obs}
    assert kinds == {("trunk", "capsule", "rigid", False), ("wire", "capsule", "rigid", False),
                     ("branch", "capsule", "rigid", True), ("leaf", "sphere", "soft", True)}
    assert len({o.name for o in obs}) == len(obs)
    again = generate_canopy(canopy.config, scenario.build_robot(), scenario.q0(scenario.build_robot()),
                            viewpoint=np.array([0.15, -0.8, 1.0]))
    assert [(o.name, o.position.tolist(), o.radius) for o in again.obstacles] == \
        [(o.name, o.position.tolist(), o.radius) for o in obs]
    other = Scenario.load("panda_canopy_depth", overrides=["canopy.seed=2"]).canopy()
    assert other.obstacles[20].position.tolist() != obs[20].position.tolist()


def test_reachable_fruits_are_reached_clear_of_everything_rigid(scenario):
    """Each reachable fruit's configuration: within the joint limits, the task point on the fruit
    (Pinocchio, 1 mm), every link d_safe clear of the trunk, the wires and the branches (python-fcl)."""
    robot = scenario.build_robot()
    canopy = scenario.canopy()
    d_safe = scenario.data["controller"]["d_safe"]
    rigid = [_fcl(o) for o in canopy.obstacles if o.material == "rigid"]
    data = robot.model.createData()
    reachable = [f for f in canopy.fruits if f.reachable]
    assert reachable and np.allclose(np.sort(canopy.waypoints, axis=0), np.sort([f.position for f in reachable], axis=0))
    for f in reachable:
        assert np.all(f.q >= robot.q_min) and np.all(f.q <= robot.q_max)
        pin.framesForwardKinematics(robot.model, data, f.q)
        assert np.linalg.norm(data.oMf[robot.ee_frame_id].translation - f.position) < 1e-3
        links = [_capsule(*c) for c in link_capsules(robot, f.q)]
        assert min(_distance(a, b) for a in links for b in rigid) >= d_safe - 1e-6


def test_path_and_start_kept_clear(scenario):
    """Branches keep the hand's capsule + d_safe off every leg of the path; nothing comes within 3 cm
    of the arm at its start; no leaf cuts into a fruit (python-fcl)."""
    robot = scenario.build_robot()
    canopy = scenario.canopy()
    q0 = scenario.q0(robot)
    hand = max(c.radius for c in robot.capsules)
    d_safe = scenario.data["controller"]["d_safe"]
    points = scenario.build_path(robot, q0).points
    legs = [_capsule(a, b, hand + d_safe) for a, b in itertools.pairwise(points)]
    branches = [_fcl(o) for o in canopy.obstacles if o.name.startswith("branch")]
    assert min(_distance(leg, b) for leg in legs for b in branches) >= 0.03 - 1e-6
    start = [_capsule(*c) for c in link_capsules(robot, q0)]
    assert min(_distance(a, _fcl(o)) for a in start for o in canopy.obstacles) >= 0.03 - 1e-6
    fruits = [_fcl(o) for o in canopy.scenery()]
    leaves = [_fcl(o) for o in canopy.obstacles if o.name.startswith("leaf")]
    assert min(_distance(f, leaf) for f in fruits for leaf in leaves) >= 0.0


def test_fruits_partly_behind_leaves(scenario):
    """From the scenario's camera, the leaves hide part of every fruit it would see without them, and
    at least two fruits stay partly in view."""
    robot = scenario.build_robot()
    camera = DepthCamera.from_scenario(scenario, robot)
    q0 = scenario.q0(robot)
    leaves = np.array([n.startswith("leaf") for n in camera.names[:len(camera.visible)]])
    seen = camera.render(q0, 0.0)[1].hit
    camera.visible[leaves] = False
    bare = camera.render(q0, 0.0)[1].hit
    partly = 0
    for f in scenario.scenery():
        k = camera.names.index(f.name)
        with_leaves, without = (seen == k).sum(), (bare == k).sum()
        if without:
            assert with_leaves < without
        partly += with_leaves > 0
    assert partly >= 2


def test_an_unreachable_fruit_is_reported_with_its_reason():
    """Seed 11's fruit0 hangs against a wire: the report says so, and its clearest configuration does
    cut into the wire (python-fcl); a canopy beyond the arm's reach is refused, each fruit's reason named."""
    scen = Scenario.load("panda_canopy_depth", overrides=["canopy.seed=11"])
    canopy = scen.canopy()
    robot = scen.build_robot()
    bad = [f for f in canopy.fruits if not f.reachable]
    assert bad and len(canopy.waypoints) == len(canopy.fruits) - len(bad)
    f = bad[0]
    assert "wire0" in f.reason and "cuts" in f.reason
    wire = next(o for o in canopy.obstacles if o.name == "wire0")
    links = [_capsule(*c) for c in link_capsules(robot, f.q)]
    assert min(_distance(a, _fcl(wire)) for a in links) < 0
    assert f.name in [x["name"] for x in canopy.summary()["fruits"] if not x["reachable"]]
    with pytest.raises(ConfigError) as err:
        Scenario.load("panda_canopy_depth", overrides=["canopy.row_x=1.6", "canopy.depth=0.3"])
    assert err.value.key == "canopy.seed" and "beyond the arm's reach" in str(err.value)


def test_the_scenario_uses_it(scenario):
    robot = scenario.build_robot()
    canopy = scenario.canopy()
    assert len(scenario.build_obstacles()) == len(canopy.obstacles)
    assert [o.name for o in scenario.scenery()] == [f.name for f in canopy.fruits]
    points = scenario.build_path(robot, scenario.q0(robot)).points
    assert np.allclose(points[1:], canopy.waypoints)
    camera = scenario.camera_config()
    assert camera.mount == "world" and camera.width == 640


def test_twenty_seeded_depth_canopies():
    scens = depth_canopies()
    assert [s.data["canopy"]["seed"] for s in scens] == list(range(1, 21))
    assert all(len(s.canopy().waypoints) >= 1 for s in scens)
    reached = sum(len(s.canopy().waypoints) for s in scens)
    assert 40 <= reached < 60  # most fruits reachable, a few against the row


@pytest.mark.parametrize(("overrides", "key"), [
    (["canopy.leaves=20"], "canopy.seed"),  # a [canopy] table without its seed
    (["canopy.seed=-1"], "canopy.seed"),
    (["canopy.seed=1", "canopy.leaves=-3"], "canopy.leaves"),
    (["canopy.seed=1", "canopy.fruits=0"], "canopy.fruits"),
    (["canopy.seed=1", "canopy.z_range=[0.5]"], "canopy.z_range"),
    (["canopy.seed=1", "canopy.z_range=[0.5, 0.6]"], "canopy.z_range"),
    (["canopy.seed=1", "canopy.leaf_radius=[0.0, 0.02]"], "canopy.leaf_radius"),
    (["canopy.seed=1", "canopy.depth=0.9"], "canopy.depth"),
    (["canopy.seed=1", "canopy.width=0"], "canopy.width"),
    (["canopy.seed=1", "canopy.row_x=0.4", "canopy.depth=0.1"], "canopy.row_x"),  # the trunk at the start
    (["canopy.seed=1", "canopy.fruit_radius=0"], "canopy.fruit_radius"),
])
def test_bad_canopy_keys_name_the_key(overrides, key):
    with pytest.raises(ConfigError) as err:
        Scenario.load("panda_canopy", overrides=overrides)
    assert err.value.key == key and err.value.source == "panda_canopy (packaged)"


def test_waypoints_come_from_a_canopy_or_the_file():
    raw = {"robot": {"kind": "panda"}, "path": {"duration": 3.0}, "sim": {"duration": 4.0}}
    with pytest.raises(ConfigError) as err:
        Scenario.from_dict(raw)
    assert err.value.key == "path.waypoints"
    scen = Scenario.from_dict({**raw, "canopy": {"seed": 4}})
    robot = scen.build_robot()
    assert np.allclose(scen.build_path(robot, scen.q0(robot)).points[1:], scen.canopy().waypoints)
    with pytest.raises(ConfigError) as err:
        Scenario.from_dict({"path": {"waypoints": [[1.0, -1.5]], "duration": 2.0}, "canopy": {"seed": 1}})
    assert err.value.key == "canopy.seed" and "spatial arm" in str(err.value)


def test_config_defaults_are_the_documented_ones():
    cfg = CanopyConfig()
    assert not cfg.enabled and (cfg.leaves, cfg.branches, cfg.fruits, cfg.wires) == (300, 12, 3, 3)


def test_a_table_of_defaults_written_back_is_no_canopy():
    """A validated scenario's data without its unset values (as written back to TOML) loads again with
    no canopy and no camera; a [canopy] that sets a key but not its seed is still an error."""
    data = Scenario.load("panda_canopy").data
    raw = {k: ({kk: vv for kk, vv in v.items() if vv is not None} if isinstance(v, dict) else v)
           for k, v in data.items()}
    again = Scenario.from_dict(raw)
    assert again.canopy() is None and not again.camera_config().enabled
    with pytest.raises(ConfigError) as err:
        Scenario.from_dict({**raw, "canopy": {**raw["canopy"], "leaves": 20}})
    assert err.value.key == "canopy.seed"
