"""The per-tick state: every rigid-body quantity and distance a law needs, computed once.

A :class:`TickState` holds copies of one tick's arrays (M, N = C q̇ + G, the task and link Jacobians
and drifts, the link–obstacle pairs) that tasks, constraints and the Python reference laws
(:mod:`qpctl.law`) only read. The compiled tick's workspace makes them
(:meth:`qpctl.tick.Workspace.snapshot`; :class:`qpctl.dynamics.Dynamics` on a workspace of its own).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from qpctl.errors import InvalidStateError
from qpctl.geometry.distance import PairSet


@dataclass
class SelfPairState:
    """The self-collision pairs at one tick (copies): distance [m], ḣ's row nᵀ(J_p − J_q) (k, n),
    ḣ [m/s] and ḧ at q̈ = 0 [m/s²]."""

    distance: np.ndarray
    normal: np.ndarray
    row: np.ndarray
    hdot: np.ndarray
    drift: np.ndarray


@dataclass
class TickState:
    """Quantities at (q, v, t); n joints, m task coordinates, L links, k pairs within the cutoff.

    Units: positions [m], velocities [m/s], accelerations [m/s²], M [kg·m²], N [N·m].
    """

    t: float
    q: np.ndarray  # (n,)
    v: np.ndarray  # (n,)
    M: np.ndarray  # (n, n) joint-space inertia, symmetric
    N: np.ndarray  # (n,) C(q, q̇) q̇ + G(q)
    x: np.ndarray  # (m,) task point position
    xdot: np.ndarray  # (m,) task point velocity J q̇
    J: np.ndarray  # (m, n) task Jacobian
    drift: np.ndarray  # (m,) J̇ q̇
    link_jac: np.ndarray  # (L, 3, n) Jacobians of the links' mid-points (Ryu's W_b weighting)
    segments: np.ndarray  # (L, 2, 3) link capsule axes, world frame
    pairs: PairSet  # link–obstacle pairs within the cutoff
    pair_jac: np.ndarray  # (k, 3, n) Jacobians of the link witness points
    pair_drift: np.ndarray  # (k, 3) J̇_p q̇ of the link witness points
    clearance: float  # least signed distance over the pairs (inf when none within the cutoff)
    timing: dict[str, float] = field(default_factory=dict)  # stage wall times [µs]
    # where the task has orientation rows: every oriented task frame's rotation (F, 3, 3, world;
    # RobotModel.oriented_frames' order)
    rotations: np.ndarray | None = None
    self_pairs: SelfPairState | None = None  # where the controller keeps links apart
    _barrier_drift: np.ndarray | None = field(default=None, repr=False)  # (k,) set by the workspace
    _jdot: np.ndarray | None = field(default=None, repr=False)  # (m, n) where the law needs J̇ (jdot_en)

    @property
    def n(self) -> int:
        return int(self.v.shape[0])  # degrees of freedom (q has nq entries, more with continuous joints)

    def jdot(self) -> np.ndarray:
        """J̇ (m, n) of the task point: in the states of :meth:`Dynamics.compute`, and in a controller's
        snapshots when its law uses J̇ e_N (``LawGains.jdot_en``). The state is data: it does not call
        back into :class:`Dynamics` for it."""
        if self._jdot is None:
            raise ValueError("this TickState was built without J̇ (LawGains.jdot_en is off)")
        return self._jdot

    def barrier_drift(self) -> np.ndarray:
        """(k,) the part of each pair's ḧ that does not depend on q̈ [m/s²].

        With ḣ(q, q̇, t) = nᵀ(J_p q̇ − v_obs), ḧ = nᵀJ_p q̈ + ∂ḣ/∂q q̇ + ∂ḣ/∂t; this returns the last two
        terms, which include what the rigid-point drift nᵀ(J̇_p q̇ − a_obs) leaves out: the normal's
        rotation and the witness points sliding over the surfaces. Closed form for sphere and capsule
        obstacles (:func:`qpctl.kernels.pairs.barrier_drift`), a look-ahead difference of ḣ through
        python-fcl for the other shapes (:meth:`qpctl.tick.Workspace._look_ahead`).
        """
        if self._barrier_drift is None:
            raise ValueError("this TickState was built without the barrier drift")
        return self._barrier_drift


def validate_state(q: np.ndarray, v: np.ndarray, t: float, n: int,
                   nq: int | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """Check shapes and finiteness of a joint state (q of ``nq`` entries, default n; v of n);
    :class:`InvalidStateError` otherwise."""
    nq = n if nq is None else nq
    for name, val in (("q", q), ("v", v), ("t", t)):
        try:
            bad = val is None or isinstance(val, (str, bytes, bool, np.bool_)) or bool(np.iscomplexobj(val))
        except ValueError:  # a ragged nested sequence: reported below
            bad = False
        if bad:
            what = "a real number of seconds" if name == "t" else f"an array of {n} real numbers"
            raise InvalidStateError(f"{name} must be {what}, got {val!r}")
    try:
        q = np.asarray(q, dtype=float).reshape(-1) if np.ndim(q) <= 1 else np.asarray(q, dtype=float)
        v = np.asarray(v, dtype=float).reshape(-1) if np.ndim(v) <= 1 else np.asarray(v, dtype=float)
        t = float(t)
    except (TypeError, ValueError) as exc:
        raise InvalidStateError(f"q, v must be arrays of numbers and t a number: {exc}") from exc
    if q.shape != (nq,) or v.shape != (n,):
        shapes = f"({n},)" if nq == n else f"({nq},) and ({n},)"
        raise InvalidStateError(f"q and v must have shape {shapes}, got {q.shape} and {v.shape}")
    if not (np.isfinite(q).all() and np.isfinite(v).all() and math.isfinite(t)):
        raise InvalidStateError(f"non-finite state: q={q.tolist()}, v={v.tolist()}, t={t}")
    return q, v, t
