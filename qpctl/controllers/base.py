"""The controller interface every law implements — the one thing another simulator must call.

    tau = controller.torque(q, v, t)

* ``q`` joint positions [rad] (or [m] for prismatic joints), shape (n,), in the order of
  ``controller.robot.joint_names`` (Pinocchio's order);
* ``v`` joint velocities [rad/s], shape (n,), same order;
* ``t`` time [s] on the reference path's clock;
* returns joint torques [N·m], shape (n,), same order; hold them constant over the control period.

Call it once per control period, in time order, with the measured state (no look-ahead, no
integrator stages); call :meth:`Controller.reset` before starting a new run (the QP keeps warm
starts). The law uses its own model (``controller.robot``: inertias, gravity) for M and N, so the
simulated robot must be that robot. A simulator with another joint order or extra joints maps
by name: :class:`qpctl.adapters.JointMap` (a mismatch is a ConfigError listing both sets).

:meth:`Controller.step` returns a :class:`ControlOutput` with the torque and the per-tick
diagnostics (tracking error, null-space error, singularity flag, solver statistics).
"""

from __future__ import annotations

import dataclasses
import enum
import math
import time
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from qpctl.dynamics import Dynamics
from qpctl.errors import ConfigError, InvalidStateError
from qpctl.geometry.obstacles import Obstacle
from qpctl.kernels import codes
from qpctl.law import LawGains
from qpctl.paths import PosePath, Reference, WaypointPath
from qpctl.robot.model import RobotModel
from qpctl.state import TickState, validate_state
from qpctl.tick import RecordLayout, Workspace
from qpctl.warmup import warmup


class TickStatus(enum.Enum):
    """What produced a tick's torque."""

    CLOSED_FORM = "closed_form"  # a closed-form law (paper, hsu)
    SOLVED = "solved"  # the QP, solved and its answer checked against the hard rows
    FALLBACK = "fallback"  # the QP failed; an entry of the fallback chain (info["fallback"]) gave it
    CUSTOM = "custom"  # a law written in Python that did not say


@dataclass
class ControlOutput:
    """One tick's command and diagnostics."""

    tau: np.ndarray  # (n,) joint torques [N·m]
    qdd: np.ndarray  # (n,) commanded joint accelerations [rad/s²]
    ref: Reference  # x_d, ẋ_d, ẍ_d
    x: np.ndarray  # (m,) task point position [m]
    e_null: np.ndarray  # (n,) null-space velocity error [rad/s] (zeros where the law has none)
    clearance: float  # least link–obstacle distance seen by the controller [m] (inf if none within reach)
    singular: bool  # a pseudo-inverse was damped at this tick
    compute_us: float = 0.0  # wall time of the whole tick [µs]
    info: dict[str, Any] = field(default_factory=dict)  # law-specific: QP status, iterations, timings
    status: TickStatus = TickStatus.CUSTOM


class RecordOutput(ControlOutput):
    """A tick's output read from its record: one float64 array (:class:`~qpctl.tick.RecordLayout`),
    copied once per tick; the arrays are views into it and ``info`` is built on first access."""

    def __init__(self, rec: np.ndarray, layout: RecordLayout, info: dict[str, Any] | None = None,
                 compute_us: float = 0.0, stages: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)) -> None:
        # no dataclass __init__: the fields are properties reading the record
        self._rec, self._layout, self._extra = rec, layout, info
        self._info: dict[str, Any] | None = None
        self._stages = stages  # [s]: Pinocchio, the state kernel, the law (and QP rows), the solve;
        # negative: read from the record, where the kernel measured it [µs]
        self.compute_us = compute_us

    tau = property(lambda self: self._rec[self._layout.tau])  # type: ignore[assignment]
    qdd = property(lambda self: self._rec[self._layout.qdd])  # type: ignore[assignment]
    x = property(lambda self: self._rec[self._layout.x])  # type: ignore[assignment]
    e_null = property(lambda self: self._rec[self._layout.e_null])  # type: ignore[assignment]

    @property
    def ref(self) -> Reference:  # type: ignore[override]
        lay = self._layout
        return Reference(self._rec[lay.x_ref], self._rec[lay.xd_ref], self._rec[lay.xdd_ref])

    @property
    def clearance(self) -> float:  # type: ignore[override]
        return float(self._rec[self._layout.scalars + codes.R_CLEARANCE])

    @property
    def singular(self) -> bool:  # type: ignore[override]
        return bool(self._rec[self._layout.scalars + codes.R_SINGULAR])

    @property
    def status(self) -> TickStatus:  # type: ignore[override]
        return TickStatus.CLOSED_FORM

    @property
    def iterations(self) -> int:
        """The QP solver's iterations this tick (0 for the closed forms)."""
        return int(self._rec[self._layout.scalars + codes.R_ITERATIONS])

    def scalar(self, index: int) -> float:
        """The record's scalar ``index`` (one of :mod:`qpctl.kernels.codes`' R_* constants)."""
        return float(self._rec[self._layout.scalars + index])

    def _get_info(self) -> dict[str, Any]:
        """Per-tick diagnostics (stage timings [µs], pairs, and the law's own), built on first access."""
        if self._info is None:
            pin_s, state_s, build_s, solve_s = self._stages
            r, s = self._rec, self._layout.scalars
            if pin_s < 0:  # the rigid-body pass ran inside the tick's kernel (qpctl.kernels.pin_native)
                pin_s = r[s + codes.R_RIGID_US] * 1e-6
            if state_s < 0:  # measured inside the tick's kernel and kept in the record [µs]
                state_s = r[s + codes.R_STATE_US] * 1e-6
            if build_s < 0:
                build_s, solve_s = r[s + codes.R_BUILD_US] * 1e-6, r[s + codes.R_SOLVE_US] * 1e-6
            info: dict[str, Any] = {"rigid_us": pin_s * 1e6, "state_us": (pin_s + state_s) * 1e6,
                                    "build_us": float(build_s) * 1e6, "pairs": int(r[s + codes.R_PAIRS])}
            if solve_s:
                info["solve_us"] = float(solve_s) * 1e6
            if self._extra:
                info.update(self._extra)
            self._decode(info)
            self._info = info
        return self._info

    def renew(self, compute_us: float, stages: tuple[float, float, float, float]) -> None:
        """This output for a new tick whose record the caller has copied into it (a compiled tick
        reuses its last output when the caller kept neither it nor a view of its arrays)."""
        self._extra, self._info, self._stages, self.compute_us = None, None, stages, compute_us

    def _set_info(self, value: dict[str, Any]) -> None:
        self._info = value

    info = property(_get_info, _set_info)  # type: ignore[assignment]

    def _decode(self, info: dict[str, Any]) -> None:
        """Add the law's own entries from the record (none for the closed forms)."""


#: sys.getrefcount of a tick's output that only the tick still holds: the controller's own reference
#: and its ``last``, the local name and getrefcount's argument; of the output's record: the output's
#: and the argument. A compiled tick reuses such an output (its record overwritten): nothing allocated.
IDLE_REFS, IDLE_REC_REFS = 4, 2
#: sys.getrefcount of the output before the last (the compiled ticks keep two that take turns) that
#: only the tick holds: the controller's spare slot, the local name and getrefcount's argument. A loop
#: that keeps each output until the next tick (``out = ctrl.step(...)``) holds the last one while the
#: next tick runs, never the one before: the two alternate and nothing is allocated.
SPARE_REFS = 3
#: What a one-call kernel is given as ``out`` on a tick whose output Python writes itself: an empty
#: record, so the kernel copies nothing (qpctl.kernels.tick.copy_record).
NO_RECORD = np.empty(0)


_LOCKED: set[int] = set()  # the kernels that compile no more signatures in this process (by id)


def lock_compilation(kernel: Any) -> None:
    """After its first call, a one-call tick's kernel takes only the types it was compiled for: any
    other argument is a TypeError at dispatch (which the controller turns into :func:`fast_state`'s
    checks and conversions), never a compilation inside a control loop."""
    if id(kernel) not in _LOCKED:
        kernel.disable_compile()
        _LOCKED.add(id(kernel))


def call_compiling(kernel: Any, *args: Any) -> Any:
    """``kernel(*args)``, allowed to compile or load a signature (say, a workspace of other types)."""
    kernel.disable_compile(False)
    try:
        return kernel(*args)
    finally:
        if id(kernel) in _LOCKED:
            kernel.disable_compile()


_F64 = np.dtype(np.float64)
_ND = np.ndarray
_STRIDES = (8,)  # one dimension, its float64 entries adjacent: C-contiguous


def plain_vectors(q: Any, v: Any) -> bool:
    """q and v as a one-call tick's compiled entry point (:func:`qpctl.kernels.tick.address_entry`)
    takes them unchecked: float64, one-dimensional, C-contiguous ndarrays (anything else goes through
    numba's dispatcher).
    The strides say both of the last two at once (a tuple, where ``flags`` builds an object)."""
    return (type(q) is _ND and type(v) is _ND and q.dtype is _F64 and v.dtype is _F64
            and q.strides == _STRIDES and v.strides == _STRIDES)


def fast_state(q: Any, v: Any, t: Any, n: int, nq: int | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """(q, v, t) as the kernels take them: contiguous float64 arrays of n and a float. The common case
    (already so) costs a few attribute checks; anything else goes through :func:`validate_state`,
    which raises :class:`InvalidStateError` for what it cannot accept. Finiteness of q and v is
    checked by the kernels (:meth:`Controller._state`)."""
    nq = n if nq is None else nq
    if (type(q) is np.ndarray and type(v) is np.ndarray and q.dtype == np.float64 and v.dtype == np.float64
            and q.shape == (nq,) and v.shape == (n,) and q.flags.c_contiguous and v.flags.c_contiguous
            and isinstance(t, float) and math.isfinite(t)):
        return q, v, t
    q, v, t = validate_state(q, v, t, n, nq)
    return np.ascontiguousarray(q), np.ascontiguousarray(v), t


class Controller(ABC):
    """Base class: owns the robot, the reference path, the scene, and the per-tick state computer.

    Subclasses implement :meth:`control`, which reads a :class:`TickState` and returns a
    :class:`ControlOutput`.
    """

    kind: str = "controller"
    solver: str = "closed-form"

    def __init__(self, robot: RobotModel, path: WaypointPath, obstacles: Sequence[Obstacle] = (),
                 gains: LawGains | None = None, *, broadphase: bool | None = None) -> None:
        self.robot = robot
        self.path = path
        self.obstacles = list(obstacles)
        self.gains = gains or LawGains()
        if any(o.v_ref is not None for o in self.obstacles):
            own = tuple(float("nan") if o.v_ref is None else float(o.v_ref) for o in self.obstacles)
            self.gains = dataclasses.replace(self.gains, obstacle_v_ref=own)
        if path.dim != robot.m_position:
            raise ConfigError(f"path points have {path.dim} coordinates but the robot's task has "
                              f"{robot.m_position}", key="path.waypoints")
        if robot.m_orientation and not isinstance(path, PosePath):
            raise ConfigError("an orientation task needs a PosePath (a rotation at every point)",
                              key="path.orientations")
        if robot.m_orientation:
            path.check_frames(len(robot.oriented_frames))  # type: ignore[attr-defined]
        if robot.m_orientation and self.gains.jdot_en:
            raise ConfigError("the J̇e_N term is implemented for position tasks only", key="controller.jdot_en")
        self.broadphase = broadphase
        self.dynamics = Dynamics(robot, self.obstacles, cutoff=self.cutoff, broadphase=broadphase)
        self.last: ControlOutput | None = None
        self._ws: Workspace | None = None
        self.warm = False  # warmup() has run

    @classmethod
    def from_config(cls, cfg: dict[str, Any], robot: RobotModel, path: WaypointPath,
                    obstacles: Sequence[Obstacle], gains: LawGains, *, broadphase: bool | None = None
                    ) -> Controller:
        """Built from a scenario's validated ``[controller]`` table (:mod:`qpctl.controllers.factory`);
        a kind with settings of its own beyond the law gains reads them from ``cfg``."""
        return cls(robot, path, obstacles, gains, broadphase=broadphase)

    def reference(self, state: TickState) -> Reference:
        """The task's reference at the state's time [s] (m rows): the path's point, then the
        orientation rows (:mod:`qpctl.orientation`), which depend on the state's orientation."""
        ref = self.path(state.t)
        if not self.robot.m_orientation:
            return ref
        from qpctl.orientation import orientation_reference

        assert isinstance(self.path, PosePath) and state.rotations is not None
        parts = [orientation_reference(self.robot, state.rotations[j], *self.path.orientation(state.t, j), frame=f)
                 for j, f in enumerate(self.robot.oriented_frames)]  # the kernel's too
        return Reference(*(np.concatenate([a, *(p[i] for p in parts)]) for i, a in enumerate(ref)))

    @property
    def cutoff(self) -> float:
        """Distance [m] beyond which link–obstacle pairs are not queried."""
        return self.gains.d_influence

    @property
    def n(self) -> int:
        return self.robot.nv

    # -- the compiled tick ------------------------------------------------------------------------
    def workspace(self) -> Workspace:
        """The arrays this controller's compiled tick runs on (built on first use)."""
        if self._ws is None:
            self._ws = self._make_workspace()
        return self._ws

    def _make_workspace(self) -> Workspace:
        """A law written in Python (:meth:`control`) may read any of the state, the barrier drift too."""
        return Workspace(self.robot, self.obstacles, self.path, self.gains, self.cutoff, broadphase=self.broadphase,
                         barrier_drift=True, native_rigid=True)

    def warmup(self) -> float:
        """Compile (or load from the on-disk cache) every kernel of the tick (:func:`qpctl.warmup.warmup`,
        once per process), build this controller's workspace and run two ticks at its home pose (the
        QP's first tick sets its solver up), then :meth:`reset`; returns the seconds it took. Call it
        before a real-time loop starts, so that no tick compiles, loads or allocates a workspace;
        ``qpctl warmup`` fills the on-disk cache ahead of time."""
        start = time.perf_counter()
        warmup()
        for k in range(2):
            self.step(self.robot.q_home.astype(float), np.zeros(self.n), 1e-3 * k)
        self.reset()
        self.warm = True
        return time.perf_counter() - start

    def _state(self, q: np.ndarray, v: np.ndarray, t: float) -> Workspace:
        """Run the tick's state on the workspace (after :func:`fast_state`); InvalidStateError if q or v
        is not finite or the dynamics overflow."""
        ws = self._ws if self._ws is not None else self.workspace()
        if ws.state(q, v, t) < 0:
            self._bad_state(q, v, t)
        if self.gains.jdot_en:
            ws.Jdot[:] = self.dynamics.task_jacobian_derivative(q, v)
        return ws

    @staticmethod
    def _bad_state(q: np.ndarray, v: np.ndarray, t: float) -> None:
        """Raise the InvalidStateError of a state the kernels refused (non-finite, or overflowing)."""
        if not (np.isfinite(q).all() and np.isfinite(v).all() and math.isfinite(t)):
            raise InvalidStateError(f"non-finite state: q={q.tolist()}, v={v.tolist()}, t={t}")
        raise InvalidStateError(f"the dynamics overflow at this state: q={q.tolist()}, v={v.tolist()}")

    def torque(self, q: np.ndarray, v: np.ndarray, t: float) -> np.ndarray:
        """Joint torques [N·m] for state (q, v) at time t [s] (see module docstring)."""
        return self.step(q, v, t).tau

    def step(self, q: np.ndarray, v: np.ndarray, t: float) -> ControlOutput:
        """One control tick: the state once (compiled), then the law :meth:`control` on a snapshot of it;
        records wall time in ``compute_us``. The built-in laws override this with compiled ticks."""
        start = time.perf_counter()
        q, v, t = fast_state(q, v, t, self.n, self.robot.nq)
        ws = self._state(q, v, t)
        state = ws.snapshot()
        t_state = time.perf_counter()
        out = self.control(state)
        end = time.perf_counter()
        out.compute_us = (end - start) * 1e6
        out.info.setdefault("state_us", (t_state - start) * 1e6)  # Pinocchio, the state kernel, the snapshot
        out.info.setdefault("rigid_us", ws.pin_s * 1e6)
        out.info["pairs"] = len(state.pairs)
        self.last = out
        return out

    @abstractmethod
    def control(self, state: TickState) -> ControlOutput:
        """The law: torques from the state of this tick."""

    def reset(self) -> None:
        """Forget anything kept between ticks (warm starts, filters)."""
        self.last = None
