"""The compiled QP tick's parts around its kernels: :func:`compiled_spec` (whether the tasks and
constraints are the standard ones the kernels assemble, and their description), :class:`QPOutput`
(a tick's output read from its record) and :class:`QPLayout` (one of the QP's two layouts, the task
hard or relaxed, with its solver). :class:`~qpctl.controllers.qp_compiled.CompiledTick` runs them.
"""

from __future__ import annotations

import math
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
from qpctl.controllers.base import RecordOutput, TickStatus
from qpctl.controllers.relaxation import TaskRelaxation
from qpctl.errors import ConfigError
from qpctl.kernels import codes
from qpctl.kernels import tick as K
from qpctl.outcome import SOLUTION_RTOL, SolveOutcome, checked_solve, solve_status
from qpctl.solvers.base import QPSolver
from qpctl.solvers.daqp_ import STATUS as DAQP_STATUS
from qpctl.solvers.daqp_ import DAQPSolver
from qpctl.tasks.tasks import AccelerationTask, DampingTask, EndEffectorTask, PostureTask, Task
from qpctl.tick import QPBuffers, QPSpec, Workspace

__all__ = ["QPLayout", "QPOutput", "compiled_spec", "daqp_word"]


def compiled_spec(tasks: Sequence[Task], constraints: Sequence[Constraint], n: int) -> QPSpec | None:
    """The compiled assembly's description of these tasks and constraints, or None when they are not
    exactly the standard ones (an AccelerationTask, an EndEffectorTask, at most one PostureTask and
    one DampingTask; at most one TorqueLimit, JointLimit, ObstacleBarrier, SelfCollisionBarrier and
    depth map's field rows — a constraint with a ``field_spec()``, :class:`~qpctl.tick.FieldSpec`):
    those go through the Python formulation (:mod:`qpctl.controllers.qp_reference`)."""
    kinds = [type(t) for t in tasks]
    if kinds.count(AccelerationTask) != 1 or kinds.count(EndEffectorTask) != 1:
        return None
    if kinds.count(PostureTask) > 1 or kinds.count(DampingTask) > 1:
        return None
    if len(kinds) != 2 + kinds.count(PostureTask) + kinds.count(DampingTask):
        return None
    ckinds = [type(c) for c in constraints]
    fields = [c for c in constraints if callable(getattr(c, "field_spec", None))  # the depth map's rows
              and getattr(c, "smooth", True)]  # (smooth: the compiled ones are)
    if any(ckinds.count(k) > 1 for k in ckinds) or not all(
            k in (TorqueLimit, JointLimit, ObstacleBarrier, SelfCollisionBarrier) or c in fields
            for k, c in zip(ckinds, constraints, strict=True)):
        return None
    acc = next(t for t in tasks if isinstance(t, AccelerationTask))
    ee = next(t for t in tasks if isinstance(t, EndEffectorTask))
    post = next((t for t in tasks if isinstance(t, PostureTask)), None)
    damp = next((t for t in tasks if isinstance(t, DampingTask)), None)
    order = [t for t in tasks if isinstance(t, (PostureTask, DampingTask))]
    if len(order) == 2 and isinstance(order[0], DampingTask):  # the kernel adds the posture first
        return None
    if post is not None and post.q_ref.shape != (n,):  # n: the configuration's entries (nq)
        raise ConfigError(f"q_ref has {post.q_ref.size} entries, the robot {n}", key="PostureTask.q_ref")
    torque = next((c for c in constraints if isinstance(c, TorqueLimit)), None)
    joint = next((c for c in constraints if isinstance(c, JointLimit)), None)
    barrier = next((c for c in constraints if isinstance(c, ObstacleBarrier)), None)
    brakes = {id(c.braking): c.braking for c in (joint, barrier) if c is not None and c.braking is not None}
    if len(brakes) > 1 or (brakes and torque is None):
        return None  # two different brakes, or one without the torque limits: the Python formulation
    sc = next((c for c in constraints if isinstance(c, SelfCollisionBarrier)), None)
    if sc is not None and sc.joints is not joint:
        return None  # the kernel caps the self rows' push with this JointLimit's ±q̈_max (or none without one)
    starts = np.cumsum([0] + [c.rows for c in constraints])[:-1].tolist()
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
        braking=next(iter(brakes.values()), None),
        field=fields[0].field_spec() if fields else None,  # type: ignore[attr-defined]
        slack_columns=[(r0, col, float(l1), float(l2)) for c, r0 in zip(constraints, starts, strict=True)
                       if c.slack is not None and c.rows for entries, weights in [c.slack_columns()]
                       for col, (l1, l2) in zip(entries.T, weights, strict=True)],
    )




class QPOutput(RecordOutput):
    """A compiled QP tick's output: the record, and the solver's word; ``info`` built on first access
    (status — the solver's word — and ``solve_status`` (:class:`~qpctl.outcome.SolveStatus`),
    iterations, solver, stage timings [µs], slack norm, active rows, and the fallback's entries when
    one produced the torque); :attr:`outcome` the solve as a typed record.

    ``words``: (status, iterations, solver, hard first, hard used, refusal, relaxed iterations, budget
    exhausted) of the tick, which ``info`` spells out (:meth:`TaskRelaxation.report`); ``extra``, a
    fallback's info dict, when one produced the torque."""

    def __init__(self, rec: np.ndarray, layout: Any, extra: dict[str, Any] | None, compute_us: float,
                 stages: tuple[float, float, float, float], solved: bool, words: tuple[Any, ...] = ()) -> None:
        super().__init__(rec, layout, extra, compute_us, stages)
        self._solved, self._words = solved, words

    def renew_qp(self, compute_us: float, stages: tuple[float, float, float, float], solved: bool,
                 words: tuple[Any, ...]) -> None:
        """This output for a new tick whose record the caller has copied into it (the reuse of
        :meth:`CompiledTick.step`)."""
        self._extra, self._info, self._stages, self.compute_us = None, None, stages, compute_us
        self._solved, self._words = solved, words

    @property
    def status(self) -> TickStatus:  # type: ignore[override]
        return TickStatus.SOLVED if self._solved else TickStatus.FALLBACK

    @property
    def iterations(self) -> int:
        if self._extra:
            return int(self._extra["iterations"])
        if not self._words:
            return 0
        iters = self._words[1]  # None: a fast tick's, in the record
        return int(self._rec[self._layout.scalars + codes.R_ITERATIONS] if iters is None else iters)

    def _get_info(self) -> dict[str, Any]:
        if self._info is None and self._extra is None and self._words:
            status, iters, solver, hard_first, used_hard, refusal, relaxed_iters, exhausted = self._words
            if iters is None:
                iters = int(self._rec[self._layout.scalars + codes.R_ITERATIONS])
            extra: dict[str, Any] = {"status": status, "iterations": iters, "solver": solver}
            TaskRelaxation.report(extra, hard_first, used_hard, refusal, relaxed_iters)
            if exhausted:
                extra["budget_exhausted"] = True
            self._extra = extra
        return super()._get_info()

    info = property(_get_info, RecordOutput._set_info)  # type: ignore[assignment]

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
        info["active_rows"] = [name for bit, name in ((2, "field"), (1, "obstacles"), (0, "torque_limits"))
                               if mask >> bit & 1]


def daqp_word(flag: int) -> str:
    return DAQP_STATUS.get(int(flag), f"exitflag {int(flag)}")


class QPLayout:
    """One of the QP's layouts (the task hard, or relaxed) and the solver that solves it; the last
    answer as (x or None, status, iterations, solver)."""

    def __init__(self, ws: Workspace, buf: QPBuffers, solver: QPSolver) -> None:
        self.ws, self.buf, self.solver = ws, buf, solver
        self.nat = solver.native(buf) if type(solver) is DAQPSolver else None
        self.last: tuple[np.ndarray | None, str, int, str] = (None, "", 0, solver.name)

    def native_outcome(self, code: int) -> tuple[int, str, int]:
        """(code, status, iterations) of the native kernel's solve of this layout; a failed or rejected
        solve frees DAQP's workspace, so the next tick starts cold rather than from a failed working set
        (warm-started from one, DAQP was seen to report "solved" with the rows broken on every later tick
        of an infeasible stretch, where a cold start reports it infeasible)."""
        nat = self.nat
        assert nat is not None
        iters = int(nat.flag[1])
        if code == 0:
            self.last = (nat.x, "solved", iters, self.solver.name)
            return 0, "solved", iters
        if code in (1, 2):
            status = "nonfinite_problem"
        elif code == 4:  # DAQP said solved, the answer breaks a hard row: its working set is no warm start
            status = "inaccurate" if np.isfinite(nat.x).all() else "nonfinite_solution"
            nat.free()
        else:
            status = daqp_word(nat.flag[0])
            nat.free()
        self.last = (None, status, iters, self.solver.name)
        return code if code in (1, 2) else 3, status, iters

    def solve(self, deadline: float, *, terms_done: bool, l1: float | None = None) -> tuple[int, str, int]:
        """The law's terms (unless ``terms_done``) and this layout's rows, solved within what is left of
        the budget, judged as a hard answer when ``l1`` (the task's ℓ₁ weight) is given
        (:meth:`TaskRelaxation.judge`), then checked (:func:`qpctl.kernels.finish.qp_finish` writes τ,
        q̈ and the record when it holds); build and solve times [µs] into the record (added to an
        earlier attempt's when ``terms_done``). Returns (code, status, iterations), code 0: solved and
        accepted; 1: M not positive definite; 2: non-finite problem; 3: failed, timed out or refused."""
        ws, buf, solver, nat = self.ws, self.buf, self.solver, self.nat
        rec, s = ws.rec, ws.layout.scalars
        left_us = math.inf
        if deadline != math.inf:
            left_us = (deadline - time.perf_counter()) * 1e6
            if nat is not None:
                nat.set_time_limit(max(left_us * 1e-6, 1e-9))
            else:
                solver.set_time_limit(max(left_us, 0.0))
        build0, solve0 = (rec[s + codes.R_BUILD_US], rec[s + codes.R_SOLVE_US]) if terms_done else (0.0, 0.0)
        t0 = time.perf_counter()
        code = (K.qp_rebuild if terms_done else K.qp_terms_and_build)(ws.work, buf.H, buf.f, buf.rows, buf.bu, buf.bl)
        t1 = time.perf_counter()
        rec[s + codes.R_BUILD_US], rec[s + codes.R_SOLVE_US] = build0 + (t1 - t0) * 1e6, solve0
        if code or left_us <= 0:
            status = "nonfinite_problem" if code else "time_limit"
            self.last = (None, status, 0, solver.name)
            return code or 3, status, 0
        x: np.ndarray | None
        if nat is not None:
            flag = 1 if nat.ready else nat.setup()
            if flag < 0:  # DAQP could not even set the QP up (its exit flag says why)
                nat.flag[0], nat.flag[1] = flag, 0
            elif K.native_solve(nat.dq) <= 0:
                nat.free()
            x, status, iters = (nat.x, "solved", int(nat.flag[1])) if nat.flag[0] > 0 else (None, daqp_word(nat.flag[0]),
                                                                                           int(nat.flag[1]))
        elif type(solver) is DAQPSolver:
            x, status, iters = solver.solve_buffers(buf.H, buf.f, buf.rows, buf.bu, buf.bl, buf.sense)
        else:
            sol = checked_solve(solver, buf.problem, deadline, check=False)
            x, status, iters = (sol.x if sol.found else None), sol.status, sol.iterations
        if x is not None and l1 is not None and np.isfinite(x).all():
            refusal = TaskRelaxation.judge(buf.problem, x, l1, SOLUTION_RTOL)
            if refusal:  # feasible, the hard QP's optimum, but not the relaxed QP's
                status, x = refusal, None
        if x is not None and not K.qp_finish(ws.work, x, buf.rows, buf.bu, buf.bl, SOLUTION_RTOL, False):
            # The solver's own test runs on its scaled problem: a row it scaled up (say nᵀJ_p ≈ 1e-5
            # at a link's fixed base) can be violated by m/s² in our units while it reports "solved".
            status = "inaccurate" if np.isfinite(x).all() else "nonfinite_solution"
            x = None
            if nat is not None:
                nat.free()
        rec[s + codes.R_SOLVE_US] = solve0 + (time.perf_counter() - t1) * 1e6
        if x is not None:
            rec[s + codes.R_ITERATIONS] = iters
        self.last = (x, status, iters, solver.name)
        return (0 if x is not None else 3), status, iters
