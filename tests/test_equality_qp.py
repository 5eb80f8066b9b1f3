"""The hard QP's answer where no inequality binds (qpctl.kernels.equality_qp) against DAQP's own solve.

Where the hard-first tick takes the minimum on the task's rows (its record's iteration count 0), DAQP
called cold on the same QP (the layout's H, f, rows and bounds, through the ``daqp`` package) must give
the same x and the same multipliers, and numpy's KKT residual must vanish; where a row or a bound cuts
through that minimum, the kernel must decline and leave its outputs alone.
"""

from __future__ import annotations

import importlib.metadata

import daqp
import numpy as np
import pytest

from qpctl import Scenario
from qpctl.kernels.daqp_pack import ACTIVE, IMMUTABLE
from qpctl.kernels.equality_qp import equality_minimum
from qpctl.run import simulate
from qpctl.solvers import daqp_native

# The closed loop's ticks take the path only inside the one-call hard-first kernel, which runs on DAQP's C
# API, used only with a DAQP version whose structs it was checked against (tests/test_daqp_pack.py
# requires that path with the pinned version, so this skip cannot hide it there). The kernel's own test
# below runs with any DAQP.
CHECKED = importlib.metadata.version("daqp") in daqp_native.CHECKED_VERSIONS
C_API = pytest.mark.skipif(not CHECKED, reason=f"DAQP {importlib.metadata.version('daqp')} is not one qpctl's C-API "
                           "path was checked against: the controller solves through daqp.Model, and the tick never "
                           "takes the equality shortcut")


def _daqp_cold(H, f, rows, bu, bl):
    """DAQP's answer (x, λ, exit flag) on the layout's arrays, from an empty working set."""
    nv = H.shape[0]
    sense = np.zeros(bu.shape[0], np.int32)
    sense[nv:][bu[nv:] == bl[nv:]] = 5  # the equality rows as the layouts mark them (qpctl.tick.QPBuffers)
    x, _fval, flag, info = daqp.solve(H.copy(), f.copy(), rows.copy(), bu.copy(), bl.copy(), sense)
    return np.asarray(x), np.asarray(info["lam"]), flag


@C_API
@pytest.mark.parametrize("name", ["panda_spheres", "paper"])
def test_the_minimum_on_the_task_rows_is_daqps_answer(name):
    """On every 4th state of the scene's closed loop (QP, DAQP): the ticks whose answer came without
    DAQP (iterations 0) are the hard QP's — DAQP cold on the same arrays gives the same x (1e-9
    relative) and the task rows' multipliers (1e-7), Hx + f + Eᵀλ = 0 and E x = e hold by numpy, every
    other row and bound holds — and the working set DAQP keeps for the next tick is the equalities
    alone. The path is taken on at least a third of the ticks and never where a row or bound binds."""
    scen = Scenario.load(name, ["sim.duration=3.0"])
    traj = simulate(scen, kind="qp", solver="daqp").trajectory
    ctrl = scen.build_controller("qp", "daqp")
    path = ctrl.qp_path()
    hard = path.hard
    buf, nat = hard.buf, hard.nat
    nv, n_in, m = buf.nv, buf.n_in, buf.n_eq
    taken = binding = 0
    ticks = range(0, len(traj.t), 4)
    for k in ticks:
        out = ctrl.step(traj.q[k], traj.v[k], float(traj.t[k]))
        if out.info.get("relaxed") is not None or out.iterations != 0:
            binding += out.info["active"] > 0
            continue
        taken += 1
        assert out.info["active"] == 0, k  # no row within 1e-6 of a bound: none binds
        H, f, rows, bu, bl = buf.H, buf.f, buf.rows, buf.bu, buf.bl
        x, lam = nat.x.copy(), nat.lam.copy()
        xd, lamd, flag = _daqp_cold(H, f, rows, bu, bl)
        assert flag > 0
        scale = max(1.0, np.abs(xd).max())
        np.testing.assert_allclose(x, xd, rtol=0, atol=1e-9 * scale, err_msg=f"tick {k}")
        eq = slice(nv + n_in, nv + n_in + m)
        np.testing.assert_allclose(lam[eq], lamd[eq], rtol=0, atol=1e-7 * max(1.0, np.abs(lamd[eq]).max()))
        assert not lam[:nv + n_in].any() and not lamd[:nv + n_in].any()  # no inequality multiplier
        E, e = rows[n_in:n_in + m], bu[eq]
        np.testing.assert_allclose(E @ x, e, rtol=0, atol=1e-9 * max(1.0, np.abs(e).max()))
        grad = H @ x + f + E.T @ lam[eq]
        assert np.abs(grad).max() <= 1e-8 * max(1.0, np.abs(f).max(), np.abs(H @ x).max()), (k, grad)
        assert (bl[:nv] <= x).all() and (x <= bu[:nv]).all()
        C = rows[:n_in] @ x
        assert (bl[nv:nv + n_in] <= C).all() and (C <= bu[nv:nv + n_in]).all()
        assert not any(s & ACTIVE and not s & IMMUTABLE for s in nat.sense_full), k
    assert taken >= len(ticks) // 3, (taken, len(ticks))
    assert binding > 0  # the scene has ticks where a row binds: there DAQP answered (iterations ≥ 1)


def test_a_row_or_bound_through_the_minimum_declines_it():
    """A 3-variable QP with one equality row: its minimum on the equality alone (by numpy's KKT solve)
    is returned when the inequality row and the bounds hold, equal to DAQP's; moving the row's upper
    bound, or one simple bound, just past that minimum (by 1e-9 and by 1e-3) makes the kernel decline
    and leave x and λ untouched; DAQP's answer then has the row or bound binding (by 1e-3: another x)."""
    rng = np.random.default_rng(7)
    A = rng.standard_normal((3, 3))
    H = A @ A.T + 3 * np.eye(3)
    f = rng.standard_normal(3)
    E = rng.standard_normal((1, 3))
    e = np.array([0.4])
    K = np.block([[H, E.T], [E, np.zeros((1, 1))]])
    sol = np.linalg.solve(K, np.concatenate([-f, e]))
    xs = sol[:3]  # the minimum on E x = e: the KKT system's own solution
    c = rng.standard_normal(3)
    rows = np.vstack([c, E])
    nv, n_in, m = 3, 1, 1

    def bounds(row_hi, x_hi):
        bu = np.concatenate([np.full(nv, x_hi), [row_hi], e])
        bl = np.concatenate([np.full(nv, -10.0), [-10.0], e])
        return bu, bl

    def run(bu, bl):
        x, lam = np.full(nv, 7.0), np.full(nv + n_in + m, 7.0)
        ok = equality_minimum(H, f, rows, bu, bl, n_in, m, x, lam, np.zeros((nv, nv)), np.zeros((nv, m)),
                              np.zeros((m, m)), np.zeros((m, m + 2)), np.zeros(nv))
        return ok, x, lam

    ok, x, lam = run(*bounds(c @ xs + 0.1, 10.0))
    assert ok
    np.testing.assert_allclose(x, xs, rtol=0, atol=1e-12)
    xd, lamd, flag = _daqp_cold(H, f, rows, *bounds(c @ xs + 0.1, 10.0))
    assert flag > 0
    np.testing.assert_allclose(x, xd, rtol=0, atol=1e-10)
    np.testing.assert_allclose(lam, lamd, rtol=0, atol=1e-10)
    for cut in (1e-9, 1e-3):  # (a cut of 1e-9 is within DAQP's own tolerance: it returns the minimum itself)
        for bu, bl in (bounds(c @ xs - cut, 10.0), bounds(c @ xs + 0.1, xs.max() - cut)):
            ok, x, lam = run(bu, bl)
            assert not ok and (x == 7.0).all() and (lam == 7.0).all()
            xd, _lamd, flag = _daqp_cold(H, f, rows, bu, bl)
            assert flag > 0 and (cut < 1e-6 or np.abs(xd - xs).max() > 1e-6)  # the cut row or bound binds
