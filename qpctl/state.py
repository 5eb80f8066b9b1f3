"""The per-tick state: every rigid-body quantity and distance a law needs, computed once.

:class:`Dynamics` owns the Pinocchio data and the distance engine; :meth:`Dynamics.compute` runs
one ``computeAllTerms`` pass (M, N = C q̇ + G, joint Jacobians, zero-acceleration kinematics for the
drift terms) and one distance query, and returns a :class:`TickState` that tasks, constraints and
closed-form laws only read.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin

from qpctl.errors import InvalidStateError
from qpctl.geometry.distance import DistanceEngine, PairSet
from qpctl.geometry.obstacles import Obstacle
from qpctl.robot.model import RobotModel

_SPHERE, _CAPSULE, _OTHER = 0, 1, 2  # obstacle kinds for the barrier drift


def skew(p: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -p[2], p[1]], [p[2], 0.0, -p[0]], [-p[1], p[0], 0.0]])


# Levi-Civita symbol as a (3, 9) matrix: row j holds ε_ijk over (i, k), so (p @ _LEVI_CIVITA) holds
# Σ_j ε_ijk p_j = skew(p)_ik.
_LEVI_CIVITA = np.zeros((3, 3, 3))
_LEVI_CIVITA[0, 1, 2] = _LEVI_CIVITA[1, 2, 0] = _LEVI_CIVITA[2, 0, 1] = 1.0
_LEVI_CIVITA[0, 2, 1] = _LEVI_CIVITA[2, 1, 0] = _LEVI_CIVITA[1, 0, 2] = -1.0
_LEVI_CIVITA = _LEVI_CIVITA.transpose(1, 0, 2).reshape(3, 9)


def skews(p: np.ndarray) -> np.ndarray:
    """(k, 3, 3) cross-product matrices of k vectors (k, 3): ``skews(p) @ b`` is p × b, batched (one
    product; ``np.cross`` costs ~30 µs a call on arrays this small)."""
    return (p @ _LEVI_CIVITA).reshape(-1, 3, 3)


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise a × b of (k, 3) arrays."""
    return np.matmul(skews(a), b[:, :, None])[:, :, 0]


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
    timing: dict[str, float] = field(default_factory=dict)  # stage wall times [µs]: "rigid_us", "distance_us"
    _dynamics: Dynamics | None = field(default=None, repr=False)
    _jdot: np.ndarray | None = field(default=None, repr=False)
    _barrier_drift: np.ndarray | None = field(default=None, repr=False)
    # per capsule body (L rows): world spatial velocity (v at the origin, ω) and the q̈ = 0
    # acceleration field a(p) = offset + K p of its points; set when pairs exist (barrier drift)
    _body_vel: np.ndarray | None = field(default=None, repr=False)
    _acc_offset: np.ndarray | None = field(default=None, repr=False)
    _acc_K: np.ndarray | None = field(default=None, repr=False)

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
        rotation and the witness points sliding over the surfaces (:meth:`Dynamics.barrier_drift`).
        """
        if self._barrier_drift is None:
            assert self._dynamics is not None
            self._barrier_drift = self._dynamics.barrier_drift(self)
        return self._barrier_drift


def validate_state(q: np.ndarray, v: np.ndarray, t: float, n: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Check shapes and finiteness of a joint state; :class:`InvalidStateError` otherwise."""
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
    if q.shape != (n,) or v.shape != (n,):
        raise InvalidStateError(f"q and v must have shape ({n},), got {q.shape} and {v.shape}")
    if not (np.isfinite(q).all() and np.isfinite(v).all() and math.isfinite(t)):
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
        self._cap_joints = [c.joint_id for c in robot.capsules]
        self._cap_local = np.array([[c.p0, c.p1] for c in robot.capsules], float).reshape(-1, 2, 3)
        self._support = self._support_masks()
        # per obstacle, for the closed-form barrier drift: kind, radius, axis vector s (capsule: the
        # segment from c₀ = centre − s/2 to c₀ + s; zero for a sphere)
        self._radii = np.array([c.radius for c in robot.capsules], float)
        self._obstacle_kind = np.array([{"sphere": _SPHERE, "capsule": _CAPSULE}.get(o.shape, _OTHER)
                                        for o in self.obstacles], int)
        self._obstacle_radius = np.array([o.radius for o in self.obstacles], float)
        self._obstacle_axis = np.array([o.length * o.axis / np.linalg.norm(o.axis) if o.shape == "capsule"
                                        else np.zeros(3) for o in self.obstacles], float).reshape(-1, 3)
        self._tril = np.tril_indices(self.model.nv, -1)

    def _support_masks(self) -> np.ndarray:
        """(L, n): 1 where joint velocity k moves capsule i's body. ``data.J`` (every joint's world
        Jacobian column) times row i is that body's world Jacobian, what ``getJointJacobian(…, WORLD)``
        returns — for all capsules in one product."""
        model = self.model
        mask = np.zeros((len(self._cap_joints), model.nv))
        for i, jid in enumerate(self._cap_joints):
            for k in model.supports[jid]:
                if k > 0:
                    joint = model.joints[k]
                    mask[i, joint.idx_v : joint.idx_v + joint.nv] = 1.0
        return mask

    def _capsule_segments(self, data: pin.Data) -> np.ndarray:
        """(L, 2, 3) the capsule axes in the world frame [m] (after a kinematics pass on ``data``)."""
        H = np.array([data.oMi[j].homogeneous for j in self._cap_joints]).reshape(-1, 4, 4)
        return np.matmul(self._cap_local, H[:, :3, :3].transpose(0, 2, 1)) + H[:, None, :3, 3]

    def _acceleration_field(self, data: pin.Data, velocity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per capsule body, the classical acceleration at q̈ = 0 of its point p [m] (world frame) is
        a + α × p + ω × (v + ω × p) = offset + K p, with offset = a + ω × v (L, 3) and K = α× + ω×ω×
        (L, 3, 3); ``velocity`` (L, 6) = (v, ω) are the bodies' world spatial velocities and (a, α)
        their accelerations at the world origin. J̇_p q̇ of a point is its acceleration at q̈ = 0."""
        acc = np.array([pin.getAcceleration(self.model, data, j, pin.WORLD).vector for j in self._cap_joints])
        W = skews(velocity[:, 3:])
        offset = acc[:, :3] + np.matmul(W, velocity[:, :3, None])[:, :, 0]  # (L, 3)
        K = skews(acc[:, 3:]) + W @ W  # (L, 3, 3)
        return offset, K

    @staticmethod
    def _point_jacobians(body_jac: np.ndarray, points: np.ndarray) -> np.ndarray:
        """(k, 3, n) Jacobians of world points (k, 3) [m] fixed to bodies whose world Jacobians are
        (k, 6, n): J_v − p × J_ω, column by column."""
        return body_jac[:, :3] - skews(points) @ body_jac[:, 3:]

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
        start = time.perf_counter()
        self._kinematics(q, v)
        M = data.M.copy()  # Pinocchio fills the upper triangle
        M[self._tril] = M.T[self._tril]
        N = data.nle.copy()
        if not np.isfinite(N).all():  # e.g. speeds so large that C(q, q̇)q̇ overflows
            raise InvalidStateError(f"the dynamics overflow at this state: q={q.tolist()}, v={v.tolist()}")
        fid = self.robot.ee_frame_id
        x = data.oMf[fid].translation[self._axes].copy()
        Jf = pin.getFrameJacobian(model, data, fid, pin.LOCAL_WORLD_ALIGNED)[:3]
        J = Jf[self._axes].copy()
        drift = pin.getFrameClassicalAcceleration(model, data, fid, pin.LOCAL_WORLD_ALIGNED).linear[self._axes].copy()
        segments = self._capsule_segments(data)
        body_jac = data.J[None] * self._support[:, None, :]  # (L, 6, n)
        link_jac = self._point_jacobians(body_jac, 0.5 * (segments[:, 0] + segments[:, 1]))
        rigid = time.perf_counter()
        if self.obstacles:
            self.engine.update(segments, t)
            pairs = self.engine.pairs(self.cutoff)
        else:
            pairs = PairSet.empty()
        distance = time.perf_counter()
        k = len(pairs)
        body_vel = offset = K = None
        if k:
            P = pairs.p_link
            pair_jac = self._point_jacobians(body_jac[pairs.link], P)
            body_vel = body_jac @ v
            offset, K = self._acceleration_field(data, body_vel)
            pair_drift = offset[pairs.link] + np.matmul(K[pairs.link], P[:, :, None])[:, :, 0]
        else:
            pair_jac = np.empty((0, 3, model.nv))
            pair_drift = np.empty((0, 3))
        clearance = float(pairs.distance.min()) if k else float("inf")
        end = time.perf_counter()
        timing = {"rigid_us": ((rigid - start) + (end - distance)) * 1e6, "distance_us": (distance - rigid) * 1e6}
        return TickState(t, q, v, M, N, x, J @ v, J, drift, link_jac, segments, pairs, pair_jac, pair_drift,
                         clearance, timing, _dynamics=self, _body_vel=body_vel, _acc_offset=offset, _acc_K=K)

    def barrier_drift(self, state: TickState) -> np.ndarray:
        """∂ḣ/∂q q̇ + ∂ḣ/∂t per pair [m/s²]: ḧ at q̈ = 0, exact.

        Sphere and capsule obstacles (separated, or a sphere penetrating) in closed form
        (:meth:`_closed_form_drift`); boxes, cylinders, penetrating capsules and parallel axes by a
        look-ahead finite difference of ḣ (:meth:`_look_ahead_drift`).
        """
        pairs = state.pairs
        k = len(pairs)
        if k == 0:
            return np.zeros(0)
        kind = self._obstacle_kind[pairs.obstacle]
        closed = (kind == _SPHERE) | ((kind == _CAPSULE) & (pairs.distance > 1e-6))
        out = np.empty(k)
        rest = np.flatnonzero(~closed)
        if closed.any():
            idx = np.flatnonzero(closed)
            drift, ok = self._closed_form_drift(state, idx)
            out[idx] = drift
            rest = np.sort(np.concatenate([rest, idx[~ok]]))
        if rest.size:
            out[rest] = self._look_ahead_drift(state, rest)
        return out

    def _closed_form_drift(self, state: TickState, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """ḧ at q̈ = 0 of the pairs ``idx`` whose obstacle is a sphere or a capsule (axis c₀ + σ s);
        also whether each was computable (False: near-parallel axes, both closest points free).

        The axis points p = a + τu on the link and q = c₀ + σs on the obstacle are closest, so with
        w = p − q, ρ = |w|, n = w/ρ and h = ρ − radii − d_s: ḣ = nᵀẇ and ḧ = nᵀẅ + (|ẇ|² − (nᵀẇ)²)/ρ.
        ẇ = v_p − v_q + τ̇u − σ̇s and nᵀẅ = nᵀ(a_p − a_q) + 2τ̇ nᵀu̇ (v_p, a_p: the body point's
        velocity and q̈ = 0 acceleration; u̇ = ω × u; obstacles translate, ṡ = 0; n ⊥ u where τ is
        interior and τ̈ = 0 where it is clamped, likewise for σ). τ̇, σ̇ keep the closest-point
        conditions wᵀu = 0, wᵀs = 0 for the free parameters (0 for a clamped one).
        """
        pairs = state.pairs
        links, obs = pairs.link[idx], pairs.obstacle[idx]
        n = pairs.normal[idx]
        p = pairs.p_link[idx] + self._radii[links][:, None] * n
        qo = pairs.p_obstacle[idx] - self._obstacle_radius[obs][:, None] * n
        w = p - qo
        rho = np.sqrt((w * w).sum(axis=1))
        seg = state.segments[links]
        a, u = seg[:, 0], seg[:, 1] - seg[:, 0]
        L2 = (u * u).sum(axis=1)
        tau = ((p - a) * u).sum(axis=1) / np.maximum(L2, 1e-300)
        t_free = (tau > 1e-9) & (tau < 1.0 - 1e-9) & (L2 > 1e-18)
        s = self._obstacle_axis[obs]
        S2 = (s * s).sum(axis=1)
        c0 = self.engine._centres[obs] - 0.5 * s
        sigma = ((qo - c0) * s).sum(axis=1) / np.maximum(S2, 1e-300)
        s_free = (sigma > 1e-9) & (sigma < 1.0 - 1e-9) & (S2 > 1e-18)
        assert state._body_vel is not None and state._acc_offset is not None and state._acc_K is not None
        vel = state._body_vel[links]
        omega = vel[:, 3:]
        v_p = vel[:, :3] + cross(omega, p)
        a_p = state._acc_offset[links] + np.matmul(state._acc_K[links], p[:, :, None])[:, :, 0]
        u_dot = cross(omega, u)
        dv = v_p - pairs.v_obstacle[idx]
        e1 = -((dv * u).sum(axis=1) + (w * u_dot).sum(axis=1))  # L²τ̇ − (u·s)σ̇ = e1
        e2 = -(dv * s).sum(axis=1)  # (u·s)τ̇ − |s|²σ̇ = e2
        us = (u * s).sum(axis=1)
        det = us * us - L2 * S2
        both = t_free & s_free
        ok = ~both | (np.abs(det) > 1e-9 * L2 * S2)
        with np.errstate(divide="ignore", invalid="ignore"):
            tau_dot = np.where(both, (us * e2 - S2 * e1) / det, np.where(t_free, e1 / L2, 0.0))
            sigma_dot = np.where(both, (L2 * e2 - us * e1) / det, np.where(s_free, -e2 / S2, 0.0))
        tau_dot = np.where(ok, tau_dot, 0.0)
        sigma_dot = np.where(ok, sigma_dot, 0.0)
        w_dot = dv + tau_dot[:, None] * u - sigma_dot[:, None] * s
        nw = (n * w_dot).sum(axis=1)
        drift = ((n * (a_p - pairs.a_obstacle[idx])).sum(axis=1) + 2.0 * tau_dot * (n * u_dot).sum(axis=1)
                 + ((w_dot * w_dot).sum(axis=1) - nw * nw) / np.maximum(rho, 1e-12))
        return drift, ok & (rho > 1e-9)

    def _look_ahead_drift(self, state: TickState, idx: np.ndarray) -> np.ndarray:
        """∂ḣ/∂q q̇ + ∂ḣ/∂t of the pairs ``idx`` by a forward difference along the motion (q + δq̇, t + δ).

        ḣ is re-evaluated with the witness points and normal recomputed by python-fcl at the
        look-ahead state and the same q̇; δ = ``drift_step`` balances truncation (O(δ)) and the
        distance query's noise (O(1e-8/δ)).
        """
        pairs = state.pairs
        k = idx.size
        delta = self.drift_step
        q1, t1 = state.q + delta * state.v, state.t + delta
        model, data = self.model, self._probe_data
        pin.forwardKinematics(model, data, q1, state.v)
        segments = self._capsule_segments(data)
        links = pairs.link[idx].tolist()
        obstacles = pairs.obstacle[idx]
        self._probe.update(segments, t1, links=sorted(set(links)))
        hdot0 = np.einsum("ri,ri->r", pairs.normal[idx], state.pair_jac[idx] @ state.v - pairs.v_obstacle[idx])
        normal, p_link = np.empty((k, 3)), np.empty((k, 3))
        for r, (i, j) in enumerate(zip(links, obstacles.tolist())):
            _, normal[r], p_link[r], _ = self._probe.pair(i, j)
        v_obs = self._probe.obstacle_velocities(obstacles)
        body = np.array([pin.getVelocity(model, data, self._cap_joints[i], pin.WORLD).vector for i in links])
        v_point = body[:, :3] + cross(body[:, 3:], p_link)  # velocity of the look-ahead witness points
        hdot1 = np.einsum("ri,ri->r", normal, v_point - v_obs)
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
