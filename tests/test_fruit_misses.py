"""Why a fruit was missed (qpctl.perception.misses): each cause on a run built to have it, the order in
which they are tried, and a real camera run whose reference has not yet come to any fruit."""

from __future__ import annotations

import numpy as np
import pytest

from qpctl.perception.misses import CAUSES, explain_misses

P = np.array([[0.5, 0.0, 0.5], [0.35, -0.15, 0.35]])  # two fruits on one line; the second always reached
MARGIN = 0.062


def _run(short_ref=0.0, short_x=0.01):
    """1 s at 1 ms: x_d goes straight to fruit 1 (``short_ref`` [m] short of it) by 0.5 s, then to fruit
    2; x follows, ``short_x`` [m] short of fruit 1 at its closest (0.5 s), exactly on fruit 2 at the end."""
    t = np.linspace(0.0, 1.0, 1001)
    start = np.array([0.4, -0.1, 0.4])
    a = P[0] - short_ref * (P[0] - start) / np.linalg.norm(P[0] - start)
    s = np.clip(t / 0.5, 0.0, 1.0)[:, None]
    u = np.clip((t - 0.5) / 0.5, 0.0, 1.0)[:, None]
    x_ref = start + s * (a - start) + u * (P[1] - a)
    x = x_ref.copy()
    x[:, 2] -= short_x * np.exp(-(((t - 0.5) / 0.2) ** 2))  # below fruit 1 by short_x at 0.5 s, 0 at the end
    q = np.zeros((len(t), 7))
    kw = dict(q_min=-np.full(7, 2.0), q_max=np.full(7, 2.0), clearance=np.full(len(t), 0.2),
              fallback=np.array([""] * len(t), dtype=object), believed=np.full(len(t), np.inf), margin=MARGIN,
              kappa=np.ones(len(t)))
    return t, x, x_ref, q, kw


def _explain(t, x, x_ref, q, kw):
    out = explain_misses(P, t, x, x_ref, q, **kw)
    assert [m["fruit"] for m in out] == [0]  # fruit 2 is reached: not listed
    keys = {"fruit", "error_mm", "t_s", "cause", "reason"} | ({"held_by"} if out[0]["cause"] == "reference" else set())
    assert set(out[0]) == keys and out[0]["cause"] in CAUSES
    return out[0]


def test_a_reached_fruit_is_not_a_miss():
    t, x, x_ref, q, kw = _run(short_x=0.004)
    assert explain_misses(P, t, x, x_ref, q, **kw) == []


def test_the_reference_that_never_came():
    t, x, x_ref, q, kw = _run(short_ref=0.02, short_x=0.0)
    kw["kappa"][-1] = 0.25
    m = _explain(t, x, x_ref, q, kw)
    assert m["cause"] == "reference" and m["error_mm"] == pytest.approx(20.0, abs=0.1)
    assert "closest 20 mm" in m["reason"] and "was waiting (κ 0.25" in m["reason"]
    assert m["held_by"] == "" and "held by none of" in m["reason"]
    kw["kappa"][-1] = 1.0  # at full pace at the end: not waiting, only late
    assert "had not come to it yet" in _explain(t, x, x_ref, q, kw)["reason"]


def test_what_held_the_task_point_while_the_reference_waited():
    """At the run's last tick, in the order of the causes: a fallback, a joint at its limit, the rigid
    rows' margin; each only where it holds at the end (the same at the closest approach does not count)."""
    t, x, x_ref, q, kw = _run(short_ref=0.02, short_x=0.0)
    kw["kappa"][-1] = 0.0
    q[500, 2] = -2.0 + 1e-3  # at the closest approach only: not what holds it at the end
    assert _explain(t, x, x_ref, q, kw)["held_by"] == ""
    kw["believed"][-1] = MARGIN + 2e-3
    m = _explain(t, x, x_ref, q, kw)
    assert m["held_by"] == "rigid_margin" and "rigid rows' margin (the map's rigid clearance 64 mm)" in m["reason"]
    q[-1, 5] = 2.0 - 5e-3
    m = _explain(t, x, x_ref, q, kw)
    assert m["held_by"] == "joint_limit" and "joint 6 (upper) at its limit" in m["reason"]
    kw["fallback"][-30] = "safe_stop"
    m = _explain(t, x, x_ref, q, kw)
    assert m["held_by"] == "fallback" and "a fallback (safe_stop)" in m["reason"]


def test_a_fallback_at_the_closest_approach():
    t, x, x_ref, q, kw = _run()
    kw["fallback"][540] = "safe_stop"  # 40 ms after the closest approach
    q[500, 3] = 2.0 - 1e-3  # a joint at its limit too: the fallback comes first
    m = _explain(t, x, x_ref, q, kw)
    assert m["cause"] == "fallback" and "safe_stop" in m["reason"]
    assert m["error_mm"] == pytest.approx(10.0, abs=0.01) and m["t_s"] == pytest.approx(0.5)
    kw["fallback"][540], kw["fallback"][640] = "", "safe_stop"  # 0.14 s after it: not its cause
    assert _explain(t, x, x_ref, q, kw)["cause"] == "joint_limit"


def test_a_joint_at_its_limit():
    t, x, x_ref, q, kw = _run()
    q[500, 1] = -2.0 + 5e-3
    kw["believed"][:] = MARGIN  # held by the margin too: the limit comes first
    m = _explain(t, x, x_ref, q, kw)
    assert m["cause"] == "joint_limit" and "joint 2 (lower)" in m["reason"]


def test_held_by_the_rigid_rows_margin():
    t, x, x_ref, q, kw = _run()
    kw["believed"][500] = MARGIN + 0.003
    kw["clearance"][500] = 0.064
    m = _explain(t, x, x_ref, q, kw)
    assert m["cause"] == "rigid_margin" and "rigid clearance 65 mm" in m["reason"]
    assert "nearer than any there is" not in m["reason"]
    kw["clearance"][500] = 0.3  # the truth far beyond: the map saw something that is not there
    assert "nearer than any there is" in _explain(t, x, x_ref, q, kw)["reason"]
    kw["believed"][500] = MARGIN + 0.006  # beyond the tolerance: not held by the margin
    assert _explain(t, x, x_ref, q, kw)["cause"] == "lagged"


def test_lagged_when_nothing_else_holds():
    t, x, x_ref, q, kw = _run(short_x=0.03)
    m = _explain(t, x, x_ref, q, kw)
    assert m["cause"] == "lagged" and "closest 30 mm at 0.5 s, 30 mm behind it" in m["reason"]
