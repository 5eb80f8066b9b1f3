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
