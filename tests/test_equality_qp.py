"""The hard QP's answer on DAQP's last working set (qpctl.kernels.equality_qp) against DAQP's own solve.

Where the hard-first tick takes the minimum on the task's rows and the working set (its record's
iteration count 0), DAQP called cold on the same QP (the layout's H, f, rows and bounds, through the
``daqp`` package, from an empty working set) must give the same x and the same multipliers, and numpy's
KKT conditions must hold; where a row or a bound cuts through that minimum, or a held constraint's
multiplier has the wrong sign, the kernel must decline and leave its outputs alone.
"""

from __future__ import annotations

import importlib.metadata

import daqp
import numpy as np
import pytest

from qpctl import Scenario
from qpctl.kernels.equality_qp import active_set_minimum
from qpctl.run import simulate
from qpctl.solvers import daqp_native

# The closed loop's ticks take the path only inside the one-call hard-first kernel, which runs on DAQP's C
# API, used only with a DAQP version whose structs it was checked against (tests/test_daqp_pack.py
# requires that path with the pinned version, so this skip cannot hide it there). The kernel's own tests
# below run with any DAQP.
CHECKED = importlib.metadata.version("daqp") in daqp_native.CHECKED_VERSIONS
C_API = pytest.mark.skipif(not CHECKED, reason=f"DAQP {importlib.metadata.version('daqp')} is not one qpctl's C-API "
                           "path was checked against: the controller solves through daqp.Model, and the tick never "
                           "takes the working-set shortcut")


def _daqp_cold(H, f, rows, bu, bl):
    """DAQP's answer (x, λ, exit flag) on the layout's arrays, from an empty working set."""
    nv = H.shape[0]
    sense = np.zeros(bu.shape[0], np.int32)
    sense[nv:][bu[nv:] == bl[nv:]] = 5  # the equality rows as the layouts mark them (qpctl.tick.QPBuffers)
    x, _fval, flag, info = daqp.solve(H.copy(), f.copy(), rows.copy(), bu.copy(), bl.copy(), sense)
    return np.asarray(x), np.asarray(info["lam"]), flag


def _check_closed_loop(ctrl, traj, held_kinds):
    """Every 4th state of ``traj`` through ``ctrl`` (QP, DAQP): the record's active count against numpy's on
    every hard tick; on those whose answer came without DAQP (iterations 0) DAQP's cold solve, numpy's
    KKT conditions and the multipliers' sides (the docstring below). Returns the held kinds' counts."""
    hard = ctrl.qp_path().hard
    buf, nat = hard.buf, hard.nat
    nv, n_in, m, n = buf.nv, buf.n_in, buf.n_eq, buf.n
    taken = 0
    held = {"bound": 0, "row": 0, "slack": 0}
    ticks = range(0, len(traj.t), 4)
    for k in ticks:
        out = ctrl.step(traj.q[k], traj.v[k], float(traj.t[k]))
        if out.info.get("relaxed") is not None:
            continue
        H, f, rows, bu, bl = buf.H, buf.f, buf.rows, buf.bu, buf.bl
        x, lam = nat.x.copy(), nat.lam.copy()
        # the record's count of rows and bounds at a bound (the check reads the row products the
        # working-set answer left, or computes them after DAQP) against numpy's on the same x
        Cx = rows[:n_in] @ x
        bounded = np.isfinite(bl[nv:nv + n_in]) | np.isfinite(bu[nv:nv + n_in])
        at_row = bounded & (np.minimum(abs(Cx - bl[nv:nv + n_in]), abs(Cx - bu[nv:nv + n_in])) <= 1e-6 * (1 + abs(Cx)))
        at_bound = np.minimum(abs(x[:n] - bl[:n]), abs(x[:n] - bu[:n])) <= 1e-6
        assert out.info["active"] == at_row.sum() + at_bound.sum(), k
        if out.iterations != 0:
            continue
        taken += 1
        xd, lamd, flag = _daqp_cold(H, f, rows, bu, bl)
        assert flag > 0
        scale = max(1.0, np.abs(xd).max())
        np.testing.assert_allclose(x, xd, rtol=0, atol=1e-9 * scale, err_msg=f"tick {k}")
        np.testing.assert_allclose(lam, lamd, rtol=0, atol=1e-7 * max(1.0, np.abs(lamd).max()), err_msg=f"tick {k}")
        A = np.vstack([np.eye(nv), rows])  # every constraint's row by layout index: the bounds', then the rows'
        grad = H @ x + f + A.T @ lam
        assert np.abs(grad).max() <= 1e-8 * max(1.0, np.abs(f).max(), np.abs(H @ x).max()), (k, grad)
        Ax = A @ x
        tol = 1e-9 * np.maximum(1.0, np.abs(Ax))
        assert (bl - tol <= Ax).all() and (Ax <= bu + tol).all(), k
        up, lo = lam > 0, lam < 0  # a multiplier pushes from the side its constraint is held at
        assert np.allclose(Ax[up], bu[up], rtol=0, atol=1e-9 * scale), k
        assert np.allclose(Ax[lo], bl[lo], rtol=0, atol=1e-9 * scale), k
        held["bound"] += bool(lam[:n].any())
        held["slack"] += bool(lam[n:nv].any())
        held["row"] += bool(lam[nv:nv + n_in].any())
        assert (bu[nv + n_in:nv + n_in + m] == bl[nv + n_in:nv + n_in + m]).all()  # the task rows: equalities
    assert taken >= 0.9 * len(ticks), (taken, len(ticks))
    for kind in held_kinds:
        assert held[kind] > 0, f"no tick took the path with a {kind} held"
    return held


@C_API
@pytest.mark.parametrize(("name", "duration", "held_kinds"), [("panda_spheres", 6.0, ("bound", "row")),
                                                             ("paper", 3.0, ("row",))])
def test_the_minimum_on_the_working_set_is_daqps_answer(name, duration, held_kinds):
    """On every 4th state of the scene's closed loop (QP, DAQP): the ticks whose answer came without
    DAQP (iterations 0) are the hard QP's — DAQP cold on the same arrays gives the same x (1e-9
    relative) and multipliers (1e-7), and by numpy: Hx + f + Aᵀλ = 0, every row and bound holds, each
    multiplier has its side's sign (≥ 0 at an upper bound, ≤ 0 at a lower one) and is zero off its
    bound. Almost every tick takes the path (the working set changes rarely), among them ticks with an
    inequality held (a nonzero multiplier outside the task rows): on the Panda both a simple bound (joint
    6's upper q̈ bound, held from t ≈ 4 s) and a row (an obstacle's barrier), on the planar arm a row."""
    scen = Scenario.load(name, [f"sim.duration={duration}"])
    traj = simulate(scen, kind="qp", solver="daqp").trajectory
    _check_closed_loop(scen.build_controller("qp", "daqp"), traj, held_kinds)


@C_API
def test_slack_columns_held_at_zero_are_fixed_and_the_answer_is_daqps():
    """A depth map's rows add a slack column σ_l ≥ 0 per link (H 1e-9 there, ℓ₁ cost 1e7): the
    kernel fixes each σ at its held bound and solves on q̈, each σ's multiplier from its row of the KKT
    conditions. On the Panda's closed loop among the ``panda_spheres`` spheres seen as a point cloud
    (2,000 points on each, 2 cm voxels; 3 s): the same checks as above, against DAQP's cold solve of
    the whole 14-variable QP — ≥ 90 % of the hard ticks take it, with a σ bound, a q̈ bound and a row
    held among them."""
    from qpctl.perception import DepthMap, PerceptionConfig, PointCloud
    from qpctl.perception.rows import FieldBarrier
    from qpctl.perception.synthetic import sphere_surface_points
    from qpctl.simulation.simulator import Simulator

    class Fixed:  # a fixed map, as a Perception hands its snapshot
        def __init__(self, snapshot):
            self.snapshot = snapshot

    scen = Scenario.load("panda_spheres")
    cfg = PerceptionConfig(voxel=0.02, bounds_min=[-0.8, -0.8, -0.1], bounds_max=[0.8, 0.8, 1.2], truncation=0.3,
                           depth_noise=0.0)
    m = DepthMap(cfg)
    m.integrate(PointCloud(sphere_surface_points(scen.build_obstacles()), 0.0))

    def controller():
        ctrl = scen.build_controller("qp", "daqp")
        ctrl.add_constraint(FieldBarrier(Fixed(m.snapshot()), ctrl.robot, cfg, d_safe=ctrl.gains.d_safe,
                                         cutoff=ctrl.cutoff, k0=ctrl.config.barrier_k0, k1=ctrl.config.barrier_k1))
        return ctrl

    ctrl = controller()
    assert ctrl.qp_path().hard.buf.nv > ctrl.robot.nv  # the slack columns are there
    traj = Simulator(ctrl, dt=1e-3, duration=3.0, obstacles=scen.build_obstacles()).run(scen.q0(ctrl.robot))
    _check_closed_loop(controller(), traj, ("slack", "bound", "row"))


def _qp3():
    """A 3-variable QP with one equality row E x = e, one inequality row c x ≤ hi and bounds ±10 on x,
    and its minimum on the equality alone (numpy's KKT solve)."""
    rng = np.random.default_rng(7)
    A = rng.standard_normal((3, 3))
    H = A @ A.T + 3 * np.eye(3)
    f = rng.standard_normal(3)
    E = rng.standard_normal((1, 3))
    e = np.array([0.4])
    K = np.block([[H, E.T], [E, np.zeros((1, 1))]])
    xs = np.linalg.solve(K, np.concatenate([-f, e]))[:3]
    c = rng.standard_normal(3)
    return H, f, np.vstack([c, E]), e, c, xs


def _bounds(e, row_hi, x_hi):
    bu = np.concatenate([np.full(3, x_hi), [row_hi], e])
    bl = np.concatenate([np.full(3, -10.0), [-10.0], e])
    return bu, bl


def _run(H, f, rows, bu, bl, held=(), low=()):
    """active_set_minimum with the task row (layout index 4) and ``held`` (layout indices, ``low`` their
    sides) as equalities; x and λ start at 7 (to see whether they were written)."""
    nv, n_in, m = 3, 1, 1
    w = np.array([4, *held, 0, 0], np.int64)[:nv]
    lw = np.array([False, *low, False, False])[:nv]
    x, lam = np.full(nv, 7.0), np.full(nv + n_in + m, 7.0)
    cx = np.full(n_in, 7.0)
    ok = active_set_minimum(H, f, rows, bu, bl, n_in, m, w, lw, 1 + len(held), x, lam, np.zeros((nv, nv)),
                            np.zeros((nv, nv)), np.zeros((nv, nv)), np.zeros((nv, nv + 2)), np.zeros(nv), cx)
    if ok:  # the inequality row's product, for the tick's check to read (held or not)
        np.testing.assert_allclose(cx, rows[:n_in] @ x, rtol=1e-14, atol=1e-14)
    return ok, x, lam


def test_a_row_or_bound_through_the_minimum_declines_it():
    """No inequality held: the minimum on the equality alone is returned when the row and the bounds hold,
    equal to DAQP's; moving the row's upper bound, or one simple bound, just past that minimum (by 1e-9
    and by 1e-3) makes the kernel decline and leave x and λ untouched; DAQP's answer then has the row or
    bound binding (by 1e-3: another x)."""
    H, f, rows, e, c, xs = _qp3()
    ok, x, lam = _run(H, f, rows, *_bounds(e, c @ xs + 0.1, 10.0))
    assert ok
    np.testing.assert_allclose(x, xs, rtol=0, atol=1e-12)
    xd, lamd, flag = _daqp_cold(H, f, rows, *_bounds(e, c @ xs + 0.1, 10.0))
    assert flag > 0
    np.testing.assert_allclose(x, xd, rtol=0, atol=1e-10)
    np.testing.assert_allclose(lam, lamd, rtol=0, atol=1e-10)
    for cut in (1e-9, 1e-3):  # (a cut of 1e-9 is within DAQP's own tolerance: it returns the minimum itself)
        for bu, bl in (_bounds(e, c @ xs - cut, 10.0), _bounds(e, c @ xs + 0.1, xs.max() - cut)):
            ok, x, lam = _run(H, f, rows, bu, bl)
            assert not ok and (x == 7.0).all() and (lam == 7.0).all()
            xd, _lamd, flag = _daqp_cold(H, f, rows, bu, bl)
            assert flag > 0 and (cut < 1e-6 or np.abs(xd - xs).max() > 1e-6)  # the cut row or bound binds


@pytest.mark.parametrize("which", ["row", "bound"])
def test_a_held_row_or_bound_gives_daqps_answer_and_the_wrong_side_declines(which):
    """The row (layout index 3) or the largest variable's upper bound cut 0.2 through the minimum binds in
    DAQP's answer. Held at that side, the kernel returns DAQP's x and λ (1e-10; the held multiplier > 0);
    held at its lower side (the wrong side: its bound there is −10, far away), or held where it is cut
    the other way (0.2 beyond the minimum: its multiplier would pull, < 0), it declines, untouched; held
    twice (dependent rows) it declines; without holding it, too (the cut makes it violated)."""
    H, f, rows, e, c, xs = _qp3()
    i = int(np.argmax(xs))
    idx = 3 if which == "row" else i
    val = (c @ xs if which == "row" else xs[i])
    bu, bl = _bounds(e, val - 0.2, 10.0) if which == "row" else _bounds(e, c @ xs + 0.1, 10.0)
    if which == "bound":
        bu[i] = val - 0.2
    xd, lamd, flag = _daqp_cold(H, f, rows, bu, bl)
    assert flag > 0 and lamd[idx] > 0  # DAQP holds it at its upper bound
    ok, x, lam = _run(H, f, rows, bu, bl, held=(idx,), low=(False,))
    assert ok
    np.testing.assert_allclose(x, xd, rtol=0, atol=1e-10)
    np.testing.assert_allclose(lam, lamd, rtol=0, atol=1e-10)
    for held, low in (((idx,), (True,)), ((idx, idx), (False, False)), ((), ())):
        ok, x, lam = _run(H, f, rows, bu, bl, held=held, low=low)
        assert not ok and (x == 7.0).all() and (lam == 7.0).all(), (held, low)
    bu2 = bu.copy()
    bu2[idx] = val + 0.2  # cut the other way: the minimum is inside, holding it at val + 0.2 pulls x out
    xd2, lamd2, _ = _daqp_cold(H, f, rows, bu2, bl)
    assert lamd2[idx] == 0.0  # it does not bind: DAQP's answer is the minimum on the equality alone
    np.testing.assert_allclose(xd2, xs, rtol=0, atol=1e-10)
    ok, x, lam = _run(H, f, rows, bu2, bl, held=(idx,), low=(False,))
    assert not ok and (x == 7.0).all() and (lam == 7.0).all()


def _soft_qp(weight):
    """_qp3 with a slack column σ ≥ 0 on its inequality row made soft and raised through the minimum:
    c x + σ ≥ c x* + 0.5, σ's cost ``weight``·σ + 1e-9·σ²/2 (the field rows' form)."""
    H, f, rows, e, c, xs = _qp3()
    H4 = np.zeros((4, 4))
    H4[:3, :3], H4[3, 3] = H, 1e-9
    f4 = np.append(f, weight)
    rows4 = np.zeros((2, 4))
    rows4[0, :3], rows4[0, 3], rows4[1, :3] = c, 1.0, rows[1]
    bu = np.concatenate([np.full(3, 10.0), [np.inf], [np.inf], e])
    bl = np.concatenate([np.full(3, -10.0), [0.0], [c @ xs + 0.5], e])
    return H4, f4, rows4, bu, bl


@pytest.mark.parametrize("weight", [1e7, 1e-3])
def test_a_slack_column_is_fixed_at_its_bound_and_declined_where_it_should_give(weight):
    """The QP's slack column held at σ = 0 with the soft row held at its bound: with σ dear (1e7) the
    kernel's answer on q̈ alone is DAQP's, x and every multiplier (σ's from its KKT row, 1e7 − μ < 0 at
    its lower bound); with σ cheap (1e-3) σ's multiplier has the wrong sign — DAQP's answer uses σ > 0 —
    and the kernel declines, x and λ untouched. The slack column left out of the working set declines."""
    H, f, rows, bu, bl = _soft_qp(weight)
    nv, n_in, m = 4, 1, 1
    xd, lamd, flag = _daqp_cold(H, f, rows, bu, bl)
    assert flag > 0

    def run(w, low):
        x, lam, cx = np.full(nv, 7.0), np.full(nv + n_in + m, 7.0), np.zeros(n_in)
        ok = active_set_minimum(H, f, rows, bu, bl, n_in, m, np.array(w + [0] * (nv - len(w)), np.int64),
                                np.array(low + [False] * (nv - len(low))), len(w), x, lam, np.zeros((3, 3)),
                                np.zeros((nv, nv)), np.zeros((nv, nv)), np.zeros((nv, nv + 2)), np.zeros(nv), cx)
        return ok, x, lam

    ok, x, lam = run([5, 3, 4], [False, True, True])  # the task row, σ at 0, the soft row at its lower bound
    if weight > 1.0:
        assert ok and xd[3] == 0.0
        # numpy's KKT solve on q̈ with σ = 0 and both rows held: x and their multipliers, exactly; DAQP's
        # cold solve of the whole QP agrees within its own tolerance (H's 1e-9 beside 1e7 costs it ~1e-7)
        K = np.block([[H[:3, :3], rows[:, :3].T], [rows[:, :3], np.zeros((2, 2))]])
        kkt = np.linalg.solve(K, np.concatenate([-f[:3], bl[4:]]))
        np.testing.assert_allclose(x, np.append(kkt[:3], 0.0), rtol=0, atol=1e-12)
        np.testing.assert_allclose(lam[4:], kkt[3:], rtol=1e-12)
        assert lam[3] == pytest.approx(-(f[3] + kkt[3] * rows[0, 3]), rel=1e-12)  # σ's row of Hx + f + Aᵀλ = 0
        assert lam[3] < 0  # σ pushed from its lower bound
        np.testing.assert_allclose(x, xd, rtol=0, atol=1e-5)
        np.testing.assert_allclose(lam, lamd, rtol=1e-5, atol=1e-5)
    else:
        assert xd[3] > 0.1  # DAQP lets the row give way through σ
        assert not ok and (x == 7.0).all() and (lam == 7.0).all()
    ok, x, _ = run([5, 4], [False, True])  # σ not held: not fixed, so not this kernel's
    assert not ok and (x == 7.0).all()
