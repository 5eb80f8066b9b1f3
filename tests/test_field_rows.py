"""The depth map's rows in the compiled tick (qpctl.kernels.field_rows) against the Python path's
FieldBarrier.compute (qpctl.perception.rows): the same rows and bounds to 1e-12, rigid and soft rows
active, with the scene's primitives beside them; and the controller's torque on both paths."""

from __future__ import annotations

import numpy as np
import pytest

from qpctl import Scenario
from qpctl.perception import Perception, PerceptionConfig, PointCloud
from qpctl.perception.rows import FieldBarrier

CFG = PerceptionConfig(voxel=0.02, bounds_min=[-0.3, -0.6, 0.0], bounds_max=[1.1, 0.6, 1.1], truncation=0.3)


def _sphere_cloud(centre: np.ndarray, radius: float, rng: np.random.Generator, n: int = 3000) -> np.ndarray:
    d = rng.normal(size=(n, 3))
    return centre + radius * d / np.linalg.norm(d, axis=1, keepdims=True)


def _controller(rng: np.random.Generator, *, compiled: bool = True):  # type: ignore[no-untyped-def]
    scen = Scenario.load("panda_spheres")
    ctrl = scen.build_controller("qp")
    robot = ctrl.robot
    seg = ctrl.dynamics.compute(robot.q_home, np.zeros(robot.nv)).segments
    rigid = _sphere_cloud(0.5 * (seg[3, 0] + seg[3, 1]) + [0.0, 0.17, 0.0], 0.05, rng)
    soft = _sphere_cloud(seg[-1, 1] + [0.0, -0.12, -0.05], 0.05, rng)
    labels = np.r_[np.full(len(rigid), 1, np.uint8), np.full(len(soft), 2, np.uint8)]
    p = Perception(CFG, robot)
    p.submit(PointCloud(np.r_[rigid, soft], 0.0, labels=labels))
    bar = p.rows_for(ctrl)
    if not compiled:
        ctrl.remove_constraint(bar.name)
        bar = _PythonOnly(p, robot, CFG, d_safe=ctrl.gains.d_safe, cutoff=ctrl.cutoff,
                          k0=ctrl.config.barrier_k0, k1=ctrl.config.barrier_k1)
        ctrl.add_constraint(bar)
    return ctrl, bar


class _PythonOnly(FieldBarrier):
    """The same rows without a compiled form: the controller takes the Python formulation."""

    field_spec = None  # type: ignore[assignment]


def _states(ctrl, rng: np.random.Generator, k: int) -> list[tuple[np.ndarray, np.ndarray, float]]:  # type: ignore[no-untyped-def]
    q0 = ctrl.robot.q_home
    return [(q0 + rng.normal(0.0, 0.08, q0.size), rng.uniform(-0.6, 0.6, q0.size), 0.05 * i) for i in range(k)]


def test_compiled_field_rows_equal_the_python_rows() -> None:
    rng = np.random.default_rng(21)
    ctrl, bar = _controller(rng)
    ws = ctrl.workspace()
    assert ws.spec is not None and ws.spec.field is not None  # the compiled path, with the field
    rigid_active = soft_active = primitive_active = speed_active = 0
    window = bar.torque  # the Python rows read its window as it was at the tick (before it remembers τ)
    assert window is not None
    for q, v, t in _states(ctrl, rng, 10):
        before = window.previous.copy(), window.t_previous.copy()
        ctrl.step(q, v, t)
        after = window.previous.copy(), window.t_previous.copy()
        problem = ctrl.last_problem
        names = np.array(problem.row_names)
        rows = np.flatnonzero(names == bar.name)
        assert rows.size == bar.rows
        got_C, got_l = np.array(problem.C[rows]), np.array(problem.l[rows])
        # the soft rows' slack σ, one per link: the last L columns, 1 on the link's soft pairs' rows and its
        # two speed rows, 0 elsewhere (the rigid pairs' rows are hard)
        L = len(ctrl.robot.capsules)
        P = 2 * L * CFG.rows_per_link
        assert bar.rows == P + 2 * L
        link, soft = _field_row_links(bar, L)
        assert np.array_equal(got_C[:, -L:], np.array([(link == j) & soft for j in range(L)], float).T)
        assert not got_C[:, ctrl.n:-L].any()
        got_C = got_C[:, :ctrl.n]
        compiled = bar.last
        state = ctrl.dynamics.compute(q, v, t)
        window.previous[:], window.t_previous[:] = before
        want = bar.compute(state, None)  # type: ignore[arg-type]
        window.previous[:], window.t_previous[:] = after
        python = bar.last
        assert np.array_equal(compiled.active, python.active)
        assert compiled.distance == pytest.approx(python.distance, abs=1e-12)
        assert np.array_equal(np.isinf(got_l), np.isinf(want.lower))
        fin = np.isfinite(want.lower)
        assert np.abs(got_C - want.C).max() <= 1e-12
        assert np.abs(got_l[fin] - want.lower[fin]).max() <= 1e-12 * max(1.0, np.abs(want.lower[fin]).max())
        speed_active += int(np.isfinite(want.lower[P:]).any())
        rigid_active += int((python.active & ~python.soft).any())
        soft_active += int((python.active & python.soft).any())
        obst = np.flatnonzero(names == "obstacles")
        primitive_active += int(np.isfinite(np.array(problem.l[obst])).any())
    assert rigid_active >= 5 and soft_active >= 5 and primitive_active >= 1 and speed_active >= 5
    L = len(ctrl.robot.capsules)
    assert np.all(problem.c[-L:] == CFG.soft_weight) and np.all(problem.lb[-L:] == 0.0)
    assert np.all(problem.ub[-L:] == np.inf)


def test_compiled_and_python_field_ticks_give_the_same_torque() -> None:
    fast, _ = _controller(np.random.default_rng(3))
    slow, _ = _controller(np.random.default_rng(3), compiled=False)
    assert fast.workspace().spec is not None and slow.workspace().spec is None
    rng = np.random.default_rng(4)
    for q, v, t in _states(fast, rng, 6):
        a, b = fast.step(q, v, t), slow.step(q, v, t)
        assert a.info.get("fallback") == b.info.get("fallback")
        assert np.allclose(a.tau, b.tau, rtol=1e-7, atol=1e-7 * np.abs(b.tau).max())


def _rushing_into_a_leaf(soft_weight: float):  # type: ignore[no-untyped-def]
    """The hand 3 cm from a soft blob, moving into it at 4 m/s: its soft rows ask more deceleration
    than the drives' torques give."""
    import dataclasses

    import pinocchio as pin

    scen = Scenario.load("panda_spheres")
    ctrl = scen.build_controller("qp", obstacles=[])
    robot = ctrl.robot
    q = robot.q_home.copy()
    seg = ctrl.dynamics.compute(q, np.zeros(robot.nv)).segments
    tip, axis = seg[-1, 1], seg[-1, 1] - seg[-1, 0]
    axis /= np.linalg.norm(axis)
    cfg = dataclasses.replace(CFG, soft_weight=soft_weight)
    p = Perception(cfg, robot)
    blob = _sphere_cloud(tip + (0.03 + robot.capsules[-1].radius + 0.05) * axis, 0.05, np.random.default_rng(5))
    p.submit(PointCloud(blob, 0.0, labels=np.full(len(blob), 2, np.uint8)))
    bar = p.rows_for(ctrl)
    data = robot.model.createData()
    pin.computeJointJacobians(robot.model, data, q)
    J = pin.getJointJacobian(robot.model, data, robot.capsules[-1].joint_id, pin.LOCAL_WORLD_ALIGNED)[:3]
    v = np.linalg.pinv(J) @ (4.0 * axis)
    return ctrl, bar, q, v


def test_the_soft_rows_slack_keeps_the_qp_feasible_where_a_leaf_cannot_be_stopped_for() -> None:
    hard_ctrl, _, q, v = _rushing_into_a_leaf(0.0)
    out = hard_ctrl.step(q, v, 0.0)
    assert hard_ctrl.workspace().spec is not None and hard_ctrl.last_problem.n_var == hard_ctrl.n + 6
    assert "fallback" in out.info and out.info["status"] == "primal_infeasible"  # the soft rows hard
    ctrl, bar, q, v = _rushing_into_a_leaf(CFG.soft_weight)
    out = ctrl.step(q, v, 0.0)
    assert "fallback" not in out.info and out.info["status"] == "solved"
    assert "field" in out.info["active_rows"]  # the record's active-row mask has the field's rows
    x = ctrl.last_solution.x
    sigma = x[-1]
    assert sigma > 1.0  # [m/s²] the leaf gives way
    problem = ctrl.last_problem
    rows = np.flatnonzero(np.array(problem.row_names) == bar.name)
    soft = rows[bar.pairs // 2:]  # the soft pairs' rows and the speed rows
    active = soft[np.isfinite(problem.l[soft])]
    assert active.size >= 1
    Cq = problem.C[active, :ctrl.n] @ x[:ctrl.n]
    assert np.all(Cq + sigma >= problem.l[active] - 1e-6)  # they hold with the slack
    assert np.any(Cq < problem.l[active] - 1.0)  # and only with it


def _field_row_links(bar: FieldBarrier, L: int) -> tuple[np.ndarray, np.ndarray]:
    """Each of the field's rows' link and whether it is a soft row (a soft pair or a speed row), from the
    documented layout: rigid pairs, soft pairs (``rows_per_link`` per link, link-major), then two speed
    rows per link."""
    rpl = bar.config.rows_per_link
    i = np.arange(bar.rows)
    pair = i < 2 * L * rpl
    link = np.where(pair, (i % (L * rpl)) // rpl, (i - 2 * L * rpl) // 2)
    return link, ~pair | (i >= L * rpl)


def _with_slack_columns(problem, rows: np.ndarray, columns: np.ndarray, weight: float):  # type: ignore[no-untyped-def]
    """``problem`` with its constraints' own slack columns replaced by ``columns`` (k, rows) on ``rows``
    of C, each σ ≥ 0 at ℓ₁ ``weight`` and the soft rows' ℓ₂: a QP the test writes itself."""
    from qpctl.perception.rows import SOFT_SLACK_L2
    from qpctl.qp import Problem

    own = ~np.any(problem.A[:, problem.n:] != 0.0, axis=0)  # after q̈: the task's s± (in A) and the σ (not)
    nv0 = problem.n + int(np.sum(~own))  # the σ columns are the last ones
    assert np.all(own[nv0 - problem.n:])
    k = columns.shape[0]
    nv = nv0 + k
    P = np.zeros((nv, nv))
    P[:nv0, :nv0] = problem.P[:nv0, :nv0]
    P[nv0:, nv0:] = SOFT_SLACK_L2 * np.eye(k)
    c = np.r_[problem.c[:nv0], np.full(k, weight)]
    A = np.c_[problem.A[:, :nv0], np.zeros((problem.A.shape[0], k))]
    C = np.c_[problem.C[:, :nv0], np.zeros((problem.C.shape[0], k))]
    C[rows, nv0:] = columns.T
    return Problem(P, c, A, problem.b.copy(), C, problem.l.copy(), problem.u.copy(),
                   np.r_[problem.lb[:nv0], np.zeros(k)], np.r_[problem.ub[:nv0], np.full(k, np.inf)], problem.n)


def _solve_quadprog(problem) -> np.ndarray:  # type: ignore[no-untyped-def]
    """quadprog (qpctl's generic solver path) on ``problem``, its costs scaled to order one (the same
    minimiser)."""
    import dataclasses

    from qpctl.solvers import make_solver

    scale = np.abs(problem.c).max()
    sol = make_solver("quadprog").solve(dataclasses.replace(problem, P=problem.P / scale, c=problem.c / scale))
    assert sol.found
    return sol.x


def test_each_links_soft_rows_have_a_slack_of_their_own() -> None:
    """The arm rushes the hand into a leaf at 1 m/s, faster than the drives can slow it for, with a
    second leaf at the upper arm: the controller's q̈ is that of the QP the test writes with one slack
    column per link (quadprog), and not that of the same QP with one column all soft rows share (there
    the hand's slack would let every other link's soft rows give way as much)."""
    import pinocchio as pin

    scen = Scenario.load("panda_spheres")
    ctrl = scen.build_controller("qp", obstacles=[])
    robot = ctrl.robot
    L, n = len(robot.capsules), ctrl.n
    q = robot.q_home.copy()
    seg = ctrl.dynamics.compute(q, np.zeros(robot.nv)).segments
    tip, axis = seg[-1, 1], seg[-1, 1] - seg[-1, 0]
    axis /= np.linalg.norm(axis)
    rng = np.random.default_rng(5)
    side = np.cross(seg[2, 1] - seg[2, 0], [0.0, 0.0, 1.0])
    leaves = np.r_[_sphere_cloud(tip + (0.03 + robot.capsules[-1].radius + 0.05) * axis, 0.05, rng),
                   _sphere_cloud(0.5 * (seg[2, 0] + seg[2, 1]) + 0.1 * side / np.linalg.norm(side), 0.04, rng)]
    p = Perception(CFG, robot)
    p.submit(PointCloud(leaves, 0.0, labels=np.full(len(leaves), 2, np.uint8)))
    bar = p.rows_for(ctrl)
    data = robot.model.createData()
    pin.computeJointJacobians(robot.model, data, q)
    J = pin.getJointJacobian(robot.model, data, robot.capsules[-1].joint_id, pin.LOCAL_WORLD_ALIGNED)[:3]
    out = ctrl.step(q, np.linalg.pinv(J) @ axis, 0.0)
    assert "fallback" not in out.info and out.info["status"] == "solved"
    problem, x = ctrl.last_problem, ctrl.last_solution.x
    rows = np.flatnonzero(np.array(problem.row_names) == bar.name)
    link, soft = _field_row_links(bar, L)
    per_link = np.array([(link == j) & soft for j in range(L)], float)
    want = _solve_quadprog(_with_slack_columns(problem, rows, per_link, CFG.soft_weight))
    other = _solve_quadprog(_with_slack_columns(problem, rows, soft[None, :].astype(float), CFG.soft_weight))
    scale = np.abs(want[:n]).max()
    assert np.abs(x[:n] - want[:n]).max() <= 1e-6 * scale
    assert np.abs(other[:n] - want[:n]).max() >= 1e-2 * scale  # the state tells the two layouts apart
    # the record's task slack is the task's s⁺ − s⁻ (before the seven σ columns)
    task = np.flatnonzero(np.any(problem.A[:, n:] != 0.0, axis=0))
    assert task.size == 6 and out.info["slack_norm"] > 0.0
    assert out.info["slack_norm"] == pytest.approx(np.linalg.norm(x[n:n + 3] - x[n + 3:n + 6]), rel=1e-12)
    # each link's σ is what its own rows lack (ℓ₁ exact penalty), some links' none, where the shared σ
    # relaxes every soft row by as much as the hand needs
    short = np.maximum(problem.l[rows] - problem.C[rows, :n] @ want[:n], 0.0)
    lack = np.array([short[(link == j) & soft].max(initial=0.0) for j in range(L)])
    assert want[-L:] == pytest.approx(lack, abs=1e-6 * lack.max())
    assert lack.min() == 0.0 and other[-1] > 0.5 * lack.max() > 1.0


def _soft_blob(robot, rng: np.random.Generator):  # type: ignore[no-untyped-def]
    """A filled soft ball (a leaf's voxels) around the hand at q_home, and the Python path's rows."""
    from qpctl.dynamics import Dynamics

    seg = Dynamics(robot).compute(robot.q_home, np.zeros(robot.nv)).segments
    d = rng.normal(size=(6000, 3))
    ball = seg[-1, 1] + [0.0, 0.0, -0.06] + 0.06 * d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(
        0.0, 1.0, (6000, 1)) ** (1 / 3)
    p = Perception(CFG)
    p.submit(PointCloud(ball, 0.0, labels=np.full(len(ball), 2, np.uint8)))
    return p, FieldBarrier(p, robot, CFG, d_safe=0.05, cutoff=0.2, k0=400.0, k1=40.0)


def _body_point(robot, q: np.ndarray, joint: int, p: np.ndarray):  # type: ignore[no-untyped-def]
    """x(q') [m] of the point of body ``joint`` that is at p at q: Pinocchio's forward kinematics."""
    import pinocchio as pin

    data = robot.model.createData()
    pin.forwardKinematics(robot.model, data, q)
    local = data.oMi[joint].actInv(p)

    def at(qq: np.ndarray) -> np.ndarray:
        pin.forwardKinematics(robot.model, data, qq)
        return data.oMi[joint].act(local)

    return at


def _fd_velocity(at, q: np.ndarray, v: np.ndarray, eps: float = 1e-6) -> np.ndarray:  # type: ignore[no-untyped-def]
    return (at(q + eps * v) - at(q - eps * v)) / (2 * eps)


def test_speed_rows_bound_the_points_velocity_a_horizon_ahead_by_finite_differences(panda_robot) -> None:
    """Each active speed row is the point's velocity h ahead along u, uᵀ(J_p q̇ + (J_p q̈ + J̇_p q̇)h),
    at most b: its value b − h(C q̈ − lower) against the velocity of the same body point after h of
    q(t) = q + q̇t + ½q̈t², by central differences of Pinocchio's forward kinematics; u is that point's
    velocity's direction now."""
    from qpctl.dynamics import Dynamics

    robot = panda_robot
    rng = np.random.default_rng(8)
    p, bar = _soft_blob(robot, rng)
    dyn = Dynamics(robot)
    h = CFG.soft_horizon
    P = bar.pairs
    checked = 0
    for _ in range(4):
        q = robot.q_home + rng.normal(0.0, 0.05, robot.nv)
        v = rng.uniform(-0.6, 0.6, robot.nv)
        st = dyn.compute(q, v, 0.0)
        ineq = bar.compute(st, None)  # type: ignore[arg-type]
        pts, u, b, _ = bar.speed_points(p.snapshot, st.segments, q, v)
        for r in np.flatnonzero(np.isfinite(b)):
            at = _body_point(robot, q, robot.capsules[r // 2].joint_id, pts[r])
            w0 = _fd_velocity(at, q, v)
            assert u[r] == pytest.approx(w0 / np.linalg.norm(w0), abs=1e-6)
            for qdd in (np.zeros(robot.nv), rng.normal(0.0, 8.0, robot.nv)):
                # the velocity's rate along q(t) by central differences over ±h (no second-order term)
                ahead = [u[r] @ _fd_velocity(at, q + s * v * h + 0.5 * qdd * h * h, v + s * qdd * h) for s in (1, -1)]
                rate = (ahead[0] - ahead[1]) / (2 * h)
                got = b[r] - h * (ineq.C[P + r] @ qdd - ineq.lower[P + r])
                assert got == pytest.approx(u[r] @ w0 + h * rate, abs=1e-3 * h * abs(rate) + 1e-9)
                checked += 1
        assert np.all(np.isinf(ineq.lower[P:][~np.isfinite(b)])) and not ineq.C[P:][~np.isfinite(b)].any()
    assert checked >= 16


def test_speed_rows_take_each_links_samples_whose_fastest_point_most_exceeds_its_bound(panda_robot) -> None:
    """Brute force: for each sample along a link's axis, the fastest of 20,000 points of the capsule's
    ball about it (body velocities by finite differences of the placements) and its bound
    b(d) = v_s + (k₀/k₁)·max(d − (√3/2 voxel + depth noise), 0), d the field there by scipy's
    map_coordinates less the radius; the two rows of the link are the two largest excesses."""
    import pinocchio as pin

    from qpctl.dynamics import Dynamics
    from qpctl.perception import reference as ref

    robot = panda_robot
    rng = np.random.default_rng(9)
    p, bar = _soft_blob(robot, rng)
    snap = p.snapshot
    e = rng.normal(size=(20000, 3))
    e /= np.linalg.norm(e, axis=1, keepdims=True)
    m_v = np.sqrt(3) / 2 * CFG.voxel + CFG.depth_noise
    S, eps = CFG.samples, 1e-6
    data = robot.model.createData()
    links_checked = stretch = funnel = 0
    for _ in range(3):
        q = robot.q_home + rng.normal(0.0, 0.05, robot.nv)
        v = rng.uniform(-0.6, 0.6, robot.nv)
        st = Dynamics(robot).compute(q, v, 0.0)
        pts, _, b, _ = bar.speed_points(snap, st.segments, q, v)
        for link, cap in enumerate(robot.capsules):
            if not np.isfinite(b[2 * link]):
                continue
            pin.forwardKinematics(robot.model, data, q + eps * v)
            Mp = data.oMi[cap.joint_id].copy()
            pin.forwardKinematics(robot.model, data, q - eps * v)
            Mm = data.oMi[cap.joint_id].copy()
            omega = pin.log3(Mp.rotation @ Mm.rotation.T) / (2 * eps)
            o_dot = (Mp.translation - Mm.translation) / (2 * eps)
            pin.forwardKinematics(robot.model, data, q)
            o = data.oMi[cap.joint_id].translation

            def speed(x: np.ndarray, o: np.ndarray = o, o_dot: np.ndarray = o_dot, omega: np.ndarray = omega
                      ) -> np.ndarray:
                return np.linalg.norm(o_dot + np.cross(omega, x - o), axis=-1)

            a, c = st.segments[link]
            axis = a + np.linspace(0.0, 1.0, S)[:, None] * (c - a)
            d = ref.field_at(snap.dist[1], snap.grad[1], snap.grid, snap.truncation, axis)[0] - cap.radius
            seen = (d < bar.cutoff) & (d + cap.radius < snap.truncation)
            excess = np.array([speed(x + cap.radius * e).max() for x in axis]) - (
                CFG.soft_speed + 10.0 * np.maximum(d - m_v, 0.0))
            top = np.sort(excess[seen])[::-1]
            got = [speed(pts[2 * link + k]) - b[2 * link + k] for k in range(2) if np.isfinite(b[2 * link + k])]
            assert len(got) == min(2, seen.sum())
            # (the samples' excesses differ by ~5e-3 m/s here; the brute force's directions miss the
            # fastest point by less than 1e-4)
            assert got == pytest.approx(top[:len(got)], abs=3e-4)
            stretch += int(np.any(b[2 * link:2 * link + 2] == CFG.soft_speed))
            funnel += int(np.any(b[2 * link:2 * link + 2] > CFG.soft_speed))
            links_checked += 1
    assert links_checked >= 6 and stretch >= 2 and funnel >= 2


# a recovery gain six times the default (and not the barrier's k₁): more than the window gives
CFG_FAST_RECOVERY = PerceptionConfig(**{**CFG.__dict__, "recovery_gain": 60.0})


def _inside_the_margin():  # type: ignore[no-untyped-def]
    """The Panda at rest at q_home, a rigid blob put 1.2 cm inside the rigid rows' margin of its
    fourth link, the last torque the gravity torque 1 ms ago: under Franka's torque-rate limits the
    window is τ_g ± 1 N·m, short of the k_r v_s (``CFG_FAST_RECOVERY``) the recovery asks of the link."""
    scen = Scenario.load("panda_spheres")
    ctrl = scen.build_controller("qp", obstacles=[])
    robot = ctrl.robot
    q, v = robot.q_home.copy(), np.zeros(robot.nv)
    seg = ctrl.dynamics.compute(q, v).segments[3]
    axis = (seg[1] - seg[0]) / np.linalg.norm(seg[1] - seg[0])
    out = np.cross(axis, [0.0, 0.0, 1.0])
    out /= np.linalg.norm(out)
    p = Perception(CFG_FAST_RECOVERY, robot)
    bar = p.rows_for(ctrl)
    gap = bar.margin - 0.012
    blob = _sphere_cloud(0.5 * (seg[0] + seg[1]) + (robot.capsules[3].radius + gap + 0.05) * out, 0.05,
                         np.random.default_rng(8))
    p.submit(PointCloud(blob, 0.0, labels=np.full(len(blob), 1, np.uint8)))
    window = bar.torque
    assert window is not None and np.all(np.isfinite(window.tau_rate_max))
    window.previous[:] = ctrl.dynamics.compute(q, v).N
    window.t_previous[0] = 0.0
    return ctrl, bar, q, v, 1e-3


def test_rigid_rows_inside_the_margin_ask_no_more_than_the_torque_window_gives() -> None:
    """Each rigid row inside the margin asks the link away at min(k₀/k₁ |h|, v_s) with gain k_r, capped at
    ℓ − ρ(ℓ − ℓ₋), [ℓ₋, ℓ] the range of c q̈ over the
    torque window from scipy's linear programme (max and min of c q̈ s.t. lo ≤ M q̈ + N ≤ hi); the
    tick is solved where the uncapped rows (the Python path without the torque window) leave the QP
    infeasible and the fallback takes the tick."""
    from scipy.optimize import linprog

    from qpctl.kernels.drives import REACH_SHARE

    ctrl, bar, q, v, t = _inside_the_margin()
    window = bar.torque
    lo, hi = window.window(t)
    out = ctrl.step(q, v, t)
    problem = ctrl.last_problem
    rows = np.flatnonzero(np.array(problem.row_names) == bar.name)
    C, low = np.array(problem.C[rows])[:, :ctrl.n], np.array(problem.l[rows])
    pairs = bar.last
    inside = np.flatnonzero(pairs.active & ~pairs.soft & (pairs.distance < bar.margin))
    assert inside.size  # the set-up: a rigid pair inside the margin
    state = ctrl.dynamics.compute(q, v, t)
    A = np.r_[state.M, -state.M]
    b = np.r_[hi - state.N, -(lo - state.N)]
    capped = 0
    for r in inside:
        c = C[r]
        most = -linprog(-c, A_ub=A, b_ub=b, bounds=(None, None)).fun
        least = linprog(c, A_ub=A, b_ub=b, bounds=(None, None)).fun
        # at rest (ḣ = 0, no drift): away at min(k₀/k₁ |h|, v_s), with the recovery gain k_r
        away = min(bar.k0 / bar.k1 * (bar.margin - pairs.distance[r]), CFG.soft_speed)
        barrier = CFG_FAST_RECOVERY.recovery_gain * away
        want = min(barrier, most - REACH_SHARE * (most - least))
        assert low[r] == pytest.approx(want, rel=1e-7, abs=1e-9)
        capped += want < barrier
    assert capped >= 1  # the cap, not the barrier, bound the row
    # the Python path's rows, with the window as it was at the tick: the same capped bounds
    after = window.previous.copy(), window.t_previous.copy()
    window.previous[:], window.t_previous[0] = state.N, 0.0
    python = bar.compute(state, None)  # type: ignore[arg-type]
    window.previous[:], window.t_previous[:] = after
    assert python.lower[inside] == pytest.approx(low[inside], rel=1e-9, abs=1e-12)
    assert out.info.get("fallback") is None and out.info["status"] == "solved"
    # the same rows uncapped: no torque window given to them (the Python path)
    slow, slow_bar, q, v, t = _inside_the_margin()
    slow.remove_constraint(slow_bar.name)
    slow.add_constraint(_PythonOnly(slow_bar.source, slow.robot, CFG_FAST_RECOVERY, d_safe=slow.gains.d_safe,
                                    cutoff=slow.cutoff, k0=slow_bar.k0, k1=slow_bar.k1))
    assert slow.step(q, v, t).info.get("fallback") is not None
