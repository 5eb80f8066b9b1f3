"""The per-tick state: every rigid-body quantity and distance a law needs, computed once.

:class:`Dynamics` owns the Pinocchio data and the distance engine; :meth:`Dynamics.compute` runs
one ``computeAllTerms`` pass (M, N = C q̇ + G, joint Jacobians, zero-acceleration kinematics for the
drift terms) and one distance query, and returns a :class:`TickState` that tasks, constraints and
closed-form laws only read.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import pinocchio as pin

from qpctl.errors import InvalidStateError
from qpctl.geometry.distance import DistanceEngine, PairSet
from qpctl.geometry.obstacles import Obstacle
from qpctl.robot.model import RobotModel


def skew(p: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -p[2], p[1]], [p[2], 0.0, -p[0]], [-p[1], p[0], 0.0]])


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
    _dynamics: "Dynamics | None" = field(default=None, repr=False)
    _jdot: np.ndarray | None = field(default=None, repr=False)
    _barrier_drift: np.ndarray | None = field(default=None, repr=False)

    @property
    def n(self) -> int:
        return int(self.q.shape[0])

    def jdot(self) -> np.ndarray:
        """J̇ (m, n), computed on first use only (the laws need it only when J̇ e_N is switched on)."""
        if self._jdot is None:
            assert self._dynamics is not None
            self._jdot = self._dynamics.task_jacobian_derivative(self.q, self.v)
        return self._jdot

    def barrier_drift(self) -> np.ndarray:
        """(k,) the part of each pair's ḧ that does not depend on q̈ [m/s²], computed on first use.

        With ḣ(q, q̇, t) = nᵀ(J_p q̇ − v_obs), ḧ = nᵀJ_p q̈ + ∂ḣ/∂q q̇ + ∂ḣ/∂t; this returns the last two
        terms, which include what the rigid-point drift nᵀ(J̇_p q̇ − a_obs) leaves out: the normal's
        rotation and the witness points sliding over the surfaces.
        """
        if self._barrier_drift is None:
            assert self._dynamics is not None
            self._barrier_drift = self._dynamics.barrier_drift(self)
        return self._barrier_drift


def validate_state(q: np.ndarray, v: np.ndarray, t: float, n: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Check shapes and finiteness of a joint state; :class:`InvalidStateError` otherwise."""
    try:
        q = np.asarray(q, dtype=float).reshape(-1) if np.ndim(q) <= 1 else np.asarray(q, dtype=float)
        v = np.asarray(v, dtype=float).reshape(-1) if np.ndim(v) <= 1 else np.asarray(v, dtype=float)
        t = float(t)
    except (TypeError, ValueError) as exc:
        raise InvalidStateError(f"q, v must be arrays of numbers and t a number: {exc}") from exc
    if q.shape != (n,) or v.shape != (n,):
        raise InvalidStateError(f"q and v must have shape ({n},), got {q.shape} and {v.shape}")
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(v)) and np.isfinite(t)):
        raise InvalidStateError(f"non-finite state: q={q.tolist()}, v={v.tolist()}, t={t}")
    return q, v, t


class Dynamics:
    """Computes :class:`TickState` for one robot in one scene.

    Args:
        robot: the robot model.
        obstacles: the scene.
        cutoff: pairs farther than this [m] are not reported (the largest influence distance).
        broadphase: see :class:`~qpctl.geometry.distance.DistanceEngine`.
    """

    def __init__(self, robot: RobotModel, obstacles: Sequence[Obstacle] = (), cutoff: float = np.inf,
                 broadphase: bool | None = None) -> None:
        self.robot = robot
        self.model = robot.model
        self.data = robot.model.createData()
        self.obstacles = list(obstacles)
        self.cutoff = float(cutoff)
        self.engine = DistanceEngine([c.radius for c in robot.capsules], self.obstacles, broadphase)
        # a second engine and data for the barrier drift's look-ahead, so the tick's own stay intact
        self._probe = DistanceEngine([c.radius for c in robot.capsules], self.obstacles, broadphase=False)
        self._probe_data = robot.model.createData()
        self.drift_step = 2e-3  # [s] look-ahead of the barrier drift's finite difference
        self._axes = list(robot.task_axes)
        self._caps = [(c.joint_id, c.p0, c.p1) for c in robot.capsules]

    def _kinematics(self, q: np.ndarray, v: np.ndarray) -> None:
        pin.computeAllTerms(self.model, self.data, q, v)  # M, nle, Jacobians; data.a at q̈ = 0
        pin.updateFramePlacements(self.model, self.data)

    def point_jacobian(self, joint_id: int, p: np.ndarray) -> np.ndarray:
        """(3, n) Jacobian of the world point p [m] fixed to joint ``joint_id``'s body (after compute)."""
        J6 = pin.getJointJacobian(self.model, self.data, joint_id, pin.WORLD)
        return J6[:3] - skew(p) @ J6[3:]

    def point_drift(self, joint_id: int, p: np.ndarray) -> np.ndarray:
        """(3,) J̇_p q̇: the classical acceleration of body point p [m] at q̈ = 0 (after compute)."""
        oMi = self.data.oMi[joint_id]
        vw = oMi.act(self.data.v[joint_id])
        aw = oMi.act(self.data.a[joint_id])
        w = vw.angular
        return aw.linear + np.cross(aw.angular, p) + np.cross(w, vw.linear + np.cross(w, p))

    def compute(self, q: np.ndarray, v: np.ndarray, t: float = 0.0) -> TickState:
        """Everything at (q [rad], v [rad/s], t [s]); raises :class:`InvalidStateError` on bad input."""
        q, v, t = validate_state(q, v, t, self.model.nv)
        model, data = self.model, self.data
        self._kinematics(q, v)
        M = np.triu(data.M) + np.triu(data.M, 1).T
        N = data.nle.copy()
        fid = self.robot.ee_frame_id
        x = data.oMf[fid].translation[self._axes].copy()
        Jf = pin.getFrameJacobian(model, data, fid, pin.LOCAL_WORLD_ALIGNED)[:3]
        J = Jf[self._axes].copy()
        drift = pin.getFrameClassicalAcceleration(model, data, fid, pin.LOCAL_WORLD_ALIGNED).linear[self._axes].copy()
        L = len(self._caps)
        segments = np.empty((L, 2, 3))
        link_jac = np.empty((L, 3, model.nv))
        for i, (jid, p0, p1) in enumerate(self._caps):
            oMi = data.oMi[jid]
            segments[i, 0] = oMi.act(p0)
            segments[i, 1] = oMi.act(p1)
            link_jac[i] = self.point_jacobian(jid, segments[i].mean(axis=0))
        if self.obstacles:
            self.engine.update(segments, t)
            pairs = self.engine.pairs(self.cutoff)
        else:
            pairs = PairSet.empty()
        k = len(pairs)
        pair_jac = np.empty((k, 3, model.nv))
        pair_drift = np.empty((k, 3))
        for r in range(k):
            jid = self._caps[pairs.link[r]][0]
            pair_jac[r] = self.point_jacobian(jid, pairs.p_link[r])
            pair_drift[r] = self.point_drift(jid, pairs.p_link[r])
        clearance = float(pairs.distance.min()) if k else float("inf")
        return TickState(t, q, v, M, N, x, J @ v, J, drift, link_jac, segments, pairs, pair_jac, pair_drift,
                         clearance, _dynamics=self)

    def barrier_drift(self, state: TickState) -> np.ndarray:
        """∂ḣ/∂q q̇ + ∂ḣ/∂t per pair by a forward difference along the motion (q + δq̇, t + δ).

        ḣ is re-evaluated with the witness points and normal recomputed by python-fcl at the
        look-ahead state and the same q̇; δ = ``drift_step`` balances truncation (O(δ)) and the
        distance query's noise (O(1e-8/δ)).
        """
        pairs = state.pairs
        k = len(pairs)
        if k == 0:
            return np.zeros(0)
        delta = self.drift_step
        q1, t1 = state.q + delta * state.v, state.t + delta
        model, data = self.model, self._probe_data
        pin.forwardKinematics(model, data, q1, state.v)
        segments = np.empty_like(state.segments)
        for i, (jid, p0, p1) in enumerate(self._caps):
            segments[i, 0] = data.oMi[jid].act(p0)
            segments[i, 1] = data.oMi[jid].act(p1)
        self._probe.update(segments, t1)
        hdot0 = np.einsum("ri,rin,n->r", pairs.normal, state.pair_jac, state.v) - np.einsum(
            "ri,ri->r", pairs.normal, pairs.v_obstacle)
        hdot1 = np.empty(k)
        for r in range(k):
            i, j = int(pairs.link[r]), int(pairs.obstacle[r])
            _, n, p_link, _ = self._probe.pair(i, j)
            jid = self._caps[i][0]
            vw = data.oMi[jid].act(data.v[jid])
            v_point = vw.linear + np.cross(vw.angular, p_link)
            hdot1[r] = n @ (v_point - self.obstacles[j].velocity_at(t1))
        return (hdot1 - hdot0) / delta

    def task_jacobian_derivative(self, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        """J̇ (m, n) of the task point at (q, v)."""
        pin.computeJointJacobiansTimeVariation(self.model, self.data, q, v)
        dJ = pin.getFrameJacobianTimeVariation(self.model, self.data, self.robot.ee_frame_id,
                                               pin.LOCAL_WORLD_ALIGNED)[:3]
        return dJ[self._axes].copy()

    def forward_dynamics(self, q: np.ndarray, v: np.ndarray, tau: np.ndarray) -> np.ndarray:
        """q̈ = M⁻¹(τ − N) by Pinocchio's ABA [rad/s²]."""
        return pin.aba(self.model, self.data, q, v, tau).copy()
