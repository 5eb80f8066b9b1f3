"""Braking-aware rows (issue 22, item 1; qpctl.kernels.braking, qpctl.constraints.braking).

* the compiled rows (the problem the tick's kernel wrote) equal the Python path's (Formulation.build on
  the same constraints) to 1e-12, on states where the braking bounds bind;
* a braking bound against one recomputed from independent quantities: the clearance by python-fcl,
  its rate and the barrier's drift by finite differences of that distance along the motion, the
  point's row by finite differences of the distance in q, M and N by Pinocchio;
* where every braking bound is slack the torques are bit-identical to the controller without them.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from qpctl import Scenario
from qpctl.controllers.qp import QPController
from qpctl.geometry.distance import DistanceEngine
from qpctl.kernels.stopping import max_closing_acceleration
from qpctl.law import law_terms

SEED = 2202
PLANAR = ("paper", ["robot.tau_max=1500.0", "robot.tau_rate_max=3000.0", 'controller.braking="on"'])
SCENES = {"planar-rate": PLANAR, "panda_canopy": ("panda_canopy", [])}


def controller(key: str, braking: str = "on") -> QPController:
    name, overrides = SCENES[key]
    overrides = [o for o in overrides if not o.startswith("controller.braking")] + [f'controller.braking="{braking}"']
    ctrl = Scenario.load(name, overrides=overrides).build_controller("qp")
    assert isinstance(ctrl, QPController)
    assert (ctrl.braking is not None) == (braking == "on")
    return ctrl


def fast_states(ctrl: QPController, rng: np.random.Generator, k: int) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """k states with a link within the braking cutoff of an obstacle, moving at up to 3 rad/s."""
    robot = ctrl.robot
    lo = np.where(np.isfinite(robot.q_min), robot.q_min, -np.pi)
    hi = np.where(np.isfinite(robot.q_max), robot.q_max, np.pi)
    out = []
    for _ in range(2000):
        q, v = rng.uniform(lo + 0.05, hi - 0.05), rng.uniform(-3.0, 3.0, robot.nv)
        if ctrl.dynamics.compute(q, v, 0.1).clearance < ctrl.cutoff:
            out.append((q, v, 0.1))
        if len(out) == k:
            return out
    raise AssertionError("too few states near an obstacle")


def bounds(ctrl: QPController, q: np.ndarray, v: np.ndarray, t: float) -> tuple[np.ndarray, ...]:
    ctrl.reset()
    ctrl.step(q, v, t)
    p = ctrl.last_problem
    rows = ctrl.formulation().barrier_rows
    n = ctrl.n
    return np.array(p.l[rows]), np.array(p.lb[:n]), np.array(p.ub[:n])


@pytest.mark.parametrize("key", list(SCENES))
def test_compiled_braking_rows_equal_the_python_path(key):
    """Barrier rows and joint bounds of the compiled tick against Formulation.build (the constraints'
    numpy path) to 1e-12 relative (+1e-12 absolute), on 16 moving states near obstacles; in at least
    two of them a braking bound is above the plain barrier's (braking off)."""
    rng = np.random.default_rng(SEED)
    on, off = controller(key), controller(key, "off")
    form = on.formulation()
    tighter = 0
    for q, v, t in fast_states(on, rng, 16):
        l_on, lb, ub = bounds(on, q, v, t)
        l_off, _, _ = bounds(off, q, v, t)
        state = on.dynamics.compute(q, v, t)
        want = form.build(state, law_terms(state, on.path(t), on.gains, weighted=True), relax=True)
        rows = form.barrier_rows
        for got, ref in ((l_on, want.l[rows]), (lb, want.lb[: on.n]), (ub, want.ub[: on.n])):
            fin = np.isfinite(ref)
            assert np.array_equal(fin, np.isfinite(got)), (got, ref)
            np.testing.assert_allclose(got[fin], ref[fin], rtol=1e-12, atol=1e-12)
        with np.errstate(invalid="ignore"):
            tighter += bool(np.any(np.nan_to_num(l_on, neginf=-1e300) > np.nan_to_num(l_off, neginf=-1e300) + 1e-9))
    assert tighter >= 2, tighter


def test_braking_bound_against_finite_differences():
    """The planar arm with a rate limit, states moving towards an obstacle: for the nearest pair whose
    braking bound binds, −a* − ḧ₀ recomputed from the distance d(q) (python-fcl): h = d − d_s, its
    row c = ∂d/∂q and closing speed −c q̇ by central differences, the drift ḧ₀ = q̇ᵀ∇²d q̇ by a second
    difference along q̇, A and J from c, M and N (Pinocchio), equals the compiled row's bound to 1e-4."""
    rng = np.random.default_rng(SEED + 1)
    ctrl = controller("planar-rate")
    robot, b = ctrl.robot, ctrl.braking
    assert b is not None
    engine = DistanceEngine([c.radius for c in robot.capsules], ctrl.obstacles, broadphase=False)
    data = robot.model.createData()

    def distance(q: np.ndarray, link: int, obs: int) -> float:
        pin.forwardKinematics(robot.model, data, q)
        seg = np.array([[data.oMi[c.joint_id].act(c.p0), data.oMi[c.joint_id].act(c.p1)] for c in robot.capsules])
        engine.update(seg, 0.0)
        return float(engine.pair(link, obs)[0])

    checked = 0
    for q, v, t in fast_states(ctrl, rng, 40):
        l_on, _, _ = bounds(ctrl, q, v, t)
        ws = ctrl.workspace()
        k = int(ws.cnt[0])
        state = ctrl.dynamics.compute(q, v, t)
        for r in range(min(k, l_on.size)):
            p = int(ws.order[r])
            link, obs = int(ws.pr_link[p]), int(ws.pr_obs[p])
            e = 1e-6
            d = distance(q, link, obs)
            c = np.array([(distance(q + e * u, link, obs) - distance(q - e * u, link, obs)) / (2 * e)
                          for u in np.eye(robot.nv)])
            s = 1e-4
            drift = (distance(q + s * v, link, obs) - 2 * d + distance(q - s * v, link, obs)) / s**2
            y = np.linalg.solve(state.M, c)
            best = min(float(np.abs(y) @ np.maximum(b.tau_max - np.abs(state.N), 0)), np.inf)
            jerk = float(np.abs(y) @ b.tau_rate)
            if not best > 1e-9:  # a point the drives cannot move along n (a link's base): no bound
                continue
            a_star = max_closing_acceleration(d - ctrl.gains.d_safe, -float(c @ v), 0.0, b.dt, b.share * best,
                                              b.share * jerk, b.margin, best)
            if a_star >= best:
                continue
            classic = -ctrl.config.barrier_k1 * float(c @ v) - ctrl.config.barrier_k0 * (d - ctrl.gains.d_safe) - drift
            want = max(-a_star - drift, classic if d < ctrl.gains.d_influence else -np.inf)
            assert l_on[r] == pytest.approx(want, rel=1e-4, abs=1e-4 * (1 + abs(drift))), (r, l_on[r], want)
            checked += 1
    assert checked >= 5, checked


@pytest.mark.parametrize("key", list(SCENES))
def test_slack_braking_rows_leave_the_torque_bit_identical(key):
    """Issue 22, item 6: over 30 ticks of a run from the scene's start (the braking controller's
    motion), on every tick where the controller without braking rows meets every braking row
    strictly (its q̈: C q̈ > l, q̈ inside the joint bounds) the two torques are bit-identical."""
    on, off = controller(key), controller(key, "off")
    sc_name, overrides = SCENES[key]
    sc = Scenario.load(sc_name, overrides=overrides)
    q, v = sc.q0(on.robot), np.zeros(on.n)
    dt = 1e-3
    same = 0
    rows = on.formulation().barrier_rows
    n = on.n
    for k in range(30):
        t = k * dt
        a, b = on.step(q, v, t), off.step(q, v, t)
        p = on.last_problem
        qdd_off = np.array(b.qdd)
        C, lo = np.array(p.C)[rows, :n], np.array(p.l)[rows]
        fin = np.isfinite(lo)
        slack = bool(np.all(C[fin] @ qdd_off > lo[fin] + 1e-9) and np.all(qdd_off > np.array(p.lb)[:n])
                     and np.all(qdd_off < np.array(p.ub)[:n]))
        if slack:
            assert np.array_equal(a.tau, b.tau), (k, a.tau - b.tau)
            same += 1
        qdd = np.array(a.qdd)
        q, v = q + dt * v + 0.5 * dt * dt * qdd, v + dt * qdd
    assert same >= 20, same
