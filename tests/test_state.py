"""Every Jacobian and drift term of :class:`TickState` against finite differences.

Independent quantities: world positions from a separate forward-kinematics pass (or the
hand-derived thin-rod model for the planar arm), and signed distances straight from python-fcl.

* Jacobians: central differences, step h = 1e-6 → truncation O(h²) ≈ 1e-12, rounding ≈ 1e-10;
  tolerance 1e-7 (absolute, positions are O(1 m)).
* Drifts J̇q̇ of body-fixed points: the second central difference of the point's world position
  along q(s) = q + s q̇, since d²/ds² p(q + s q̇) = J̇q̇ when q̈ = 0. Step 1e-4 → truncation
  ≈ 1e-9, rounding ≈ 1e-16/1e-8 = 1e-8; tolerance 1e-6 (drifts are O(1–10 m/s²)).
* ∂d/∂q = nᵀJ_p: central differences of python-fcl's signed distance, step 1e-6. Sphere and
  capsule obstacles get fcl's closed-form distances (exact to rounding: FD noise ≈ 1e-10), so the
  tolerance is 1e-6 (gradients are O(1 m)). Capsule–box distances come from fcl's GJK (libccd),
  whose distance is good to ~5e-6 m and whose obstacle witness point — hence n — only to ~1e-3
  (measured over 400 random Panda and planar configurations: median error of nᵀJ_p 2e-6, worst
  1.1e-3, independent of the FD step); the box tolerances are 1e-5 on the witness-point spacing
  and 5e-3 on the gradient, which still catch any sign or frame error (those are O(1)).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pinocchio as pin
import pytest

from qpctl import InvalidStateError, Obstacle
from qpctl.dynamics import Dynamics
from qpctl.robot.model import RobotModel

H_JAC = 1e-6
H_ACC = 1e-4


def fd_jacobian(f: Callable[[np.ndarray], np.ndarray], q: np.ndarray, h: float = H_JAC) -> np.ndarray:
    cols = []
    for i in range(q.size):
        dq = np.zeros_like(q)
        dq[i] = h
        cols.append((np.asarray(f(q + dq)) - np.asarray(f(q - dq))) / (2 * h))
    return np.stack(cols, axis=-1)


def fd_drift(f: Callable[[np.ndarray], np.ndarray], q: np.ndarray, v: np.ndarray, h: float = H_ACC) -> np.ndarray:
    """d²/ds² f(q + s v) at s = 0: the acceleration of the point at q̈ = 0, i.e. J̇ q̇."""
    return (np.asarray(f(q + h * v)) - 2 * np.asarray(f(q)) + np.asarray(f(q - h * v))) / h**2


class BodyPoint:
    """World position of a point fixed to joint ``jid``'s body, by an independent FK pass."""

    def __init__(self, robot: RobotModel, jid: int, q: np.ndarray, p_world: np.ndarray) -> None:
        self.robot, self.jid = robot, jid
        self.data = robot.model.createData()
        pin.forwardKinematics(robot.model, self.data, q)
        self.local = self.data.oMi[jid].actInv(np.asarray(p_world, float))

    def __call__(self, q: np.ndarray) -> np.ndarray:
        pin.forwardKinematics(self.robot.model, self.data, q)
        return self.data.oMi[self.jid].act(self.local)


def task_position(robot: RobotModel) -> Callable[[np.ndarray], np.ndarray]:
    data = robot.model.createData()

    def x(q: np.ndarray) -> np.ndarray:
        pin.framesForwardKinematics(robot.model, data, q)
        return data.oMf[robot.ee_frame_id].translation[list(robot.task_axes)].copy()

    return x


@pytest.fixture(params=["planar", "panda"])
def robot(request, planar, panda_robot) -> RobotModel:
    return planar if request.param == "planar" else panda_robot


def test_task_jacobian_and_drift_equal_finite_differences(robot, random_states):
    dyn = Dynamics(robot)
    x = task_position(robot)
    for q, v in random_states(robot, 5):
        s = dyn.compute(q, v, 0.0)
        np.testing.assert_allclose(s.x, x(q), atol=1e-12)
        np.testing.assert_allclose(s.J, fd_jacobian(x, q), atol=1e-7)
        np.testing.assert_allclose(s.xdot, fd_jacobian(x, q) @ v, atol=1e-7)
        np.testing.assert_allclose(s.drift, fd_drift(x, q, v), atol=1e-6)
        # J̇ itself: the time derivative of J along q(t) = q + t q̇.
        jdot_fd = (dyn.compute(q + H_JAC * v, v).J - dyn.compute(q - H_JAC * v, v).J) / (2 * H_JAC)
        s = dyn.compute(q, v, 0.0)
        np.testing.assert_allclose(s.jdot(), jdot_fd, atol=1e-7)
        np.testing.assert_allclose(s.jdot() @ v, s.drift, atol=1e-9)


def test_mass_matrix_and_bias_are_pinocchios(robot, random_states):
    """M symmetric and N = RNEA(q, q̇, 0): the inverse-dynamics definition of C q̇ + G."""
    dyn = Dynamics(robot)
    data = robot.model.createData()
    for q, v in random_states(robot, 3):
        s = dyn.compute(q, v)
        np.testing.assert_allclose(s.M, s.M.T, atol=0)
        np.testing.assert_allclose(s.N, pin.rnea(robot.model, data, q, v, np.zeros(robot.nv)), atol=1e-9)
        qdd = np.random.default_rng(1).normal(size=robot.nv)
        np.testing.assert_allclose(s.M @ qdd + s.N, pin.rnea(robot.model, data, q, v, qdd), atol=1e-9)


def test_link_segments_match_thin_rod_model(planar, thin_rod, random_states):
    dyn = Dynamics(planar)
    for q, v in random_states(planar, 5):
        s = dyn.compute(q, v)
        joints = thin_rod.joint_positions(q)
        np.testing.assert_allclose(s.segments[:, 0, :2], joints[:-1], atol=1e-12)
        np.testing.assert_allclose(s.segments[:, 1, :2], joints[1:], atol=1e-12)
        for k in range(3):  # mid-point Jacobians: the thin-rod model's, independent of Pinocchio
            np.testing.assert_allclose(s.link_jac[k, :2], thin_rod.point_jacobian(q, k, 0.5), atol=1e-12)
            np.testing.assert_allclose(s.link_jac[k, 2], 0.0, atol=1e-14)


def test_link_midpoint_jacobians_equal_finite_differences(robot, random_states):
    dyn = Dynamics(robot)
    for q, v in random_states(robot, 3):
        s = dyn.compute(q, v)
        for k, cap in enumerate(robot.capsules):
            point = BodyPoint(robot, cap.joint_id, q, s.segments[k].mean(axis=0))
            np.testing.assert_allclose(s.link_jac[k], fd_jacobian(point, q), atol=1e-7)


# -- pairs: witness points, their Jacobians and drifts, and ∂d/∂q ------------------------------------
def _obstacle_near(shape: str, robot: RobotModel, q: np.ndarray, rng: np.random.Generator,
                   velocity: np.ndarray | None = None) -> Obstacle:
    """An obstacle of ``shape`` beside a random link, 5–20 cm clear of it (no penetration)."""
    s = Dynamics(robot).compute(q, np.zeros(robot.nv))
    k = rng.integers(len(robot.capsules))
    a, b = s.segments[k]
    axis = (b - a) / np.linalg.norm(b - a)
    if robot.m == 2:
        side = np.array([-axis[1], axis[0], 0.0]) * rng.choice([-1.0, 1.0])
    else:
        side = np.cross(axis, rng.normal(size=3))
        side /= np.linalg.norm(side)
    extent = 0.12
    centre = a + rng.uniform(0.3, 0.7) * (b - a) + side * (robot.capsules[k].radius + extent * 1.8
                                                        + rng.uniform(0.05, 0.2))
    if robot.m == 2:
        centre[2] = 0.0
    kw: dict = {"velocity": velocity if velocity is not None else np.zeros(3)}
    if shape == "sphere":
        return Obstacle("sphere", centre, radius=extent, **kw)
    if shape == "box":
        return Obstacle("box", centre, size=np.array([extent, 1.5 * extent, extent]), **kw)
    axis_o = np.array([0.0, 0.0, 1.0]) if robot.m == 2 else rng.normal(size=3)
    return Obstacle("capsule", centre, radius=0.5 * extent, length=2 * extent, axis=axis_o, **kw)


@pytest.mark.parametrize("shape", ["sphere", "box", "capsule"])
def test_pair_jacobians_drifts_and_distance_gradient(robot, shape, rng, random_states):
    checked = 0
    for q, v in random_states(robot, 3):
        obstacle = _obstacle_near(shape, robot, q, rng)
        dyn = Dynamics(robot, [obstacle])
        s = dyn.compute(q, v)
        assert len(s.pairs) == len(robot.capsules)  # cutoff = inf: every link is a pair
        for r in range(len(s.pairs)):
            d = s.pairs.distance[r]
            if d < 0.02:  # ∂d/∂q is only claimed away from contact
                continue
            cap = robot.capsules[s.pairs.link[r]]
            point = BodyPoint(robot, cap.joint_id, q, s.pairs.p_link[r])
            Jp = s.pair_jac[r]
            np.testing.assert_allclose(Jp, fd_jacobian(point, q), atol=1e-7)
            np.testing.assert_allclose(s.pair_drift[r], fd_drift(point, q, v), atol=1e-6)
            n = s.pairs.normal[r]
            assert np.linalg.norm(n) == pytest.approx(1.0, abs=1e-9)
            # Witness points: d apart along n (n points from the obstacle to the link).
            np.testing.assert_allclose(s.pairs.p_link[r] - s.pairs.p_obstacle[r], d * n,
                                       atol=1e-5 if shape == "box" else 1e-9)

            link, obs = s.pairs.link[r], s.pairs.obstacle[r]

            def dist(qq: np.ndarray, dyn: Dynamics = dyn, link: int = link, obs: int = obs) -> float:
                p = dyn.compute(qq, np.zeros(robot.nv)).pairs
                return float(p.distance[(p.link == link) & (p.obstacle == obs)][0])

            grad_fd = fd_jacobian(dist, q)
            np.testing.assert_allclose(n @ Jp, grad_fd, atol=5e-3 if shape == "box" else 1e-6)
            checked += 1
    assert checked >= 3


def test_distance_rate_with_moving_obstacle(planar, rng):
    """ḋ = nᵀ(J_p q̇ − v_obs): finite difference of d along (q + t q̇, t), obstacle moving."""
    q, v = np.array([0.3, 0.8, -0.5]), np.array([0.7, -0.4, 0.9])
    vel = np.array([0.3, -0.2, 0.0])
    obstacle = _obstacle_near("sphere", planar, q, rng, velocity=vel)
    dyn = Dynamics(planar, [obstacle])
    s = dyn.compute(q, v, 0.5)
    h = 1e-6
    for r in range(len(s.pairs)):
        sel = (s.pairs.link[r], s.pairs.obstacle[r])

        def d_at(t: float, sel: tuple = sel) -> float:
            p = dyn.compute(q + (t - 0.5) * v, v, t).pairs
            return float(p.distance[(p.link == sel[0]) & (p.obstacle == sel[1])][0])

        rate_fd = (d_at(0.5 + h) - d_at(0.5 - h)) / (2 * h)
        np.testing.assert_allclose(s.pairs.v_obstacle[r], vel)
        assert s.pairs.normal[r] @ (s.pair_jac[r] @ v - s.pairs.v_obstacle[r]) == pytest.approx(rate_fd, abs=1e-6)


@pytest.mark.parametrize("shape", ["sphere", "capsule", "box"])
def test_barrier_drift_equals_second_difference_of_distance(robot, shape, rng, random_states):
    """TickState.barrier_drift() is ḧ at q̈ = 0: the second central difference of the signed distance
    along (q + s q̇, t + s), the obstacle translating and swaying. Spheres and capsules are in closed
    form: tolerance 1e-5 m/s² (step 1e-4: truncation ≈ 1e-8, rounding ≈ 1e-16/1e-8). Boxes use the
    look-ahead finite difference (2 ms ahead, GJK's witness noise): 0.1 m/s² + 5 %."""
    checked = 0
    for q, v in random_states(robot, 3):
        obstacle = _obstacle_near(shape, robot, q, rng, velocity=rng.uniform(-0.3, 0.3, 3) * [1, 1, robot.m == 3])
        obstacle.amplitude, obstacle.frequency = rng.uniform(-0.1, 0.1, 3) * [1, 1, robot.m == 3], 0.7
        dyn = Dynamics(robot, [obstacle])
        t0 = float(rng.uniform(0.0, 1.0))
        s = dyn.compute(q, v, t0)
        drift = s.barrier_drift()
        h = 1e-4
        for r in range(len(s.pairs)):
            if s.pairs.distance[r] < 0.02:
                continue
            sel = (s.pairs.link[r], s.pairs.obstacle[r])

            def d_at(step: float, sel: tuple = sel, dyn: Dynamics = dyn, q: np.ndarray = q, v: np.ndarray = v,
                     t0: float = t0) -> float:
                p = dyn.compute(q + step * v, v, t0 + step).pairs
                return float(p.distance[(p.link == sel[0]) & (p.obstacle == sel[1])][0])

            hddot = (d_at(h) - 2 * d_at(0.0) + d_at(-h)) / h**2
            tol = 1e-5 if shape != "box" else 0.1 + 0.05 * abs(hddot)
            assert drift[r] == pytest.approx(hddot, abs=tol), (shape, r, drift[r], hddot)
            checked += 1
    assert checked >= 3


def test_barrier_drift_of_an_earlier_state_is_unchanged_by_later_ones(panda_robot, rng, random_states):
    """barrier_drift() is lazy: evaluated after the engine has moved on to another state (a moving
    capsule elsewhere), it still describes its own tick."""
    q, v = random_states(panda_robot, 1)[0]
    obstacle = _obstacle_near("capsule", panda_robot, q, rng, velocity=np.array([0.3, -0.2, 0.1]))
    dyn = Dynamics(panda_robot, [obstacle])
    now = dyn.compute(q, v, 0.2).barrier_drift()
    s = dyn.compute(q, v, 0.2)
    dyn.compute(q + 0.1, v, 1.7)  # the engine's obstacle has moved 0.45 m since
    np.testing.assert_array_equal(s.barrier_drift(), now)


def test_cutoff_limits_pairs_and_clearance(planar):
    q = planar.q_home
    far = Obstacle("sphere", np.array([5.0, 5.0, 0.0]), radius=0.1)
    near = Obstacle("sphere", np.array([-1.0, -1.0, 0.0]) + np.array([0.3, 0.0, 0.0]), radius=0.1)
    s = Dynamics(planar, [far, near], cutoff=0.5).compute(q, np.zeros(3))
    # Link 2 runs from (−1, 0) to (−1, −1); the near sphere's centre is 0.3 m from it, so d = 0.15.
    assert set(s.pairs.obstacle.tolist()) == {1}
    assert s.clearance == pytest.approx(0.3 - 0.1 - planar.capsules[0].radius, abs=1e-9)
    assert Dynamics(planar, [far], cutoff=0.5).compute(q, np.zeros(3)).clearance == np.inf


@pytest.mark.parametrize("q, v", [([np.nan, 0, 0], [0, 0, 0]), ([0, 0], [0, 0, 0]), ([0, 0, 0], [0, np.inf, 0])])
def test_invalid_state_is_rejected(planar, q, v):
    with pytest.raises(InvalidStateError):
        Dynamics(planar).compute(np.array(q, float), np.array(v, float))


def test_a_state_is_data_that_does_not_call_back(planar):
    """A TickState holds no reference to Dynamics: J̇ is in it where the law uses it (Dynamics.compute,
    a controller's snapshot under jdot_en), and asking for it elsewhere is an error, not a computation."""
    import dataclasses

    from qpctl import LawGains, WaypointPath
    from qpctl.controllers.qp import QPController

    q, v = np.array([np.pi, np.pi / 2, 0.0]), np.array([0.3, -0.2, 0.1])
    state = Dynamics(planar).compute(q, v, 0.1)
    assert "_dynamics" not in {f.name for f in dataclasses.fields(state)}
    assert state.jdot().shape == (2, 3)
    path = WaypointPath([[-1.0, -2.0], [1.0, -1.5]], duration=1.0)
    for jdot_en in (False, True):
        ctrl = QPController(planar, path, [], LawGains(jdot_en=jdot_en))
        ctrl.step(q, v, 0.1)
        snap = ctrl.workspace().snapshot()
        if jdot_en:
            np.testing.assert_allclose(snap.jdot(), state.jdot(), rtol=1e-12, atol=1e-12)
        else:
            with pytest.raises(ValueError, match="without J̇"):
                snap.jdot()
