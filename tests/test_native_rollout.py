"""The brake rollout's native loop (qpctl.native, brake_rollout.cpp) against the Python loop and the
Pinocchio bindings: Pinocchio's ABA and RNEA through the library's handle equal the bindings' bit for
bit; the native loop's certificates and the times at which it asks for the clearance equal the Python
loop's (the same operations in the same order, so equality, not a tolerance); the guard gives the
same torques either way; robots on a Lie group keep the Python loop; the library is built on this
machine's Pinocchio."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
import test_rollout as cases

from qpctl import Obstacle, native, panda, planar_arm
from qpctl.safety.rollout import BrakeRollout
from qpctl.simulation import Simulator

#: The Pinocchio versions the native library was built and checked against here; elsewhere a build
#: failure is reported by why_unavailable() and the Python loop serves.
CHECKED_PINOCCHIO = ("4.1.0",)


def lib_or_skip():
    """The library; a skip only on a Pinocchio the build was not checked against (the brake rollout and
    the rigid-body pass then run their Python paths, tested in test_rollout.py and everywhere else);
    with a checked one, unavailable is a failure."""
    lib = native.library()
    if lib is None and pin.__version__ not in CHECKED_PINOCCHIO:
        pytest.skip(f"the native library is not built for Pinocchio {pin.__version__}, a version it was not "
                    "checked against (the brake rollout and the rigid-body pass then run their Python paths, "
                    f"tested in test_rollout.py and everywhere else): "
                    f"{native.why_unavailable()}")
    assert lib is not None, native.why_unavailable()
    return lib


def test_the_library_builds_with_a_checked_pinocchio():
    """With a Pinocchio it was checked against, the library builds and the rollout uses it: a broken
    build cannot pass for an unavailable one."""
    if pin.__version__ not in CHECKED_PINOCCHIO:
        pytest.skip(f"Pinocchio {pin.__version__} is not one the native build was checked against")
    assert native.library() is not None, native.why_unavailable()
    ctrl, _, _ = cases.planar_case()
    assert BrakeRollout(ctrl.robot, Simulator(ctrl, dt=cases.DT, duration=cases.DT).world, cases.DT).native is not None


def ur5():
    """The UR5 of example-robot-data, from its URDF (another robot than qpctl's own two)."""
    urdf = native.prefix() / "share/example-robot-data/robots/ur_description/urdf/ur5_robot.urdf"
    return pin.buildModelFromUrdf(str(urdf))


@pytest.mark.parametrize("which", ["planar", "panda", "ur5"])
def test_aba_and_rnea_through_the_handle_equal_the_bindings(which, rng):
    """200 random states: the handle's model (serialized, loaded in C++) gives pin.aba's and pin.rnea's
    results exactly."""
    lib = lib_or_skip()
    model = {"planar": lambda: planar_arm().model, "panda": lambda: panda().model, "ur5": ur5}[which]()
    text = model.saveToString().encode()
    h = lib.qpb_new(text, len(text))
    assert h
    try:
        data = model.createData()
        out = np.zeros(model.nv)
        for _ in range(200):
            q = pin.randomConfiguration(model, -np.pi * np.ones(model.nq), np.pi * np.ones(model.nq))
            v, u = rng.normal(0, 2, model.nv), rng.normal(0, 20, model.nv)
            lib.qpb_aba(h, q.ctypes.data, v.ctypes.data, u.ctypes.data, out.ctypes.data)
            assert np.array_equal(out, pin.aba(model, data, q, v, u))
            lib.qpb_rnea(h, q.ctypes.data, v.ctypes.data, u.ctypes.data, out.ctypes.data)
            assert np.array_equal(out, pin.rnea(model, data, q, v, u))
    finally:
        lib.qpb_free(h)


def both(ctrl):
    sim = Simulator(ctrl, dt=cases.DT, duration=cases.DT)
    fast, slow = BrakeRollout(ctrl.robot, sim.world, cases.DT), BrakeRollout(ctrl.robot, sim.world, cases.DT)
    slow.native = None
    return fast, slow


def recorded(rollout, monkeypatch):
    """The times at which ``rollout`` evaluates its world clearance, recorded."""
    times: list[float] = []
    world = rollout.world
    monkeypatch.setattr(rollout, "world", lambda q, t: times.append(t) or world(q, t))
    return times


CASES = {
    "planar": lambda: cases.planar_case(),
    "no-rate": lambda: cases.planar_case(rate=np.inf),
    "contact": lambda: cases.planar_case(obstacles=[Obstacle("sphere", [-0.72, -1.45], radius=0.1)]),
    "moving": lambda: cases.planar_case(obstacles=[Obstacle("sphere", [-1.6, -1.0], radius=0.1, velocity=[0.3, -0.4])]),
    "panda": cases.panda_case,
}


def settles_recorded(rollout, monkeypatch):
    """The settled states ``rollout`` tests for a rest — (step time, the test's answer) — recorded."""
    tests: list[tuple[float, bool]] = []
    test = rollout.settled_rest
    monkeypatch.setattr(rollout, "settled_rest", lambda *a: tests.append((a[5], test(*a))) or tests[-1][1])
    return tests


@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("gain", [4.0, 25.0, 60.0])
@pytest.mark.parametrize("exact", [True, False])
@pytest.mark.parametrize("settle", [False, True])
def test_native_certificates_equal_the_python_loops(case, gain, exact, settle, monkeypatch):
    """Each case × gain × exact/lazy × settled or not, stop_below 0 and −∞, margin 0 and 0.05 m: the
    certificate (verdict, steps, time to rest, least clearance), the clearance's evaluation times and
    the settled states tested for a rest (and the answers) are equal."""
    lib_or_skip()
    ctrl, q, v = CASES[case]()
    fast, slow = both(ctrl)
    assert fast.native is not None
    tau_prev = cases.gravity(ctrl.robot, q)
    for stop, margin in ((0.0, 0.0), (-np.inf, 0.0), (0.0, 0.05)):
        tf, ts = recorded(fast, monkeypatch), recorded(slow, monkeypatch)
        sf, ss = settles_recorded(fast, monkeypatch), settles_recorded(slow, monkeypatch)
        a = fast.run(q, v, tau_prev, 0.3, gain, stop_below=stop, margin=margin, exact=exact, settle=settle)
        b = slow.run(q, v, tau_prev, 0.3, gain, stop_below=stop, margin=margin, exact=exact, settle=settle)
        assert a == b
        assert tf == ts and len(tf) >= 1
        assert sf == ss and (settle or not sf)
        monkeypatch.undo()
    assert fast.native is not None  # still the native loop after the patches


def test_the_cases_reach_every_settle_answer(monkeypatch):
    """Across the cases, gains and margins the settle is tried, accepted (the certificate viable, ended
    there), and refused with the rollout going on past it (the answers the equality above compares)."""
    lib_or_skip()
    answers = set()
    for fast, q, v, tau_prev, gain in case_rollouts((4.0, 25.0, 60.0)):
        for margin in (0.0, 0.05):
            tests = settles_recorded(fast, monkeypatch)
            c = fast.run(q, v, tau_prev, 0.3, gain, stop_below=0.0, margin=margin, settle=True)
            monkeypatch.undo()
            end = 0.3 + c.steps * cases.DT
            for t, accepted in tests:
                if accepted:
                    assert c.viable and t == pytest.approx(end, abs=1e-9)
                    answers.add("accepted")
                else:
                    assert end > t
                    answers.add("refused, went on")
    assert {"accepted", "refused, went on"} <= answers


def case_rollouts(gains):
    """(the native rollout, q, q̇, τ_prev, gain) for every case × gain."""
    for make in CASES.values():
        ctrl, q, v = make()
        fast, _ = both(ctrl)
        tau_prev = cases.gravity(ctrl.robot, q)
        for gain in gains:
            yield fast, q, v, tau_prev, gain


def test_the_cases_reach_every_ending():
    """The cases above end at rest viable, at rest within the margin, on contact and at the horizon
    (so the equality covers each of qpb_advance's answers)."""
    lib_or_skip()
    ends = set()
    for fast, q, v, tau_prev, gain in case_rollouts((4.0, 25.0)):
        c = fast.run(q, v, tau_prev, 0.3, gain, stop_below=0.0)
        ends.add("rest" if c.viable else "contact" if c.min_clearance < 0 else "other")
        h = fast.run(q, v, tau_prev, 0.3, gain, horizon=0.01)
        ends.add("horizon" if (not h.viable and h.steps == 5) else "?")
    assert {"rest", "contact", "horizon"} <= ends


def test_a_joint_limit_ends_the_native_loop_as_the_python_one():
    """The limit set after the rollouts were made (both read the robot's limits at each run)."""
    lib_or_skip()
    ctrl, q, v = cases.planar_case(obstacles=[])
    fast, slow = both(ctrl)
    ctrl.robot.q_min[1] = q[1] - 0.05
    tau_prev = cases.gravity(ctrl.robot, q)
    a, b = fast.run(q, v, tau_prev, 0.0, 10.0), slow.run(q, v, tau_prev, 0.0, 10.0)
    assert a == b and not a.viable and 0 < a.steps < 100


def test_non_finite_state_fails_in_both():
    lib_or_skip()
    ctrl, q, v = cases.planar_case()
    fast, slow = both(ctrl)
    v = v.copy()
    v[1] = np.nan
    tau_prev = cases.gravity(ctrl.robot, q)
    a, b = fast.run(q, v, tau_prev, 0.0, 25.0), slow.run(q, v, tau_prev, 0.0, 25.0)
    assert a == b and not a.viable and a.steps == 0


def test_the_guard_applies_the_same_torques_native_or_not():
    """A QP behind the guard, 150 ticks of the planar case's path in the simulator, native against the
    Python loop: the applied torques and the guard's counts are equal."""
    lib_or_skip()
    from qpctl.safety import BackupGuard

    runs = []
    for use_native in (True, False):
        ctrl, q, _ = cases.planar_case()
        guard = BackupGuard(ctrl, dt=cases.DT)
        if not use_native:
            guard.brake.native = None
        sim = Simulator(guard, dt=cases.DT, duration=150 * cases.DT)
        tr = sim.run(q)
        runs.append((tr.tau, dict(guard.stats, check_us=None)))
    assert np.array_equal(runs[0][0], runs[1][0])
    assert runs[0][1] == runs[1][1]
    assert runs[0][1]["checked"] > 100


def test_a_robot_on_a_lie_group_keeps_the_python_loop():
    """Continuous joints (nq ≠ nv): no native handle for the rollout, and the library refuses such a
    model by name."""
    lib = lib_or_skip()
    from test_lie_joints import _kinova

    robot = _kinova()
    assert robot.lie
    rollout = BrakeRollout(robot, _world(robot), cases.DT)
    assert rollout.native is None
    text = robot.model.saveToString().encode()
    assert not lib.qpb_new(text, len(text))
    assert b"nq == nv" in lib.qpb_error()


def _world(robot):
    from qpctl.tick import WorldClearance

    return WorldClearance(robot, [])


def test_a_failed_build_names_its_reason_and_leaves_nothing(tmp_path, monkeypatch):
    """A compiler that fails: NativeBuildError naming it, no library file left behind; and where the
    library is unavailable the rollout takes the Python loop."""
    monkeypatch.setenv("QPCTL_NATIVE_DIR", str(tmp_path))
    monkeypatch.setenv("CXX", "/bin/false")
    with pytest.raises(native.NativeBuildError, match="/bin/false failed"):
        native.build()
    assert not list(tmp_path.iterdir())
    monkeypatch.setattr(native, "library", lambda: None)
    ctrl, _, _ = cases.planar_case()
    assert BrakeRollout(ctrl.robot, Simulator(ctrl, dt=cases.DT, duration=cases.DT).world, cases.DT).native is None


@pytest.mark.parametrize("case", ["planar", "panda"])
def test_the_native_successor_equals_the_python_step(case, rng):
    """A proposal held over one step (the guard's successor): qpb_step's state equals the Python loop's
    RK4 step bit for bit, 50 random torques."""
    lib_or_skip()
    ctrl, q, v = CASES[case]()
    fast, slow = both(ctrl)
    for _ in range(50):
        tau = rng.normal(0, 30, ctrl.robot.nv)
        a, b = fast.successor(q, v, tau), slow.successor(q, v, tau)
        assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
        assert not np.array_equal(a[0], q)
