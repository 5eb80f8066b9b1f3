"""The tick's rigid-body pass on the native library (qpctl.native.rigid, rigid_pass.cpp; called by the
compiled tick through qpctl.kernels.pin_native) against the Pinocchio bindings: its views hold the
bindings' crba and nonLinearEffects bit for bit; controllers with it give the torques of the same
controllers on Python's rigid_pass, bit for bit, on the same states; a gravity changed after the
controller was built counts from the next tick; the stage time is reported; robots on a Lie group
and machines without the library keep Python's pass."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
from test_native_rollout import lib_or_skip, ur5

from qpctl import Scenario, native, panda, planar_arm
from qpctl.errors import InvalidStateError
from qpctl.native.rigid import NativeRigid
from qpctl.run import simulate


@pytest.mark.parametrize("which", ["planar", "panda", "ur5"])
def test_the_views_hold_the_bindings_crba_and_nle(which, rng):
    """100 random states: oMi, a_gf, J, M's upper triangle and nle equal the bindings' exactly."""
    lib_or_skip()
    model = {"planar": lambda: planar_arm().model, "panda": lambda: panda().model, "ur5": ur5}[which]()
    rp = NativeRigid.create(model)
    assert rp is not None
    data = model.createData()
    for _ in range(100):
        q = pin.randomConfiguration(model, -np.pi * np.ones(model.nq), np.pi * np.ones(model.nq))
        v = rng.normal(0, 2, model.nv)
        rp.run(q, v)
        pin.crba(model, data, q, pin.Convention.WORLD)
        pin.nonLinearEffects(model, data, q, v)
        assert np.array_equal(np.triu(rp.views["Mt"].T), np.triu(data.M))
        assert np.array_equal(rp.views["Jt"].T, data.J)
        assert np.array_equal(rp.views["nle"], data.nle)
        for j in range(model.njoints):
            assert np.array_equal(rp.views["oMi"][j, :9].reshape(3, 3).T, data.oMi[j].rotation)
            assert np.array_equal(rp.views["oMi"][j, 9:], data.oMi[j].translation)
            assert np.array_equal(rp.views["acc_gf"][j], data.a_gf[j].vector)
    with pytest.raises(ValueError, match="shapes"):
        rp.run(np.zeros(model.nq + 1), np.zeros(model.nv))


def _recorded(scenario: str, ticks: int):
    traj = simulate(Scenario.load(scenario), kind="qp", solver="daqp").trajectory
    idx = range(0, min(len(traj.t), 3 * ticks), 3)
    return [(np.ascontiguousarray(traj.q[k]), np.ascontiguousarray(traj.v[k]), float(traj.t[k])) for k in idx]


def _pair(scen: Scenario, kind: str, monkeypatch):
    """The controller built with the native pass, and again with the library unavailable."""
    def build():
        c = scen.build_controller(kind, "daqp") if kind == "qp" else scen.build_controller(kind)
        c.warmup()
        return c

    a = build()
    with monkeypatch.context() as m:
        m.setattr(native, "library", lambda: None)
        b = build()
    return a, b


def _ws(c):
    return c.qp_path().ws if c.kind == "qp" else c.workspace()


@pytest.mark.parametrize("scenario", ["panda_spheres", "paper"])
@pytest.mark.parametrize("kind", ["qp", "paper", "hsu"])
def test_controllers_give_the_python_pass_torques(scenario, kind, monkeypatch):
    """The same 300 recorded states through each controller with and without the native pass: the
    same torques bit for bit, and the native pass's stage time reported (> 0, < the tick)."""
    lib_or_skip()
    scen = Scenario.load(scenario)
    fast, slow = _pair(scen, kind, monkeypatch)
    assert not _ws(fast).py_rigid and _ws(slow).py_rigid
    for q, v, t in _recorded(scenario, 300):
        a, b = fast.step(q, v, t), slow.step(q, v, t)
        assert np.array_equal(a.tau, b.tau), t
        assert 0 < a.info["rigid_us"] < a.compute_us
    fast.reset()
    q, v, t = _recorded(scenario, 1)[0]
    with pytest.raises(InvalidStateError):
        fast.step(np.append(q, 0.0), v, t)
    with pytest.raises(InvalidStateError):
        fast.step(q * np.nan, v, t)


@pytest.mark.parametrize("kind", ["qp", "paper"])
def test_a_gravity_changed_after_the_build_counts_from_the_next_tick(kind, monkeypatch):
    """model.gravity set after both controllers exist: the native pass reads it on the next tick
    (the same torques as Python's pass, which reads the model itself), and they differ from the
    torques before the change."""
    lib_or_skip()
    scen = Scenario.load("panda_spheres")
    fast, slow = _pair(scen, kind, monkeypatch)
    q, v, t = _recorded("panda_spheres", 1)[0]
    before = fast.step(q, v, t).tau.copy()
    for c in (fast, slow):
        c.reset()
    models = (fast.robot.model, slow.robot.model)
    g = models[0].gravity.linear.copy()
    try:
        for m in models:
            m.gravity.linear = np.array([0.0, 0.0, -3.7])
        a, b = fast.step(q, v, t).tau, slow.step(q, v, t).tau
        assert np.array_equal(a, b)
        assert not np.allclose(a, before)
    finally:
        for m in models:
            m.gravity.linear = g


def test_a_lie_robot_and_a_missing_library_keep_pythons_pass(monkeypatch):
    """A configuration that is not a vector space (a continuous joint), and no library: no native pass."""
    from test_lie_joints import _kinova
    lib_or_skip()
    assert NativeRigid.create(_kinova().model) is None
    monkeypatch.setattr(native, "library", lambda: None)
    assert NativeRigid.create(panda().model) is None
