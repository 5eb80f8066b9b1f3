"""The QP controller's compiled path: the standard tasks and constraints, on the tick's kernels.

The kernels write the cost and rows in place into DAQP's layout (:class:`qpctl.tick.QPBuffers`,
one layout with the task's slack and one without) and check the answer. Two ways through a tick:

* **one kernel call** on DAQP's C API (no tick budget; :func:`qpctl.kernels.tick.tick_qp_native_hard_first`):
  the state, the law's terms, the rows, DAQP's solve and the check — with the task hard first where
  :class:`~qpctl.controllers.relaxation.TaskRelaxation` says so, the relaxed QP otherwise;
* **stage by stage** (a tick budget, another solver, or DAQP without its C API): the state, then each
  QP the relaxation policy asks for, its rows built by a kernel, solved within what is left of the
  budget (the other solvers through a :class:`~qpctl.qp.Problem` of views onto the same arrays) and
  checked by a kernel.

A failed solve goes to :class:`~qpctl.controllers.qp_failure.Failures` on snapshots of the tick.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from qpctl.controllers.base import (
    IDLE_REC_REFS,
    IDLE_REFS,
    NO_RECORD,
    SPARE_REFS,
    call_compiling,
    fast_state,
    lock_compilation,
    plain_vectors,
)
from qpctl.controllers.qp_failure import Failures
from qpctl.controllers.qp_layout import QPLayout, QPOutput, daqp_word
from qpctl.controllers.relaxation import REFUSALS, TaskRelaxation
from qpctl.errors import InvalidStateError
from qpctl.fallbacks import FallbackContext
from qpctl.kernels import codes
from qpctl.kernels import tick as K
from qpctl.kernels.native_qp import new_native_qp, shortcut_scratch
from qpctl.law import LawGains
from qpctl.outcome import SOLUTION_RTOL
from qpctl.qp import Problem, Solution
from qpctl.solvers.base import QPSolver
from qpctl.tick import QPBuffers, Workspace, rigid_pass

_now = time.perf_counter
getrefcount = sys.getrefcount
IN_KERNEL = (-1.0, -1.0, -1.0, -1.0)  # a one-call tick's stage times: every one measured in its kernel


class CompiledTick:
    """The QP tick on the kernels (module docstring). ``solvers``: the hard layout's and the relaxed
    one's (warm starts of their own); ``mode``: ``controller.task_relaxation``; ``budget_us()``: the
    tick budget [µs] (0: none); ``state(q, v, t)`` runs the tick's state in Python (the controller's,
    with J̇ for the law when it needs it); ``bad_state`` raises the state's error."""

    def __init__(self, ws: Workspace, solvers: tuple[QPSolver, QPSolver], mode: str, budget_us: Callable[[], float],
                 gains: LawGains, failures: Failures, state: Callable[[np.ndarray, np.ndarray, float], Any],
                 bad_state: Callable[[np.ndarray, np.ndarray, float], None]) -> None:
        assert ws.spec is not None and ws.hard is not None and ws.relaxed is not None
        self.ws, self.gains, self.failures, self.budget_us = ws, gains, failures, budget_us
        self._state, self._bad_state = state, bad_state
        slack = ws.relaxed.relaxed  # without a slack the relaxed layout is the hard one
        self.hard = QPLayout(ws, ws.hard, solvers[0])
        self.relaxed = QPLayout(ws, ws.relaxed, solvers[1])
        native = self.relaxed.nat is not None and self.hard.nat is not None
        self._nat_h, self._nat_r = self.hard.nat, self.relaxed.nat  # (fast_step's: DAQP's C API, when native)
        self.relax = TaskRelaxation(mode if slack else "always", solvers[1].name, native)
        self.native_args: tuple[Any, ...] | None = None  # the one-call kernel's arguments after the state
        if native:
            nh, nr = self.hard.nat, self.relaxed.nat
            assert nh is not None and nr is not None
            self.native_args = (*nh.kernel_args, nh.lam, *nr.kernel_args, SOLUTION_RTOL, float(ws.spec.slack_l1),
                                *shortcut_scratch(nh.x.shape[0], ws.n))
        # the one-call tick's QP arguments as one compiled argument (qpctl.kernels.native_qp)
        self.packed: Any = None if self.native_args is None else new_native_qp(ws.work, *self.native_args)
        self._last_problem: Problem | None = None
        self._last: tuple[np.ndarray | None, str, int, str] | Solution | None = None
        self._last_lay: QPLayout | None = None  # the layout whose answer a fast tick used (last, when read)
        self._slack_at = ws.layout.scalars + codes.R_SLACK
        # a fast tick's words (QPOutput): iterations None, read from the record
        self._words_hard = ("solved", None, self.hard.solver.name, self.relax.hard_first(True), True, "", None, False)
        self._words_relaxed = ("solved", None, self.relaxed.solver.name, self.relax.hard_first(True), False, "", None,
                               False)
        self._out: QPOutput | None = None  # the last output, reused when nobody else holds it
        self._spare: QPOutput | None = None  # the one before, reused when nobody else holds it (fast_step)
        # K.tick_qp_at's compiled entry point for these argument types, and its first two: the packed
        # QP's numba type and address (held: self.packed) — qpctl.kernels.tick.address_entry
        self._entry: Any = None
        self._ty: Any = None
        self._addr = 0

    def reset(self) -> None:
        self.relax.reset()

    def _output(self, compute_us: float, stages: tuple[float, float, float, float], ok: bool,
                words: tuple[Any, ...], extra: dict[str, Any] | None) -> QPOutput:
        """The tick's output: the last one, its record overwritten, when only this tick and the
        controller still refer to it and to its record (CPython's reference counts say so: the caller
        kept neither it nor a view of its arrays) — nothing is allocated; else a new one."""
        out, ws = self._out, self.ws
        if extra is None and out is not None and sys.getrefcount(out) <= IDLE_REFS and \
                sys.getrefcount(out._rec) <= IDLE_REC_REFS:
            np.copyto(out._rec, ws.rec)
            out.renew_qp(compute_us, stages, ok, words)
            return out
        out = QPOutput(ws.rec.copy(), ws.layout, extra, compute_us, stages, ok, words)
        self._spare, self._out = self._out, out  # (the last one, kept by the caller, may be the spare next)
        return out

    def fast_step(self, q: Any, v: Any, t: Any, start: float) -> QPOutput | None:
        """The common tick in as few Python statements as it takes, or None (before anything ran that
        :meth:`step` would not run again) when this tick is not one: rigid_pass, then the one-call
        kernel through its compiled entry point (q and v float64 C vectors, t a float, both DAQP
        workspaces set up; the caller, :meth:`QPController.step`, has seen no tick budget), then the
        output. A tick whose kernel reports anything but a solve on the first QP it tried goes on in
        :meth:`_after_native`, as :meth:`step`'s would; one before the entry point exists (the first),
        or of other types, goes to :meth:`step`.

        The output is one of two that take turns (:data:`~qpctl.controllers.base.IDLE_REFS`): the
        last one when the caller dropped it, else the one before when the caller dropped that — a loop
        that keeps each tick's output until the next (``out = ctrl.step(...)``) allocates nothing;
        one that keeps more gets new ones."""
        entry, ws = self._entry, self.ws
        if entry is None or ws.lie:  # (an angle view of q: step's)
            return None
        py_rigid = ws.py_rigid  # (else the kernel runs Pinocchio's pass itself: qpctl.kernels.pin_native)
        if py_rigid:
            try:
                rigid_pass(ws.model, ws.data, q, v)
            except Exception:  # noqa: BLE001 — not a state Pinocchio takes: step() checks it and says why
                return None
        # the stages' times: all the kernel's (read from the record), or Pinocchio's pass in Python first
        stages = (_now() - start, -1.0, -1.0, -1.0) if py_rigid else IN_KERNEL
        if not (isinstance(t, float) and plain_vectors(q, v)):
            return None
        relax, nat_h = self.relax, self._nat_h
        try_hard = relax.always_hard or (relax.skip_rule and relax._try_hard)
        if not self._nat_r.ready or (try_hard and not nat_h.ready):  # type: ignore[union-attr]
            return None
        if ws._field is not None:
            ws.sync_field()
        out, turn = self._out, False  # the last output, else the one before, when nobody else holds it
        if out is None or getrefcount(out) > IDLE_REFS or getrefcount(out._rec) > IDLE_REC_REFS:
            out, turn = self._spare, True
            if out is None or getrefcount(out) > SPARE_REFS or getrefcount(out._rec) > IDLE_REC_REFS:
                out = None
        rec = np.empty(ws.rec.shape[0]) if out is None else out._rec  # (allocated only when both are kept)
        code, hard, hard_next = entry(self._ty, self._addr, q, v, t, try_hard, rec)
        if code or hard > 0:
            out = None  # (its record untouched; the tick's output is written by _after_native)
            code, hard = self._state_python(code, hard, q, v, t, try_hard)
            if hard in (3, 4):
                nat_h.free()  # type: ignore[union-attr]  # as in _native: no warm start from a failed working set
            return self._after_native(code, hard, stages, q, start)
        used_hard = hard == 0
        if relax.skip_rule:  # the skip rule's memory (its rule, hard_next, ran in the kernel)
            relax._try_hard = hard_next
        self._last_lay = self.hard if used_hard else self.relaxed  # last and last_problem, when read
        words = self._words_hard if used_hard else self._words_relaxed
        if out is None:
            out = QPOutput(rec, ws.layout, None, 0.0, stages, True, words)
        else:
            out._extra = out._info = None
            out._stages, out._solved, out._words = stages, True, words
        if turn:
            self._spare, self._out = self._out, out
        out.compute_us = (_now() - start) * 1e6
        return out

    @property
    def last(self) -> tuple[np.ndarray | None, str, int, str] | Solution | None:
        """The last tick's answer: (x or None, status, iterations, solver), or the fallback's Solution."""
        lay = self._last_lay
        if lay is not None:  # a fast tick's: read now, before the next tick overwrites it
            self._last_lay = None
            nat = lay.nat
            assert nat is not None
            lay.last = self._last = (nat.x, "solved", int(nat.flag[1]), lay.solver.name)
            self._last_problem = lay.buf.problem
        return self._last

    @last.setter
    def last(self, value: tuple[np.ndarray | None, str, int, str] | Solution | None) -> None:
        self._last_lay, self._last = None, value

    @property
    def last_problem(self) -> Problem | None:
        """The last tick's QP (views onto the workspace's arrays)."""
        if self._last_lay is not None:
            self.last  # noqa: B018 — resolves the fast tick's lazy answer and problem
        return self._last_problem

    @last_problem.setter
    def last_problem(self, value: Problem | None) -> None:
        if self._last_lay is not None:
            self.last  # noqa: B018
        self._last_problem = value

    def step(self, q: np.ndarray, v: np.ndarray, t: float, start: float) -> QPOutput:
        """One tick (module docstring); ``start``: when the controller's step began (the budget's
        clock, and ``compute_us``'s). On the one-call path nothing checks a good state in Python: the
        compiled tick's dispatcher takes only float64 arrays and a float, the kernel checks their
        length and finiteness, and :class:`~qpctl.errors.InvalidStateError` is raised only when it
        reports a bad state."""
        ws = self.ws
        ws.sync_field()  # the depth map's newest snapshot (a reference swap; nothing without a map)
        budget = self.budget_us()
        one_call = self.packed is not None and budget <= 0
        relax = self.relax
        hard_first, try_hard = relax.hard_first(one_call), relax.try_hard(one_call)
        relaxed_iters: int | None = None
        deadline = start + budget * 1e-6 if budget > 0 else math.inf
        if one_call:
            code, hard, stages, q = self._native(q, v, t, try_hard)
            return self._after_native(code, hard, stages, q, start)
        else:
            q, v, t = fast_state(q, v, t, ws.n, ws.nq)
            self._state(q, v, t)
            stages = (ws.pin_s, ws.state_s, -1.0, -1.0)
            lay, refusal = (self.hard if try_hard else self.relaxed), ""
            code, status, iters = lay.solve(deadline, terms_done=False,
                                            l1=float(ws.spec.slack_l1) if try_hard else None)  # type: ignore[union-attr]
            used_hard = try_hard and code == 0
            if try_hard and code == 3:  # the task conflicts with the hard rows, or its answer was refused: relax
                refusal, lay = status, self.relaxed
                code, status, relaxed_iters = lay.solve(deadline, terms_done=True)
        return self._finish(code, status, iters, lay, used_hard, refusal, relaxed_iters, hard_first, one_call, stages,
                            deadline, start, q)

    def _after_native(self, code: int, hard: int, stages: tuple[float, float, float, float], q: np.ndarray,
                      start: float) -> QPOutput:
        """The one-call tick after its kernel: what became of the hard QP and the answer used, the
        relaxation's memory, a failure's fallback, the output."""
        used_hard = hard == 0
        lay = self.hard if used_hard else self.relaxed
        code, status, iters = lay.native_outcome(code)
        refusal = "" if hard <= 0 else REFUSALS.get(hard) or daqp_word(self.hard.nat.flag[0])  # type: ignore[union-attr]
        return self._finish(code, status, iters, lay, used_hard, refusal, None, self.relax.hard_first(True), True,
                            stages, math.inf, start, q)

    def _finish(self, code: int, status: str, iters: int, lay: QPLayout, used_hard: bool, refusal: str,
                relaxed_iters: int | None, hard_first: bool, one_call: bool,
                stages: tuple[float, float, float, float], deadline: float, start: float,
                q: np.ndarray) -> QPOutput:
        ws, relax = self.ws, self.relax
        if code == 1:
            raise InvalidStateError(f"the inertia matrix is not positive definite at q={np.asarray(q).tolist()}")
        self.last_problem, self.last = lay.buf.problem, lay.last
        ok = code == 0
        relax.after(one_call, used_hard, ok, float(ws.rec[ws.layout.scalars + codes.R_SLACK]))
        words = (status, iters, lay.solver.name, hard_first, used_hard, refusal, relaxed_iters, status == "time_limit")
        extra: dict[str, Any] | None = None
        if not ok:
            extra = {"status": status, "iterations": iters, "solver": lay.solver.name}
            relax.report(extra, hard_first, used_hard, refusal, relaxed_iters)
            if status == "time_limit":
                extra["budget_exhausted"] = True
            self._fall_back(lay.buf, status, extra, deadline)
        return self._output((time.perf_counter() - start) * 1e6, stages, ok, words, extra)

    def _native(self, q: Any, v: Any, t: Any,
                try_hard: bool) -> tuple[int, int, tuple[float, float, float, float], np.ndarray]:
        """The tick on DAQP's C API: one kernel call (:func:`qpctl.kernels.tick.tick_qp`) when both
        DAQP workspaces are set up and the state needs no Python; else the state, DAQP's set-up
        (:meth:`_setup`) and the same kernel after it. Returns (code, hard, stages, q): the kernel's
        code, what became of the hard QP (−1 not tried, 0 used, 3 DAQP failed, 4 rejected by the
        check of its rows, 7 not the relaxed QP's answer), and q as the kernels took it."""
        ws = self.ws
        nat_h, nat_r = self.hard.nat, self.relaxed.nat
        assert nat_h is not None and nat_r is not None
        if ws.fast and nat_r.ready and (nat_h.ready or not try_hard):
            try:
                if not isinstance(t, float):  # a bool or an int would pass numba's conversions
                    raise TypeError(t)
                t0 = time.perf_counter()
                ws.before_kernel(q, v)
                t1 = time.perf_counter()
                qk = ws.joint_view(q)
                entry = self._entry
                if entry is not None and plain_vectors(qk, v):
                    code, hard, _ = entry(self._ty, self._addr, qk, v, t, try_hard, NO_RECORD)
                else:
                    code, hard, _ = K.tick_qp(self.packed, qk, v, t, try_hard, NO_RECORD)
            except Exception:  # noqa: BLE001 — not two float64 arrays and a float: check, convert, once more
                q, v, t = fast_state(q, v, t, ws.n, ws.nq)  # InvalidStateError if it cannot
                t0 = time.perf_counter()
                ws.before_kernel(q, v)
                t1 = time.perf_counter()
                code, hard, _ = call_compiling(K.tick_qp, self.packed, ws.joint_view(q), v, t, try_hard,
                                               NO_RECORD)
            lock_compilation(K.tick_qp)
            if self._entry is None:
                found = K.address_entry(K.tick_qp_at, self.packed, try_hard=True, out=NO_RECORD)
                self._entry, self._ty, self._addr = found or (None, None, 0)
            code, hard = self._state_python(code, hard, q, v, t, try_hard)
            stages = (t1 - t0 if ws.py_rigid else -1.0, -1.0, -1.0, -1.0)
        else:
            q, v, t = fast_state(q, v, t, ws.n, ws.nq)
            self._state(q, v, t)
            code, hard_ready = self._setup(try_hard)
            hard = -1
            if code == 0:
                code, hard = K.qp_tick_native_hard_first(self.packed, try_hard and hard_ready)
            if try_hard and not hard_ready:
                hard = 3  # DAQP could not set the hard QP up (its exit flag in nat_h.flag)
            stages = (ws.pin_s, ws.state_s, -1.0, -1.0)  # the set-up is in "other"
        if hard in (3, 4):
            nat_h.free()  # a failed or rejected working set is no warm start: cold the next time it is tried
        return code, hard, stages, q

    def _state_python(self, code: int, hard: int, q: np.ndarray, v: np.ndarray, t: float,
                      try_hard: bool) -> tuple[int, int]:
        """The one-call kernel's (code, hard) after Python finished a state it waited for (STATE_PYTHON:
        python-fcl's pairs, a look-ahead drift) and the rest of the tick ran; InvalidStateError for
        a state it refused."""
        if code == codes.STATE_PYTHON:
            self.ws.finish_state(q, v, t)
            return K.qp_tick_native_hard_first(self.packed, try_hard)  # type: ignore[no-any-return]
        if code < 0:
            if code == codes.BAD_SHAPE:
                raise InvalidStateError(f"q and v must have shapes ({self.ws.nq},) and ({self.ws.n},), "
                                        f"got {np.shape(q)} and {np.shape(v)}")
            self._bad_state(q, v, t)
        return code, hard

    def _setup(self, try_hard: bool) -> tuple[int, bool]:
        """DAQP's workspaces set up where they are not (the first tick, and after a failure freed one):
        each QP's arrays written from this tick's state, then DAQP's set-up on them. Returns (code,
        whether the hard QP is ready): code as :meth:`QPLayout.solve`'s (0: both go to the kernel)."""
        ws, hb, rb = self.ws, self.hard.buf, self.relaxed.buf
        nat_h, nat_r = self.hard.nat, self.relaxed.nat
        assert nat_h is not None and nat_r is not None
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

    def _fall_back(self, buf: QPBuffers, status: str, info: dict[str, Any], deadline: float) -> None:
        """The solve failed: strict mode raises; else the fallback chain on snapshots of the tick (the
        rare path, in Python); the torque it settles on goes into the workspace's record."""
        ws = self.ws
        self.failures.raise_if_strict(buf.problem, status, info, None)
        t0 = time.perf_counter()
        state, terms = ws.snapshot(), ws.terms()
        relaxed = self.relaxed.buf

        def build_relaxed() -> Problem:
            K.qp_build(ws.work, relaxed.H, relaxed.f, relaxed.rows, relaxed.bu, relaxed.bl)
            return relaxed.problem

        def paper_qdd() -> np.ndarray:  # the paper law on the tick's terms, by the kernel the paper law's tick runs
            K.closed_form(ws.work, True)
            return ws.qdd.copy()

        ctx = FallbackContext(state, terms, self.gains, buf.problem, self.failures.window(state.t), deadline,
                              None if buf.relaxed else build_relaxed, paper_qdd=paper_qdd)
        tau, qdd, problem, sol = self.failures.fall_back(ctx, None, status, info)
        self.last_problem = problem
        if sol is not None:
            self.last = sol
        ws.qdd[:], ws.tau[:] = qdd, tau
        K.write_record(ws.work, terms.singular)
        info["fallback_us"] = (time.perf_counter() - t0) * 1e6  # the snapshot included
