"""The QP controller (``qp``): the paper's law as a quadratic program solved every tick.

    minimise   ½‖M(q̈ − q̈₀)‖² + ρ₁‖s‖₁ + ½ρ₂‖s‖²          (AccelerationTask, EndEffectorTask slack)
    subject to J q̈ + s = a                                   (EndEffectorTask; a from eq. 7)
               −τ_max ≤ M q̈ + N ≤ τ_max                     (TorqueLimit)
               joint position / speed barriers on q̈          (JointLimit)
               ḧ + k₁ḣ + k₀h ≥ 0 per (link, obstacle) pair     (ObstacleBarrier)

q̈₀ = −M⁻¹N + K_N e_N and a, e_N are exactly the paper law's (:mod:`qpctl.law`), so with no
inequality active and s = 0 the minimiser is q̈ = J_M⁺ a + (I − J_M⁺J) q̈₀ — the paper's law (eq. 19).
The ℓ₁ slack is an exact penalty: it stays exactly zero while the task is feasible.

Tasks and constraints are objects in :attr:`QPController.tasks` and :attr:`QPController.constraints`;
add or remove them with :meth:`add_task`, :meth:`remove_task`, :meth:`add_constraint`,
:meth:`remove_constraint`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from qpctl.constraints.constraints import Constraint, JointLimit, ObstacleBarrier, TorqueLimit
from qpctl.controllers.base import ControlOutput, Controller
from qpctl.errors import ConfigError
from qpctl.formulation import Formulation
from qpctl.geometry.obstacles import Obstacle
from qpctl.law import LawGains, closed_form_acceleration, law_terms
from qpctl.paths import WaypointPath
from qpctl.qp import Problem, Solution
from qpctl.robot.model import RobotModel
from qpctl.solvers.base import QPSolver, make_solver
from qpctl.state import TickState
from qpctl.tasks.tasks import AccelerationTask, EndEffectorTask, PostureTask, Task

FALLBACK_CLOSED_FORM = "closed-form"
FALLBACK_BRAKE = "brake"


@dataclass
class QPConfig:
    """Settings of the QP controller (the ``[controller]`` keys of a scenario; units in brackets).

    solver: a name from ``qpctl solvers``; solver_settings: passed to it (tolerances, max_iter...).
    torque_limits / joint_limits: include those constraints when the robot has finite limits.
    barrier_k0 [1/s²], barrier_k1 [1/s]: obstacle barrier gains; barrier_drift: "exact" (look-ahead
    finite difference of ḣ, default) or "rigid" (nᵀJ̇_p q̇ only, DESIGN.md §2's approximation); joint_k0, joint_k1: joint-position
    barrier gains; velocity_gain [1/s]: joint-speed barrier gain.
    slack_l1, slack_l2: task slack weights (ℓ₁ exact penalty, ℓ₂ regulariser).
    task_relaxation: "always" — solve with the task slack every tick; "on_failure" — solve with the
    task hard first and with the slack only when that fails (infeasible); "auto" — "on_failure" for
    osqp (ADMM converges slowly and its polishing fails with the ℓ₁ slack), "always" otherwise.
    max_pairs: obstacle rows (0: 4 per link, at most links × obstacles).
    fallback: what to use when the solver fails, tried in order: solver names, "closed-form"
    (the paper law, torques clipped to the limits) or "brake" (τ = N − M·k q̇, clipped).
    tick_budget_us: solver time budget per tick [µs] (0: none); passed as the solver's time limit
    where it has one.
    posture / posture_weight: an optional PostureTask.
    """

    solver: str = "proxqp"
    solver_settings: dict[str, Any] = field(default_factory=dict)
    torque_limits: bool = True
    joint_limits: bool = True
    barrier_k0: float = 400.0
    barrier_k1: float = 40.0
    barrier_drift: str = "exact"
    joint_k0: float = 100.0
    joint_k1: float = 20.0
    velocity_gain: float = 50.0
    slack_l1: float = 1e6
    slack_l2: float = 1e2
    max_pairs: int = 0
    task_relaxation: str = "auto"
    fallback: list[str] = field(default_factory=lambda: [FALLBACK_CLOSED_FORM])
    tick_budget_us: float = 0.0
    posture: list[float] | None = None
    posture_weight: float = 0.0

    @classmethod
    def from_dict(cls, cfg: dict[str, Any]) -> "QPConfig":
        keys = cls.__dataclass_fields__.keys()
        return cls(**{k: v for k, v in cfg.items() if k in keys})


class QPController(Controller):
    """Per-tick QP controller (see module docstring)."""

    kind = "qp"

    def __init__(self, robot: RobotModel, path: WaypointPath, obstacles: Sequence[Obstacle] = (),
                 gains: LawGains | None = None, config: QPConfig | None = None, *,
                 tasks: Sequence[Task] | None = None, constraints: Sequence[Constraint] | None = None,
                 broadphase: bool | None = None) -> None:
        super().__init__(robot, path, obstacles, gains, broadphase=broadphase)
        self.config = config or QPConfig()
        cfg = self.config
        self._solver = make_solver(cfg.solver, cfg.solver_settings)
        self._solver_soft = make_solver(cfg.solver, cfg.solver_settings)
        if cfg.task_relaxation not in ("auto", "always", "on_failure"):
            raise ConfigError(f"must be auto, always or on_failure, got {cfg.task_relaxation!r}",
                              key="controller.task_relaxation")
        for name in cfg.fallback:
            if name not in (FALLBACK_CLOSED_FORM, FALLBACK_BRAKE):
                make_solver(name)  # unknown names fail now, not in the middle of a run
        self._fallback_solvers: dict[str, QPSolver] = {}
        if tasks is None:
            tasks = [AccelerationTask(), EndEffectorTask(cfg.slack_l1, cfg.slack_l2)]
            if cfg.posture_weight > 0:
                tasks.append(PostureTask(cfg.posture if cfg.posture is not None else robot.q_home,
                                         cfg.posture_weight))
        if constraints is None:
            constraints = []
            if cfg.torque_limits and np.any(np.isfinite(robot.tau_max)):
                constraints.append(TorqueLimit(robot.tau_max))
            finite = np.isfinite(np.concatenate([robot.q_min, robot.q_max, robot.v_max]))
            if cfg.joint_limits and np.any(finite):
                constraints.append(JointLimit(robot.q_min, robot.q_max, robot.v_max, k0=cfg.joint_k0,
                                              k1=cfg.joint_k1, kv=cfg.velocity_gain))
            if self.obstacles:
                cap = cfg.max_pairs or len(robot.capsules) * min(len(self.obstacles), 4)
                constraints.append(ObstacleBarrier(cap, self.gains.d_safe, k0=cfg.barrier_k0, k1=cfg.barrier_k1,
                                                   drift=cfg.barrier_drift))
        self.tasks: list[Task] = list(tasks)
        self.constraints: list[Constraint] = list(constraints)
        self._formulation: Formulation | None = None
        self.last_problem: Problem | None = None
        self.last_solution: Solution | None = None

    @classmethod
    def from_config(cls, cfg: dict[str, Any], robot: RobotModel, path: WaypointPath,
                    obstacles: Sequence[Obstacle], gains: LawGains, *, broadphase: bool | None = None
                    ) -> "QPController":
        return cls(robot, path, obstacles, gains, QPConfig.from_dict(cfg), broadphase=broadphase)

    @property
    def solver(self) -> str:  # type: ignore[override]
        return self._solver.name

    # -- composition ----------------------------------------------------------------------------
    def add_task(self, task: Task) -> None:
        self.tasks.append(task)
        self._formulation = None

    def remove_task(self, name: str) -> Task:
        return self._remove(self.tasks, name)  # type: ignore[return-value]

    def add_constraint(self, constraint: Constraint) -> None:
        self.constraints.append(constraint)
        self._formulation = None

    def remove_constraint(self, name: str) -> Constraint:
        return self._remove(self.constraints, name)  # type: ignore[return-value]

    def _remove(self, items: list[Any], name: str) -> Any:
        for i, item in enumerate(items):
            if item.name == name:
                self._formulation = None
                return items.pop(i)
        raise ConfigError(f"no {name!r}; present: {', '.join(x.name for x in items)}", key=name)

    def set_solver(self, name: str, settings: dict[str, Any] | None = None) -> None:
        """Swap the solver (its warm start starts afresh)."""
        self._solver = make_solver(name, settings)
        self._solver_soft = make_solver(name, settings)
        self.config.solver = name

    def reset(self) -> None:
        super().reset()
        self._solver.reset()
        self._solver_soft.reset()
        for s in self._fallback_solvers.values():
            s.reset()

    # -- the law ----------------------------------------------------------------------------------
    def formulation(self) -> Formulation:
        if self._formulation is None:
            self._formulation = Formulation(self.n, self.tasks, self.constraints)
            self._solver.reset()
            self._solver_soft.reset()
        return self._formulation

    @property
    def relaxation(self) -> str:
        """The task-relaxation strategy in force ("always" or "on_failure")."""
        mode = self.config.task_relaxation
        if mode == "auto":
            return "on_failure" if self._solver.name == "osqp" else "always"
        return mode

    def _fallback(self, name: str, state: TickState, terms: Any, problem: Problem) -> tuple[np.ndarray, Solution | None]:
        if name == FALLBACK_CLOSED_FORM:
            qdd, _ = closed_form_acceleration(state, terms, self.gains, weighted=True)
            return qdd, None
        if name == FALLBACK_BRAKE:
            return -self.gains.kv * state.v, None
        solver = self._fallback_solvers.get(name)
        if solver is None:
            solver = self._fallback_solvers[name] = make_solver(name)
        sol = solver.solve(problem)
        return sol.x[: self.n], sol

    def control(self, state: TickState) -> ControlOutput:
        n = self.n
        ref = self.path(state.t)
        terms = law_terms(state, ref, self.gains, weighted=True)
        t0 = time.perf_counter()
        form = self.formulation()
        hard_first = self.relaxation == "on_failure"
        problem = form.build(state, terms, relax=not hard_first)
        t1 = time.perf_counter()
        sol = (self._solver if hard_first else self._solver_soft).solve(problem)
        t2 = time.perf_counter()
        build_us, solve_us = (t1 - t0) * 1e6, (t2 - t1) * 1e6
        info: dict[str, Any] = {"status": sol.status, "iterations": sol.iterations, "solver": sol.solver}
        if hard_first and not sol.found:  # the task conflicts with the hard rows: let it give way
            problem = form.build(state, terms, relax=True)
            t3 = time.perf_counter()
            sol = self._solver_soft.solve(problem)
            t4 = time.perf_counter()
            build_us += (t3 - t2) * 1e6
            solve_us += (t4 - t3) * 1e6
            info.update(relaxed=True, hard_status=info["status"], status=sol.status,
                        iterations=info["iterations"] + sol.iterations)
        info["build_us"], info["solve_us"] = build_us, solve_us
        if sol.found:
            qdd = sol.x[:n]
            x = sol.x
        else:
            qdd, x = None, None
            for name in self.config.fallback:
                cand, fsol = self._fallback(name, state, terms, problem)
                if fsol is None or fsol.found:
                    qdd = cand
                    x = fsol.x if fsol is not None else None
                    info["fallback"] = name
                    break
            if qdd is None:
                qdd = -self.gains.kv * state.v
                info["fallback"] = FALLBACK_BRAKE
        tau = state.M @ qdd + state.N
        # The solver meets the torque rows to its tolerance; clip that residue (and any fallback's
        # excess) so the commanded torque never exceeds a limit the controller was asked to hold.
        limit = next((c.tau_max for c in self.constraints if isinstance(c, TorqueLimit)), None)
        clipped = tau if limit is None else np.clip(tau, -limit, limit)
        if np.any(clipped != tau):
            info["clipped"] = float(np.max(np.abs(clipped - tau)))
            tau = clipped
            qdd = np.linalg.solve(state.M, tau - state.N)
        if x is not None:
            s = x[n:]
            half = s.size // 2
            info["slack_norm"] = float(np.linalg.norm(s[:half] - s[half:]))
            Cx = problem.C @ x
            tol = 1e-6 * (1.0 + np.abs(Cx))
            act = (np.abs(Cx - problem.l) <= tol) | (np.abs(Cx - problem.u) <= tol)
            bnd = (np.abs(x[:n] - problem.lb[:n]) <= 1e-6) | (np.abs(x[:n] - problem.ub[:n]) <= 1e-6)
            info["active"] = int(np.count_nonzero(act) + np.count_nonzero(bnd))
            info["active_rows"] = sorted({problem.row_names[i] for i in np.flatnonzero(act)})
        for con in self.constraints:
            if isinstance(con, ObstacleBarrier) and con.dropped:
                info["pairs_dropped"] = con.dropped
        self.last_problem, self.last_solution = problem, sol
        return ControlOutput(tau=tau, qdd=qdd, ref=ref, x=state.x, e_null=terms.e_null,
                             clearance=state.clearance, singular=terms.singular, info=info)
