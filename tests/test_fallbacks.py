"""The fallback chain's strategies (issue 15, item 2): registered by name, they find rows by their
kind in the tick's Problem — so a user's own barrier class is kept by the safe stop — and
constraints keep no per-tick state."""

from __future__ import annotations

import numpy as np
import pytest

from qpctl import ConfigError, LawGains, Obstacle, Scenario, WaypointPath, planar_arm
from qpctl.constraints import BARRIER, Constraint, ObstacleBarrier
from qpctl.constraints.constraints import TorqueLimit
from qpctl.controllers.qp import FALLBACK_SAFE_STOP, QPConfig, QPController
from qpctl.fallbacks import FALLBACKS, Attempt, Fallback, register_fallback
from qpctl.qp import Solution
from qpctl.solvers.proxqp_ import ProxQPSolver

Q0 = np.array([np.pi, np.pi / 2, 0.0])
PATH = WaypointPath([[-1.0, -2.0], [1.0, -1.5]], duration=1.0)
RUSHING = [Obstacle("sphere", [-0.8, -1.5, 0.0], radius=0.1)]  # link 3 at d_safe
V_APPROACH = np.array([0.0, 0.0, 1.3])  # the brake breaks the barrier by 3.3 m/s²; 400 N·m can hold it


@pytest.fixture
def failing_solver(monkeypatch):
    monkeypatch.setattr(ProxQPSolver, "solve", lambda self, problem: Solution(
        False, np.zeros(problem.n_var), "max_iter", 1000, 0.0, self.name))


class UserBarrier(Constraint):
    """A user's own barrier class (not an ObstacleBarrier): its rows are the obstacle barrier's,
    under another name; ``kind`` says whether they are barrier rows."""

    name = "my_barrier"

    def __init__(self, kind: str) -> None:
        self.kind = kind
        self.inner = ObstacleBarrier(4, LawGains().d_safe)
        self.rows = self.inner.rows

    def compute(self, state, terms):
        return self.inner.compute(state, terms)


def safe_stop_margin(kind: str) -> float:
    """The least (C q̈ − l) of the user's rows at the safe stop's q̈ [m/s²]."""
    robot = planar_arm(tau_max=400.0)
    ctrl = QPController(robot, PATH, RUSHING, LawGains(), QPConfig(solver="proxqp", fallback=[FALLBACK_SAFE_STOP]),
                        constraints=[TorqueLimit(robot.tau_max), UserBarrier(kind)])
    out = ctrl.step(Q0, V_APPROACH, 0.1)
    assert out.info["fallback"] == FALLBACK_SAFE_STOP
    problem = ctrl.last_problem
    rows = [i for i, name in enumerate(problem.row_names) if name == "my_barrier"]
    lo = problem.l[rows]
    active = np.isfinite(lo)
    assert active.any()
    return float(np.min((problem.C[rows, :3] @ out.qdd - lo)[active] / (1.0 + np.abs(lo[active]))))


def test_safe_stop_keeps_a_user_barrier_by_its_kind(failing_solver):
    assert safe_stop_margin(BARRIER) >= -1e-5  # kept (DAQP's tolerance)
    assert safe_stop_margin("my_rows") < -0.1  # not a barrier: the safe stop is the brake here


def test_problem_rows_carry_their_kind():
    ctrl = QPController(planar_arm(tau_max=400.0), PATH, RUSHING, LawGains(), QPConfig())
    ctrl.step(Q0, np.zeros(3), 0.1)
    problem = ctrl.last_problem
    assert len(problem.row_kinds) == len(problem.row_names) == problem.C.shape[0]
    barrier = problem.rows_of(BARRIER)
    assert barrier.size and all(problem.row_names[i] == ObstacleBarrier.name for i in barrier)
    assert set(problem.row_kinds) == {"torque", BARRIER, "self_collision"}


def test_a_registered_strategy_is_used_by_name(failing_solver):
    class Hold(Fallback):
        name = "hold"

        def __call__(self, ctx):
            return Attempt(np.zeros(ctx.state.n), self.name)

    register_fallback("hold", Hold)
    try:
        ctrl = QPController(planar_arm(tau_max=400.0), PATH, [], LawGains(),
                            QPConfig(solver="proxqp", fallback=["hold"]))
        out = ctrl.step(Q0, np.zeros(3), 0.1)
        assert out.info["fallback"] == "hold" and out.info["fallback_reason"] == "max_iter"
        state = ctrl.dynamics.compute(Q0, np.zeros(3), 0.1)
        np.testing.assert_allclose(out.tau, state.N, rtol=1e-9)  # q̈ = 0: gravity compensation
        raw = Scenario.load("paper").data  # and a scenario file may name it
        scen = Scenario.from_dict({**raw, "controller": {**raw["controller"], "fallback": ["hold", "brake"]}},
                                  source="t")
        assert scen.build_controller("qp").config.fallback == ["hold", "brake"]
    finally:
        FALLBACKS.pop("hold")
    with pytest.raises(ConfigError, match="hold"):
        Scenario.from_dict({**raw, "controller": {**raw["controller"], "fallback": ["hold"]}}, source="t")


def test_constraints_keep_no_tick_state():
    """Pairs beyond the barrier's capacity come back in its output (Inequality.dropped), not as an
    attribute the controller reads back."""
    barrier = ObstacleBarrier(1, 0.05)
    obstacles = [Obstacle("sphere", [-0.8, -1.5, 0.0], radius=0.1), Obstacle("sphere", [-1.2, -0.6, 0.0], radius=0.1)]
    ctrl = QPController(planar_arm(tau_max=400.0), PATH, obstacles, LawGains(), QPConfig(), constraints=[barrier])
    before = dict(vars(barrier))
    state = ctrl.dynamics.compute(Q0, np.zeros(3), 0.1)
    assert len(state.pairs) >= 2
    from qpctl.law import law_terms

    out = barrier.compute(state, law_terms(state, PATH(0.1), ctrl.gains, weighted=True))
    assert out.dropped == len(state.pairs) - 1
    assert vars(barrier).keys() == before.keys() and not hasattr(barrier, "dropped")
    assert ctrl.step(Q0, np.zeros(3), 0.1).info["pairs_dropped"] == len(state.pairs) - 1


def _failing_panda_ticks(ticks: int = 200):
    """The Panda + 10 spheres with a 20 N·m/s torque-rate limit, started at 0.5 rad/s on every joint:
    the QP is infeasible (the rate window cannot brake the approach) and the compiled tick falls back
    on most ticks. Yields the controller after each tick."""
    ctrl = Scenario.load("panda_spheres", overrides=["robot.tau_rate_max=20"]).build_controller("qp")
    q0 = ctrl.robot.q_home.astype(float)
    for k in range(ticks):
        ctrl.step(q0 + 0.001 * k, np.full(ctrl.n, 0.5), 0.001 * k)
        yield ctrl


def test_the_compiled_tick_s_closed_form_fallback_equals_numpy_s(monkeypatch):
    """The ClosedForm fallback on the compiled tick takes q̈ from the kernel (ctx.paper_qdd); on every
    failing tick it equals qpctl.law's numpy closed form on the same snapshot and terms to 1e-9
    (relative to the larger of 1 and |q̈|), and their verdicts (used, or why not) agree."""
    from qpctl.fallbacks import ClosedForm, FallbackContext
    from qpctl.law import closed_form_acceleration

    seen = []
    call = ClosedForm.__call__

    def both(self, ctx):
        assert ctx.paper_qdd is not None  # the compiled tick offers its kernel
        got = call(self, ctx)
        compiled = ctx.paper_qdd()
        reference, _ = closed_form_acceleration(ctx.state, ctx.terms, ctx.gains, weighted=True)
        numpy_ctx = FallbackContext(ctx.state, ctx.terms, ctx.gains, ctx.problem, ctx.window)
        seen.append((compiled, reference, got.word, call(self, numpy_ctx).word))
        return got

    monkeypatch.setattr(ClosedForm, "__call__", both)
    for _ in _failing_panda_ticks():
        pass
    assert len(seen) >= 100  # the scene fails on most ticks (147 of 200 here)
    for compiled, reference, word, numpy_word in seen:
        np.testing.assert_allclose(compiled, reference, rtol=0, atol=1e-9 * max(1.0, np.abs(reference).max()))
        assert word == numpy_word


def test_the_safe_stop_without_its_unused_rows_gives_the_same_answer(monkeypatch):
    """The safe stop keeps only the barrier rows in force (finite l); the rows of unused pair slots
    (l = −inf) and their slacks change nothing: on every failing tick its q̈ equals that of the same QP
    with every slot kept (solved by DAQP too), to DAQP's tolerance."""
    from qpctl.fallbacks import SafeStop
    from qpctl.qp import Problem
    from qpctl.solvers.daqp_ import DAQPSolver

    pairs = []
    call = SafeStop.__call__

    def both(self, ctx):
        got = call(self, ctx)
        p, n = ctx.problem, ctx.state.n
        rows = p.rows_of(BARRIER)
        if got.qdd is None or np.isfinite(p.l[rows]).all():
            return got
        state, k = ctx.state, rows.size
        H = state.M.T @ state.M
        P = np.zeros((n + k, n + k))
        P[:n, :n], P[n:, n:] = H, SafeStop.WEIGHT * max(float(np.trace(H)) / n, 1e-12) * np.eye(k)
        C = np.zeros((k + n, n + k))
        C[:k, :n], C[:k, n:], C[k:, :n] = p.C[rows, :n], np.eye(k), state.M
        lo, hi = ctx.window
        qb = ctx.gains.kv * (ctx.terms.g - state.v)
        full = Problem(P, np.concatenate([-H @ qb, np.zeros(k)]), np.zeros((0, n + k)), np.zeros(0), C,
                       np.concatenate([p.l[rows], lo - state.N]), np.concatenate([np.full(k, np.inf), hi - state.N]),
                       np.concatenate([p.lb[:n], np.zeros(k)]), np.concatenate([p.ub[:n], np.full(k, np.inf)]), n)
        sol = DAQPSolver().solve(full)
        assert sol.found
        pairs.append((got.qdd, sol.x[:n]))
        return got

    monkeypatch.setattr(SafeStop, "__call__", both)
    for _ in _failing_panda_ticks():
        pass
    assert len(pairs) >= 100
    for ours, full in pairs:
        np.testing.assert_allclose(ours, full, rtol=0, atol=1e-6 * max(1.0, np.abs(full).max()))


def test_scale_into_window_is_the_largest_scale_that_keeps_the_window():
    """scale_into_window(window, state, q̈) = s·q̈ with s ∈ [0, 1] the largest for which M s q̈ + N stays
    in the window, checked against the window itself on random cases: at s the torque is inside (to
    1e-9), and either s = 1, or some joint's torque is at its bound, or s = 0 with N already outside."""
    from types import SimpleNamespace

    from qpctl.controllers.qp_failure import scale_into_window

    rng = np.random.default_rng(2026)
    seen = {"one": 0, "bound": 0, "zero": 0}
    for _ in range(300):
        n = int(rng.integers(2, 8))
        A = rng.normal(size=(n, n))
        state = SimpleNamespace(M=A @ A.T + n * np.eye(n), N=rng.normal(0.0, 20.0, n))
        hi = rng.uniform(5.0, 60.0, n)
        window = (-hi, hi)
        qdd = rng.normal(0.0, 10.0 ** rng.uniform(-1, 2), n)
        out = scale_into_window(window, state, qdd)
        s = float(out @ qdd / (qdd @ qdd))
        np.testing.assert_allclose(out, s * qdd, rtol=0, atol=1e-12 * np.abs(qdd).max())
        assert 0.0 <= s <= 1.0
        tau = state.M @ out + state.N
        if np.all(np.abs(state.N) <= hi):
            assert np.all(tau <= hi + 1e-9) and np.all(tau >= -hi - 1e-9)
        if s == 1.0:
            seen["one"] += 1
        elif s == 0.0:
            seen["zero"] += 1
            assert not np.all(np.abs(state.N) < hi) or np.any(np.isclose(np.abs(state.N), hi))
        else:
            seen["bound"] += 1
            assert np.min(np.minimum(hi - tau, tau + hi)) <= 1e-9 * (1.0 + hi.max())
    assert min(seen.values()) > 0, seen  # every case met
