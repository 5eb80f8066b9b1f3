"""Self-collision pairs from a robot's SRDF (qpctl.robot.srdf, qpctl.geometry.self_collision).

The independent reference is Pinocchio's own SRDF reader: ``pin.removeCollisionPairs`` on the URDF's
collision geometry model with all pairs added; what it removes are the SRDF's pairs.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from qpctl import Scenario
from qpctl.errors import ConfigError
from qpctl.geometry.self_collision import fcl_self_distances, self_collision_pairs
from qpctl.robot.files import package_dirs
from qpctl.robot.model import RobotModel, example_robot_data_path
from qpctl.robot.srdf import disabled_pairs, find_srdf

URDF = example_robot_data_path("panda_description/urdf/panda.urdf")
SRDF = example_robot_data_path("panda_description/srdf/panda.srdf")
FINGERS = ["panda_finger_joint1", "panda_finger_joint2"]


def pinocchio_pairs(urdf, srdf) -> tuple[set[frozenset[str]], set[frozenset[str]]]:
    """(kept, removed) link pairs of the URDF's collision geometry, by Pinocchio's SRDF reader."""
    model = pin.buildModelFromUrdf(str(urdf))
    geom = pin.buildGeomFromUrdf(model, str(urdf), pin.COLLISION, package_dirs=package_dirs(urdf))
    link = [model.frames[o.parentFrame].name for o in geom.geometryObjects]
    geom.addAllCollisionPairs()
    every = {frozenset((link[p.first], link[p.second])) for p in geom.collisionPairs}
    pin.removeCollisionPairs(model, geom, str(srdf))
    kept = {frozenset((link[p.first], link[p.second])) for p in geom.collisionPairs}
    return kept, every - kept


def test_disabled_pairs_are_those_pinocchio_removes():
    robot = RobotModel.from_urdf(URDF, "panda_hand", locked_joints=FINGERS)
    ours = disabled_pairs(SRDF, robot.link_names())
    kept, removed = pinocchio_pairs(URDF, SRDF)  # Pinocchio pairs geometry on different joints only
    assert {p for p in ours if p in kept | removed} == removed
    assert not ours & kept
    assert len(ours) == 35  # the file's <disable_collisions> elements, all distinct


def test_srdf_pairs_leave_what_the_srdf_keeps(rng):
    robot = RobotModel.from_urdf(URDF, "panda_hand", locked_joints=FINGERS).with_robot_files()
    assert robot.srdf == SRDF.resolve()  # found beside the URDF
    sel = self_collision_pairs(robot, 0.02)
    kept, removed = pinocchio_pairs(URDF, SRDF)
    caps = robot.capsules
    model = robot.model
    for i, j in sel.pairs:  # some link pair of theirs Pinocchio keeps; two joints, neither the other's parent
        assert any(frozenset((a, b)) in kept for a in caps[i].links for b in caps[j].links)
        a, b = caps[i].joint_id, caps[j].joint_id
        assert a != b and model.parents[a] != b and model.parents[b] != a
    reasons = set(sel.excluded.values())
    assert reasons <= {"one rigid body", "adjacent", "disabled by the SRDF", "within d_safe at home"}
    for (i, j), why in sel.excluded.items():
        pairs = {frozenset((a, b)) for a in caps[i].links for b in caps[j].links} & (kept | removed)
        if why == "disabled by the SRDF":
            assert pairs <= removed
        elif why == "within d_safe at home":
            assert fcl_self_distances(robot, robot.q_home, [(i, j)])[0] <= 0.02
    # every pair of the L(L-1)/2 is kept or excluded, once
    assert len(sel.pairs) + len(sel.excluded) == len(caps) * (len(caps) - 1) // 2
    # the kept pairs are apart at home by more than d_safe (python-fcl)
    assert np.all(fcl_self_distances(robot, robot.q_home, sel.pairs) > 0.02)


def test_srdf_naming_a_link_the_model_lacks(tmp_path, panda_robot):
    bad = tmp_path / "bad.srdf"
    bad.write_text('<robot name="panda"><disable_collisions link1="panda_link1" link2="panda_link99"/></robot>')
    with pytest.raises(ConfigError, match=r"^robot\.srdf: bad\.srdf names link 'panda_link99', which the model "
                                          r"lacks; its links: panda_hand"):
        panda_robot.with_srdf(bad)
    bad.write_text("<robot name='panda'><disable_collisions link1=")
    with pytest.raises(ConfigError, match=r"robot\.srdf: bad\.srdf is not valid XML"):
        panda_robot.with_srdf(bad)
    with pytest.raises(ConfigError, match="SRDF not found"):
        panda_robot.with_srdf(tmp_path / "none.srdf")
    # the built-in Panda's hand-made capsules do not name their links: an SRDF cannot apply
    with pytest.raises(ConfigError, match="do not name their links"):
        panda_robot.with_robot_files(srdf=SRDF)


def test_scenario_finds_the_srdf_beside_an_example_robot_data_urdf():
    raw = {"robot": {"kind": "urdf", "urdf": "package://example-robot-data/robots/ur_description/urdf/ur5_robot.urdf",
                     "ee_frame": "tool0"},
           "path": {"waypoints": [[0.4, 0.2, 0.4]], "duration": 1.0}, "sim": {"duration": 0.01}}
    robot = Scenario.from_dict(raw).build_robot()
    assert robot.srdf is not None and robot.srdf.name == "ur5.srdf"
    assert frozenset(("shoulder_link", "upper_arm_link")) in robot.disabled_pairs
    raw["robot"]["srdf"] = "none"
    assert Scenario.from_dict(raw).build_robot().srdf is None
    raw["robot"]["srdf"] = "missing.srdf"
    with pytest.raises(ConfigError, match=r"robot\.srdf: SRDF not found"):
        Scenario.from_dict(raw)


def test_find_srdf_layouts(tmp_path):
    (tmp_path / "urdf").mkdir()
    (tmp_path / "srdf").mkdir()
    urdf = tmp_path / "urdf" / "arm_robot.urdf"
    assert find_srdf(urdf) is None
    (tmp_path / "srdf" / "arm.srdf").write_text("<robot/>")
    assert find_srdf(urdf) == tmp_path / "srdf" / "arm.srdf"
    (tmp_path / "urdf" / "arm_robot.srdf").write_text("<robot/>")
    assert find_srdf(urdf) == tmp_path / "srdf" / "arm.srdf"  # the srdf/ folder first
