"""Property-based tests (hypothesis) over random states, scenes and gains.

* The QP's torque is finite, within ±τ_max, equal to Pinocchio's RNEA of the returned q̈, and —
  whenever the QP itself produced it (no fallback) — its constraint rows hold when recomputed here
  from q̈ and a fresh per-tick state, not from the solver's residuals: the torque rows, the joint-limit
  bounds (Panda) and every obstacle barrier ḧ + k₁ḣ + k₀h ≥ 0.
* When the solver fails (forced here by a spent tick budget), the fallback chain still returns a
  finite torque within the limits and says which fallback it used.
* The closed forms (``paper``, ``hsu``) never return NaN, at singular configurations included.

Example counts are small so the fast suite stays fast. The profile is chosen by the environment:
``QPCTL_HYPOTHESIS_PROFILE=ci`` (default: derandomised — the same examples on every run, no example
database) or ``dev`` (random examples, failures remembered in ``.hypothesis/``);
``QPCTL_HYPOTHESIS_SCALE=10`` multiplies every example count for a longer search.
"""

from __future__ import annotations

import os

import numpy as np
import pinocchio as pin
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from baselines import HsuController, PaperController
from qpctl import LawGains, Obstacle, WaypointPath, panda, planar_arm
from qpctl.constraints import JointLimit, ObstacleBarrier
from qpctl.controllers.qp import (
    BUILT_IN_FALLBACKS,
    FALLBACK_BRAKE,
    FALLBACK_CLOSED_FORM,
    FALLBACK_SAFE_STOP,
    SOLUTION_RTOL,
    QPConfig,
    QPController,
)
from qpctl.dynamics import Dynamics
from qpctl.solvers import available_solvers

_COMMON = dict(deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
settings.register_profile("ci", derandomize=True, database=None, print_blob=True, **_COMMON)
settings.register_profile("dev", **_COMMON)
PROFILE = settings.get_profile(os.environ.get("QPCTL_HYPOTHESIS_PROFILE", "ci"))
SCALE = max(1, int(os.environ.get("QPCTL_HYPOTHESIS_SCALE", "1")))


def budget(examples: int) -> settings:
    return settings(PROFILE, max_examples=examples * SCALE)


# Random states often make the QP infeasible (a link racing toward an obstacle under torque limits);
# proxsuite then stalls for seconds unless the tick has a budget — which a real-time user sets.
TICK_BUDGET_US = 20_000.0
PLANAR_TAU = 1000.0  # [N·m]: the arm's gravity torque peaks at 3 · 10 kg · 9.81 m/s² · 1.5 m ≈ 440 N·m
SOLVERS = [s for s in ("proxqp", "osqp", "daqp") if s in available_solvers()]
# The controller accepts a solver's answer only if every row holds to SOLUTION_RTOL relative to
# 1 + |its bound| (solvers test their own scaled problem); the rows recomputed here get twice that.
ROW_RTOL = 2 * SOLUTION_RTOL

finite = dict(allow_nan=False, allow_infinity=False)
# Configurations where the planar arm is singular (outstretched, folded back) are drawn often.
SINGULAR_Q = [np.zeros(3), np.array([-np.pi / 2, 0.0, 0.0]), np.array([np.pi, 0.0, 0.0]), np.array([0.3, np.pi, 0.0])]
planar_q = st.one_of(st.sampled_from(SINGULAR_Q), arrays(float, 3, elements=st.floats(-np.pi, np.pi, **finite)))
planar_v = st.one_of(st.just(np.zeros(3)), arrays(float, 3, elements=st.floats(-4.0, 4.0, **finite)))


@st.composite
def gains(draw: st.DrawFn) -> LawGains:
    d_safe = draw(st.floats(0.0, 0.1))
    return LawGains(kp=draw(st.floats(1.0, 400.0)), kv=draw(st.floats(1.0, 60.0)), kn=draw(st.floats(0.0, 40.0)),
                    v_ref=draw(st.floats(0.0, 2.0)), d_safe=d_safe, d_influence=d_safe + draw(st.floats(0.02, 0.5)),
                    pinv_eps=draw(st.sampled_from([1e-4, 1e-3, 1e-2])), jdot_en=draw(st.booleans()))


@st.composite
def obstacle(draw: st.DrawFn, centre: np.ndarray, spread: float, planar: bool) -> Obstacle:
    """A sphere, box or capsule about ``centre`` [m] (in the plane z = 0 for the planar arm), maybe moving."""
    shape = draw(st.sampled_from(["sphere", "box", "capsule"]))
    offset = np.array([draw(st.floats(-spread, spread)) for _ in range(3)])
    if planar:
        offset[2] = 0.0
    moving = draw(st.booleans())
    velocity = [draw(st.floats(-0.5, 0.5)) for _ in range(3)] if moving else [0.0, 0.0, 0.0]
    if planar:
        velocity[2] = 0.0
    kw: dict = {"velocity": velocity}
    if shape == "box":
        kw["size"] = [draw(st.floats(0.05, 0.5)) for _ in range(3)]
    else:
        kw["radius"] = draw(st.floats(0.03, 0.3))
    if shape == "capsule":
        kw["length"] = draw(st.floats(0.05, 0.6))
        kw["axis"] = [draw(st.floats(-1, 1)), draw(st.floats(-1, 1)), 1.0]
    return Obstacle(shape, centre + offset, **kw)


def point_in_reach(draw: st.DrawFn, centre: np.ndarray, radius: float, dims: int) -> list[float]:
    direction = np.array([draw(st.floats(-1, 1)) for _ in range(dims)]) + 1e-3
    r = draw(st.floats(0.2, 0.95)) * radius
    return (centre[:dims] + r * direction / np.linalg.norm(direction)).tolist()


@st.composite
def planar_case(draw: st.DrawFn) -> dict:
    g = draw(gains())
    obstacles = [draw(obstacle(np.zeros(3), 3.0, planar=True)) for _ in range(draw(st.integers(0, 3)))]
    path = WaypointPath([point_in_reach(draw, np.zeros(3), 3.0, 2) for _ in range(2)],
                        duration=draw(st.floats(0.5, 3.0)))
    config = QPConfig(solver=draw(st.sampled_from(SOLVERS)), barrier_k0=draw(st.floats(10.0, 1000.0)),
                      barrier_k1=draw(st.floats(2.0, 100.0)), tick_budget_us=TICK_BUDGET_US)
    tau_max = draw(st.sampled_from([np.inf, PLANAR_TAU, 600.0]))
    return dict(robot=planar_arm(tau_max=tau_max), path=path, obstacles=obstacles, gains=g, config=config,
                q=draw(planar_q), v=draw(planar_v), t=draw(st.floats(0.0, 3.5)))


PANDA = panda()


@st.composite
def panda_case(draw: st.DrawFn) -> dict:
    lo, hi = PANDA.q_min, PANDA.q_max
    frac = arrays(float, PANDA.nv, elements=st.floats(0.01, 0.99))
    q = lo + draw(frac) * (hi - lo)
    v = draw(arrays(float, PANDA.nv, elements=st.floats(-1.5, 1.5, **finite)))
    shoulder = np.array([0.0, 0.0, 0.333])
    obstacles = [draw(obstacle(shoulder + [0.3, 0.0, 0.2], 0.6, planar=False)) for _ in range(draw(st.integers(0, 3)))]
    path = WaypointPath([point_in_reach(draw, shoulder, 0.8, 3) for _ in range(2)], duration=draw(st.floats(0.5, 3.0)))
    config = QPConfig(solver=draw(st.sampled_from(SOLVERS)), tick_budget_us=TICK_BUDGET_US)
    return dict(robot=PANDA, path=path, obstacles=obstacles, gains=draw(gains()), config=config, q=q, v=v,
                t=draw(st.floats(0.0, 3.5)))


def check_qp_tick(case: dict) -> None:
    robot = case["robot"]
    q, v, t = case["q"], case["v"], case["t"]
    ctrl = QPController(robot, case["path"], case["obstacles"], case["gains"], case["config"])
    out = ctrl.step(q, v, t)
    tau, qdd, info = out.tau, out.qdd, out.info
    event(f"{case['config'].solver}: {info.get('fallback') or info['status']}")
    assert tau.shape == (robot.nv,) and np.all(np.isfinite(tau)) and np.all(np.isfinite(qdd))
    assert np.all(np.abs(tau) <= robot.tau_max), (tau, robot.tau_max)
    # τ = M q̈ + N, by Pinocchio's recursive Newton–Euler (not the controller's M and N).
    rnea = pin.rnea(robot.model, robot.model.createData(), q, v, qdd)
    np.testing.assert_allclose(tau, rnea, rtol=1e-7, atol=1e-6 * (1 + np.max(np.abs(tau))))
    if "fallback" in info:
        assert info["fallback"] in (*BUILT_IN_FALLBACKS, *SOLVERS), info
        assert info["fallback_reason"] != "solved"
        if info["fallback"] not in SOLVERS:
            return
    rtol = ROW_RTOL
    # Joint-limit bounds on q̈ (second-order position barrier, first-order speed barrier).
    for con in ctrl.constraints:
        if isinstance(con, JointLimit):
            with np.errstate(invalid="ignore"):
                lo = np.maximum(-con.k1 * v - con.k0 * (q - con.q_min), -con.kv * (con.v_max + v))
                hi = np.minimum(-con.k1 * v + con.k0 * (con.q_max - q), con.kv * (con.v_max - v))
            # ... within the drives' acceleration limits ±q̈_max, which win where the barriers ask more
            a = con.qdd_max
            assert np.all(np.abs(qdd) <= a * (1 + rtol)), (qdd, a)
            lo, hi = np.maximum(lo, -a), np.minimum(hi, a)
            ok = lo <= hi  # where the state is already outside its limits the bounds meet
            scale = 1.0 + np.maximum(np.abs(lo), np.abs(hi))
            assert np.all(qdd[ok] >= lo[ok] - rtol * scale[ok]), (qdd, lo)
            assert np.all(qdd[ok] <= hi[ok] + rtol * scale[ok]), (qdd, hi)
    # Obstacle barriers, from a fresh state (its own Pinocchio data and python-fcl queries).
    barrier = next((c for c in ctrl.constraints if isinstance(c, ObstacleBarrier)), None)
    if barrier is None:
        return
    state = Dynamics(robot, case["obstacles"], cutoff=case["gains"].d_influence).compute(q, v, t)
    pairs = state.pairs
    drift = state.barrier_drift()
    for r in np.argsort(pairs.distance, kind="stable")[: barrier.rows]:
        n, Jp = pairs.normal[r], state.pair_jac[r]
        h = pairs.distance[r] - case["gains"].d_safe
        hdot = n @ (Jp @ v) - n @ pairs.v_obstacle[r]
        hddot = n @ (Jp @ qdd) + drift[r]
        terms = np.array([hddot, barrier.k1 * hdot, barrier.k0 * h, drift[r]])
        bound = barrier.k1 * hdot + barrier.k0 * h + drift[r]  # the row is nᵀJ_p q̈ ≥ −bound
        assert hddot + barrier.k1 * hdot + barrier.k0 * h >= -rtol * (1.0 + abs(bound)), (r, terms, info)


@budget(60)
@given(planar_case())
def test_qp_tick_on_random_planar_scenes(case):
    check_qp_tick(case)


@budget(25)
@given(panda_case())
def test_qp_tick_on_random_panda_scenes(case):
    check_qp_tick(case)


@budget(40)
@given(planar_case(), st.sampled_from([[FALLBACK_CLOSED_FORM], [FALLBACK_BRAKE], ["daqp", FALLBACK_CLOSED_FORM], [],
                                       [FALLBACK_CLOSED_FORM, FALLBACK_SAFE_STOP], [FALLBACK_SAFE_STOP]]))
def test_fallback_chain_on_random_states(case, chain):
    """A tick budget already spent when the QP would start: every solver is skipped, the chain's
    closed form, safe stop or brake (or the implicit final brake) gives a finite torque within the
    limits."""
    chain = [c for c in chain if c in BUILT_IN_FALLBACKS or c in available_solvers()]
    cfg = case["config"]
    cfg.fallback, cfg.tick_budget_us = chain, 1e-3
    robot = case["robot"]
    ctrl = QPController(robot, case["path"], case["obstacles"], case["gains"], cfg)
    out = ctrl.step(case["q"], case["v"], case["t"])
    info = out.info
    event(info["fallback"])
    assert info["status"] == "time_limit" and info["budget_exhausted"]
    assert info["fallback"] in BUILT_IN_FALLBACKS
    assert np.all(np.isfinite(out.tau)) and np.all(np.abs(out.tau) <= robot.tau_max)
    np.testing.assert_allclose(out.tau, pin.rnea(robot.model, robot.model.createData(), case["q"], case["v"],
                                                 out.qdd), rtol=1e-7, atol=1e-6 * (1 + np.max(np.abs(out.tau))))
    if info["fallback"] == FALLBACK_CLOSED_FORM and np.all(np.isinf(robot.tau_max)):
        # the closed form was judged safe and nothing limited it: it is the paper law's torque
        paper = PaperController(robot, case["path"], case["obstacles"], case["gains"])
        np.testing.assert_allclose(out.tau, paper.torque(case["q"], case["v"], case["t"]), rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("law", [PaperController, HsuController])
@budget(50)
@given(case=planar_case())
def test_closed_forms_never_return_nan(law, case):
    ctrl = law(case["robot"], case["path"], case["obstacles"], case["gains"])
    out = ctrl.step(case["q"], case["v"], case["t"])
    event(f"singular={out.singular}")
    assert np.all(np.isfinite(out.tau)) and np.all(np.isfinite(out.qdd)) and np.all(np.isfinite(out.e_null))
    if any(np.array_equal(case["q"], s) for s in SINGULAR_Q[:2]):  # outstretched: J has rank 1
        assert out.singular


def panda_task_terms(robot, q: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(x, J, J̇q̇, J̇) of the Panda's task point from Pinocchio's own per-frame functions (not the
    library's tick state): position [m], world-aligned linear Jacobian, drift = classical acceleration
    at q̈ = 0 [m/s²], and J̇ for the paper's optional J̇e_N term."""
    model, data, fid = robot.model, robot.model.createData(), robot.ee_frame_id
    pin.forwardKinematics(model, data, q, v, np.zeros(robot.nv))
    pin.updateFramePlacements(model, data)
    x = data.oMf[fid].translation.copy()
    drift = pin.getFrameClassicalAcceleration(model, data, fid, pin.LOCAL_WORLD_ALIGNED).linear.copy()
    pin.computeJointJacobians(model, data, q)
    J = pin.getFrameJacobian(model, data, fid, pin.LOCAL_WORLD_ALIGNED)[:3].copy()
    pin.computeJointJacobiansTimeVariation(model, data, q, v)
    Jdot = pin.getFrameJacobianTimeVariation(model, data, fid, pin.LOCAL_WORLD_ALIGNED)[:3].copy()
    return x, J, drift, Jdot


@budget(25)
@given(case=panda_case())
def test_closed_forms_never_return_nan_on_panda(case):
    """Both closed forms on the Panda (m = 3 < n = 7): finite, τ = M q̈ + N (Pinocchio's RNEA), and away
    from singularities the task is met exactly, J q̈ = a with a = ẍ_d + K_v ė + K_p e − J̇q̇ (+ J̇e_N when
    ``jdot_en``) from Pinocchio and the path here; and q̈ − q̈₀ is W-orthogonal to J's null space (the
    weighted least-change solution: W = MᵀM, q̈₀ = −M⁻¹N + K_N e_N for the paper law; W = I,
    q̈₀ = K_N e_N for Hsu's)."""
    robot, q, v, t, gains = case["robot"], case["q"], case["v"], case["t"], case["gains"]
    model, data = robot.model, robot.model.createData()
    x, J, drift, Jdot = panda_task_terms(robot, q, v)
    ref = case["path"](t)
    M = pin.crba(model, data, q)
    M = np.triu(M) + np.triu(M, 1).T
    N = pin.nonLinearEffects(model, data, q, v)
    null = np.linalg.svd(J)[2][3:].T  # (7, 4) basis of J's null space
    for law in (PaperController, HsuController):
        out = law(robot, case["path"], case["obstacles"], gains).step(q, v, t)
        event(f"{law.kind}: singular={out.singular}")
        assert np.all(np.isfinite(out.tau)) and np.all(np.isfinite(out.qdd)) and np.all(np.isfinite(out.e_null))
        tau_scale = 1.0 + np.max(np.abs(out.tau))
        np.testing.assert_allclose(out.tau, pin.rnea(model, data, q, v, out.qdd), rtol=0, atol=1e-9 * tau_scale)
        np.testing.assert_allclose(out.x, x, rtol=0, atol=1e-12)
        if out.singular:
            continue
        a = ref.xdd + gains.kv * (ref.xd - J @ v) + gains.kp * (ref.x - x) - drift
        if gains.jdot_en:
            a = a + Jdot @ out.e_null
        np.testing.assert_allclose(J @ out.qdd, a, rtol=0, atol=1e-7 * (1.0 + np.max(np.abs(a))))
        if law is PaperController:
            W, qdd0 = M.T @ M, -np.linalg.solve(M, N) + gains.kn * out.e_null
        else:
            W, qdd0 = np.eye(robot.nv), gains.kn * out.e_null
        residual = null.T @ W @ (out.qdd - qdd0)
        assert np.max(np.abs(residual)) <= 1e-7 * (1.0 + np.max(np.abs(W @ (out.qdd - qdd0)))), (law.kind, residual)
