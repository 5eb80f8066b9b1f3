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

Two paths run the same law. With the standard tasks and constraints above (what every scenario
builds), :meth:`QPController.step` is the compiled tick: the kernels of :mod:`qpctl.kernels.tick`
write the cost and rows in place into DAQP's layout (:class:`qpctl.tick.QPBuffers`), the solver
reads them (DAQP on a persistent model; the others through a :class:`~qpctl.qp.Problem` of views
onto the same arrays) and a kernel checks the answer. With any other task or constraint, the state
is computed by the same kernels and the problem is stacked in Python by
:class:`~qpctl.formulation.Formulation` (:meth:`QPController.control`), which is also the reference
the tests hold the compiled assembly against. A failed solve takes the fallback chain in Python on
either path (:mod:`qpctl.fallbacks`: strategies registered by name, finding rows by their kind), or,
with ``strict=True``, raises :class:`~qpctl.errors.InfeasibleError` / :class:`~qpctl.errors.SolverError`.
Each tick reports the solver's word (``info["status"]``) and its :class:`~qpctl.outcome.SolveStatus`
(``info["solve_status"]``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import partial
from typing import Any, cast

import numpy as np
import pinocchio as pin

from qpctl.config import check_fields, setting
from qpctl.constraints.constraints import (
    Constraint,
    JointLimit,
    ObstacleBarrier,
    SelfCollisionBarrier,
    TorqueLimit,
)
from qpctl.controllers.base import Controller, ControlOutput, RecordOutput, TickStatus, fast_state
from qpctl.errors import ConfigError, InfeasibleError, InvalidStateError, SolverError
from qpctl.fallbacks import (
    BRAKE,
    CLOSED_FORM,
    FALLBACKS,
    SAFE_STOP,
    Attempt,
    Fallback,
    FallbackContext,
    brake_acceleration,
    make_fallback,
    run_chain,
)
from qpctl.formulation import Formulation
from qpctl.geometry.obstacles import Obstacle
from qpctl.geometry.self_collision import named_pairs, self_collision_pairs
from qpctl.kernels import codes
from qpctl.kernels import tick as K
from qpctl.law import LawGains, LawTerms, law_terms
from qpctl.outcome import SOLUTION_RTOL, SolveOutcome, SolveStatus, checked_solve, solve_status
from qpctl.paths import WaypointPath
from qpctl.qp import Problem, Solution, penalty_is_exact
from qpctl.robot.model import RobotModel
from qpctl.solvers.base import DEFAULT_SOLVER, QPSolver, make_solver
from qpctl.solvers.daqp_ import STATUS as DAQP_STATUS
from qpctl.solvers.daqp_ import DAQPSolver
from qpctl.state import TickState
from qpctl.tasks.tasks import (
    DEFAULT_DAMPING,
    AccelerationTask,
    DampingTask,
    EndEffectorTask,
    PostureTask,
    Task,
)
from qpctl.tick import QPBuffers, QPSpec, Workspace

FALLBACK_CLOSED_FORM = CLOSED_FORM  # the fallback chain's built-in strategies (qpctl.fallbacks)
FALLBACK_BRAKE = BRAKE
FALLBACK_SAFE_STOP = SAFE_STOP
BUILT_IN_FALLBACKS = tuple(FALLBACKS)


@dataclass
class QPConfig:
    """Settings of the QP controller (the ``[controller]`` keys of a scenario; units in brackets).

    solver: a name from ``qpctl solvers``; solver_settings: passed to it (tolerances, max_iter...).
    torque_limits / joint_limits: include those constraints when the robot has finite limits.
    barrier_k0 [1/s²], barrier_k1 [1/s]: obstacle barrier gains; barrier_drift: "exact" (default:
    closed form for sphere and capsule obstacles, a look-ahead finite difference of ḣ for the others)
    or "rigid" (nᵀJ̇_p q̇ only, DESIGN.md §2's approximation); joint_k0, joint_k1: joint-position
    barrier gains; velocity_gain [1/s]: joint-speed barrier gain.
    slack_l1, slack_l2: task slack weights (ℓ₁ exact penalty, ℓ₂ regulariser).
    task_relaxation: "always" — solve with the task slack every tick; "on_failure" — solve with the
    task hard first and with the slack only when that fails or its answer is not the relaxed QP's;
    "auto" — "on_failure" for osqp (ADMM converges slowly and its polishing fails with the ℓ₁ slack),
    the task hard first inside DAQP's compiled tick (a smaller QP, same answer), "always" otherwise.
    max_pairs: obstacle rows (0: 4 per link, at most links × obstacles).
    fallback: the failure policy — what produces the torque when the solver fails (infeasible,
    iteration or time limit, numerical error, non-finite data), tried in order:

    * a solver name (``qpctl solvers``), e.g. ``"daqp"``: that solver on the same tick's QP (with the
      task slack), skipped once the tick budget is spent;
    * ``"closed-form"`` — the paper law (eq. 19) when it is safe, i.e. no link is within d_safe of an
      obstacle and its q̈ meets every obstacle-barrier row of the tick's QP; otherwise on down the
      chain (status ``within_d_safe`` or ``barrier_violated``);
    * ``"safe-stop"`` — the brake below corrected by a small QP (DAQP, tens of µs) that keeps the
      barrier rows as well as the torque limits allow: where they cannot all hold it decelerates the
      approach as hard as the limits allow (:class:`qpctl.fallbacks.SafeStop`);
    * ``"brake"`` — q̈ = k_v (g − q̇): come to rest, except that links within d_influence back away
      along the obstacle sensor's reference velocity g (g = 0 when no obstacle is near), k_v the
      task's velocity gain [1/s].

    ``"brake"`` always produces a torque, so entries after it are never used; when every entry fails,
    the brake is used. Any fallback's q̈ is clipped to the joint-limit bounds and its torque to ±τ_max
    (the brake and the closed form scaled toward gravity compensation, direction kept). The tick's
    ``info`` records ``fallback`` (what produced the torque), ``fallback_reason`` (the QP's status)
    and ``fallback_tried`` ("name:status" of the entries that failed); the run's metrics count
    ``qp_fallbacks`` by name.
    tick_budget_us: wall-time budget of a tick [µs] (0: none), from the start of
    :meth:`QPController.step` (state, QP build and every solver attempt). Each solver attempt gets
    what is left as its time limit (osqp, clarabel, daqp: their own; proxqp: an iteration cap from its
    measured cost per iteration; quadprog: cannot be stopped, the clock is checked after);
    once it is spent no further solver is tried and the chain goes on with its built-in entries
    (``"closed-form"``, ``"safe-stop"``, ``"brake"``: tens of µs each). ``info["budget_exhausted"]``
    marks such ticks.
    posture / posture_weight: an optional PostureTask.
    damping [1], damping_gain [1/s]: the DampingTask's relative weight ρ and gain K_d (ρ = 0: none,
    the QP then reduces exactly to the paper law where no inequality is active).
    task_weights: one per task row (> 0): how much more a row's slack costs (EndEffectorTask).
    self_collision: keep the arm's own links ``self_d_safe`` [m] apart (a SelfCollisionBarrier on
    the pairs :func:`qpctl.geometry.self_collision.self_collision_pairs` keeps, or on
    ``self_collision_pairs``, pairs of link names), with the obstacle barrier's gains.
    """

    solver: str = DEFAULT_SOLVER
    solver_settings: dict[str, Any] = field(default_factory=dict)
    torque_limits: bool = True
    joint_limits: bool = True
    barrier_k0: float = setting(400.0, valid="positive", unit="1/s²")
    barrier_k1: float = setting(40.0, valid="positive", unit="1/s")
    barrier_drift: str = "exact"
    joint_k0: float = setting(100.0, valid="positive", unit="1/s²")
    joint_k1: float = setting(20.0, valid="positive", unit="1/s")
    velocity_gain: float = setting(50.0, valid="positive", unit="1/s")
    slack_l1: float = setting(1e6, valid="nonnegative")
    slack_l2: float = setting(1e2, valid="nonnegative")
    max_pairs: int = 0
    task_relaxation: str = "auto"
    fallback: list[str] = field(default_factory=lambda: [FALLBACK_CLOSED_FORM, FALLBACK_SAFE_STOP])
    tick_budget_us: float = setting(0.0, valid="nonnegative", unit="µs")
    posture: list[float] | None = None
    posture_weight: float = setting(0.0, valid="nonnegative")
    damping: float = setting(DEFAULT_DAMPING, valid="nonnegative")
    damping_gain: float = setting(10.0, valid="nonnegative", unit="1/s")
    task_weights: list[float] | None = None
    self_collision: bool = True
    self_d_safe: float = 0.02
    self_collision_pairs: list[list[str]] | None = None

    def __post_init__(self) -> None:
        if isinstance(self.fallback, str) or not all(isinstance(x, str) for x in self.fallback):
            raise ConfigError(f"must be a list of names, got {self.fallback!r}", key="controller.fallback")
        self.fallback = list(self.fallback)
        check_fields(self, "controller")
        if isinstance(self.max_pairs, bool) or not isinstance(self.max_pairs, int) or self.max_pairs < 0:
            raise ConfigError(f"must be an integer >= 0, got {self.max_pairs!r}", key="controller.max_pairs")

    @classmethod
    def from_dict(cls, cfg: dict[str, Any]) -> QPConfig:
        keys = cls.__dataclass_fields__.keys()
        return cls(**{k: v for k, v in cfg.items() if k in keys})


class QPOutput(RecordOutput):
    """A compiled QP tick's output: the record, and the solver's word; ``info`` built on first access
    (status — the solver's word — and ``solve_status`` (:class:`~qpctl.outcome.SolveStatus`),
    iterations, solver, stage timings [µs], slack norm, active rows, and the fallback's entries when
    one produced the torque); :attr:`outcome` the solve as a typed record."""

    def __init__(self, rec: np.ndarray, layout: Any, extra: dict[str, Any], compute_us: float,
                 stages: tuple[float, float, float, float], solved: bool) -> None:
        super().__init__(rec, layout, extra, compute_us, stages)
        self._solved = solved

    @property
    def status(self) -> TickStatus:  # type: ignore[override]
        return TickStatus.SOLVED if self._solved else TickStatus.FALLBACK

    @property
    def iterations(self) -> int:
        return int(self._extra["iterations"]) if self._extra else 0

    @property
    def outcome(self) -> SolveOutcome:
        """The tick's solve (the last attempt's word; x is not kept on the compiled path:
        :attr:`QPController.last_outcome` has it)."""
        info = self.info
        return SolveOutcome(info["solve_status"], info["status"], int(info["iterations"]), info["solver"],
                            float(info.get("solve_us", 0.0)))

    def _decode(self, info: dict[str, Any]) -> None:
        r, s = self._rec, self._layout.scalars
        info["solve_status"] = solve_status(info["status"])
        if r[s + codes.R_DROPPED]:
            info["pairs_dropped"] = int(r[s + codes.R_DROPPED])
        if not self._solved:
            return
        if r[s + codes.R_CLIPPED]:
            info["clipped"] = float(r[s + codes.R_CLIPPED])
        if r[s + codes.R_RATE_HITS]:
            info["rate_limited"] = int(r[s + codes.R_RATE_HITS])
        info["slack_norm"] = float(r[s + codes.R_SLACK])
        info["active"] = int(r[s + codes.R_ACTIVE])
        mask = int(r[s + codes.R_ACTIVE_MASK])
        info["active_rows"] = [name for bit, name in ((1, "obstacles"), (0, "torque_limits")) if mask >> bit & 1]


def compiled_spec(tasks: Sequence[Task], constraints: Sequence[Constraint], n: int) -> QPSpec | None:
    """The compiled assembly's description of these tasks and constraints, or None when they are not
    exactly the standard ones (an AccelerationTask, an EndEffectorTask, at most one PostureTask; at
    most one TorqueLimit, JointLimit and ObstacleBarrier): those go through the Python formulation."""
    kinds = [type(t) for t in tasks]
    if kinds.count(AccelerationTask) != 1 or kinds.count(EndEffectorTask) != 1:
        return None
    if kinds.count(PostureTask) > 1 or kinds.count(DampingTask) > 1:
        return None
    if len(kinds) != 2 + kinds.count(PostureTask) + kinds.count(DampingTask):
        return None
    ckinds = [type(c) for c in constraints]
    if any(ckinds.count(k) > 1 for k in ckinds) or not all(
            k in (TorqueLimit, JointLimit, ObstacleBarrier, SelfCollisionBarrier) for k in ckinds):
        return None
    acc = next(t for t in tasks if isinstance(t, AccelerationTask))
    ee = next(t for t in tasks if isinstance(t, EndEffectorTask))
    post = next((t for t in tasks if isinstance(t, PostureTask)), None)
    damp = next((t for t in tasks if isinstance(t, DampingTask)), None)
    order = [t for t in tasks if isinstance(t, (PostureTask, DampingTask))]
    if len(order) == 2 and isinstance(order[0], DampingTask):  # the kernel adds the posture first
        return None
    if post is not None and post.q_ref.shape != (n,):
        raise ConfigError(f"q_ref has {post.q_ref.size} entries, the robot {n}", key="PostureTask.q_ref")
    torque = next((c for c in constraints if isinstance(c, TorqueLimit)), None)
    joint = next((c for c in constraints if isinstance(c, JointLimit)), None)
    barrier = next((c for c in constraints if isinstance(c, ObstacleBarrier)), None)
    return QPSpec(
        acc_weight=acc.weight, slack_l1=ee.slack_l1, slack_l2=ee.slack_l2,
        posture=None if post is None else (post.q_ref, post.weight, post.kp, post.kd),
        damping=None if damp is None else (damp.weight, damp.gain),
        rows=[(c.name, c.rows) for c in constraints if c.rows],
        torque=torque,
        joint_limits=None if joint is None else (joint.q_min, joint.q_max, joint.v_max, joint.k0, joint.k1, joint.kv,
                                                 joint.qdd_max),
        barrier=None if barrier is None else (barrier.rows, barrier.k0, barrier.k1, barrier.drift == "rigid"),
        row_names=[c.name for c in constraints for _ in range(c.rows)],
        row_kinds=[c.kind for c in constraints for _ in range(c.rows)],
        self_barrier=next(((c.k0, c.k1, c.d_safe) for c in constraints if isinstance(c, SelfCollisionBarrier)), None),
        task_weights=ee.weights,
    )


class QPController(Controller):
    """Per-tick QP controller (see module docstring)."""

    kind = "qp"

    def __init__(self, robot: RobotModel, path: WaypointPath, obstacles: Sequence[Obstacle] = (),
                 gains: LawGains | None = None, config: QPConfig | None = None, *,
                 tasks: Sequence[Task] | None = None, constraints: Sequence[Constraint] | None = None,
                 broadphase: bool | None = None, strict: bool = False) -> None:
        super().__init__(robot, path, obstacles, gains, broadphase=broadphase)
        self.config = config or QPConfig()
        # strict: a failed solve raises InfeasibleError / SolverError (with the problem and the
        # outcome) instead of taking the fallback chain
        self.strict = strict
        cfg = self.config
        self._solver = make_solver(cfg.solver, cfg.solver_settings)
        self._solver_soft = make_solver(cfg.solver, cfg.solver_settings)
        if cfg.task_relaxation not in ("auto", "always", "on_failure"):
            raise ConfigError(f"must be auto, always or on_failure, got {cfg.task_relaxation!r}",
                              key="controller.task_relaxation")
        # The chain's strategies are built now: an unknown name fails here, not in the middle of a run.
        self._fallbacks: dict[str, Fallback] = {name: make_fallback(name) for name in cfg.fallback}
        self._tick_start: float | None = None
        self._hard_first = self.relaxation == "on_failure"
        self._try_hard = True  # the native hard-first path: try the hard QP this tick (_step_hard_first)
        self._hf_ws: Workspace | None = None  # the workspace _hf was found for (_hard_first_args)
        self._hf: tuple[Any, Any, tuple[Any, ...]] | None = None
        if tasks is None:
            tasks = [AccelerationTask(), EndEffectorTask(cfg.slack_l1, cfg.slack_l2, cfg.task_weights)]
            if cfg.posture_weight > 0:
                tasks.append(PostureTask(cfg.posture if cfg.posture is not None else robot.q_home,
                                         cfg.posture_weight))
            if cfg.damping > 0:
                tasks.append(DampingTask(cfg.damping, cfg.damping_gain))
        if constraints is None:
            constraints = []
            if cfg.torque_limits and np.any(np.isfinite(np.concatenate([robot.tau_max, robot.tau_rate_max]))):
                constraints.append(TorqueLimit(robot.tau_max, robot.tau_rate_max))
            finite = np.isfinite(np.concatenate([robot.q_min, robot.q_max, robot.v_max, robot.qdd_max]))
            if cfg.joint_limits and np.any(finite):
                constraints.append(JointLimit(robot.q_min, robot.q_max, robot.v_max, k0=cfg.joint_k0,
                                              k1=cfg.joint_k1, kv=cfg.velocity_gain, qdd_max=robot.qdd_max))
            if self.obstacles:
                cap = cfg.max_pairs or len(robot.capsules) * min(len(self.obstacles), 4)
                constraints.append(ObstacleBarrier(cap, self.gains.d_safe, k0=cfg.barrier_k0, k1=cfg.barrier_k1,
                                                   drift=cfg.barrier_drift))
            if cfg.self_collision:
                pairs = (named_pairs(robot, cfg.self_collision_pairs) if cfg.self_collision_pairs is not None
                         else self_collision_pairs(robot, cfg.self_d_safe))
                if pairs.pairs:
                    constraints.append(SelfCollisionBarrier(pairs.pairs, cfg.self_d_safe, k0=cfg.barrier_k0,
                                                            k1=cfg.barrier_k1))
        selfc = next((c for c in constraints if isinstance(c, SelfCollisionBarrier)), None)
        if selfc is not None:  # the Python path's states carry these pairs' distances
            selfc.cutoff = min(self.cutoff, selfc.d_safe + selfc.REACH)
            self.dynamics.self_pairs, self.dynamics.self_cutoff = selfc.pairs, selfc.cutoff
        self.tasks: list[Task] = list(tasks)
        self.constraints: list[Constraint] = list(constraints)
        self._formulation: Formulation | None = None
        self._last_problem: Problem | None = None
        self._last: tuple[np.ndarray | None, str, int, str] | Solution | None = None

    @classmethod
    def from_config(cls, cfg: dict[str, Any], robot: RobotModel, path: WaypointPath,
                    obstacles: Sequence[Obstacle], gains: LawGains, *, broadphase: bool | None = None
                    ) -> QPController:
        return cls(robot, path, obstacles, gains, QPConfig.from_dict(cfg), broadphase=broadphase)

    @property
    def solver(self) -> str:  # type: ignore[override]
        return self._solver.name

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
        self._hard_first = self.relaxation == "on_failure"
        self._hf_ws = self._hf = None  # the native hard-first path is looked up again

    def reset(self) -> None:
        super().reset()
        limit = self._torque_limit_constraint()
        if limit is not None:
            limit.forget()
        self._solver.reset()
        self._solver_soft.reset()
        for fb in self._fallbacks.values():
            fb.reset()
        self._try_hard = True

    # -- the law ----------------------------------------------------------------------------------
    def formulation(self) -> Formulation:
        if self._formulation is None:
            self._formulation = Formulation(self.n, self.tasks, self.constraints)
            self._solver.reset()
            self._solver_soft.reset()
        return self._formulation

    @property
    def relaxation(self) -> str:
        """The task-relaxation strategy of the Python paths ("always" or "on_failure"); under "auto"
        DAQP's compiled tick takes the task hard first on its own (:meth:`_native_hard_first`)."""
        mode = self.config.task_relaxation
        if mode == "auto":
            return "on_failure" if self._solver.name == "osqp" else "always"
        return mode

    def _make_workspace(self) -> Workspace:
        spec = compiled_spec(self.tasks, self.constraints, self.n)
        selfc = next((c for c in self.constraints if isinstance(c, SelfCollisionBarrier)), None)
        if selfc is not None:
            selfc.cutoff = min(self.cutoff, selfc.d_safe + selfc.REACH)
        return Workspace(self.robot, self.obstacles, self.path, self.gains, self.cutoff, spec=spec,
                         broadphase=self.broadphase, barrier_drift=spec is None,
                         self_pairs=selfc.pairs if selfc is not None else (),
                         self_cutoff=selfc.cutoff if selfc is not None else math.inf)

    @property
    def last_problem(self) -> Problem | None:
        """The QP of the last tick (on the compiled path: views onto the workspace's arrays)."""
        return self._last_problem

    @property
    def last_solution(self) -> Solution | None:
        """The solver's answer at the last tick (None before the first)."""
        last = self._last
        if isinstance(last, tuple):
            x, status, iters, name = last
            nv = self._last_problem.n_var if self._last_problem is not None else self.n
            last = Solution(x is not None, x.copy() if x is not None else np.zeros(nv), status, iters, 0.0, name)
            self._last = last
        return last

    @property
    def last_outcome(self) -> SolveOutcome | None:
        """The last tick's solve as a typed record (None before the first): status, the solver's
        word, iterations, solver, x (read-only; None when the solve failed)."""
        sol = self.last_solution
        return None if sol is None else SolveOutcome.of(sol)

    def _raise_if_strict(self, problem: Problem, word: str, info: dict[str, Any]) -> None:
        """In strict mode, a failed solve raises instead of falling back: :class:`InfeasibleError`
        when the hard rows cannot all hold, :class:`SolverError` for any other failure; both carry
        the problem and the outcome (``err.problem``, ``err.outcome``)."""
        if not self.strict:
            return
        sol = self.last_solution
        outcome = SolveOutcome(solve_status(word), word, int(info.get("iterations", 0)), str(info.get("solver", "")),
                               float(info.get("solve_us", 0.0)), None if sol is None else SolveOutcome.of(sol).x)
        kind = InfeasibleError if outcome.status is SolveStatus.INFEASIBLE else SolverError
        raise kind(f"the QP failed ({outcome.status.value}: {word}) with solver {outcome.solver}", status=word,
                   problem=problem, outcome=outcome)

    # -- the compiled tick -------------------------------------------------------------------------
    def step(self, q: np.ndarray, v: np.ndarray, t: float) -> ControlOutput:
        """One tick; ``compute_us`` is its wall time, from which the tick budget counts."""
        start = time.perf_counter()
        ws = self._ws if self._ws is not None else self.workspace()
        if ws.spec is None:  # custom tasks or constraints: the Python formulation
            self._tick_start = start
            try:
                return super().step(q, v, t)
            finally:
                self._tick_start = None
        q, v, t = fast_state(q, v, t, self.n)
        budget = self.config.tick_budget_us
        deadline = start + budget * 1e-6 if budget > 0 else math.inf
        if budget <= 0:
            hf = self._hf if self._hf_ws is ws else self._hard_first_args(ws)
            if hf is not None:
                return self._step_hard_first(ws, hf, q, v, t, start)
        hard_first = self._hard_first
        buf = ws.hard if hard_first else ws.relaxed
        assert buf is not None  # the compiled path's layouts (workspace() built them)
        solver = self._solver if hard_first else self._solver_soft
        nat = self._fast_native(ws, solver, buf) if budget <= 0 and not hard_first else None
        if nat is not None:  # computeAllTerms, then the whole tick in one kernel call
            t0 = time.perf_counter()
            pin.computeAllTerms(ws.model, ws.data, q, v)
            t1 = time.perf_counter()
            code = K.tick_qp_native(ws.work, q, v, t, *nat.kernel_args, SOLUTION_RTOL)
            if code == codes.STATE_PYTHON:
                ws.finish_state(q, v, t)
                code = K.qp_tick_native(ws.work, *nat.kernel_args, SOLUTION_RTOL)
            if code < 0:
                self._bad_state(q, v, t)
            code, status, iters = self._native_outcome(code, nat, solver)
            stages = (t1 - t0, -1.0, -1.0, -1.0)
        else:
            self._state(q, v, t)
            code, status, iters = self._solve_layout(solver, buf, deadline, terms_done=False)
            stages = (ws.pin_s, ws.state_s, -1.0, -1.0)
        if code == 1:
            raise InvalidStateError(f"the inertia matrix is not positive definite at q={q.tolist()}")
        extra: dict[str, Any] = {"status": status, "iterations": iters, "solver": solver.name}
        if hard_first and code == 3:  # the task conflicts with the hard rows: let it give way
            assert ws.relaxed is not None
            buf = ws.relaxed
            code, status2, iters2 = self._solve_layout(self._solver_soft, buf, deadline, terms_done=True)
            extra.update(relaxed=True, hard_status=status, status=status2, iterations=iters + iters2)
            status = status2
        self._last_problem = buf.problem
        if status == "time_limit":
            extra["budget_exhausted"] = True
        ok = code == 0
        if not ok:
            self._compiled_fallback(ws, buf, status, extra, deadline, hard_first)
        end = time.perf_counter()
        out = QPOutput(ws.rec.copy(), ws.layout, extra, (end - start) * 1e6, stages, ok)
        self.last = out
        return out

    def _native_hard_first(self, ws: Workspace) -> bool:
        """Whether this tick solves the task hard first on DAQP's C API (task_relaxation "auto", the
        compiled assembly, DAQP's native path for both layouts, a task with slack): the hard QP has no
        slack variables (n instead of n + 2m), and its answer is used only where it is the relaxed
        QP's too (:func:`qpctl.kernels.hard_first.penalty_exact` on DAQP's multipliers), so the torques are
        those of the relaxed QP on every tick."""
        if self.config.task_relaxation != "auto" or type(self._solver) is not DAQPSolver:
            return False
        if ws.hard is None or ws.relaxed is None or not ws.relaxed.relaxed:
            return False
        hard, soft = cast(DAQPSolver, self._solver), cast(DAQPSolver, self._solver_soft)
        return hard.native(ws.hard) is not None and soft.native(ws.relaxed) is not None

    def _hard_first_args(self, ws: Workspace) -> tuple[Any, Any, tuple[Any, ...]] | None:
        """(the hard and relaxed QPs' native DAQP, the kernel's arguments after the state) for this
        workspace when :meth:`_native_hard_first` holds, else None; kept until the workspace changes
        (the per-tick path reads it instead of looking the solvers up again)."""
        hf = None
        if self._native_hard_first(ws):
            assert ws.spec is not None and ws.hard is not None and ws.relaxed is not None
            nat_h = cast(DAQPSolver, self._solver).native(ws.hard)
            nat_r = cast(DAQPSolver, self._solver_soft).native(ws.relaxed)
            assert nat_h is not None and nat_r is not None
            hf = (nat_h, nat_r, (*nat_h.kernel_args, nat_h.lam, *nat_r.kernel_args, SOLUTION_RTOL,
                                 float(ws.spec.slack_l1)))
        self._hf_ws, self._hf = ws, hf
        return hf

    def _step_hard_first(self, ws: Workspace, hf: tuple[Any, Any, tuple[Any, ...]], q: np.ndarray,
                         v: np.ndarray, t: float, start: float) -> QPOutput:
        """:meth:`step` on the native hard-first path (:meth:`_native_hard_first`): one kernel call
        (:func:`qpctl.kernels.tick.tick_qp_native_hard_first`) when both DAQP workspaces are set up and
        the state needs no Python; else the state, the set-up (:meth:`_hard_first_setup`) and the same
        kernel after it. The hard QP is skipped on the ticks after one where the task gave way (its
        slack non-zero)."""
        nat_h, nat_r, args = hf
        try_hard = self._try_hard
        if ws.fast and nat_r.ready and (nat_h.ready or not try_hard):
            t0 = time.perf_counter()
            pin.computeAllTerms(ws.model, ws.data, q, v)
            t1 = time.perf_counter()
            code, hard = K.tick_qp_native_hard_first(ws.work, q, v, t, *args, try_hard)
            if code == codes.STATE_PYTHON:
                ws.finish_state(q, v, t)
                code, hard = K.qp_tick_native_hard_first(ws.work, *args, try_hard)
            if code < 0:
                self._bad_state(q, v, t)
            stages = (t1 - t0, -1.0, -1.0, -1.0)
        else:
            self._state(q, v, t)
            code, hard_ready = self._hard_first_setup(ws, nat_h, nat_r, try_hard)
            hard = -1
            if code == 0:
                code, hard = K.qp_tick_native_hard_first(ws.work, *args, try_hard and hard_ready)
            if try_hard and not hard_ready:
                hard = 3  # DAQP could not set the hard QP up (its exit flag in nat_h.flag)
            stages = (ws.pin_s, ws.state_s, -1.0, -1.0)  # the set-up is in "other"
        if code == 1:
            raise InvalidStateError(f"the inertia matrix is not positive definite at q={q.tolist()}")
        if hard in (3, 4):
            nat_h.free()  # a failed or rejected working set is no warm start: cold the next time it is tried
        used_hard = hard == 0
        nat, solver = (nat_h, self._solver) if used_hard else (nat_r, self._solver_soft)
        code, status, iters = self._native_outcome(code, nat, solver)
        extra: dict[str, Any] = {"status": status, "iterations": iters, "solver": solver.name}
        if not used_hard:
            extra["relaxed"] = True
            if hard > 0:
                extra["hard_status"] = {4: "inaccurate", 7: "penalty_inexact"}.get(
                    hard, DAQP_STATUS.get(int(nat_h.flag[0]), f"exitflag {int(nat_h.flag[0])}"))
        buf = ws.hard if used_hard else ws.relaxed
        assert buf is not None  # both layouts exist on this path (_native_hard_first)
        self._last_problem = buf.problem
        ok = code == 0
        self._try_hard = used_hard or (ok and ws.rec[ws.layout.scalars + codes.R_SLACK] <= 1e-12)
        if not ok:
            self._compiled_fallback(ws, buf, status, extra, math.inf, False)
        end = time.perf_counter()
        out = QPOutput(ws.rec.copy(), ws.layout, extra, (end - start) * 1e6, stages, ok)
        self.last = out
        return out

    def _hard_first_setup(self, ws: Workspace, nat_h: Any, nat_r: Any, try_hard: bool) -> tuple[int, bool]:
        """DAQP's workspaces set up where they are not (the first tick, and after a failure freed one):
        each QP's arrays written from this tick's state, then DAQP's set-up on them. Returns (code,
        whether the hard QP is ready): code as :meth:`_solve_layout`'s (0: both go to the kernel)."""
        hb, rb = ws.hard, ws.relaxed
        assert hb is not None and rb is not None
        terms_done = False
        if try_hard and not nat_h.ready:
            code = K.qp_terms_and_build(ws.work, hb.H, hb.f, hb.rows, hb.bu, hb.bl)
            if code:
                return code, False
            terms_done = True
            flag = nat_h.setup()
            if flag < 0:
                nat_h.flag[0] = flag
        if not nat_r.ready:
            code = (K.qp_rebuild if terms_done else K.qp_terms_and_build)(ws.work, rb.H, rb.f, rb.rows, rb.bu, rb.bl)
            if code:
                return code, nat_h.ready
            flag = nat_r.setup()
            if flag < 0:  # DAQP could not even set the relaxed QP up (its exit flag says why)
                nat_r.flag[0], nat_r.flag[1] = flag, 0
                return 3, nat_h.ready
        return 0, nat_h.ready

    def _fast_native(self, ws: Workspace, solver: QPSolver, buf: QPBuffers) -> Any:
        """The native DAQP of ``buf`` when this tick can run as one kernel call (no tick budget; DAQP's
        workspace already set up; nothing for Python between state and law), else None."""
        if not ws.fast or type(solver) is not DAQPSolver:
            return None
        nat = solver.native(buf)
        return nat if nat is not None and nat.ready else None

    def _solve_layout(self, solver: QPSolver, buf: QPBuffers, deadline: float, *,
                      terms_done: bool) -> tuple[int, str, int]:
        """The law's terms (unless ``terms_done``) and the QP's rows written into ``buf``, solved within
        what is left of the budget, the answer checked (:func:`qpctl.kernels.finish.qp_finish` writes τ,
        q̈ and the record when it holds); the build and solve times [µs] go into the record (added to
        those of an earlier attempt in this tick when ``terms_done``). Returns (code, status,
        iterations), code 0: solved and accepted; 1: M not positive definite; 2: non-finite problem;
        3: failed, timed out or rejected."""
        ws = self._ws
        assert ws is not None
        rec, s = ws.rec, ws.layout.scalars
        # The task hard first (task_relaxation "on_failure"): an answer is used only if the relaxed QP
        # would give the same one (checked here, so DAQP goes through Python rather than its kernel)
        check_penalty = self._hard_first and not buf.relaxed and ws.relaxed is not None and ws.relaxed.relaxed
        nat = solver.native(buf) if type(solver) is DAQPSolver and not check_penalty else None
        left_us = math.inf
        if deadline != math.inf:
            left_us = (deadline - time.perf_counter()) * 1e6
            if nat is not None:
                nat.set_time_limit(max(left_us * 1e-6, 1e-9))
            else:
                solver.set_time_limit(max(left_us, 0.0))
        if nat is not None and nat.ready and not terms_done and left_us > 0:
            code = K.qp_tick_native(ws.work, buf.H, buf.f, buf.rows, buf.bu, buf.bl, *nat.addresses, nat.flag,
                                    nat.x, SOLUTION_RTOL)  # the whole tick in one call; times in the record
            return self._native_outcome(code, nat, solver)
        before_build, before_solve = (rec[s + codes.R_BUILD_US], rec[s + codes.R_SOLVE_US]) if terms_done else (0.0, 0.0)
        t0 = time.perf_counter()
        code = (K.qp_rebuild if terms_done else K.qp_terms_and_build)(ws.work, buf.H, buf.f, buf.rows, buf.bu, buf.bl)
        t1 = time.perf_counter()
        rec[s + codes.R_BUILD_US], rec[s + codes.R_SOLVE_US] = before_build + (t1 - t0) * 1e6, before_solve
        if code:
            self._last = (None, "nonfinite_problem", 0, solver.name)
            return code, "nonfinite_problem", 0
        if left_us <= 0:
            self._last = (None, "time_limit", 0, solver.name)
            return 3, "time_limit", 0
        if nat is not None:
            flag = 1 if nat.ready else nat.setup()
            if flag < 0:  # DAQP could not even set the QP up (its exit flag says why)
                nat.flag[0], nat.flag[1], code = flag, 0, 3
            else:
                code = K.native_solve_finish(ws.work, buf.rows, buf.bu, buf.bl, *nat.addresses, nat.flag, nat.x,
                                             SOLUTION_RTOL)
            rec[s + codes.R_SOLVE_US] = before_solve + (time.perf_counter() - t1) * 1e6
            return self._native_outcome(code, nat, solver)
        if type(solver) is DAQPSolver:
            x, status, iters = solver.solve_buffers(buf.H, buf.f, buf.rows, buf.bu, buf.bl, buf.sense)
        else:
            sol = checked_solve(solver, buf.problem, deadline, check=False)
            x, status, iters = (sol.x if sol.found else None), sol.status, sol.iterations
        if (x is not None and check_penalty and np.isfinite(x).all()
                and not penalty_is_exact(buf.problem, x, ws.spec.slack_l1)):  # type: ignore[union-attr]
            # Feasible, and the hard QP's optimum, but not the relaxed QP's: the task's multipliers
            # exceed the slack weight, so every other solver (task relaxed) trades tracking for torque
            status, x = "penalty_inexact", None
        if x is not None and not K.qp_finish(ws.work, x, buf.rows, buf.bu, buf.bl, SOLUTION_RTOL):
            # The solver's own test runs on its scaled problem: a row it scaled up (say nᵀJ_p ≈ 1e-5
            # at a link's fixed base) can be violated by m/s² in our units while it reports "solved".
            status = "inaccurate" if np.isfinite(x).all() else "nonfinite_solution"
            x = None
        rec[s + codes.R_SOLVE_US] = before_solve + (time.perf_counter() - t1) * 1e6
        if x is not None:
            rec[s + codes.R_ITERATIONS] = iters
        self._last = (x, status, iters, solver.name)
        return (0 if x is not None else 3), status, iters

    def _native_outcome(self, code: int, nat: Any, solver: QPSolver) -> tuple[int, str, int]:
        """(code, status, iterations) of a native DAQP tick (see :meth:`_solve_layout`); a failed or
        rejected solve frees DAQP's workspace, so the next tick starts cold rather than from a failed
        working set (warm-started from one, DAQP was seen to report "solved" with the rows broken on
        every later tick of an infeasible stretch, where a cold start reports it infeasible)."""
        iters = int(nat.flag[1])
        if code == 0:
            self._last = (nat.x, "solved", iters, solver.name)
            return 0, "solved", iters
        if code in (1, 2):
            status = "nonfinite_problem"
        elif code == 4:  # DAQP said solved, the answer breaks a hard row: its working set is no warm start
            status = "inaccurate" if np.isfinite(nat.x).all() else "nonfinite_solution"
            nat.free()
        else:
            status = DAQP_STATUS.get(int(nat.flag[0]), f"exitflag {int(nat.flag[0])}")
            nat.free()
        self._last = (None, status, iters, solver.name)
        return code if code in (1, 2) else 3, status, iters

    def _compiled_fallback(self, ws: Workspace, buf: QPBuffers, status: str, info: dict[str, Any],
                           deadline: float, hard_first: bool) -> None:
        """The solve failed: strict mode raises; else the fallback chain on snapshots of the tick (the
        rare path, in Python); the torque it settles on goes into the workspace's record."""
        self._raise_if_strict(buf.problem, status, info)
        t0 = time.perf_counter()
        state = ws.snapshot()
        terms = ws.terms()

        def relaxed() -> Problem:
            rb = ws.relaxed
            assert rb is not None
            K.qp_build(ws.work, rb.H, rb.f, rb.rows, rb.bu, rb.bl)
            return rb.problem

        ctx = self._fallback_context(state, terms, buf.problem, deadline, None if buf.relaxed else relaxed)
        tau, qdd, problem, sol = self._fall_back(ctx, None, status, info)
        self._last_problem = problem
        if sol is not None:
            self._last = sol
        ws.qdd[:], ws.tau[:] = qdd, tau
        K.write_record(ws.work, terms.singular)
        info["fallback_us"] = (time.perf_counter() - t0) * 1e6  # the snapshot included

    def _torque_limit_constraint(self) -> TorqueLimit | None:
        return next((c for c in self.constraints if isinstance(c, TorqueLimit)), None)

    def _torque_window(self, t: float) -> tuple[np.ndarray, np.ndarray] | None:
        """The torques [N·m] the drives accept at t [s] (TorqueLimit.window), or None without limits."""
        limit = self._torque_limit_constraint()
        return None if limit is None else limit.window(t)

    def _scale_to_torque_limits(self, state: TickState, qdd: np.ndarray) -> np.ndarray:
        """s·q̈ with the largest s ∈ [0, 1] that keeps M s q̈ + N within the torque window (±τ_max and
        the rate limit; direction kept, unlike a per-joint clip; s = 0, gravity compensation alone,
        when N itself is outside it — the final clip then holds the window)."""
        window = self._torque_window(state.t)
        if window is None or not np.isfinite(qdd).all():
            return qdd
        t_lo, t_hi = window
        d = state.M @ qdd
        with np.errstate(divide="ignore", invalid="ignore"):
            hi = np.where(d > 0, (t_hi - state.N) / d, np.inf)
            lo = np.where(d < 0, (t_lo - state.N) / d, np.inf)
        scale = float(np.clip(np.min(np.concatenate([hi, lo, [1.0]])), 0.0, 1.0))
        return qdd * scale

    def _fallback_context(self, state: TickState, terms: LawTerms, problem: Problem, deadline: float,
                          build_relaxed: Any) -> FallbackContext:
        """What the chain's strategies read: ``build_relaxed()`` gives the tick's QP with the task
        slack when ``problem`` has none (None: it has)."""
        return FallbackContext(state, terms, self.gains, problem, self._torque_window(state.t), deadline,
                               build_relaxed)

    def _fall_back(self, ctx: FallbackContext, sol: Solution | None, word: str,
                   info: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, Problem, Solution | None]:
        """The fallback chain (:func:`qpctl.fallbacks.run_chain`, the QP having failed with ``word``)
        and its q̈ made safe to command (:meth:`_finish_fallback`); returns (τ, q̈, the problem of the
        solution used, the solution: a fallback solver's, else ``sol``)."""
        t0 = time.perf_counter()
        info["fallback_reason"] = word
        att = run_chain([self._fallbacks[name] for name in self.config.fallback], ctx, info)
        problem = att.problem if att.solution is not None and att.problem is not None else ctx.problem
        tau, qdd = self._finish_fallback(ctx, att, problem, info)
        info["fallback_us"] = (time.perf_counter() - t0) * 1e6
        return tau, qdd, problem, att.solution if att.solution is not None else sol

    def _finish_fallback(self, ctx: FallbackContext, att: Attempt, problem: Problem,
                         info: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
        """A fallback's q̈ within the joint-limit bounds (the QP's bounds on q̈, where finite) and, unless a
        solver produced it, scaled into the torque limits; τ = M q̈ + N, never non-finite, clipped to
        ±τ_max. Returns (τ, q̈)."""
        n, state = self.n, ctx.state
        assert att.qdd is not None
        lb, ub = problem.lb[:n], problem.ub[:n]
        qdd = np.minimum(np.maximum(att.qdd, np.where(np.isfinite(lb), lb, att.qdd)),
                         np.where(np.isfinite(ub), ub, att.qdd))
        fsol = att.solution
        if fsol is None:
            qdd = self._scale_to_torque_limits(state, qdd)
        tau = state.M @ qdd + state.N
        if not np.isfinite(tau).all():  # last line of defence: never command a non-finite torque
            info["nonfinite_replaced"] = True
            info["fallback"] = FALLBACK_BRAKE
            fsol = None
            qdd = brake_acceleration(ctx)
            tau = state.M @ qdd + state.N
            if not np.isfinite(tau).all():
                tau = np.where(np.isfinite(tau), tau, 0.0)
                qdd = np.linalg.solve(state.M, tau - state.N)
        tau, qdd = self._clip_torque(state, tau, qdd, info)
        if fsol is not None:
            self._solution_info(problem, fsol.x, info)
        return tau, qdd

    def _clip_torque(self, state: TickState, tau: np.ndarray, qdd: np.ndarray,
                     info: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
        """The solver meets the torque rows to its tolerance; clip that residue (and any fallback's
        excess) so the commanded torque never leaves the window the drives accept (±τ_max, rate)."""
        window = self._torque_window(state.t)
        clipped = tau if window is None else np.minimum(np.maximum(tau, window[0]), window[1])  # np.clip, cheaper
        if (clipped != tau).any():
            info["clipped"] = float(np.max(np.abs(clipped - tau)))
            tau = clipped
            qdd = np.linalg.solve(state.M, tau - state.N)
        return tau, qdd

    def _solution_info(self, problem: Problem, x: np.ndarray, info: dict[str, Any]) -> None:
        """Slack norm, active-row count and the families with an active row, at the solver's x."""
        n = self.n
        s = x[n:]
        half = s.size // 2
        slack = s[:half] - s[half:]
        info["slack_norm"] = math.sqrt(float(slack @ slack))
        Cx = problem.C @ x
        act = np.minimum(np.abs(Cx - problem.l), np.abs(Cx - problem.u)) <= 1e-6 * (1.0 + np.abs(Cx))
        xq = x[:n]
        bnd = np.minimum(np.abs(xq - problem.lb[:n]), np.abs(xq - problem.ub[:n])) <= 1e-6
        info["active"] = int(np.count_nonzero(act)) + int(np.count_nonzero(bnd))
        info["active_rows"] = sorted({name for name, lo, hi in self.formulation().row_ranges if act[lo:hi].any()})

    def control(self, state: TickState) -> ControlOutput:
        """The tick on the Python path (any tasks and constraints, custom ones included): build the QP
        from the tasks and constraints (:class:`Formulation`), solve it, check the answer, τ = M q̈ + N;
        when the solve fails, the fallback chain — or, in strict mode, :class:`SolverError`."""
        t0 = time.perf_counter()
        deadline = self._deadline(t0)
        ref = self.reference(state)
        terms = law_terms(state, ref, self.gains, weighted=True)
        problem, solved, info = self._build_and_solve(state, terms, deadline, t0)
        sol: Solution | None = solved
        if solved.found:
            qdd = solved.x[: self.n]
            tau, qdd = self._clip_torque(state, state.M @ qdd + state.N, qdd, info)
            self._solution_info(problem, solved.x, info)
        else:
            self._last_problem, self._last = problem, solved
            self._raise_if_strict(problem, solved.status, info)
            hard = self.relaxation == "on_failure" and not info.get("relaxed")  # the chain's solvers get the slack
            ctx = self._fallback_context(state, terms, problem, deadline,
                                         partial(self.formulation().build, state, terms, relax=True) if hard else None)
            tau, qdd, problem, sol = self._fall_back(ctx, solved, solved.status, info)
        dropped = self.formulation().dropped(state, terms)
        if dropped:
            info["pairs_dropped"] = dropped
        self._last_problem, self._last = problem, sol
        self._remember(state.t, tau)
        return ControlOutput(tau=tau, qdd=qdd, ref=ref, x=state.x, e_null=terms.e_null, clearance=state.clearance,
                             singular=terms.singular, info=info,
                             status=TickStatus.FALLBACK if "fallback" in info else TickStatus.SOLVED)

    def _remember(self, t: float, tau: np.ndarray) -> None:
        """The torque [N·m] commanded at t [s]: the next tick's rate limit is about it."""
        limit = self._torque_limit_constraint()
        if limit is not None:
            limit.remember(tau, t)

    def _deadline(self, now: float) -> float:
        """When the tick budget ends (``time.perf_counter`` time; inf without a budget), counted from
        the start of :meth:`step` (or ``now`` when :meth:`control` is called directly)."""
        budget = self.config.tick_budget_us
        start = self._tick_start if self._tick_start is not None else now
        return start + budget * 1e-6 if budget > 0 else math.inf

    def _build_and_solve(self, state: TickState, terms: LawTerms, deadline: float,
                         t0: float) -> tuple[Problem, Solution, dict[str, Any]]:
        """The tick's QP built and solved, the answer checked (:meth:`_solve_checked`). Under
        task_relaxation "on_failure" the task is hard first (its answer used only where the relaxed
        QP's is the same), relaxed when that fails. Returns (problem, solution, info: status words,
        iterations, solver, build and solve times [µs] from ``t0``)."""
        form = self.formulation()
        hard_first = self.relaxation == "on_failure"
        problem = form.build(state, terms, relax=not hard_first)
        t1 = time.perf_counter()
        l1 = form.penalty_weights(state, terms) if hard_first else None
        sol = self._solve_checked(self._solver if hard_first else self._solver_soft, problem, deadline, l1)
        t2 = time.perf_counter()
        info: dict[str, Any] = {"status": sol.status, "iterations": sol.iterations, "solver": sol.solver,
                                "build_us": (t1 - t0) * 1e6, "solve_us": (t2 - t1) * 1e6}
        if hard_first and not sol.found and sol.status != "nonfinite_problem":  # let the task give way
            problem = form.build(state, terms, relax=True)
            t3 = time.perf_counter()
            sol = self._solve_checked(self._solver_soft, problem, deadline)
            info.update(relaxed=True, hard_status=info["status"], status=sol.status,
                        iterations=info["iterations"] + sol.iterations, build_us=info["build_us"] + (t3 - t2) * 1e6,
                        solve_us=info["solve_us"] + (time.perf_counter() - t3) * 1e6)
        if sol.status == "time_limit":
            info["budget_exhausted"] = True
        info["solve_status"] = solve_status(sol.status)
        return problem, sol, info

    def _solve_checked(self, solver: QPSolver, problem: Problem, deadline: float,
                       l1: np.ndarray | None = None) -> Solution:
        """One solve (:func:`qpctl.outcome.checked_solve`) of a finite problem ("nonfinite_problem"
        otherwise: no solver can be trusted with NaN data, e.g. a degenerate distance query); with the
        task's ℓ₁ weights ``l1`` (the task hard), an answer is kept only if the relaxed QP's is the same."""
        if not problem.is_finite():
            return Solution(False, np.zeros(problem.n_var), "nonfinite_problem", solver=solver.name)
        sol = checked_solve(solver, problem, deadline)
        if sol.found and l1 is not None and np.isfinite(l1).any() and not penalty_is_exact(problem, sol.x, l1):
            return Solution(False, np.zeros(problem.n_var), "penalty_inexact", sol.iterations, sol.solve_us, sol.solver)
        return sol
