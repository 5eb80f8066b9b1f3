"""Robot models against independent computations.

The planar arm's M(q), N(q, q̇) = C q̇ + G, end-effector position and 2×3 Jacobian are compared
with the hand-derived thin-rod model in ``conftest.ThinRodArm`` (Lagrangian of n planar rods;
Christoffel symbols from complex-step derivatives of that analytic M). Pinocchio works in double
precision on the same formulas, so agreement is to ~1e-12 relative; the tolerances below
(1e-9 relative to the matrix scale) leave room for rounding only, so any modelling slip
(wrong COM, inertia, gravity axis, joint offset) fails.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from qpctl import ConfigError, UnknownFrameError, load_robot, panda, planar_arm
from qpctl.robot.model import RobotModel, example_robot_data_path

RTOL = 1e-9


def _pin_terms(robot: RobotModel, q: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, ...]:
    model, data = robot.model, robot.model.createData()
    M = pin.crba(model, data, q)
    M = np.triu(M) + np.triu(M, 1).T
    N = pin.nonLinearEffects(model, data, q, v).copy()
    G = pin.computeGeneralizedGravity(model, data, q).copy()
    pin.framesForwardKinematics(model, data, q)
    x = data.oMf[robot.ee_frame_id].translation.copy()
    pin.computeJointJacobians(model, data, q)
    J = pin.getFrameJacobian(model, data, robot.ee_frame_id, pin.LOCAL_WORLD_ALIGNED)[:3].copy()
    return M, N, G, x, J


def test_planar_arm_matches_thin_rod_model(planar, thin_rod, random_states):
    for q, v in random_states(planar, 10):
        M, N, G, x, J = _pin_terms(planar, q, v)
        scale_M = np.abs(thin_rod.mass_matrix(q)).max()
        np.testing.assert_allclose(M, thin_rod.mass_matrix(q), rtol=0, atol=RTOL * scale_M)
        np.testing.assert_allclose(G, thin_rod.gravity(q), rtol=0, atol=RTOL * 3 * 10 * 9.81 * 3)
        N_ref = thin_rod.coriolis_vector(q, v) + thin_rod.gravity(q)
        np.testing.assert_allclose(N, N_ref, rtol=0, atol=RTOL * max(np.abs(N_ref).max(), 1.0))
        np.testing.assert_allclose(x[:2], thin_rod.ee(q), rtol=0, atol=1e-12)
        assert abs(x[2]) < 1e-14  # the arm stays in the x–y plane
        np.testing.assert_allclose(J[:2], thin_rod.ee_jacobian(q), rtol=0, atol=1e-12)
        np.testing.assert_allclose(J[2], 0.0, atol=1e-14)


def test_planar_arm_coriolis_is_quadratic_in_velocity(planar, thin_rod, rng):
    """C(q, q̇)q̇ scales with |q̇|² (a check of the reference model itself, not of Pinocchio)."""
    q, v = rng.uniform(-np.pi, np.pi, 3), rng.normal(size=3)
    c1 = thin_rod.coriolis_vector(q, v)
    np.testing.assert_allclose(thin_rod.coriolis_vector(q, 2 * v), 4 * c1, rtol=1e-12)
    # Skew-symmetry of Ṁ − 2C (a textbook identity): q̇ᵀ(Ṁ − 2C)q̇ = 0 ⇔ q̇ᵀ C q̇ = ½ q̇ᵀ Ṁ q̇.
    Mdot = np.einsum("ijk,k->ij", thin_rod.dM(q), v)
    assert v @ c1 == pytest.approx(0.5 * v @ Mdot @ v, rel=1e-10, abs=1e-10)


def test_planar_arm_conventions(planar):
    assert planar.nv == 3 and planar.m == 2 and planar.task_axes == (0, 1)
    np.testing.assert_allclose(planar.model.gravity.linear, [0.0, -9.81, 0.0])
    np.testing.assert_allclose(planar.q_home, [np.pi, np.pi / 2, 0.0])
    # The paper's start pose: link 1 along −x, links 2 and 3 straight down: tip at (−1, −2).
    data = planar.model.createData()
    pin.framesForwardKinematics(planar.model, data, planar.q_home)
    np.testing.assert_allclose(data.oMf[planar.ee_frame_id].translation, [-1.0, -2.0, 0.0], atol=1e-12)
    # Each capsule spans its link, from the joint to the next joint.
    for cap in planar.capsules:
        assert np.linalg.norm(cap.p1 - cap.p0) == pytest.approx(1.0)
    assert pin.computeTotalMass(planar.model) == pytest.approx(30.0)


def test_planar_arm_other_sizes(thin_rod, rng):
    """n, length, mass and gravity are honoured (4 links of 0.7 m, 2.5 kg, g = 3.7)."""
    robot = planar_arm(4, length=0.7, mass=2.5, gravity=3.7)
    ref = type(thin_rod)(4, 0.7, 2.5, 3.7)
    for _ in range(3):
        q, v = rng.uniform(-np.pi, np.pi, 4), rng.normal(size=4)
        M, N, _, x, J = _pin_terms(robot, q, v)
        np.testing.assert_allclose(M, ref.mass_matrix(q), atol=1e-12)
        np.testing.assert_allclose(N, ref.coriolis_vector(q, v) + ref.gravity(q), atol=1e-10)
        np.testing.assert_allclose(x[:2], ref.ee(q), atol=1e-12)
        np.testing.assert_allclose(J[:2], ref.ee_jacobian(q), atol=1e-12)


@pytest.mark.parametrize("kwargs, key", [({"length": -1.0}, "robot.length"), ({"mass": 0.0}, "robot.mass"),
                                         ({"radius": float("nan")}, "robot.radius")])
def test_planar_arm_rejects_bad_sizes(kwargs, key):
    with pytest.raises(ConfigError) as exc:
        planar_arm(**kwargs)
    assert exc.value.key == key


def test_load_robot_names():
    assert load_robot("planar3").nv == 3
    assert load_robot("planar5").nv == 5
    with pytest.raises(ConfigError) as exc:
        load_robot("planarX")
    assert exc.value.key == "robot.kind"
    with pytest.raises(ConfigError):
        load_robot("kuka")


def test_unknown_frame_lists_frames(planar):
    with pytest.raises(UnknownFrameError) as exc:
        planar.frame_id("gripper")
    assert "ee" in exc.value.available and "gripper" in str(exc.value)


# -- Panda ------------------------------------------------------------------------------------------
def test_panda_loads_offline_from_example_robot_data(no_network):
    """The URDF comes from the installed example-robot-data package; no network is touched."""
    import importlib.metadata

    urdf = example_robot_data_path("panda_description/urdf/panda.urdf")
    dist = importlib.metadata.distribution("example-robot-data")
    assert urdf.is_file()
    assert Path(dist.locate_file("")).resolve() in urdf.parents
    robot = panda()
    assert robot.name == "panda" and robot.nv == 7 and robot.m == 3
    assert robot.model.gravity.linear[2] == pytest.approx(-9.81)
    # The URDF's limits are carried over, fingers locked.
    assert np.all(np.isfinite(robot.q_min)) and np.all(robot.q_min < robot.q_max)
    np.testing.assert_allclose(robot.tau_max, [87, 87, 87, 87, 12, 12, 12])
    assert np.all(np.isfinite(robot.v_max)) and np.all(robot.v_max > 0)
    assert len(robot.capsules) == 7


def test_panda_task_point_is_offset_from_hand(panda_robot, random_states):
    """The task point is 0.1034 m along the hand's z axis (between the fingertips)."""
    model, data = panda_robot.model, panda_robot.model.createData()
    hand = model.getFrameId("panda_hand", pin.FrameType.BODY)
    for q, _ in random_states(panda_robot, 3):
        pin.framesForwardKinematics(model, data, q)
        oMh = data.oMf[hand]
        expected = oMh.translation + oMh.rotation @ np.array([0.0, 0.0, 0.1034])
        np.testing.assert_allclose(data.oMf[panda_robot.ee_frame_id].translation, expected, atol=1e-12)


def test_from_urdf_default_capsules_span_links(tmp_path):
    """Without capsules, each link gets one from its joint to its child joint."""
    urdf = example_robot_data_path("panda_description/urdf/panda.urdf")
    robot = RobotModel.from_urdf(urdf, "panda_hand", locked_joints=["panda_finger_joint1", "panda_finger_joint2"])
    assert robot.nv == 7 and len(robot.capsules) == 7
    for cap in robot.capsules[:-1]:
        child = cap.joint_id + 1
        np.testing.assert_allclose(cap.p1, robot.model.jointPlacements[child].translation)
    with pytest.raises(ConfigError):
        RobotModel.from_urdf(tmp_path / "missing.urdf", "x")
    with pytest.raises(UnknownFrameError):
        RobotModel.from_urdf(urdf, "no_such_frame")
