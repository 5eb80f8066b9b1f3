"""qpctl.controllers.closed_form: the closed forms' thin shell (issue 23, item 5) — bad states are an
InvalidStateError reported by the kernel, other array types are converted, and an output nobody kept
is reused (the same object, its record overwritten) while a kept one keeps its tick's values."""

from __future__ import annotations

import itertools
import weakref

import numpy as np
import pytest

from qpctl import Scenario
from qpctl.errors import InvalidStateError

Q0, V0 = np.array([np.pi, np.pi / 2, 0.0]), np.array([0.1, -0.2, 0.3])


@pytest.fixture(scope="module", params=["paper", "hsu"])
def law(request):
    ctrl = Scenario.load("paper").build_controller(request.param)
    ctrl.warmup()
    return ctrl


@pytest.mark.parametrize("bad", ["nan q", "inf v", "short q", "nan t", "text", "bool t", "2-D q"])
def test_bad_states_raise_invalid_state_error(law, bad):
    q, v, t = Q0.copy(), V0.copy(), 0.3
    if bad == "nan q":
        q[1] = np.nan
    elif bad == "inf v":
        v[2] = -np.inf
    elif bad == "short q":
        q = q[:2]
    elif bad == "nan t":
        t = float("nan")
    elif bad == "bool t":
        t = True  # numba would take it as 1.0: a bool is no time
    elif bad == "2-D q":
        q = q[None, :]
    else:
        v = "fast"
    before = law.step(Q0 + 0.05, V0, 0.29)  # the output the refused tick would reuse (nobody else holds it)
    tau, qdd, x = before.tau.copy(), before.qdd.copy(), before.x.copy()
    del before
    with pytest.raises(InvalidStateError):
        law.step(q, v, t)
    # the refused tick wrote nothing into the last output's record (the kernel copies it on success only)
    for got, want in ((law.last.tau, tau), (law.last.qdd, qdd), (law.last.x, x)):
        np.testing.assert_array_equal(got, want)
    assert np.isfinite(law.step(Q0, V0, 0.3).tau).all()


def test_outputs_reused_only_when_nobody_holds_them(law):
    """The torque of the float64 state equals that of its list and float32 forms (to float32's
    rounding); an output kept across later ticks keeps its values; one dropped is reused."""
    ref = law.step(Q0, V0, 0.3).tau.copy()
    np.testing.assert_allclose(law.step(Q0.tolist(), V0.tolist(), 0.3).tau, ref, rtol=0, atol=0)
    np.testing.assert_allclose(law.step(Q0.astype(np.float32), V0.astype(np.float32), 0.3).tau, ref, rtol=1e-4,
                               atol=1e-4 * np.abs(ref).max())
    kept = law.step(Q0, V0, 0.3)
    for k in range(5):
        law.step(Q0 + 0.01 * k, V0, 0.3 + 1e-3 * k)
    np.testing.assert_array_equal(kept.tau, ref)
    del kept
    first = id(law.step(Q0, V0, 0.31))
    again = law.step(Q0, V0, 0.32)
    assert id(again) == first
    np.testing.assert_array_equal(again._rec, law.workspace().rec)  # the kernel's copy: all of it, timings too


def test_outputs_take_turns_in_a_loop_that_keeps_the_last(law):
    """``out = law.step(...)`` keeps the last output while the next tick runs: the tick writes the one
    before instead (two objects alternating: weak references to every output all alive at the end), the
    held one keeps its torque, and every torque equals that of the same tick in a loop that keeps all
    its outputs (each a new object)."""
    states = [(Q0 + 0.01 * k, V0 - 0.02 * k, 0.3 + 1e-3 * k) for k in range(12)]
    kept = [law.step(q, v, t) for q, v, t in states]
    assert len({id(o) for o in kept}) == len(kept)
    want = [o.tau.copy() for o in kept]
    del kept
    out, refs = None, []
    for (q, v, t), w in zip(states, want, strict=True):
        prev, prev_tau = out, (None if out is None else out.tau.copy())
        out = law.step(q, v, t)
        refs.append(weakref.ref(out))
        np.testing.assert_array_equal(out.tau, w)
        if prev is not None:
            assert out is not prev
            np.testing.assert_array_equal(prev.tau, prev_tau)
        del prev
    del out
    alive = [r() for r in refs]
    assert all(o is not None for o in alive) and len({id(o) for o in alive}) == 2
    assert all(a is not b for a, b in itertools.pairwise(alive))


def test_the_common_tick_goes_past_the_dispatcher(law, monkeypatch):
    """After its first tick, a float64 state with a Python or numpy float time is one call of the
    kernel's compiled entry point: the dispatcher (here made to fail) is not called, and the torque is
    the dispatcher's own; a list state still goes through it."""
    from qpctl.kernels import tick as K

    ref = law.step(Q0, V0, 0.3).tau.copy()

    def refuse(*args):
        raise AssertionError("the dispatcher was called")

    refuse.disable_compile = lambda *args: None  # type: ignore[attr-defined]  # as a dispatcher's (lock_compilation)

    monkeypatch.setattr(K, "tick_closed_form", refuse)
    for t in (0.3, np.float64(0.3)):
        np.testing.assert_array_equal(law.step(Q0, V0, t).tau, ref)
    with pytest.raises(AssertionError, match="dispatcher"):
        law.step(Q0.tolist(), V0, 0.3)
