"""What a rest must clear (qpctl.safety.sweep, issue 22 items 2 and 4): the swaying obstacles' sweeps,
decided against python-fcl; a stopped arm the oracle no longer certifies where a swaying obstacle comes
back to it, nor where its creep reaches a static one.

References: the sweep of a sphere along its segment is a capsule, whose distance to the links python-fcl
gives (``DistanceEngine`` on a capsule obstacle); a box's sweep is sampled densely with python-fcl."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from qpctl import LawGains, Obstacle, WaypointPath, planar_arm
from qpctl.controllers.qp import QPConfig, QPController
from qpctl.geometry.distance import DistanceEngine
from qpctl.safety import certify, rollout
from qpctl.safety.rollout import BrakeRollout
from qpctl.safety.sweep import TOLERANCE, RestClearance, swaying
from qpctl.simulation import Simulator

DT = 2e-3
Q = np.array([np.pi, np.pi / 2, 0.0])


def segments(robot, q):
    data = robot.model.createData()
    pin.forwardKinematics(robot.model, data, q)
    return np.array([[data.oMi[c.joint_id].act(c.p0), data.oMi[c.joint_id].act(c.p1)] for c in robot.capsules])


def fcl_clearance(robot, q, obstacles, t=0.0):
    engine = DistanceEngine([c.radius for c in robot.capsules], obstacles, broadphase=False)
    engine.update(segments(robot, q), t)
    return engine.min_distance()


def controller(obstacles):
    robot = planar_arm(tau_max=1500.0).with_limits(tau_rate_max=3000.0)
    path = WaypointPath([[-1.0, -2.0], [1.0, -1.5]], duration=2.0)
    return QPController(robot, path, obstacles, LawGains(d_influence=0.3, d_safe=0.05), QPConfig())


def test_only_obstacles_that_sway_in_place_have_a_sweep():
    sway = Obstacle("sphere", [0.0, 0.0], radius=0.1, amplitude=[0.1, 0.0, 0.0], frequency=1.0)
    drift = Obstacle("sphere", [0.0, 0.0], radius=0.1, velocity=[0.1, 0.0, 0.0], amplitude=[0.1, 0.0, 0.0],
                     frequency=1.0)
    assert swaying(sway) and not swaying(drift)
    assert not swaying(Obstacle("sphere", [0.0, 0.0], radius=0.1))
    assert not swaying(Obstacle("sphere", [0.0, 0.0], radius=0.1, amplitude=[0.1, 0.0, 0.0], frequency=0.0))
    robot = planar_arm()
    assert not RestClearance(robot, [drift]) and RestClearance(robot, [sway, drift])


def test_a_spheres_sweep_is_cleared_as_python_fcl_measures_its_capsule(rng):
    """100 spheres swaying near the arm at rest: where python-fcl's distance from the links to the capsule
    the sphere sweeps exceeds the margin by more than the tolerance, the sweep is clear; where it is
    below the margin, it is not (both cases drawn)."""
    robot = planar_arm()
    seg = segments(robot, Q)
    margin, seen = 0.02, {True: 0, False: 0}
    for _ in range(100):
        link = seg[rng.integers(3)]
        p0 = link[0] + rng.uniform(0, 1) * (link[1] - link[0]) + np.r_[rng.normal(0, 0.4, 2), 0.0]
        amp = np.r_[rng.normal(0, 0.2, 2), 0.0]
        r = float(rng.uniform(0.05, 0.15))
        sway = Obstacle("sphere", p0, radius=r, amplitude=amp, frequency=float(rng.uniform(0.3, 1.5)))
        a = float(np.linalg.norm(amp))
        swept = Obstacle("capsule", p0, radius=r, length=2 * a, axis=amp / a)
        exact = fcl_clearance(robot, Q, [swept])
        clear = RestClearance(robot, [sway]).clear(Q, margin)
        if exact > margin + TOLERANCE:
            assert clear, exact
            seen[True] += 1
        elif exact < margin:
            assert not clear, exact
            seen[False] += 1
    assert min(seen.values()) >= 10, seen


def test_a_boxs_sweep_is_cleared_as_python_fcl_samples_it(rng):
    """40 boxes swaying near the arm: the decision agrees with python-fcl's least distance over 2001
    positions along the sweep (1 mm apart at most) wherever that least distance is more than 1 mm from
    the margin."""
    robot = planar_arm()
    seg = segments(robot, Q)
    margin, agreed = 0.02, 0
    for _ in range(40):
        link = seg[rng.integers(3)]
        p0 = link[0] + rng.uniform(0, 1) * (link[1] - link[0]) + np.r_[rng.normal(0, 0.35, 2), 0.0]
        amp = np.r_[rng.normal(0, 0.15, 2), 0.0]
        box = Obstacle("box", p0, size=[0.2, 0.1, 0.3], amplitude=amp, frequency=0.8)
        engine = DistanceEngine([c.radius for c in robot.capsules], [box], broadphase=False)
        least = np.inf
        for t in np.arcsin(np.linspace(-1, 1, 2001)) / (2 * np.pi * 0.8):
            engine.update(seg, t)
            least = min(least, engine.min_distance())
        if abs(least - margin) > 1e-3:
            assert RestClearance(robot, [box]).clear(Q, margin) == (least > margin), least
            agreed += 1
    assert agreed >= 30


def test_a_stop_where_a_swaying_sphere_comes_back_is_not_a_rest():
    """The arm at rest at q, a sphere swaying at 0.5 Hz up toward the tip of its vertical last link,
    0.27 m away at t = 0 (the oracle's rest window is 0.05 s): where the swing's end overlaps the tip's
    capsule by 0.03 m (at t = 0.5 s), no brake is verified — neither by the oracle nor by the guard's
    rollout —, though every rollout comes to rest with the sphere far; where the swing ends 0.06 m short
    of it, the same state is certified."""
    robot = planar_arm()
    tip = segments(robot, Q)[2, 1]  # (−1, −2): the last link hangs along −y
    r = 0.1
    for gap, viable in ((-0.03, False), (0.06, True)):
        end = tip[:2] + np.array([0.0, -(robot.capsules[2].radius + r + gap)])  # the swing's end, at t = 0.5 s
        sway = Obstacle("sphere", end - [0.0, 0.3], radius=r, amplitude=[0.0, 0.3, 0.0], frequency=0.5)
        ctrl = controller([sway])
        rest = np.zeros(3)
        gravity = pin.computeGeneralizedGravity(robot.model, robot.model.createData(), Q)
        assert fcl_clearance(robot, Q, [sway], 0.0) == pytest.approx(gap + 0.3, abs=1e-6)
        assert fcl_clearance(robot, Q, [sway], 0.5) == pytest.approx(gap, abs=1e-6)
        cert = certify(ctrl, Q, rest, gravity, 0.0, DT)
        assert cert.viable == viable and np.isfinite(cert.t_rest) and cert.min_clearance > 0.2
        lean = BrakeRollout(ctrl.robot, Simulator(ctrl, dt=DT, duration=DT).world, DT)
        assert lean.run(Q, rest, gravity, 0.0, 25.0, exact=False).viable == viable


def test_a_rest_within_its_creep_of_a_static_obstacle_is_not_verified():
    """The arm at rest but for joint 1 at 0.009 rad/s (under the rest speed) with a static sphere ahead
    of the tip: the κ = 25 brake comes to rest after 50 ms with its clearance above 0 all along in both
    cases, but where the sphere is 0.65 mm ahead the rest ends 0.09 mm from it and the creep still to
    come (Σρᵢ|q̇ᵢ|/κ, 0.32 mm) reaches it: the rest is not verified, by the oracle nor by the guard's
    rollout; 2 mm ahead (1.4 mm at rest) it is."""
    robot = planar_arm()
    data = robot.model.createData()
    v = np.array([0.009, 0.0, 0.0])
    pin.computeJointJacobians(robot.model, data, Q)
    tip = segments(robot, Q)[2, 1]
    J = pin.getJointJacobian(robot.model, data, 3, pin.LOCAL_WORLD_ALIGNED)
    ahead = J[:3] @ v + np.cross(J[3:] @ v, tip - data.oMi[3].translation)  # the tip's velocity
    ahead /= np.linalg.norm(ahead)
    gravity = pin.computeGeneralizedGravity(robot.model, data, Q)
    r = 0.1
    for gap, viable in ((6.5e-4, False), (2e-3, True)):
        sphere = Obstacle("sphere", tip[:2] + (robot.capsules[2].radius + r + gap) * ahead[:2], radius=r)
        ctrl = controller([sphere])
        assert fcl_clearance(robot, Q, [sphere]) == pytest.approx(gap, abs=1e-6)
        sim = Simulator(ctrl, dt=DT, duration=DT)
        cert = rollout(sim, Q, v, gravity, 0.0, 25.0, margin=0.0, stop_below=0.0)
        assert cert.viable == viable and np.isfinite(cert.t_rest) and cert.min_clearance > 0
        lean = BrakeRollout(ctrl.robot, sim.world, DT)
        assert lean.run(Q, v, gravity, 0.0, 25.0, exact=False).viable == viable


def test_a_rest_whose_creep_crosses_a_joint_limit_is_not_verified():
    """Joint 1 at 0.009 rad/s toward its upper limit, the κ = 25 brake: it travels 0.26 mrad before the
    oracle's rest (50 ms) and 0.36 mrad in all (0.009/25, the law's). With the limit 0.3 mrad ahead the
    rollout keeps it but the stop's end does not: not verified, by the oracle nor by the guard's
    rollout; 0.5 mrad ahead it is."""
    v = np.array([0.009, 0.0, 0.0])
    for ahead, viable in ((3e-4, False), (5e-4, True)):
        ctrl = controller([Obstacle("sphere", [3.0, 3.0], radius=0.1)])
        ctrl.robot.q_max[0] = Q[0] + ahead
        gravity = pin.computeGeneralizedGravity(ctrl.robot.model, ctrl.robot.model.createData(), Q)
        sim = Simulator(ctrl, dt=DT, duration=DT)
        cert = rollout(sim, Q, v, gravity, 0.0, 25.0, margin=0.0, stop_below=0.0)
        assert cert.viable == viable and np.isfinite(cert.t_rest)
        lean = BrakeRollout(ctrl.robot, sim.world, DT)
        assert lean.run(Q, v, gravity, 0.0, 25.0, exact=False).viable == viable


def inside(data, c, centre, r):
    """True if the ball (centre, r) lies inside capsule c posed by ``data``'s kinematics."""
    a, b = data.oMi[c.joint_id].act(c.p0), data.oMi[c.joint_id].act(c.p1)
    s = np.clip((centre - a) @ (b - a) / ((b - a) @ (b - a)), 0, 1)
    return np.linalg.norm(centre - (a + s * (b - a))) + r <= c.radius + 1e-12


@pytest.mark.parametrize("which", ["planar", "panda"])
def test_the_fixed_part_lies_inside_the_arm_in_every_configuration(which, rng):
    """fixed_part's balls and base capsules are inside the posed capsules of their links at 200 random
    configurations (point–segment distance + the ball's radius ≤ the capsule's radius); the planar arm's
    is the ball of its first capsule's radius about the base, the Panda's one about its first axis."""
    from qpctl.robot.model import panda
    from qpctl.safety.sweep import fixed_part

    robot = planar_arm() if which == "planar" else panda()
    fixed = fixed_part(robot)
    assert fixed and all(r > 0 for _, _, r in fixed)
    data = robot.model.createData()
    first = [c for c in robot.capsules if c.joint_id in (0, 1)]
    lo = np.where(np.isfinite(robot.q_min), robot.q_min, -np.pi)
    hi = np.where(np.isfinite(robot.q_max), robot.q_max, np.pi)
    for _ in range(200):
        q = rng.uniform(lo, hi)
        pin.forwardKinematics(robot.model, data, q)
        for p0, p1, r in fixed:
            assert np.allclose(p0, p1)  # balls: no base capsules on these robots

            assert any(inside(data, c, p0, r) for c in first)
    if which == "planar":
        assert len(fixed) == 1 and np.allclose(fixed[0][0], 0) and fixed[0][2] == pytest.approx(robot.capsules[0].radius)


def test_a_sphere_swinging_through_the_base_strikes_the_fixed_part_when_its_surface_reaches_it():
    """A sphere swaying along x through the planar arm's base: fixed_struck gives the first tick at which
    its centre, x(t) = x₀ + A sin(2πft), is within r + 0.05 m of the base (the analytic time); a sphere
    whose swing stops 2 cm short never strikes it, nor does a static one."""
    from test_soak_brake import fixed_struck

    r, f, x0 = 0.1, 0.5, 0.4
    for short, expect in ((-0.05, True), (0.02, False)):
        reach = r + 0.05 + short  # the swing's nearest centre to the base
        sway = Obstacle("sphere", [x0, 0.0], radius=r, amplitude=[-(x0 - reach), 0.0, 0.0], frequency=f)
        got = fixed_struck(controller([sway]), DT, 2.0)
        if not expect:
            assert got is None
            continue
        t = np.arange(0, 2.0 + DT / 2, DT)
        centre = x0 - (x0 - reach) * np.sin(2 * np.pi * f * t)
        assert got == pytest.approx(t[np.argmax(centre < r + 0.05)], abs=1e-12)
    assert fixed_struck(controller([Obstacle("sphere", [0.16, 0.0], radius=r)]), DT, 2.0) is None


def test_an_obstacles_speed_bound_bounds_its_centres_finite_difference_speed(rng):
    """speed_bound (|v| + 2πf|A|, the Lipschitz constant of the hold's and the lazy clearance's bounds)
    is at least the centre's speed from finite differences of position_at over 2,000 times, and is reached
    where drift and sway point the same way (within 1e-4 of the peak speed)."""
    for _ in range(20):
        v, a = rng.normal(0, 0.3, 3), rng.normal(0, 0.2, 3)
        o = Obstacle("sphere", [0.0, 0.0, 0.0], radius=0.1, velocity=v, amplitude=a, frequency=float(rng.uniform(0.1, 2)))
        t = np.linspace(0, 5, 2000)
        h = 1e-6
        speed = [np.linalg.norm(o.position_at(x + h) - o.position_at(x - h)) / (2 * h) for x in t]
        assert max(speed) <= o.speed_bound + 1e-6
    aligned = Obstacle("sphere", [0.0, 0.0, 0.0], radius=0.1, velocity=[0.2, 0, 0], amplitude=[0.1, 0, 0], frequency=1.0)
    h = 1e-6
    peak = np.linalg.norm(aligned.position_at(h) - aligned.position_at(-h)) / (2 * h)  # at t = 0 both add up
    assert peak == pytest.approx(aligned.speed_bound, abs=1e-4) and aligned.speed_bound == pytest.approx(0.2 + 0.2 * np.pi)
