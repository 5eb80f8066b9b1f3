"""qpctl.controllers.qp_compiled: the thin Python shell around the one-call QP tick (issue 23, item 5).

On the one-call path (DAQP's C API, no tick budget) nothing checks a good state in Python: the
compiled tick's dispatcher takes only float64 arrays and a float, the kernel checks the length and
finiteness, and a bad state is an InvalidStateError. The output reuses the last one when the caller
kept neither it nor a view of its arrays: after warm-up a tick allocates nothing.
"""

from __future__ import annotations

import dataclasses
import itertools
import tracemalloc
import weakref

import numpy as np
import pytest

from qpctl.bench.scenes import spheres_scene
from qpctl.bench.suites import ControllerSpec, closed_loop
from qpctl.controllers.qp_compiled import CompiledTick
from qpctl.errors import InvalidStateError


@pytest.fixture(scope="module")
def scene_and_states():
    """The Panda + 10 spheres scene and 400 states of its closed-loop QP run."""
    scene = spheres_scene()
    run = closed_loop(scene, ControllerSpec("qp", "daqp"), max_ticks=400)
    assert run.states is not None
    return scene, run.states


def _controller(scene):
    ctrl = scene.controller("qp", "daqp")
    ctrl.warmup()
    assert isinstance(ctrl.qp_path(), CompiledTick) and ctrl.qp_path().packed is not None  # the one-call path
    return ctrl


def _kept_torques(scene, states, passes: int) -> np.ndarray:
    """A fresh controller's torques on states 100–399 after ticks 0–99 and ``passes`` − 1 passes
    over 100–399 (the same ticks in the same order as the tests' loops: the warm starts chain alike),
    every output kept (each a new object: no reuse involved)."""
    fresh = _controller(scene)
    outs = [fresh.step(states.q[k], states.v[k], float(states.t[k])) for k in range(100)]
    for _ in range(passes):
        outs = [fresh.step(states.q[k], states.v[k], float(states.t[k])) for k in range(100, 400)]
    return np.array([o.tau for o in outs])


def test_a_tick_allocates_nothing_after_warm_up(scene_and_states):
    """tracemalloc over 1,500 ticks (five passes over 300 closed-loop states; outputs not kept, as in
    a control loop that reads τ and moves on), after two traced passes: the traced memory grows by
    less than 1 byte per tick (0 on most passes; a rare pass sees a few hundred bytes of an internal
    cache of numba's dispatch or Python's allocator) and never rises by more than 4 KiB within a tick
    (the kernels' own temporaries and Pinocchio's argument conversion, ~1.8 KiB); keeping the outputs
    instead grows it by ~0.9 KiB a tick, which the test checks it can see; the output is the same
    object tick after tick; the torques are those of a fresh controller whose outputs are all kept."""
    scene, states = scene_and_states
    ctrl = _controller(scene)
    tau = np.empty((300, ctrl.n))

    def one_pass() -> None:
        for k in range(100, 400):
            ctrl.step(states.q[k], states.v[k], float(states.t[k]))
            tau[k - 100] = ctrl.last.tau

    for k in range(100):  # warm-up: the solver's working set, the reused output
        ctrl.step(states.q[k], states.v[k], float(states.t[k]))
    tracemalloc.start()
    try:
        for _ in range(2):  # tracemalloc's own first allocations
            one_pass()
        start, _ = tracemalloc.get_traced_memory()
        tracemalloc.reset_peak()
        for _ in range(5):
            one_pass()
        end, peak = tracemalloc.get_traced_memory()
        kept = [ctrl.step(states.q[k], states.v[k], float(states.t[k])) for k in range(100, 200)]
        grown, _ = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert end - start < 1500 and peak - start <= 4096, (end - start, peak - start)
    assert grown - end >= 100 * 8 * kept[0].tau.size  # the measurement sees kept outputs
    first = id(ctrl.step(states.q[0], states.v[0], 0.0))
    assert id(ctrl.step(states.q[1], states.v[1], 1e-3)) == first
    np.testing.assert_array_equal(_kept_torques(scene, states, passes=7), tau)


def test_a_loop_keeping_each_output_until_the_next_allocates_nothing(scene_and_states):
    """The loop users write, ``out = ctrl.step(...)``, holds the last output while the next tick runs:
    the two outputs take turns (the last one is held, the one before is free). Over 600 such ticks after
    warm-up the traced memory grows by less than 1 byte a tick and never by more than 4 KiB within one
    (as the loop that drops its outputs above; allocating an output a tick grows it by ~0.9 KiB);
    exactly two output objects alternate (weak references to every tick's output: all still alive at
    the end, two objects among them — an output allocated per tick and freed would leave the memory
    flat and its id perhaps recycled, but not its weak reference alive); every output still holds its
    own tick's torque while the next tick runs; and the torques equal those of a fresh controller
    whose outputs are all kept."""
    scene, states = scene_and_states
    ctrl = _controller(scene)
    tau = np.empty((300, ctrl.n))
    refs: list[weakref.ref] = []

    def one_pass(check: bool) -> None:
        out = None
        for k in range(100, 400):
            prev, prev_tau = out, (None if out is None else out.tau.copy())
            out = ctrl.step(states.q[k], states.v[k], float(states.t[k]))
            if check:
                refs.append(weakref.ref(out))
                if prev is not None:  # the held output was not the one overwritten
                    assert out is not prev
                    np.testing.assert_array_equal(prev.tau, prev_tau)
            tau[k - 100] = out.tau
            del prev

    for k in range(100):
        ctrl.step(states.q[k], states.v[k], float(states.t[k]))
    one_pass(check=True)
    alive = [r() for r in refs]
    assert all(o is not None for o in alive) and len({id(o) for o in alive}) == 2
    assert all(a is not b for a, b in itertools.pairwise(alive))
    del alive
    tracemalloc.start()
    try:
        one_pass(check=False)  # tracemalloc's own first allocations
        start, _ = tracemalloc.get_traced_memory()
        tracemalloc.reset_peak()
        for _ in range(2):
            one_pass(check=False)
        end, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert end - start < 600 and peak - start <= 4096, (end - start, peak - start)
    np.testing.assert_array_equal(_kept_torques(scene, states, passes=4), tau)


def test_a_torque_loop_takes_turns_too(scene_and_states):
    """``tau = ctrl.torque(q, v, t)`` keeps a view of the last output's record until the next tick:
    that record is not overwritten (the held torque keeps its value) and the two outputs still take
    turns (weak references to every tick's output, ``ctrl.last``, all alive at the end: two objects)."""
    scene, states = scene_and_states
    ctrl = _controller(scene)
    for k in range(100):
        ctrl.step(states.q[k], states.v[k], float(states.t[k]))
    tau, refs = None, []
    for k in range(100, 200):
        prev, prev_value = tau, (None if tau is None else tau.copy())
        tau = ctrl.torque(states.q[k], states.v[k], float(states.t[k]))
        refs.append(weakref.ref(ctrl.last))
        if prev is not None:
            np.testing.assert_array_equal(prev, prev_value)
        del prev
    alive = [r() for r in refs]
    assert all(o is not None for o in alive) and len({id(o) for o in alive}) == 2


def test_the_kernels_by_address_leave_the_structs_counts_as_they_were(scene_and_states):
    """The common ticks call their kernel with the structref's address (qpctl.kernels.lend.lent_at lends
    it to the kernel without a count of its own): over 300 ticks of the QP and of the paper law the
    reference count of the packed QP's and of the workspace's memory-info record stays what it was (a
    missing increment would free them under the controller; a missing decrement would leak them)."""
    from qpctl.controllers.closed_form import PaperController

    scene, states = scene_and_states
    ctrl = _controller(scene)
    law = scene.controller("paper")
    law.warmup()
    assert isinstance(law, PaperController)
    for c in (ctrl, law):
        c.step(states.q[0], states.v[0], float(states.t[0]))
    structs = (ctrl.qp_path().packed, law.workspace().work)
    assert ctrl.qp_path()._addr != 0 and law._addr != 0  # the by-address entry points are the ones in use
    before = [s._meminfo.refcount for s in structs]
    for k in range(1, 301):
        for c in (ctrl, law):
            c.step(states.q[k], states.v[k], float(states.t[k]))
    assert [s._meminfo.refcount for s in structs] == before


def test_the_stage_times_are_parts_of_the_tick(scene_and_states):
    """The kernels time their stages with one clock read at each boundary (each stage's end the next
    one's start): on 200 common ticks of the QP and the paper law every stage time is positive and
    together they fit in the tick's own wall time (``compute_us``, read in Python around the call) —
    a boundary taken from the wrong clock (zero, or a stage's start) would not."""
    scene, states = scene_and_states
    ctrl = _controller(scene)
    law = scene.controller("paper")
    law.warmup()
    for c, stages in ((ctrl, ("state_us", "build_us", "solve_us")), (law, ("state_us", "build_us"))):
        c.step(states.q[0], states.v[0], float(states.t[0]))
        for k in range(1, 201):
            out = c.step(states.q[k], states.v[k], float(states.t[k]))
            info = out.info
            assert 0 < info["rigid_us"] < info["state_us"], (k, info)
            assert all(info[s] > 0 for s in stages), (k, info)
            assert sum(info[s] for s in stages) < out.compute_us, (k, info, out.compute_us)


def test_kept_outputs_and_views_are_never_overwritten(scene_and_states):
    """An output the caller holds, or a view of its torque, keeps its tick's values after later ticks
    (the reuse only takes an output nobody holds)."""
    scene, states = scene_and_states
    ctrl = _controller(scene)
    first = ctrl.step(states.q[10], states.v[10], float(states.t[10]))
    tau_first, info_first = first.tau.copy(), dict(first.info)
    view = ctrl.step(states.q[20], states.v[20], float(states.t[20])).tau
    tau_view = view.copy()
    for k in range(30, 60):
        ctrl.step(states.q[k], states.v[k], float(states.t[k]))
    np.testing.assert_array_equal(first.tau, tau_first)
    assert first.info == info_first
    np.testing.assert_array_equal(view, tau_view)
    assert not np.array_equal(tau_first, tau_view)


def test_other_array_types_give_the_same_torque(scene_and_states):
    """Lists, float32 and non-contiguous arrays, an int or numpy time: the dispatcher refuses them,
    the shell converts them and the torque is the float64 state's (to float32's rounding)."""
    scene, states = scene_and_states
    k = 200
    q, v, t = states.q[k], states.v[k], float(states.t[k])
    ref = _controller(scene).step(q, v, t).tau.copy()
    wide = np.zeros((2 * q.size,))
    wide[::2] = q
    cases = {
        "lists": (q.tolist(), v.tolist(), t, 0.0),
        "non-contiguous": (wide[::2], v, t, 0.0),
        "numpy time": (q, v, np.float64(t), 0.0),
        "float32": (q.astype(np.float32), v.astype(np.float32), t, 1e-3),
    }
    for name, (qq, vv, tt, rtol) in cases.items():
        got = _controller(scene).step(qq, vv, tt).tau
        np.testing.assert_allclose(got, ref, rtol=rtol, atol=rtol * np.abs(ref).max(), err_msg=name)
    ctrl = _controller(scene)
    np.testing.assert_array_equal(ctrl.step(q, v, t).tau, ref)
    ints = _controller(scene)
    assert np.isfinite(ints.step(q, v, round(t)).tau).all()  # an int time is a time


@pytest.mark.parametrize("kind", ["qp", "paper"])
def test_other_array_types_on_the_fast_tick_give_the_same_torque(scene_and_states, kind):
    """The same once a tick has run: the next ticks call the kernel's compiled entry point, which reads
    q and v as float64 C vectors without a check of its own, so :func:`plain_vectors` must turn away a
    strided view, a view with negative strides and float32 (each would be read as other numbers)."""
    scene, states = scene_and_states
    k = 200
    q, v, t = states.q[k], states.v[k], float(states.t[k])
    before = (states.q[k - 1], states.v[k - 1], float(states.t[k - 1]))
    wide = np.zeros((2 * q.size,))
    wide[::2] = q
    q_back, v_back = np.ascontiguousarray(q[::-1])[::-1], np.ascontiguousarray(v[::-1])[::-1]
    assert not q_back.flags.c_contiguous and np.array_equal(q_back, q) and np.array_equal(v_back, v)

    def warm():
        ctrl = scene.controller(kind, "daqp" if kind == "qp" else None)
        ctrl.warmup()
        ctrl.step(*before)
        assert (ctrl.qp_path() if kind == "qp" else ctrl)._entry is not None  # the fast tick from now on
        return ctrl

    ref = warm().step(q, v, t).tau.copy()
    cases = {"q strided": (wide[::2], v, 0.0), "q backwards": (q_back, v, 0.0), "v backwards": (q, v_back, 0.0),
             "float32": (q.astype(np.float32), v.astype(np.float32), 1e-3)}
    for name, (qq, vv, rtol) in cases.items():
        got = warm().step(qq, vv, t).tau
        np.testing.assert_allclose(got, ref, rtol=rtol, atol=rtol * np.abs(ref).max() + 1e-12, err_msg=name)


@pytest.mark.parametrize("bad", ["nan q", "inf v", "short q", "long v", "2-D q", "text", "nan t", "bool t"])
def test_bad_states_raise_invalid_state_error(scene_and_states, bad):
    """Each bad state raises InvalidStateError (the kernel reports NaN, inf and wrong lengths; the
    shell's checks refuse what the dispatcher cannot take), and the controller then steps on."""
    scene, states = scene_and_states
    ctrl = _controller(scene)
    q, v, t = states.q[50].copy(), states.v[50].copy(), float(states.t[50])
    if bad == "nan q":
        q[2] = np.nan
    elif bad == "inf v":
        v[0] = np.inf
    elif bad == "short q":
        q = q[:-1]
    elif bad == "long v":
        v = np.append(v, 0.0)
    elif bad == "2-D q":
        q = q[None, :]
    elif bad == "text":
        q = "not a state"
    elif bad == "bool t":
        t = True  # numba would take it as 1.0: a bool is no time
    else:
        t = float("nan")
    ctrl.step(states.q[48], states.v[48], float(states.t[48]))  # DAQP set up again after warmup's reset
    assert ctrl.qp_path().fast_step(states.q[49], states.v[49], float(states.t[49]), 0.0) is not None
    before = ctrl.step(states.q[49], states.v[49], float(states.t[49]))  # the output a refused tick would reuse
    tau, qdd, clearance = before.tau.copy(), before.qdd.copy(), before.clearance
    del before
    with pytest.raises(InvalidStateError):
        ctrl.step(q, v, t)
    # the refused tick wrote nothing into the last output's record (the kernel copies it on success only)
    np.testing.assert_array_equal(ctrl.last.tau, tau)
    np.testing.assert_array_equal(ctrl.last.qdd, qdd)
    assert ctrl.last.clearance == clearance
    good = ctrl.step(states.q[51], states.v[51], float(states.t[51]))
    assert np.isfinite(good.tau).all()


INFO_TIMES = ("rigid_us", "state_us", "build_us", "solve_us")


def _fields(ctrl, out):
    """Every field a user or the bench reads of a QP tick's output and of the controller after it,
    timings aside (``compute_us`` and info's *_us)."""
    sol = ctrl.last_solution
    return {"tau": out.tau.copy(), "qdd": out.qdd.copy(), "x": out.x.copy(), "e_null": out.e_null.copy(),
            "ref": tuple(a.copy() for a in out.ref), "clearance": out.clearance, "singular": out.singular,
            "status": out.status, "iterations": out.iterations,
            "info": {k: val for k, val in out.info.items() if k not in INFO_TIMES},
            "outcome": dataclasses.replace(out.outcome, solve_us=0.0),
            "solution": (sol.found, sol.x.copy(), sol.status, sol.iterations, sol.solver),
            "problem": (ctrl.last_problem.n_var, ctrl.last_problem.P.copy(), ctrl.last_problem.C.copy(),
                        ctrl.last_problem.u.copy())}


def test_the_fast_tick_equals_the_general_one_field_by_field(scene_and_states):
    """Two controllers on the same 300 closed-loop states: one's ticks through :meth:`CompiledTick.
    fast_step` (the common tick, its output's record and the solver's answer read lazily), the other's
    through :meth:`CompiledTick.step` (the general tick: the dispatcher, the outcome and the output
    built as before). Every field of the outputs and of the controllers' last solve is the same, the
    timings present in both; and the fast one ran on every tick (the general one's output is not reused
    by the fast one: different objects)."""
    scene, states = scene_and_states
    fast, slow = _controller(scene), _controller(scene)
    slow_path = slow.qp_path()
    assert isinstance(slow_path, CompiledTick)
    for ctrl in (fast, slow):  # DAQP set up again after warmup's reset
        ctrl.step(states.q[99], states.v[99], float(states.t[99]))
    taken = 0
    for k in range(100, 400):
        q, v, t = states.q[k], states.v[k], (float(states.t[k]) if k % 2 else states.t[k])  # numpy's floats too
        a = fast.qp_path().fast_step(q, v, t, 0.0)
        assert a is not None
        np.testing.assert_array_equal(a._rec, fast.qp_path().ws.rec)  # the kernel's copy: all of it, timings too
        fast.last, fast._last_from = a, fast.qp_path()
        taken += 1
        b = slow_path.step(q, v, t, 0.0)
        slow.last, slow._last_from = b, slow_path
        fa, fb = _fields(fast, a), _fields(slow, b)
        for key in fa:
            np.testing.assert_equal(fa[key], fb[key], err_msg=f"tick {k}: {key}")
        assert set(a.info) == set(b.info) and all(a.info[key] >= 0 for key in INFO_TIMES if key in a.info)
        assert a.iterations == int(fast.qp_path().hard.nat.flag[1] if a.info.get("relaxed") is None
                                   else fast.qp_path().relaxed.nat.flag[1])  # the solver's own count
        del a, b
    assert taken == 300
    # the controller's step takes the fast tick: its last output is the fast path's reused object
    first = id(fast.step(states.q[0], states.v[0], 0.0))
    assert id(fast.step(states.q[1], states.v[1], 1e-3)) == first
    assert id(fast.qp_path().fast_step(states.q[2], states.v[2], 2e-3, 0.0)) == first


def test_the_common_tick_goes_past_the_dispatcher(scene_and_states, monkeypatch):
    """After the tick that sets DAQP up, a float64 state with a Python or numpy float time is one call
    of the one-call kernel's compiled entry point: the dispatcher (here made to fail) is not called;
    a list state still goes through it."""
    from qpctl.kernels import tick as K

    scene, states = scene_and_states
    ctrl = _controller(scene)
    ctrl.step(states.q[60], states.v[60], float(states.t[60]))

    def refuse(*args):
        raise AssertionError("the dispatcher was called")

    refuse.disable_compile = lambda *args: None  # type: ignore[attr-defined]  # as a dispatcher's (lock_compilation)

    monkeypatch.setattr(K, "tick_qp", refuse)
    for k in range(61, 90):
        out = ctrl.step(states.q[k], states.v[k], states.t[k] if k % 2 else float(states.t[k]))
        assert np.isfinite(out.tau).all()
    del out
    with pytest.raises(AssertionError, match="dispatcher"):
        ctrl.step(states.q[90].tolist(), states.v[90], float(states.t[90]))


def test_the_fast_tick_keeps_the_skip_rule(scene_and_states):
    """After a tick on which the task gave way the hard QP is skipped; a relaxed tick whose slack is
    back to zero (the record's slack ≤ SLACK_ZERO) makes the next fast tick try the task hard again, one
    that is not does not. (Dropping the rule's update from the fast tick passed the suite: the 300
    states above never give way.)"""
    from qpctl.kernels.hard_first import SLACK_ZERO

    scene, states = scene_and_states
    ctrl = _controller(scene)
    ctrl.step(states.q[99], states.v[99], float(states.t[99]))  # DAQP set up again after warmup's reset
    path = ctrl.qp_path()
    assert isinstance(path, CompiledTick) and path.relax.skip_rule
    again = 0
    for k in range(100, 300):
        path.relax._try_hard = False  # as after a tick on which the task gave way
        a = path.fast_step(states.q[k], states.v[k], float(states.t[k]), 0.0)
        assert a is not None and a.info.get("relaxed") is not None  # the relaxed QP only
        zero = float(path.ws.rec[path._slack_at]) <= SLACK_ZERO
        assert path.relax.try_hard(True) == zero, f"tick {k}"
        again += zero
        del a
    assert again > 0  # some relaxed ticks came back to zero slack (the rule's case was met)
    b = path.fast_step(states.q[300], states.v[300], float(states.t[300]), 0.0)
    assert b is not None and (b.info.get("relaxed") is None) == zero  # the hard QP tried as the rule said
