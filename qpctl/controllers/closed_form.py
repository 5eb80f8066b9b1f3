"""The closed-form laws: the paper's (``paper``: resolved-acceleration control, inertia-weighted
pseudo-inverse) and Hsu–Hauser–Sastry's (``hsu``, the paper's "conventional unweighted algorithm").

The paper's law, its equations (paper numbering; the OCR's ``J^1`` is read as J⁺):

    a   = ẍ_d + K_v ė + K_p e − J̇ q̇                                           (7)
    J⁺  = W⁻¹Jᵀ(J W⁻¹ Jᵀ)⁻¹,  W = MᵀM (Kazerounian–Nedungadi), damped by SVD     (5), (6)
    e_N = (I − J_b⁺ J)(g − q̇),  J_b⁺ weighted by W_b = Σ J_iᵀ J_i (Ryu)          (12), (19)
    q̈₀  = −M⁻¹N + K_N e_N                                                       (18), (19)
    q̈   = J⁺(a [+ J̇ e_N]) + (I − J⁺J) q̈₀,   τ = M q̈ + N                       (19)

The sign of the M⁻¹N term is the one that lowers torque: with q̈₀ = −M⁻¹N the null-space part of
τ − N cancels the null-space part of the bias, so τ = M q̈ + N is the least-‖τ‖ choice in W's metric
for the given task acceleration. The bracketed J̇ e_N term is ``LawGains.jdot_en``, off by default:
it feeds e_N into the task and breaks eq. (11) without helping e_N decay (the argument and the
measurement are in :mod:`qpctl.law` and the README's "Paper reproduction").

:meth:`PaperController.step` runs the compiled tick (:func:`qpctl.kernels.tick.tick_closed_form`);
:meth:`PaperController.control` is the same law written with numpy on a :class:`TickState`
(:mod:`qpctl.law`), the reference the tests hold the compiled one against.

Hsu–Hauser–Sastry's law is the same structure with the Moore–Penrose pseudo-inverse everywhere
(W = W_b = I) and no torque term in the null space:

    q̈ = J⁺ a + (I − J⁺J) K_N e_N,   e_N = (I − J⁺J)(g − q̇),   τ = M q̈ + N

The top-level ``baselines`` package re-exports both under the paper's naming.
"""

from __future__ import annotations

import sys
import time
from typing import Any

import numpy as np

from qpctl.controllers.base import (
    IDLE_REC_REFS,
    IDLE_REFS,
    NO_RECORD,
    SPARE_REFS,
    Controller,
    ControlOutput,
    RecordOutput,
    TickStatus,
    call_compiling,
    fast_state,
    lock_compilation,
    plain_vectors,
)
from qpctl.errors import InvalidStateError
from qpctl.kernels import codes
from qpctl.kernels import tick as K
from qpctl.law import closed_form_acceleration, law_terms
from qpctl.state import TickState
from qpctl.tick import Workspace, rigid_pass

_now = time.perf_counter
getrefcount = sys.getrefcount


class PaperController(Controller):
    """The paper's inertia-weighted law (eq. 19); ``weighted = False`` gives Hsu's law."""

    kind = "paper"
    weighted = True

    _out: RecordOutput | None = None  # the last output, reused when nobody else holds it
    _spare: RecordOutput | None = None  # the one before, reused when nobody else holds it
    # K.tick_closed_form_at's compiled entry point for float64 C arrays, and its first two: the
    # workspace's numba type and address (held: _entry_ws, whose work it is) — qpctl.kernels.tick.address_entry
    _entry: Any = None
    _entry_ws: Workspace | None = None
    _ty: Any = None
    _addr = 0

    def _make_workspace(self) -> Workspace:
        return Workspace(self.robot, self.obstacles, self.path, self.gains, self.cutoff, broadphase=self.broadphase,
                         native_rigid=True)

    def step(self, q: np.ndarray, v: np.ndarray, t: float) -> ControlOutput:
        """One compiled tick: state, law terms and the closed form; ``compute_us`` its wall time. On the
        one-call path nothing checks a good state in Python (the kernel checks length and finiteness,
        the dispatcher the types; anything else goes through :func:`fast_state`'s checks)."""
        start = _now()
        ws, entry = self._ws, self._entry
        if entry is not None and ws is not None and ws is self._entry_ws and not ws.lie:  # the common tick first
            ok = True
            if ws.py_rigid:  # (else the kernel runs Pinocchio's pass itself: qpctl.kernels.pin_native)
                try:
                    rigid_pass(ws.model, ws.data, q, v)
                except Exception:  # noqa: BLE001 — not a state Pinocchio takes: the checks below say why
                    ok = False
            pin_s = _now() - start if ws.py_rigid else -1.0  # (else the kernel times the pass)
            if ok and isinstance(t, float) and plain_vectors(q, v):
                out, turn = self._out, False  # the last output, else the one before, when nobody else holds it
                if out is None or getrefcount(out) > IDLE_REFS or getrefcount(out._rec) > IDLE_REC_REFS:
                    out, turn = self._spare, True  # (base.SPARE_REFS: a loop keeping each until the next)
                    if out is None or getrefcount(out) > SPARE_REFS or getrefcount(out._rec) > IDLE_REC_REFS:
                        out = None
                rec = np.empty(ws.rec.shape[0]) if out is None else out._rec  # the kernel writes the record into it
                code = entry(self._ty, self._addr, q, v, t, self.weighted, rec)
                if code == 0:
                    if out is not None:
                        out._extra = out._info = None
                        out._stages = (pin_s, -1.0, -1.0, 0.0)
                    else:
                        out = RecordOutput(rec, ws.layout, None, 0.0, (pin_s, -1.0, -1.0, 0.0))
                    if turn:
                        self._spare, self._out = self._out, out
                    out.compute_us = (_now() - start) * 1e6
                    self.last = out
                    return out
                out = None  # (its record untouched: _after_kernel writes the tick's output)
                return self._after_kernel(code, q, v, t, start, (pin_s, -1.0, -1.0, 0.0))
        if ws is None:
            ws = self.workspace()
        if ws.fast:  # rigid_pass, then one kernel call (stage times measured in it)
            try:
                if not isinstance(t, float):  # a bool or an int would pass numba's conversions
                    raise TypeError(t)
                t0 = time.perf_counter()
                ws.before_kernel(q, v)
                t1 = time.perf_counter()
                qk = ws.joint_view(q)
                entry = self._entry
                if entry is not None and self._entry_ws is ws and plain_vectors(qk, v):
                    code = entry(self._ty, self._addr, qk, v, t, self.weighted, NO_RECORD)
                else:
                    code = K.tick_closed_form(ws.work, qk, v, t, self.weighted, NO_RECORD)
            except Exception:  # noqa: BLE001 — not two float64 arrays and a float: check, convert, once more
                q, v, t = fast_state(q, v, t, self.n, self.robot.nq)  # InvalidStateError if it cannot
                t0 = time.perf_counter()
                ws.before_kernel(q, v)
                t1 = time.perf_counter()
                code = call_compiling(K.tick_closed_form, ws.work, ws.joint_view(q), v, t, self.weighted, NO_RECORD)
            lock_compilation(K.tick_closed_form)
            if self._entry is None or self._entry_ws is not ws:  # (ws holds the work the address is of)
                self._entry_ws = ws
                found = K.address_entry(K.tick_closed_form_at, ws.work, weighted=self.weighted, out=NO_RECORD)
                self._entry, self._ty, self._addr = found or (None, None, 0)
            return self._after_kernel(code, q, v, t, start, (t1 - t0 if ws.py_rigid else -1.0, -1.0, -1.0, 0.0))
        q, v, t = fast_state(q, v, t, self.n, self.robot.nq)
        self._state(q, v, t)
        mid = time.perf_counter()
        code = K.closed_form_tick(ws.work, self.weighted)
        return self._after_kernel(code, q, v, t, start, (ws.pin_s, ws.state_s, time.perf_counter() - mid, 0.0))

    def _after_kernel(self, code: int, q: Any, v: Any, t: Any, start: float,
                      stages: tuple[float, float, float, float]) -> ControlOutput:
        """The tick after its kernel: a state Python must finish, a refused state's error, the output."""
        ws = self.workspace()
        if code == codes.STATE_PYTHON:
            ws.finish_state(q, v, t)
            t2 = time.perf_counter()
            code = K.closed_form_tick(ws.work, self.weighted)
            ws.rec[ws.layout.scalars + codes.R_BUILD_US] = (time.perf_counter() - t2) * 1e6
        elif code == codes.BAD_SHAPE:
            raise InvalidStateError(f"q and v must have shapes ({self.robot.nq},) and ({self.n},), "
                                    f"got {np.shape(q)} and {np.shape(v)}")
        if code < 0:
            self._bad_state(np.asarray(q, float), np.asarray(v, float), float(t))
        if code == 1:
            raise InvalidStateError(f"the inertia matrix is not positive definite at q={np.asarray(q).tolist()}")
        out = self._out
        if out is not None and sys.getrefcount(out) <= IDLE_REFS and sys.getrefcount(out._rec) <= IDLE_REC_REFS:
            np.copyto(out._rec, ws.rec)  # nobody kept the last output nor a view of it: reuse it
            out.renew((time.perf_counter() - start) * 1e6, stages)
        else:
            out = RecordOutput(ws.rec.copy(), ws.layout, None, (time.perf_counter() - start) * 1e6, stages)
            self._spare, self._out = self._out, out
        self.last = out
        return out

    def control(self, state: TickState) -> ControlOutput:
        ref = self.reference(state)
        terms = law_terms(state, ref, self.gains, weighted=self.weighted)
        qdd, singular = closed_form_acceleration(state, terms, self.gains, weighted=self.weighted)
        tau = state.M @ qdd + state.N
        return ControlOutput(tau=tau, qdd=qdd, ref=ref, x=state.x, e_null=terms.e_null,
                             clearance=state.clearance, singular=singular,
                             info={"g_norm": float(np.linalg.norm(terms.g))}, status=TickStatus.CLOSED_FORM)


class HsuController(PaperController):
    """Unweighted resolved-acceleration control with null-space velocity tracking (Hsu et al. 1989)."""

    kind = "hsu"
    weighted = False
