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
    # (k, 3) each pair's obstacle centre at t (the engine's own array moves on with the next state)
    _pair_centres: np.ndarray | None = field(default=None, repr=False)

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
        # for the closed-form barrier drift (plain floats): link radii; per obstacle its kind, radius and
        # axis vector s (a capsule's segment runs from c₀ = centre − s/2 to c₀ + s; zero for a sphere)
        self._radii = [c.radius for c in robot.capsules]
        kinds = {"sphere": _SPHERE, "capsule": _CAPSULE}
        self._obstacle_kind = [kinds.get(o.shape, _OTHER) for o in self.obstacles]
        self._obstacle_radius = [o.radius for o in self.obstacles]
        self._obstacle_axis = [(o.length * o.axis / np.linalg.norm(o.axis)).tolist() if o.shape == "capsule"
                               else [0.0, 0.0, 0.0] for o in self.obstacles]
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
        body_vel = offset = K = centres = None
        if k:
            centres = self.engine.obstacle_positions()[pairs.obstacle]
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
                         clearance, timing, _dynamics=self, _body_vel=body_vel, _acc_offset=offset, _acc_K=K,
                         _pair_centres=centres)

    def barrier_drift(self, state: TickState) -> np.ndarray:
        """∂ḣ/∂q q̇ + ∂ḣ/∂t per pair [m/s²]: ḧ at q̈ = 0, exact.

        Sphere and capsule obstacles (separated, or a sphere penetrating) in closed form
        (:meth:`_closed_form_drift`); boxes, cylinders, penetrating capsules and parallel axes by a
        look-ahead finite difference of ḣ (:meth:`_look_ahead_drift`).
        """
        if len(state.pairs) == 0:
            return np.zeros(0)
        drift, ok = self._closed_form_drift(state)
        if not ok.all():
            rest = np.flatnonzero(~ok)
            drift[rest] = self._look_ahead_drift(state, rest)
        return drift

    def _closed_form_drift(self, state: TickState) -> tuple[np.ndarray, np.ndarray]:
        """ḧ at q̈ = 0 of every pair whose obstacle is a sphere, or a capsule (axis c₀ + σ s) apart from
        the link; and which pairs it computed (False: another shape, a penetrating capsule, or
        near-parallel axes with both closest points free — left to the look-ahead difference).

        The axis points p = a + τu on the link and q = c₀ + σs on the obstacle are closest, so with
        w = p − q, ρ = |w|, n = w/ρ and h = ρ − radii − d_s: ḣ = nᵀẇ and ḧ = nᵀẅ + (|ẇ|² − (nᵀẇ)²)/ρ.
        ẇ = v_p − v_q + τ̇u − σ̇s and nᵀẅ = nᵀ(a_p − a_q) + 2τ̇ nᵀu̇ (v_p, a_p: the body point's
        velocity and q̈ = 0 acceleration; u̇ = ω × u; obstacles translate, ṡ = 0; n ⊥ u where τ is
        interior and τ̈ = 0 where it is clamped, likewise for σ). τ̇, σ̇ keep the closest-point
        conditions wᵀu = 0, wᵀs = 0 for the free parameters (0 for a clamped one).
        """
        # Plain floats, pair by pair: with a handful of pairs per tick, ~4 µs a pair against ~100 µs
        # of numpy calls on (k, 3) arrays for ten pairs (measured on the Panda canopy).
        assert state._body_vel is not None and state._acc_offset is not None and state._acc_K is not None
        assert state._pair_centres is not None
        pairs = state.pairs
        normal, p_link, p_obs = pairs.normal.tolist(), pairs.p_link.tolist(), pairs.p_obstacle.tolist()
        v_obs, a_obs = pairs.v_obstacle.tolist(), pairs.a_obstacle.tolist()
        link, obstacle = pairs.link.tolist(), pairs.obstacle.tolist()
        segments, vel = state.segments.tolist(), state._body_vel.tolist()
        offset, K = state._acc_offset.tolist(), state._acc_K.tolist()
        radii, o_radius, o_axis = self._radii, self._obstacle_radius, self._obstacle_axis
        kinds = self._obstacle_kind
        centres, distance = state._pair_centres.tolist(), pairs.distance.tolist()
        drifts, oks = [], []
        for r in range(len(link)):
            i, j = link[r], obstacle[r]
            if not (kinds[j] == _SPHERE or (kinds[j] == _CAPSULE and distance[r] > 1e-6)):
                drifts.append(0.0)
                oks.append(False)
                continue
            nx, ny, nz = normal[r]
            rl, ro = radii[i], o_radius[j]
            px, py, pz = p_link[r][0] + rl * nx, p_link[r][1] + rl * ny, p_link[r][2] + rl * nz  # on the link's axis
            qx, qy, qz = p_obs[r][0] - ro * nx, p_obs[r][1] - ro * ny, p_obs[r][2] - ro * nz  # on the obstacle's
            wx, wy, wz = px - qx, py - qy, pz - qz
            (ax, ay, az), (bx, by, bz) = segments[i]
            ux, uy, uz = bx - ax, by - ay, bz - az
            sx, sy, sz = o_axis[j]
            cx, cy, cz = centres[r]
            vx, vy, vz, ox, oy, oz = vel[i]
            vpx, vpy, vpz = vx + oy * pz - oz * py, vy + oz * px - ox * pz, vz + ox * py - oy * px  # v + ω × p
            udx, udy, udz = oy * uz - oz * uy, oz * ux - ox * uz, ox * uy - oy * ux  # u̇ = ω × u
            (k00, k01, k02), (k10, k11, k12), (k20, k21, k22) = K[i]
            o0, o1, o2 = offset[i]
            apx = o0 + k00 * px + k01 * py + k02 * pz  # a_p = offset + K p
            apy = o1 + k10 * px + k11 * py + k12 * pz
            apz = o2 + k20 * px + k21 * py + k22 * pz
            (vox, voy, voz), (aox, aoy, aoz) = v_obs[r], a_obs[r]
            dvx, dvy, dvz = vpx - vox, vpy - voy, vpz - voz
            L2 = ux * ux + uy * uy + uz * uz
            tau_l2 = (px - ax) * ux + (py - ay) * uy + (pz - az) * uz  # τ L²
            S2 = sx * sx + sy * sy + sz * sz
            sigma_s2 = (qx - cx + 0.5 * sx) * sx + (qy - cy + 0.5 * sy) * sy + (qz - cz + 0.5 * sz) * sz  # σ |s|²
            t_free = L2 > 1e-18 and 1e-9 * L2 < tau_l2 < (1.0 - 1e-9) * L2
            s_free = S2 > 1e-18 and 1e-9 * S2 < sigma_s2 < (1.0 - 1e-9) * S2
            e1 = -(dvx * ux + dvy * uy + dvz * uz + wx * udx + wy * udy + wz * udz)  # L²τ̇ − (u·s)σ̇ = e1
            e2 = -(dvx * sx + dvy * sy + dvz * sz)  # (u·s)τ̇ − |s|²σ̇ = e2
            us = ux * sx + uy * sy + uz * sz
            tau_dot = sigma_dot = 0.0
            ok = True
            if t_free and s_free:
                det = us * us - L2 * S2
                if abs(det) > 1e-9 * L2 * S2:
                    tau_dot, sigma_dot = (us * e2 - S2 * e1) / det, (L2 * e2 - us * e1) / det
                else:  # parallel axes: the closest points are not unique
                    ok = False
            elif t_free:
                tau_dot = e1 / L2
            elif s_free:
                sigma_dot = -e2 / S2
            rho2 = wx * wx + wy * wy + wz * wz
            ok = ok and rho2 > 1e-18
            wdx = dvx + tau_dot * ux - sigma_dot * sx
            wdy = dvy + tau_dot * uy - sigma_dot * sy
            wdz = dvz + tau_dot * uz - sigma_dot * sz
            nw = nx * wdx + ny * wdy + nz * wdz
            drift = (nx * (apx - aox) + ny * (apy - aoy) + nz * (apz - aoz)
                     + 2.0 * tau_dot * (nx * udx + ny * udy + nz * udz)
                     + (wdx * wdx + wdy * wdy + wdz * wdz - nw * nw) / math.sqrt(max(rho2, 1e-24)))
            drifts.append(drift if ok else 0.0)
            oks.append(ok)
        return np.array(drifts), np.array(oks, dtype=bool)

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
