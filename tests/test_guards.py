"""Guards for behaviours no other test held (issue 17): breaking them on purpose passed the suite.

* **Barrier capacity keeps the nearest pairs.** When more link–obstacle pairs are within d_influence
  than the barrier has rows (``QPConfig.max_pairs``), the rows go to the nearest pairs, and their
  inequalities ḧ + k₁ḣ + k₀h ≥ 0 hold at the returned q̈ — for the QP and for the safe-stop
  fallback. The expected pairs, distances and barrier terms are computed here from first principles
  (the planar arm's kinematics, the closed-form segment–sphere distance and finite differences of
  h(q) along the motion), not by the code under test; the code is read only through
  ``controller.step``, ``controller.last_problem`` and ``controller.formulation().barrier_rows``.
* **d_influence must exceed d_safe strictly**: ``d_influence == d_safe`` is a ConfigError naming
  ``controller.d_influence``, in code (``LawGains``) and in a scenario (a TOML file, ``--set``).
"""

from __future__ import annotations

import numpy as np
import pytest

from baselines import PaperController
from qpctl import ConfigError, LawGains, Obstacle, Scenario, WaypointPath, planar_arm
from qpctl.controllers.qp import QPConfig, QPController

# ------------------------------------------------------------------------------------------------
# 1. Barrier capacity keeps the nearest pairs
# ------------------------------------------------------------------------------------------------
LENGTH, LINK_RADIUS = 1.0, 0.05  # planar_arm()'s unit rods, capsule radius [m]
Q0 = np.array([np.pi, np.pi / 2, 0.0])  # link 1 along −x; links 2 and 3 hang down along x = −1
V0 = np.array([0.0, 0.0, 2.0])  # link 3 swings toward +x at 2 rad/s (its tip at 2 m/s)
T0 = 0.1
PATH = WaypointPath([[-1.0, -2.0], [1.0, -1.5]], duration=1.0)
GAINS = LawGains(d_influence=0.3, d_safe=0.05)
K0, K1 = 400.0, 40.0  # barrier gains [1/s², 1/s], set explicitly in the config below
# Three spheres (r = 0.05 m) about link 3 (x = −1, y ∈ [−2, −1]). Listed far, middle, near, so that
# neither the engine's order nor the reverse of the distance order gives the nearest pairs; each has
# its own normal. Link 3 swings toward the far and near ones (+x side) and away from the middle one.
SPHERES = [
    ((-0.70, -1.30), 0.05),  # d = 0.30 − 0.10 = 0.20 m from link 3's side (and 0.32 m > d_i from link 2)
    ((-1.22, -1.50), 0.05),  # d = 0.12 m from link 3's other side
    ((-1.0 + 0.17 / np.sqrt(2), -2.0 - 0.17 / np.sqrt(2)), 0.05),  # d = 0.07 m from link 3's tip, below right:
]  # normal (−1, 1)/√2, approached at nᵀ(2 m/s, 0) = −1.41 m/s
OBSTACLES = [Obstacle("sphere", [x, y, 0.0], radius=r) for (x, y), r in SPHERES]


def link_segments(q: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The planar arm's link axes (x, y) [m]: joint i at the tip of link i−1, link i at angle q₁+…+qᵢ."""
    ends, angle = [np.zeros(2)], 0.0
    for qi in q:
        angle += qi
        ends.append(ends[-1] + LENGTH * np.array([np.cos(angle), np.sin(angle)]))
    return [(ends[i], ends[i + 1]) for i in range(len(q))]


def distance(q: np.ndarray, link: int, obstacle: int) -> float:
    """Closed-form distance [m] between link capsule ``link`` and sphere ``obstacle`` at q."""
    a, b = link_segments(q)[link]
    centre, radius = (np.asarray(c) for c in SPHERES[obstacle])
    s = np.clip((centre - a) @ (b - a) / ((b - a) @ (b - a)), 0.0, 1.0)
    return float(np.linalg.norm(a + s * (b - a) - centre) - LINK_RADIUS - radius)


def barrier_terms(link: int, obstacle: int, q: np.ndarray, v: np.ndarray, qdd: np.ndarray) -> dict[str, object]:
    """h = d − d_s, ∇h, ḣ and ḧ of a pair along q(s) = q + v s + ½ q̈ s², by central differences of
    the closed-form h (the spheres are static). ``drift`` is ḧ at q̈ = 0."""
    def h(x: np.ndarray) -> float:
        return distance(x, link, obstacle) - GAINS.d_safe

    eps = 1e-4
    grad = np.array([(h(q + eps * e) - h(q - eps * e)) / (2 * eps) for e in np.eye(q.size)])

    def second(a: np.ndarray) -> tuple[float, float]:
        hp, hm = h(q + eps * v + 0.5 * eps**2 * a), h(q - eps * v + 0.5 * eps**2 * a)
        return (hp - hm) / (2 * eps), (hp - 2 * h(q) + hm) / eps**2

    hdot, hddot = second(qdd)
    _, drift = second(np.zeros_like(q))
    return {"h": h(q), "grad": grad, "hdot": hdot, "hddot": hddot, "drift": drift}


def pairs_within_influence(q: np.ndarray) -> list[tuple[float, int, int]]:
    """(d, link, obstacle) of every pair within d_influence, nearest first."""
    found = [(distance(q, i, j), i, j) for i in range(len(q)) for j in range(len(SPHERES))]
    return sorted(p for p in found if p[0] < GAINS.d_influence)


def make_controller(max_pairs: int, path: str) -> QPController:
    """``path`` "qp": the QP answers; "safe-stop": a tick budget spent before the QP starts sends every
    tick down the fallback chain, which here is the safe stop alone."""
    chain = {"fallback": ["safe-stop"], "tick_budget_us": 1e-3} if path == "safe-stop" else {}
    cfg = QPConfig(max_pairs=max_pairs, barrier_k0=K0, barrier_k1=K1, barrier_drift="exact", **chain)
    return QPController(planar_arm(), PATH, OBSTACLES, GAINS, cfg)  # no torque limits: every barrier can hold


def test_scene_has_more_pairs_than_rows_and_the_controller_sees_them():
    """The scene's premise, from the closed form and from the controller's own tick state alike."""
    expected = pairs_within_influence(Q0)
    assert [(i, j) for _, i, j in expected] == [(2, 2), (2, 1), (2, 0)]
    np.testing.assert_allclose([d for d, _, _ in expected], [0.07, 0.12, 0.20], atol=1e-12)
    state = make_controller(1, "qp").dynamics.compute(Q0, V0, T0)
    seen = sorted(zip(state.pairs.distance.tolist(), state.pairs.link.tolist(), state.pairs.obstacle.tolist()))
    assert [(i, j) for _, i, j in seen] == [(i, j) for _, i, j in expected]
    np.testing.assert_allclose([d for d, _, _ in seen], [d for d, _, _ in expected], atol=1e-9)
    # Without the near barrier the law drives link 3 through its safety margin: the paper law (the
    # QP's minimiser when no row binds) breaks the nearest pair's inequality by far.
    qdd = PaperController(planar_arm(), PATH, OBSTACLES, GAINS).step(Q0, V0, T0).qdd
    b = barrier_terms(2, 2, Q0, V0, qdd)
    assert b["hddot"] + K1 * b["hdot"] + K0 * b["h"] < -10.0


@pytest.mark.parametrize("path", ["qp", "safe-stop"])
@pytest.mark.parametrize("max_pairs", [1, 2])
def test_barrier_rows_go_to_the_nearest_pairs_and_hold(max_pairs, path):
    ctrl = make_controller(max_pairs, path)
    out = ctrl.step(Q0, V0, T0)
    if path == "qp":
        assert "fallback" not in out.info and out.info["status"] == "solved", out.info
    else:
        assert out.info["fallback"] == "safe-stop", out.info
    assert np.all(np.isfinite(out.qdd)) and np.all(np.isfinite(out.tau))
    nearest = pairs_within_influence(Q0)[:max_pairs]
    assert len(pairs_within_influence(Q0)) > max_pairs  # more pairs than rows

    # The rows: exactly max_pairs barrier rows are active (finite lower bound), and each is the
    # barrier of one of the nearest pairs — ∇h q̈ ≥ −k₁ḣ − k₀h − (ḧ at q̈ = 0), up to a positive scale.
    problem, rows = ctrl.last_problem, ctrl.formulation().barrier_rows
    C, lower = problem.C[rows, : ctrl.n], problem.l[rows]
    assert C.shape[0] >= max_pairs
    active = np.flatnonzero(np.isfinite(lower))
    assert active.size == max_pairs, lower
    matched = []
    for r in active:
        row = C[r] / np.linalg.norm(C[r])
        bound = lower[r] / np.linalg.norm(C[r])
        hits = []
        for _, i, j in pairs_within_influence(Q0):
            b = barrier_terms(i, j, Q0, V0, out.qdd)
            g = b["grad"] / np.linalg.norm(b["grad"])
            want = (-K1 * b["hdot"] - K0 * b["h"] - b["drift"]) / np.linalg.norm(b["grad"])
            if row @ g > 1 - 1e-8 and abs(bound - want) <= 1e-5 * (1 + abs(want)):
                hits.append((i, j))
        assert len(hits) == 1, (r, C[r], lower[r], hits)
        matched += hits
    assert sorted(matched) == sorted((i, j) for _, i, j in nearest)

    # ... and their inequalities hold at the q̈ the controller returned (the solver's acceptance
    # tolerance, 1e-4 relative, is the slack allowed).
    for _, i, j in nearest:
        b = barrier_terms(i, j, Q0, V0, out.qdd)
        value = b["hddot"] + K1 * b["hdot"] + K0 * b["h"]
        scale = 1.0 + abs(K1 * b["hdot"] + K0 * b["h"] + b["drift"])
        assert value >= -1e-4 * scale, ((i, j), value, out.info)


# ------------------------------------------------------------------------------------------------
# 2. d_influence must exceed d_safe strictly
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("d_influence", [0.05, 0.04])
def test_d_influence_not_above_d_safe_is_refused_in_code(d_influence):
    with pytest.raises(ConfigError) as exc:
        LawGains(d_influence=d_influence, d_safe=0.05)
    assert exc.value.key == "controller.d_influence"
    assert "controller.d_influence" in str(exc.value)
    LawGains(d_influence=0.05 + 1e-9, d_safe=0.05)  # strictly above: accepted


TOML = """\
name = "equal_distances"
[robot]
kind = "planar3"
[path]
waypoints = [[1.0, -1.5]]
duration = 1.0
[[obstacles]]
shape = "sphere"
position = [0.6, -0.6]
radius = 0.15
[controller]
kind = "qp"
d_safe = 0.05
d_influence = {d_influence}
[sim]
dt = 0.002
duration = 0.2
"""


def test_d_influence_equal_to_d_safe_is_refused_in_a_scenario(tmp_path):
    path = tmp_path / "equal.toml"
    path.write_text(TOML.format(d_influence="0.05"))
    with pytest.raises(ConfigError) as exc:
        Scenario.load(path)
    assert exc.value.key == "controller.d_influence"
    assert str(path) in str(exc.value) and "controller.d_influence" in str(exc.value)
    assert "\n" not in str(exc.value)
    # the same file a hair above is valid, and a --set override down to d_safe is refused again
    path.write_text(TOML.format(d_influence="0.050001"))
    assert Scenario.load(path).data["controller"]["d_influence"] == 0.050001
    for overrides in (["controller.d_influence=0.05"], ["controller.d_safe=0.050001"]):
        with pytest.raises(ConfigError) as exc:
            Scenario.load(path, overrides)
        assert exc.value.key == "controller.d_influence", overrides
    # the packaged scenario too (its d_safe is 0.05)
    assert Scenario.load("paper").data["controller"]["d_safe"] == 0.05
    with pytest.raises(ConfigError) as exc:
        Scenario.load("paper", ["controller.d_influence=0.05"])
    assert exc.value.key == "controller.d_influence"
