"""Barrier gains and influence distance from the drives (issue 16, item 2; qpctl.barrier_design).

The design's formulas are checked against an integration of the barrier's boundary motion, its
drive means against a linear program over the torque box and its point Jacobian against finite
differences; the scenario key is checked end to end, and on a seeded soak scene under a torque-rate
limit where the hand-set barrier lets a link through, the designed one holds d_safe."""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest
import test_soak as soak
from scipy.optimize import linprog

from qpctl import ConfigError, Scenario
from qpctl.barrier_design import _directions, design, design_for, drive_means
from qpctl.dynamics import Dynamics
from qpctl.run import simulate


@pytest.mark.parametrize(("v", "a", "j"), [(1.0, 5.0, 50.0), (0.5, 2.0, 1e4), (2.0, 40.0, 30.0), (1.5, math.inf, 20.0)])
def test_boundary_motion_stays_within_the_drives(v, a, j):
    """From entry at h₀ = 2v/ω with ḣ₀ = −v, the boundary ḧ = −k₁ḣ − k₀h (integrated finely, not
    the closed form) needs at most a of deceleration and j of jerk, starts slack (ḧ(0) ≤ 0), never
    reaches h = 0, and one of the two bounds is tight."""
    d = design(v, a, j, d_safe=0.05, dt=1e-3)
    assert d.k1 == pytest.approx(2 * math.sqrt(d.k0))
    h, hd, dt = 2 * v / d.omega, -v, 1e-5
    acc = []
    for _ in range(int(12 / d.omega / dt)):
        hdd = -d.k1 * hd - d.k0 * h
        acc.append(hdd)
        h, hd = h + dt * hd + 0.5 * dt * dt * hdd, hd + dt * hdd
        assert h > 0
    acc = np.array(acc)
    jerk = np.abs(np.diff(acc)) / dt
    assert acc[0] <= 1e-9 and acc.max() <= a * (1 + 1e-3) and jerk.max() <= j * (1 + 1e-3)
    tight = acc.max() / a if d.limited_by == "deceleration" else jerk.max() / j
    assert tight == pytest.approx(1.0, rel=2e-3)
    lead = v * a / j if math.isfinite(a) else 0.0
    assert d.d_influence == pytest.approx(0.05 + 2 * v / d.omega + lead + v * 1e-3)


def test_design_refuses_unlimited_drives():
    with pytest.raises(ConfigError, match="finite torque or torque-rate"):
        design(1.0, math.inf, math.inf, 0.05, 1e-3)
    with pytest.raises(ConfigError, match="approach speed"):
        design(0.0, 1.0, 1.0, 0.05, 1e-3)


def test_drive_means_against_a_linear_program_and_finite_differences():
    """For the Panda at its home pose, the far end of one capsule and one direction: the deceleration
    the torques give (the box |u| ≤ τ_max − |g| pushed through nᵀJ_p M⁻¹) equals the optimum of a
    linear program over that box; J_p equals the finite-difference Jacobian of the point."""
    sc = Scenario.load("panda_canopy")
    robot = sc.build_robot()
    q = sc.q0(robot)
    model, data = robot.model, robot.model.createData()
    cap = robot.capsules[3]

    def point(qq):
        pin.forwardKinematics(model, data, qq)
        return data.oMi[cap.joint_id].act(np.asarray(cap.p1, float))

    eps = 1e-7
    Jfd = np.stack([(point(q + eps * e) - point(q - eps * e)) / (2 * eps) for e in np.eye(robot.nv)], axis=1)
    n = _directions(None)[11]
    M = pin.crba(model, data, q)
    M = np.triu(M) + np.triu(M, 1).T
    g = pin.computeGeneralizedGravity(model, data, q)
    box = np.maximum(robot.tau_max - np.abs(g), 0)
    row = n @ Jfd @ np.linalg.inv(M)
    lp = linprog(-row, bounds=list(zip(-box, box, strict=True)), method="highs")
    rate = np.broadcast_to(robot.tau_rate_max, (robot.nv,))
    lp_j = linprog(-row, bounds=list(zip(-rate, rate, strict=True)), method="highs")
    speed = float(np.abs(n @ Jfd) @ np.broadcast_to(robot.v_max, (robot.nv,)))
    # drive_means lists configurations × capsules × kept directions in order; find this entry's values
    means = drive_means(robot, q, 10.0, 1e-3, share=1.0)
    a_qdd = float(np.abs(n @ Jfd) @ np.broadcast_to(robot.qdd_max, (robot.nv,)))
    want = (min(10.0, speed), min(-lp.fun, a_qdd), -lp_j.fun)
    assert any(np.allclose(m, want, rtol=1e-5) for m in means), want


@pytest.mark.parametrize("name", ["panda_canopy", "paper"])
def test_design_for_is_the_slowest_omega_and_the_largest_influence(name):
    """Issue 22's guard: design_for's ω and influence distance against an enumeration written here over
    every point–direction of drive_means (itself held against a linear program above): ω the least of
    min(e·a/v, √(j/v)), d_i the largest of d_safe + 2v/ω + v·a/j + v·dt at that ω; and the scenario's
    controller gets that d_i. Taking the least influence (0.434 → 0.040 m on panda_canopy) fails here."""
    raw = Scenario.load(name).data
    overrides = {"barrier_design": "drives"}
    robot_raw = raw["robot"] if name != "paper" else {**raw["robot"], "tau_max": 1500.0, "tau_rate_max": 3000.0}
    sc = Scenario.from_dict({**raw, "robot": robot_raw, "controller": {**raw["controller"], **overrides}}, source="t")
    robot = sc.build_robot()
    dt, d_safe, v = raw["sim"]["dt"], raw["controller"]["d_safe"], d_speed(sc, robot)
    means = [(vv, a, j) for vv, a, j in drive_means(robot, sc.q0(robot), v, dt) if vv > 0]
    assert len(means) > 100
    omegas = [min(math.e * a / vv, math.sqrt(j / vv)) for vv, a, j in means]
    w = min(omegas)
    lead = [vv * a / j if math.isfinite(a) and math.isfinite(j) else 0.0 for vv, a, j in means]
    d_each = [d_safe + 2 * vv / w + ld + vv * dt for (vv, _, _), ld in zip(means, lead, strict=True)]
    d = design_for(robot, sc.q0(robot), v, d_safe, dt)
    assert d.omega == pytest.approx(w, rel=1e-12)
    assert d.d_influence == pytest.approx(max(d_each), rel=1e-12)
    assert max(d_each) - min(d_each) > 0.05  # [m]: the choice matters on this robot
    assert sc.build_controller("qp").gains.d_influence == pytest.approx(max(d_each), rel=1e-3)


def _soak_scene(name: str) -> dict:
    rng = np.random.default_rng(soak.SEED)
    for k in range(1, 200):
        raw = soak.panda_scene(rng, k) if k % 4 == 0 else soak.planar_scene(rng, k)
        if raw["name"] == name:
            return raw
    raise AssertionError(name)


def test_scenario_key_sets_the_controllers_barrier():
    raw = Scenario.load("panda_canopy").data
    sc = Scenario.from_dict({**raw, "controller": {**raw["controller"], "barrier_design": "drives"}}, source="t")
    robot = sc.build_robot()
    # the design from an approach speed recomputed here (the path sampled at 1 ms, not at 400 points)
    d = design_for(robot, sc.q0(robot), d_speed(sc, robot), raw["controller"]["d_safe"], raw["sim"]["dt"])
    ctrl = sc.build_controller("qp")
    assert (ctrl.config.barrier_k0, ctrl.config.barrier_k1) == pytest.approx((d.k0, d.k1), rel=1e-3)
    assert ctrl.gains.d_influence == pytest.approx(d.d_influence, rel=1e-3)
    assert ctrl.gains.d_influence == sc.gains(robot).d_influence
    assert sc.gains(robot).d_influence != raw["controller"]["d_influence"]
    for key, value, match in (("barrier_design", "auto", "manual"), ("approach_speed", -1.0, "must be a positive number")):
        with pytest.raises(ConfigError, match=match) as err:  # on load, naming the key once
            Scenario.from_dict({**raw, "controller": {**raw["controller"], "barrier_design": "drives", key: value}},
                               source="t")
        assert str(err.value).count(f"controller.{key}") == 1 and err.value.key == f"controller.{key}"
    no_limits = {**raw, "robot": {**raw["robot"], "tau_max": math.inf, "tau_rate_max": math.inf, "qdd_max": math.inf},
                 "controller": {**raw["controller"], "barrier_design": "drives"}}
    with pytest.raises(ConfigError, match="finite torque or torque-rate limits"):
        Scenario.from_dict(no_limits, source="t")


def d_speed(sc: Scenario, robot) -> float:
    """The "auto" approach speed, recomputed here: 1.5 × the path's peak speed (sampled at 1 ms) plus
    the fastest obstacle's (the canopy's are static)."""
    path = sc.build_path(robot, sc.q0(robot))
    total = float(path.starts[-1] + path.durations[-1])
    peak = max(float(np.linalg.norm(path(t).xd[:3])) for t in np.arange(0.0, total, 1e-3))
    assert all(not o.moving for o in sc.build_obstacles())
    return 1.5 * peak


def test_designed_barrier_holds_where_the_hand_set_one_lets_a_link_through():
    """soak-planar-82 (a torque-rate limit of its own, a fast path past an obstacle, valid start):
    with the soak's hand-drawn barrier the QP turns infeasible and a link goes 0.2 m into the
    obstacle; with barrier_design = "drives" the clearance stays ≥ d_safe − 1 mm, and no commanded
    torque changes faster than the limit on either run."""
    raw = _soak_scene("soak-planar-82")
    rate = raw["robot"]["tau_rate_max"]
    sc = Scenario.from_dict(raw, source=raw["name"])
    robot = sc.build_robot()
    assert Dynamics(robot, sc.build_obstacles()).compute(sc.q0(robot), np.zeros(robot.nv)).clearance >= \
        raw["controller"]["d_safe"]
    out = {}
    for mode in ("manual", "drives"):
        run = simulate(Scenario.from_dict({**raw, "controller": {**raw["controller"], "barrier_design": mode}},
                                          source=raw["name"]))
        tr = run.trajectory
        assert np.abs(np.diff(tr.tau, axis=0)).max() <= rate * (tr.t[1] - tr.t[0]) * (1 + 1e-6)
        out[mode] = float(tr.clearance.min()) - raw["controller"]["d_safe"]
    assert out["manual"] < -0.05 and out["drives"] >= -1e-3, out
