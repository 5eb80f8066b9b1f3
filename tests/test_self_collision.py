"""Self-collision barriers (issue 11): the arm's own link capsules kept apart by the QP.

The closed-form distances of the tick are held against python-fcl; the barrier's ḣ row and its
drift (ḧ at q̈ = 0, both capsules turning) against central differences of the distance along the
motion; the barrier against a posture that folds the Panda into itself.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from qpctl import ConfigError, Scenario, Simulator, WaypointPath, panda
from qpctl.controllers.qp import QPConfig, QPController
from qpctl.geometry.self_collision import adjacent, fcl_self_distances, named_pairs, self_collision_pairs
from qpctl.kernels import codes


@pytest.fixture(scope="module")
def robot():
    return panda()


@pytest.fixture(scope="module")
def pairs(robot):
    return self_collision_pairs(robot, 0.02)


def _workspace(robot, pairs):
    path = WaypointPath([[0.3, 0.0, 0.5], [0.4, 0.0, 0.4]], duration=1.0)
    return QPController(robot, path, []).workspace(), path


def test_pairs_leave_out_adjacent_and_always_close_links(robot, pairs):
    """Every kept pair is non-adjacent and clear at home by python-fcl; every left-out pair has its
    reason, and the adjacent ones are exactly the joint–parent pairs."""
    L = len(robot.capsules)
    assert len(pairs.pairs) + len(pairs.excluded) == L * (L - 1) // 2
    home = fcl_self_distances(robot, robot.q_home, pairs.pairs)
    assert np.all(home > 0.02)
    for (i, j), why in pairs.excluded.items():
        assert (why == "adjacent") == adjacent(robot, i, j)
        if why == "within d_safe at home":
            assert fcl_self_distances(robot, robot.q_home, [(i, j)])[0] < 0.02 + 1e-3
    assert all(not adjacent(robot, i, j) for i, j in pairs.pairs)
    assert len(pairs.pairs) >= 10  # the Panda: 13 of 21


def test_named_pairs_and_bad_names(robot):
    assert named_pairs(robot, [["panda_joint5", "panda_joint1"]]).pairs == ((0, 4),)
    with pytest.raises(ConfigError) as info:
        named_pairs(robot, [["panda_joint1", "nope"]])
    assert info.value.key == "controller.self_collision_pairs"


def test_distances_match_python_fcl(robot, pairs):
    """The tick's closed-form capsule–capsule distances against python-fcl's, 30 random states."""
    ws, _ = _workspace(robot, pairs)
    assert tuple(map(tuple, ws.sc_pairs)) == pairs.pairs
    rng = np.random.default_rng(7)
    compared = 0
    for _ in range(30):
        q = rng.uniform(robot.q_min, robot.q_max)
        assert ws.state(q, np.zeros(7), 0.0) == 0
        ref = fcl_self_distances(robot, q, pairs.pairs)
        cut = ws.fpar[codes.FP_SCUT]
        exact = (ws.sc_d < cut) & (ref > 1e-4)  # python-fcl reports overlap as no distance
        np.testing.assert_allclose(ws.sc_d[exact], ref[exact], atol=1e-6)
        far = ws.sc_d >= cut  # beyond the cutoff: a lower bound, itself beyond it
        assert np.all(ws.sc_d[far] <= ref[far] + 1e-9) and np.all(ref[~far & (ref > 1e-4)] < cut + 1e-9)
        compared += int(exact.sum())
    assert compared > 60


def test_barrier_rate_and_drift_are_the_distance_derivatives(robot, pairs):
    """ḣ = row·q̇ and ḧ(q̈ = 0) = drift against central differences of the kernel's own distance along
    q(s) = q + s q̇ (Pinocchio's integrate), at random moving states, for pairs within the cutoff."""
    ws, _ = _workspace(robot, pairs)
    rng = np.random.default_rng(8)
    h = 1e-6
    checked = 0

    def at(q, v, s):
        ws.state(pin.integrate(robot.model, q, v * s), v, 0.0)
        return ws.sc_d.copy(), ws.sc_hdot.copy()

    for _ in range(25):
        q, v = rng.uniform(robot.q_min + 0.2, robot.q_max - 0.2), rng.normal(size=7)
        ws.state(q, v, 0.0)
        d, row, hdot, drift = ws.sc_d.copy(), ws.sc_row.copy(), ws.sc_hdot.copy(), ws.sc_drift.copy()
        near = (d > 1e-3) & (d < ws.fpar[codes.FP_SCUT])  # rows and drifts are computed within the cutoff only
        np.testing.assert_allclose(hdot[near], row[near] @ v, atol=1e-12)
        (dp, hp), (dm, hm) = at(q, v, h), at(q, v, -h)
        np.testing.assert_allclose(hdot[near], ((dp - dm) / (2 * h))[near], atol=1e-5)
        fd = ((hp - hm) / (2 * h))[near]
        assert np.all(np.abs(drift[near] - fd) <= 1e-4 * (1 + np.abs(fd))), (drift[near], fd)
        checked += int(near.sum())
    assert checked >= 20, checked


# A Panda configuration where capsules of a kept pair (links 1 and 6) overlap, half-way to which from
# home they are apart: a posture task pulling the arm there folds it into itself (checked below).
Q_FOLD = np.array([0.226, -1.245, -2.549, -2.874, 1.433, 3.275, -1.984])


def test_folding_posture_is_stopped_at_self_d_safe(robot, pairs):
    """The end effector sent where Q_FOLD puts it and a posture task pulling toward Q_FOLD: without
    the self-collision rows links 1 and 6 pass into each other (python-fcl), with them the least
    distance stays ≥ self_d_safe − 1 mm on every tick, the task giving way."""
    assert fcl_self_distances(robot, Q_FOLD, pairs.pairs).min() < -0.005
    data = robot.model.createData()
    x = []
    for q in (robot.q_home, Q_FOLD):
        pin.framesForwardKinematics(robot.model, data, q)
        x.append(data.oMf[robot.ee_frame_id].translation.copy())
    path = WaypointPath(x, duration=2.0)
    result = {}
    for on in (False, True):
        ctrl = QPController(robot, path, [], config=QPConfig(self_collision=on, posture=list(Q_FOLD),
                                                               posture_weight=50.0))
        traj = Simulator(ctrl, dt=1e-3, duration=3.0).run(robot.q_home)
        ref = np.array([fcl_self_distances(robot, traj.q[k], pairs.pairs).min() for k in range(0, len(traj.t), 10)])
        result[on] = ref.min()
        # the simulator's self clearance is the same distance (closed form against python-fcl)
        np.testing.assert_allclose(traj.self_clearance[::10][ref > 1e-4], ref[ref > 1e-4], atol=1e-6)
    assert result[False] < -0.01
    assert result[True] >= 0.02 - 1e-3, result


def test_scenario_keys_and_metric(tmp_path):
    scen = Scenario.load("panda_canopy", ["sim.duration=0.1", 'controller.self_collision_pairs=[["panda_joint1", "panda_joint5"]]'])
    ctrl = scen.build_controller("qp")
    sc = [c for c in ctrl.constraints if c.name == "self_collision"]
    assert len(sc) == 1 and sc[0].pairs == ((0, 4),)
    off = Scenario.load("panda_canopy", ["controller.self_collision=false"]).build_controller("qp")
    assert "self_collision" not in [c.name for c in off.constraints]
    with pytest.raises(ConfigError) as info:
        Scenario.load("panda_canopy", ['controller.self_collision_pairs=[["panda_joint1"]]'])
    assert info.value.key == "controller.self_collision_pairs"
    from qpctl.run import simulate

    run = simulate(Scenario.load("panda_canopy", ["sim.duration=0.2"]), kind="qp")
    assert run.metrics["min_self_clearance"] == pytest.approx(np.min(run.trajectory.self_clearance))
    assert run.metrics["min_self_clearance"] > 0.02


# Canopy seed 2 of panda_canopy_depth at rest after 16.5 s: the arm nearly straight (joint 4 6 mrad
# short of its upper limit), capsules 1 and 3 within self_d_safe (docs/perception.md).
Q_STRAIGHT = np.array([0.609, 0.618, 0.989, -0.076, -1.114, 1.041, 1.248])


def _lp_range(c, bounds):
    """(least, most) of c x within the bounds: scipy's linear programme."""
    from scipy.optimize import linprog

    most = linprog(-c, bounds=bounds, method="highs")
    least = linprog(c, bounds=bounds, method="highs")
    assert most.status == 0 and least.status == 0
    return least.fun, -most.fun


@pytest.mark.parametrize("moving", [False, True])
def test_inside_self_d_safe_the_push_asks_no_more_than_the_acceleration_limits_give(robot, moving):
    """Inside self_d_safe a pair's row ḧ + k₁ḣ + k₀(h − d_s) ≥ 0 asks at most ℓ − ρ(ℓ − ℓ₋), [ℓ₋, ℓ]
    the range of the row's c q̈ within ±q̈_max (scipy's linear programme); outside it the barrier is
    unchanged. The compiled rows' bounds against that law (from the tick's own distance, rate and
    drift) and against the Python constraint on the same state. At Q_STRAIGHT at rest the push alone
    would ask joint 3 for more than its acceleration limit: scipy's LP on the tick's rows with the
    uncapped bound is infeasible, and the controller's QP solves (moving: a second tick, under the
    rate window, the arm turning joint 3 the way that closes the pair)."""
    from scipy.optimize import linprog

    from qpctl.kernels.drives import REACH_SHARE

    data = robot.model.createData()
    pin.framesForwardKinematics(robot.model, data, Q_STRAIGHT)
    x = data.oMf[robot.ee_frame_id].translation.copy()
    ctrl = QPController(robot, WaypointPath([x, x + [0.0, 0.0, 0.01]], duration=1.0), [],
                        config=QPConfig(self_collision=True))
    q, v, t = Q_STRAIGHT.copy(), np.zeros(7), 0.0
    sc = next(c for c in ctrl.constraints if c.name == "self_collision")
    if moving:
        ctrl.step(q, v, t)
        v = np.array([0.0, 0.0, 0.2, 0.0, 0.0, 0.0, 0.0])
        q, t = q + 1e-3 * v, 1e-3
    out = ctrl.step(q, v, t)
    assert out.info.get("status", "solved") == "solved" and out.info.get("fallback") is None
    ws, prob = ctrl.qp_path().ws, ctrl.last_problem
    rows = prob.rows_of("self_collision")
    d, hdot, drift = ws.sc_d, ws.sc_hdot, ws.sc_drift
    near = d < ws.fpar[codes.FP_SCUT]
    inside = near & (d < sc.d_safe)
    assert inside.sum() >= 1
    barrier = np.where(near, -sc.k1 * hdot - sc.k0 * (d - sc.d_safe) - drift, -np.inf)
    law = barrier.copy()
    capped = 0
    for r in np.flatnonzero(inside):
        c = np.asarray(prob.C[rows[r]])[:7]
        least, most = _lp_range(c, list(zip(-robot.qdd_max, robot.qdd_max)))
        law[r] = min(barrier[r], most - REACH_SHARE * (most - least))
        capped += law[r] < barrier[r]
    assert capped >= 1  # the cap, not the barrier, bound a row
    np.testing.assert_allclose(prob.l[rows], law, rtol=1e-9, atol=1e-9)
    py = sc.compute(ws.snapshot(), None).lower  # the Python path's constraint on the same state
    np.testing.assert_allclose(py, prob.l[rows], rtol=0, atol=1e-12)
    if moving:
        return
    # the push the row no longer asks in full: with it the tick's rows admit no q̈
    l_push = prob.l.copy()
    l_push[rows[inside]] = barrier[inside]
    fin_u, fin_l = np.isfinite(prob.u), np.isfinite(l_push)
    res = linprog(np.zeros(prob.n_var), A_ub=np.vstack([prob.C[fin_u], -prob.C[fin_l]]),
                  b_ub=np.r_[prob.u[fin_u], -l_push[fin_l]], A_eq=prob.A if prob.A.size else None,
                  b_eq=prob.b if prob.A.size else None,
                  bounds=list(zip(np.where(np.isfinite(prob.lb), prob.lb, None),
                                  np.where(np.isfinite(prob.ub), prob.ub, None))), method="highs")
    assert res.status == 2, res.message  # infeasible


def test_a_self_barrier_without_the_drives_goes_the_python_way(robot, pairs):
    """A SelfCollisionBarrier built by hand without the controller's JointLimit asks the full push
    inside self_d_safe; the compiled tick would cap it with that JointLimit's ±q̈_max, so such a
    controller takes the Python formulation, and its rows are the uncapped law; given the JointLimit,
    the compiled path."""
    from qpctl.constraints.constraints import JointLimit, SelfCollisionBarrier, TorqueLimit

    data = robot.model.createData()
    pin.framesForwardKinematics(robot.model, data, Q_STRAIGHT)
    x = data.oMf[robot.ee_frame_id].translation.copy()
    path = WaypointPath([x, x + [0.0, 0.0, 0.01]], duration=1.0)
    joints = JointLimit(robot.q_min, robot.q_max, robot.v_max, qdd_max=robot.qdd_max)
    torque = TorqueLimit(robot.tau_max, robot.tau_rate_max)
    bare = SelfCollisionBarrier(pairs.pairs, 0.02)
    ctrl = QPController(robot, path, [], constraints=[torque, joints, bare])
    assert ctrl.workspace().spec is None  # the reference path
    wired = SelfCollisionBarrier(pairs.pairs, 0.02, joints=joints)
    assert QPController(robot, path, [], constraints=[torque, joints, wired]).workspace().spec is not None
    out = ctrl.step(Q_STRAIGHT.copy(), np.zeros(7), 0.0)
    assert out.tau.shape == (7,)
    state = ctrl.dynamics.compute(Q_STRAIGHT, np.zeros(7), 0.0)
    sp = state.self_pairs
    near = sp.distance < bare.cutoff
    law = np.where(near, -bare.k1 * sp.hdot - bare.k0 * (sp.distance - bare.d_safe) - sp.drift, -np.inf)
    np.testing.assert_allclose(bare.compute(state, None).lower, law, rtol=0, atol=1e-12)
    assert np.any(near & (sp.distance < bare.d_safe) & (law > 0.1))  # the push, uncapped (0.107 m/s²)
