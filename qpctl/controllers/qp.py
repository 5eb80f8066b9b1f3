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
:meth:`remove_constraint`. The settings are :class:`~qpctl.controllers.qp_config.QPConfig` (re-exported here).

One controller, two paths with one interface (``step(q, v, t, start)``, ``reset()``,
``last_problem``, ``last``), chosen by the tasks and constraints:

* :class:`~qpctl.controllers.qp_compiled.CompiledTick` — the standard tasks and constraints above
  (what every scenario builds): the kernels write the QP in place and check the answer, DAQP's C API
  solving it inside the same kernel call (its layouts and output: :mod:`qpctl.controllers.qp_layout`);
* :class:`~qpctl.controllers.qp_reference.ReferenceTick` — any other task or constraint: the problem
  stacked in Python by :class:`~qpctl.formulation.Formulation` (:meth:`QPController.control`), also
  the reference the tests hold the compiled path against.

On both, :class:`~qpctl.controllers.relaxation.TaskRelaxation` decides whether the task is solved
hard first, and :class:`~qpctl.controllers.qp_failure.Failures` what a failed solve does: the
fallback chain (:mod:`qpctl.fallbacks`) or, with ``strict=True``, :class:`~qpctl.errors.InfeasibleError`
/ :class:`~qpctl.errors.SolverError`. Each tick reports the solver's word (``info["status"]``) and
its :class:`~qpctl.outcome.SolveStatus` (``info["solve_status"]``).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from qpctl.constraints.constraints import (
    Constraint,
    JointLimit,
    ObstacleBarrier,
    SelfCollisionBarrier,
    TorqueLimit,
)
from qpctl.controllers.base import Controller, ControlOutput
from qpctl.controllers.qp_compiled import CompiledTick
from qpctl.controllers.qp_config import (
    BUILT_IN_FALLBACKS,
    FALLBACK_BRAKE,
    FALLBACK_CLOSED_FORM,
    FALLBACK_SAFE_STOP,
    QPConfig,
    braking_model,
)
from qpctl.controllers.qp_failure import Failures
from qpctl.controllers.qp_layout import QPOutput, compiled_spec
from qpctl.controllers.qp_reference import ReferenceTick
from qpctl.controllers.relaxation import check_mode
from qpctl.errors import ConfigError
from qpctl.formulation import Formulation
from qpctl.geometry.obstacles import Obstacle
from qpctl.geometry.self_collision import named_pairs, self_collision_pairs
from qpctl.law import LawGains
from qpctl.outcome import SOLUTION_RTOL, SolveOutcome
from qpctl.paths import WaypointPath
from qpctl.qp import Problem, Solution
from qpctl.robot.model import RobotModel
from qpctl.solvers.base import make_solver
from qpctl.state import TickState
from qpctl.tasks.tasks import (
    AccelerationTask,
    DampingTask,
    EndEffectorTask,
    PostureTask,
    Task,
)
from qpctl.tick import Workspace

_now = time.perf_counter

__all__ = ["BUILT_IN_FALLBACKS", "FALLBACK_BRAKE", "FALLBACK_CLOSED_FORM", "FALLBACK_SAFE_STOP", "SOLUTION_RTOL",
           "QPConfig", "QPController", "QPOutput", "compiled_spec"]

class QPController(Controller):
    """Per-tick QP controller (see module docstring)."""

    kind = "qp"

    def __init__(self, robot: RobotModel, path: WaypointPath, obstacles: Sequence[Obstacle] = (),
                 gains: LawGains | None = None, config: QPConfig | None = None, *,
                 tasks: Sequence[Task] | None = None, constraints: Sequence[Constraint] | None = None,
                 broadphase: bool | None = None, strict: bool = False) -> None:
        super().__init__(robot, path, obstacles, gains, broadphase=broadphase)
        self.config = cfg = config or QPConfig()
        check_mode(cfg.task_relaxation)
        self._solver = make_solver(cfg.solver, cfg.solver_settings)  # the task hard
        self._solver_soft = make_solver(cfg.solver, cfg.solver_settings)  # with its slack
        self._failures = Failures(cfg.fallback, strict, self.torque_limit)
        self._tick_start: float | None = None
        self.braking = braking_model(cfg, robot)
        if self.braking is not None:  # pairs found within the braking reach beyond d_influence
            self.dynamics.cutoff = self.cutoff
        self.tasks: list[Task] = list(tasks) if tasks is not None else self._default_tasks()
        self.constraints: list[Constraint] = (list(constraints) if constraints is not None
                                              else self._default_constraints())
        selfc = next((c for c in self.constraints if isinstance(c, SelfCollisionBarrier)), None)
        if selfc is not None:  # the Python path's states carry these pairs' distances
            selfc.cutoff = min(self.gains.d_influence, selfc.d_safe + selfc.REACH)
            self.dynamics.self_pairs, self.dynamics.self_cutoff = selfc.pairs, selfc.cutoff
        self._formulation: Formulation | None = None
        self._path: CompiledTick | ReferenceTick | None = None  # the tick's path (qp_path), chosen for
        self._path_ws: Workspace | None = None  # this workspace
        self._reference: ReferenceTick | None = None
        self._last_from: CompiledTick | ReferenceTick | None = None  # the path of the last tick

    @property
    def cutoff(self) -> float:
        """Distance [m] beyond which link–obstacle pairs are not queried: d_influence, plus
        ``braking_reach`` where the rows are braking-aware."""
        braking = getattr(self, "braking", None)
        return self.gains.d_influence + (self.config.braking_reach if braking is not None else 0.0)

    def _default_tasks(self) -> list[Task]:
        cfg, robot = self.config, self.robot
        tasks: list[Task] = [AccelerationTask(), EndEffectorTask(cfg.slack_l1, cfg.slack_l2, cfg.task_weights)]
        if cfg.posture_weight > 0:
            posture = robot.configuration(cfg.posture) if cfg.posture is not None else robot.q_home  # angles → q
            tasks.append(PostureTask(posture, cfg.posture_weight, difference=robot.difference if robot.lie else None))
        if cfg.damping > 0:
            tasks.append(DampingTask(cfg.damping, cfg.damping_gain))
        return tasks

    def _default_constraints(self) -> list[Constraint]:
        cfg, robot = self.config, self.robot
        constraints: list[Constraint] = []
        if cfg.torque_limits and np.any(np.isfinite(np.concatenate([robot.tau_max, robot.tau_rate_max]))):
            constraints.append(TorqueLimit(robot.tau_max, robot.tau_rate_max))
        finite = np.isfinite(np.concatenate([robot.q_min, robot.q_max, robot.v_max, robot.qdd_max]))
        if cfg.joint_limits and np.any(finite):
            constraints.append(JointLimit(robot.q_min, robot.q_max, robot.v_max, k0=cfg.joint_k0, k1=cfg.joint_k1,
                                          kv=cfg.velocity_gain, qdd_max=robot.qdd_max,
                                          angles=robot.angles if robot.lie else None, braking=self.braking))
        if self.obstacles:
            cap = cfg.max_pairs or len(robot.capsules) * min(len(self.obstacles), 4)
            constraints.append(ObstacleBarrier(cap, self.gains.d_safe, k0=cfg.barrier_k0, k1=cfg.barrier_k1,
                                               drift=cfg.barrier_drift, braking=self.braking,
                                               d_influence=self.gains.d_influence))
        if cfg.self_collision:
            pairs = (named_pairs(robot, cfg.self_collision_pairs) if cfg.self_collision_pairs is not None
                     else self_collision_pairs(robot, cfg.self_d_safe))
            if pairs.pairs:
                constraints.append(SelfCollisionBarrier(
                    pairs.pairs, cfg.self_d_safe, k0=cfg.barrier_k0, k1=cfg.barrier_k1,
                    joints=next((c for c in constraints if isinstance(c, JointLimit)), None)))
        return constraints

    @classmethod
    def from_config(cls, cfg: dict[str, Any], robot: RobotModel, path: WaypointPath,
                    obstacles: Sequence[Obstacle], gains: LawGains, *, broadphase: bool | None = None
                    ) -> QPController:
        return cls(robot, path, obstacles, gains, QPConfig.from_dict(cfg), broadphase=broadphase)

    @property
    def solver(self) -> str:  # type: ignore[override]
        return self._solver.name

    @property
    def strict(self) -> bool:
        """A failed solve raises InfeasibleError / SolverError (with the problem and the outcome)
        instead of taking the fallback chain."""
        return self._failures.strict

    @strict.setter
    def strict(self, value: bool) -> None:
        self._failures.strict = bool(value)

    # -- composition ----------------------------------------------------------------------------
    def add_task(self, task: Task) -> None:
        self.tasks.append(task)
        self._formulation = self._ws = None

    def remove_task(self, name: str) -> Task:
        return self._remove(self.tasks, name)  # type: ignore[return-value]

    def add_constraint(self, constraint: Constraint) -> None:
        self.constraints.append(constraint)
        self._formulation = self._ws = None

    def remove_constraint(self, name: str) -> Constraint:
        return self._remove(self.constraints, name)  # type: ignore[return-value]

    def _remove(self, items: list[Any], name: str) -> Any:
        for i, item in enumerate(items):
            if item.name == name:
                self._formulation = self._ws = None
                return items.pop(i)
        raise ConfigError(f"no {name!r}; present: {', '.join(x.name for x in items)}", key=name)

    def set_solver(self, name: str, settings: dict[str, Any] | None = None) -> None:
        """Swap the solver (its warm start starts afresh)."""
        self._solver = make_solver(name, settings)
        self._solver_soft = make_solver(name, settings)
        self.config.solver = name
        self._path = self._reference = None

    def reset(self) -> None:
        super().reset()
        limit = self.torque_limit()
        if limit is not None:
            limit.forget()
        self._solver.reset()
        self._solver_soft.reset()
        self._failures.reset()
        for path in (self._path, self._reference):
            if path is not None:
                path.reset()

    # -- the law ----------------------------------------------------------------------------------
    def formulation(self) -> Formulation:
        if self._formulation is None:
            self._formulation = Formulation(self.n, self.tasks, self.constraints)
            self._solver.reset()
            self._solver_soft.reset()
        return self._formulation

    @property
    def relaxation(self) -> str:
        """The task-relaxation strategy ("always" or "on_failure") of the ticks that are not one kernel
        call on DAQP's C API (:mod:`qpctl.controllers.relaxation`)."""
        return self.qp_path().relax.strategy

    def _make_workspace(self) -> Workspace:
        spec = compiled_spec(self.tasks, self.constraints, self.robot.nq)
        selfc = next((c for c in self.constraints if isinstance(c, SelfCollisionBarrier)), None)
        if selfc is not None:
            selfc.cutoff = min(self.gains.d_influence, selfc.d_safe + selfc.REACH)
        return Workspace(self.robot, self.obstacles, self.path, self.gains, self.cutoff, spec=spec,
                         broadphase=self.broadphase, barrier_drift=spec is None,
                         self_pairs=selfc.pairs if selfc is not None else (),
                         self_cutoff=selfc.cutoff if selfc is not None else np.inf, native_rigid=True)

    def qp_path(self) -> CompiledTick | ReferenceTick:
        """The path this controller's ticks take (module docstring), for its current workspace: the
        compiled tick when the workspace has the compiled QP's layout, the reference tick otherwise."""
        ws = self.workspace()
        if self._path is None or self._path_ws is not ws:
            if ws.spec is not None:
                self._path = CompiledTick(ws, (self._solver, self._solver_soft), self.config.task_relaxation,
                                          self._budget_us, self.gains, self._failures, self._state, self._bad_state)
            else:
                self._path = self._reference_tick()
            self._path_ws = ws
        return self._path

    def _reference_tick(self) -> ReferenceTick:
        if self._reference is None:
            self._reference = ReferenceTick(self.formulation, (self._solver, self._solver_soft),
                                            self.config.task_relaxation, self._budget_us, self.gains, self._failures,
                                            self.reference, self.torque_limit)
        return self._reference

    def _budget_us(self) -> float:
        return float(self.config.tick_budget_us)

    def torque_limit(self) -> TorqueLimit | None:
        """This controller's torque limits (their window is the drives' this tick), or None."""
        return next((c for c in self.constraints if isinstance(c, TorqueLimit)), None)

    # -- the tick ---------------------------------------------------------------------------------
    def step(self, q: np.ndarray, v: np.ndarray, t: float) -> ControlOutput:
        """One tick on the controller's path; ``compute_us`` is its wall time, from which the tick
        budget counts."""
        start = _now()
        path = self._path
        if type(path) is CompiledTick and path.ws is self._ws:  # the common tick first (fast_step)
            if not self.config.tick_budget_us:  # (a budget: step's stages, each within what is left)
                fast = path.fast_step(q, v, t, start)
                if fast is not None:
                    self.last, self._last_from = fast, path
                    return fast
        else:
            path = self.qp_path()
        if isinstance(path, CompiledTick):
            out: ControlOutput = path.step(q, v, t, start)
            self._last_from = path
        else:  # the state as a TickState, then control() on it
            self._tick_start = start
            try:
                out = super().step(q, v, t)
            finally:
                self._tick_start = None
        self.last = out
        return out

    def control(self, state: TickState) -> ControlOutput:
        """The tick on the reference path (any tasks and constraints, custom ones included) on ``state``:
        the QP built from the tasks and constraints, solved, checked, τ = M q̈ + N; when the solve
        fails, the fallback chain — or, in strict mode, its error."""
        ref = self._last_from = self._reference_tick()
        return ref.control(state, self._tick_start)

    # -- what the last tick solved ------------------------------------------------------------------
    @property
    def last_problem(self) -> Problem | None:
        """The QP of the last tick (on the compiled path: views onto the workspace's arrays)."""
        path = self._last_from
        return None if path is None else path.last_problem

    @property
    def last_solution(self) -> Solution | None:
        """The solver's answer at the last tick (None before the first)."""
        path = self._last_from
        if path is None:
            return None
        last = path.last
        if isinstance(last, tuple):
            x, status, iters, name = last
            nv = path.last_problem.n_var if path.last_problem is not None else self.n
            last = Solution(x is not None, x.copy() if x is not None else np.zeros(nv), status, iters, 0.0, name)
            path.last = last
        return last

    @property
    def last_outcome(self) -> SolveOutcome | None:
        """The last tick's solve as a typed record (None before the first): status, the solver's
        word, iterations, solver, x (read-only; None when the solve failed)."""
        sol = self.last_solution
        return None if sol is None else SolveOutcome.of(sol)
