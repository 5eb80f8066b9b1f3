"""The depth map's barrier rows: the field's pairs, shaped like the primitives' rows.

For each link capsule and channel, :func:`qpctl.kernels.field.field_pairs` gives the nearest one or
two points of the field (distance d [m] from the capsule's surface, unit normal n away from the
obstacle, witness point p on the link). Each becomes a row on q̈ of the form of
:class:`~qpctl.constraints.ObstacleBarrier`'s, with the static map's ḣ = nᵀJ_p q̇ and the
rigid-point drift ḧ = nᵀ(J_p q̈ + J̇_p q̇):

* **rigid** (stems, branches; unlabeled points too): ḧ + k₁ḣ + k₀h ≥ 0 with h = d − m,
  m = d_safe + √3/2·voxel + depth noise (:meth:`PerceptionConfig.rigid_margin`): the voxel's centre
  may be √3/2 voxel from the surface it stands for, and the surface itself off by the noise. Inside
  the margin (h < 0: a new frame put a voxel within it) the link moves away at a bounded speed —
  ḧ + k_r(ḣ − v_a) ≥ 0, v_a = min(k₀/k₁·|h|, v_s), k_r = ``recovery_gain`` (10 1/s, a quarter of
  k₁ at its defaults) — and asks no more than a share of what the drives
  can give in this tick: the bound is capped at ℓ − ρ(ℓ − ℓ₋), [ℓ₋, ℓ] the range of nᵀJ_p q̈ over
  the torque window (:mod:`qpctl.kernels.drives`; ρ = :data:`~qpctl.kernels.drives.REACH_SHARE`;
  :func:`qpctl.constraints.constraints.reach_cap`).
  The margin is the map's uncertainty: a voxel inside it is escaped at a leaf's speed, not at the
  barrier's k₀/k₁·|h| (0.12 m/s for 1.2 cm), and without the cap, under a torque-rate limit, the
  row asked k₀|h| of the witness point at once, the QP was infeasible tick after tick and the safe
  stop (which knows no leaf) moved the arm (``docs/perception.md``, seed 10: 2,742 fallback ticks
  in 30 s before, 15 after);
* **soft** (leaves): ḧ + k₁(ḣ + v_s) + k₀ max(d − m_s, 0) + σ ≥ 0, v_s = ``soft_speed``,
  m_s = ``soft_margin`` (√3/2·voxel + depth noise would be where the leaf's true surface may already
  be; 0 by default): far from a leaf it is a barrier without d_safe, from m_s on it asks only
  ḣ ≥ −v_s — a link may pass through a leaf, no faster than v_s along the field's normal. σ ≥ 0 is
  the link's own slack column, which its soft rows and speed rows share (:meth:`FieldBarrier.slack_columns`,
  ℓ₁ weight ``soft_weight`` each): where the soft rows conflict with the hard ones the QP stays
  feasible, and the slack one link needs frees no other link's rows.

* **soft speed** (the metric ``soft_contact_max_speed`` is a link point's total speed, not its normal
  component; inside a leaf's voxels the field is flat and has no normal at all): two rows per link
  for the points of :func:`qpctl.kernels.field.speed_points`. Each sample along the link's axis has
  a bound b(d) = v_s + g·max(d − m_v, 0), m_v = √3/2·voxel + depth noise
  (:meth:`PerceptionConfig.soft_speed_margin`: within m_v of a leaf's voxels the capsule's surface may
  already be inside the leaf, and b = v_s), g = ``soft_funnel`` (a funnel the link slows along as it
  nears a leaf, not a wall), and a fastest point (of the capsule's ball about the sample, the one
  that moves fastest now); the two samples whose fastest points most exceed their bounds are the
  rows' points. Each row keeps the point's velocity a horizon h ahead (``soft_horizon``, one control
  period: the next tick's), w⁺ = J_p q̇ + (J_p q̈ + J̇_p q̇)h, no faster than b along the direction u
  of its velocity now: uᵀw⁺ ≤ b + σh — the tangent half-space of the ball |w⁺| ≤ b at the current
  velocity, which |w⁺| exceeds by at most |w⁺ − w|²/(2|w|), second order in the tick's change of
  velocity (the next tick's row is tangent at the new direction). As rows on q̈:
  −uᵀJ_p q̈ + σ ≥ (uᵀJ_p q̇ − b)/h + uᵀJ̇_p q̇, sharing the link's slack σ with its soft rows.

A row is active where d is within the controller's influence distance (a barrier row only with a
normal), inactive (−inf bound) elsewhere; the number of rows is fixed: 2 channels × links ×
``rows_per_link`` pairs, then 2 speed rows per link.

:class:`FieldBarrier` is the constraint on the Python path (:class:`~qpctl.formulation.Formulation`):
the reference the compiled rows (:mod:`qpctl.kernels.field_rows`, through :meth:`FieldBarrier.field_spec`)
are held to. Its point Jacobians and drifts come from Pinocchio's
joint Jacobians and their time variation, shifted to the witness points.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pinocchio as pin

from qpctl.constraints.constraints import BARRIER, Constraint, TorqueLimit, reach_cap
from qpctl.kernels import field as KF
from qpctl.law import LawTerms
from qpctl.perception.config import PerceptionConfig
from qpctl.perception.snapshot import MapSnapshot
from qpctl.qp import Inequality
from qpctl.robot.model import RobotModel
from qpctl.state import TickState
from qpctl.tick import FieldSpec

SOFT_SLACK_L2 = 1e2  # [(N·m)²/(m/s²)²] the soft rows' slack's ℓ₂ weight (as the task's slack_l2)


@dataclass(frozen=True)
class FieldPairs:
    """The field's pairs at one tick (R = 2 channels × L links × rows_per_link rows; channel-major):
    ``distance`` (R,) [m] from the capsule's surface, ``normal`` (R, 3), ``point`` (R, 3) on the link
    [m], ``link`` (R,) capsule index, ``soft`` (R,) bool, ``active`` (R,) bool (within the cutoff)."""

    distance: np.ndarray
    normal: np.ndarray
    point: np.ndarray
    link: np.ndarray
    soft: np.ndarray
    active: np.ndarray

    def obstacle_points(self) -> np.ndarray:
        """(R, 3) where each row believes the obstacle is [m]: the witness point moved by d along −n."""
        return self.point - self.distance[:, None] * self.normal


def field_pairs(snapshot: MapSnapshot, segments: np.ndarray, radii: np.ndarray, config: PerceptionConfig,
                cutoff: float, *, smooth: bool = True) -> FieldPairs:
    """Both channels' pairs for the link capsules (``segments`` (L, 2, 3) [m], ``radii`` (L,) [m]);
    a pair is active when its distance is below ``cutoff`` [m]."""
    L, R, S = len(segments), config.rows_per_link, config.samples
    out_d, out_n, out_p = np.empty(2 * L * R), np.empty((2 * L * R, 3)), np.empty((2 * L * R, 3))
    s, ds = np.empty(L * R), np.empty(S)
    g = snapshot.grid
    for ch in range(2):
        sl = slice(ch * L * R, (ch + 1) * L * R)
        KF.field_pairs(np.ascontiguousarray(segments, float), np.ascontiguousarray(radii, float),
                       snapshot.dist[ch], snapshot.grad[ch], g.origin, g.voxel, snapshot.truncation, S, R, smooth,
                       ds, out_d[sl], out_n[sl], out_p[sl], s)
    link = np.tile(np.repeat(np.arange(L), R), 2)
    soft = np.repeat([False, True], L * R)
    active = (out_d < cutoff) & np.any(out_n != 0.0, axis=1)
    return FieldPairs(out_d, out_n, out_p, link, soft, active)


class FieldBarrier(Constraint):
    """The map's rows (module docstring) for a controller reading ``source`` — a
    :class:`~qpctl.perception.Perception` or anything with a ``snapshot`` attribute.

    Args:
        source: where the newest :class:`MapSnapshot` is read, every tick.
        robot: the robot (its capsules and Pinocchio model).
        config: the ``[perception]`` settings (margins, samples, rows per link, ``soft_speed``).
        d_safe [m], cutoff [m] (the influence distance), k0 [1/s²], k1 [1/s]: as the obstacle barrier's.
        torque: the controller's torque limits, whose window caps the rigid rows inside their margin
            (None: no cap).
    """

    name = "field"
    kind = BARRIER

    def __init__(self, source: object, robot: RobotModel, config: PerceptionConfig, *, d_safe: float,
                 cutoff: float, k0: float = 400.0, k1: float = 40.0, smooth: bool = True,
                 torque: TorqueLimit | None = None) -> None:
        self.source = source
        self.torque = torque
        self.smooth = bool(smooth)  # the Python path's switch (qpctl.kernels.field); the compiled rows are smooth
        self.robot = robot
        self.config = config
        self.margin = config.rigid_margin(d_safe)
        self.soft_margin = float(config.soft_margin)
        # each link's soft rows share a slack column σ ≥ 0 of their own (cost ℓ₁σ + ½ℓ₂σ²): where they conflict
        # with the hard rows (the torque limits, a branch) the QP stays feasible and that link's leaf gives way
        self.slack = (float(config.soft_weight), SOFT_SLACK_L2) if config.soft_weight > 0 else None
        self.cutoff = float(cutoff)
        self.k0, self.k1 = float(k0), float(k1)
        self.radii = np.array([c.radius for c in robot.capsules], float)
        self.joints = np.array([c.joint_id for c in robot.capsules], int)
        self.speed_margin = config.soft_speed_margin()
        self.horizon = float(config.soft_horizon)
        self.funnel = float(config.soft_funnel)
        self.recovery_gain = float(config.recovery_gain)
        self.pairs = 2 * len(robot.capsules) * config.rows_per_link
        self.rows = self.pairs + 2 * len(robot.capsules)
        self._data = robot.model.createData()
        self._last: FieldPairs | None = None
        self._ws: Any = None  # the compiled tick's workspace, when its arrays hold the last tick's pairs
        L, R = len(robot.capsules), config.rows_per_link
        self._link = np.tile(np.repeat(np.arange(L), R), 2)
        self._soft = np.repeat([False, True], L * R)

    @property
    def last(self) -> FieldPairs | None:
        """The last tick's pairs (for metrics and figures), from whichever path computed them."""
        if self._last is None and self._ws is not None:
            d, n, p = self._ws.field_state()
            self._last = FieldPairs(d, n, p, self._link, self._soft, (d < self.cutoff) & np.any(n != 0.0, axis=1))
        return self._last

    def slack_columns(self) -> tuple[np.ndarray, np.ndarray]:
        """One slack column per link at ``soft_weight``: 1 on the link's soft rows (in the pairs' second
        half) and its two speed rows, 0 elsewhere (the rigid rows are hard)."""
        assert self.slack is not None
        L = len(self.robot.capsules)
        cols = np.zeros((self.rows, L))
        cols[np.flatnonzero(self._soft), self._link[self._soft]] = 1.0
        cols[self.pairs + np.arange(2 * L), np.repeat(np.arange(L), 2)] = 1.0
        return cols, np.tile(self.slack, (L, 1))

    def field_spec(self) -> FieldSpec:
        """These rows in the compiled tick (:mod:`qpctl.kernels.field_rows`; held to :meth:`compute`;
        :class:`ValueError` for raw rows, which only the Python path has)."""
        if not self.smooth:
            raise ValueError("the compiled field rows are smooth: a raw FieldBarrier needs the Python path")
        return FieldSpec(self.source, self, self.rows, self.config.samples, self.config.rows_per_link, self.margin,
                         self.config.soft_speed, self.cutoff, self.k0, self.k1, self.soft_margin,
                         self.speed_margin, self.horizon, self.funnel, self.recovery_gain)

    def bind(self, ws: Any) -> None:
        """A compiled tick runs on ``ws``: its arrays hold this tick's pairs (:attr:`last`)."""
        self._ws, self._last = ws, None

    def segments(self, q: np.ndarray) -> np.ndarray:
        """(L, 2, 3) the capsules' axes [m] at q [rad] (Pinocchio's forward kinematics)."""
        pin.forwardKinematics(self.robot.model, self._data, np.asarray(q, float))
        return np.array([[self._data.oMi[c.joint_id].act(c.p0), self._data.oMi[c.joint_id].act(c.p1)]
                         for c in self.robot.capsules])

    def jacobians(self, q: np.ndarray, v: np.ndarray, links: np.ndarray, points: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
        """(k, 3, n) Jacobians and (k, 3) drifts J̇_p q̇ [m/s²] of ``points`` (k, 3) [m] fixed on the
        capsules' bodies ``links`` (k,), at (q, v): Pinocchio's joint Jacobians and time variations
        (LOCAL_WORLD_ALIGNED), shifted from the joint's origin o to p: J_p = J_v − [p − o]× J_ω,
        J̇_p q̇ = J̇_v q̇ + (J̇_ω q̇) × r + ω × (ω × r), r = p − o."""
        model, data = self.robot.model, self._data
        pin.computeJointJacobiansTimeVariation(model, data, q, v)  # also the placements and J
        joints = self.joints[links]
        J6 = np.empty((len(links), 6, model.nv))
        dJ6 = np.empty((len(links), 6, model.nv))
        origin = np.empty((len(links), 3))
        for j in np.unique(joints):  # once per body, not per pair
            at = joints == j
            J6[at] = pin.getJointJacobian(model, data, int(j), pin.LOCAL_WORLD_ALIGNED)
            dJ6[at] = pin.getJointJacobianTimeVariation(model, data, int(j), pin.LOCAL_WORLD_ALIGNED)
            origin[at] = data.oMi[int(j)].translation
        r = points - origin
        Jw = J6[:, 3:]
        J = J6[:, :3] - np.cross(r[:, :, None], Jw, axis=1)  # column-wise r × J_ω
        w = Jw @ v
        a = dJ6[:, :3] @ v + np.cross(dJ6[:, 3:] @ v, r) + np.cross(w, np.cross(w, r))
        return J, a

    def body_velocities(self, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        """(L, 6) each capsule body's world velocity at the world origin [m/s] and ω [rad/s] (Pinocchio)."""
        model, data = self.robot.model, self._data
        pin.forwardKinematics(model, data, q, v)
        out = np.empty((len(self.joints), 6))
        for i, j in enumerate(self.joints):
            m = pin.getVelocity(model, data, int(j), pin.LOCAL_WORLD_ALIGNED)
            w = m.angular
            out[i, :3] = m.linear - np.cross(w, data.oMi[int(j)].translation)
            out[i, 3:] = w
        return out

    def speed_points(self, snap: MapSnapshot, segments: np.ndarray, q: np.ndarray, v: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The speed rows' points (2L, 3) [m], directions (2L, 3), bounds (2L,) [m/s] (inf: no row) and
        field distances (2L,) [m]: :func:`qpctl.kernels.field.speed_points` on the soft channel."""
        L, g = len(segments), snap.grid
        p, u, b, d = np.empty((2 * L, 3)), np.empty((2 * L, 3)), np.empty(2 * L), np.empty(2 * L)
        KF.speed_points(np.ascontiguousarray(segments, float), self.radii, snap.dist[1], g.origin, g.voxel,
                        snap.truncation, self.config.samples, self.body_velocities(q, v), self.config.soft_speed,
                        self.funnel, self.speed_margin, self.cutoff, np.empty(self.config.samples), p, u, b, d)
        return p, u, b, d

    def compute(self, state: TickState, terms: LawTerms) -> Inequality:
        n = state.n
        P = self.pairs
        C = np.zeros((self.rows, n))
        lower = np.full(self.rows, -np.inf)
        upper = np.full(self.rows, np.inf)
        snap: MapSnapshot = self.source.snapshot  # type: ignore[attr-defined]
        pairs = field_pairs(snap, state.segments, self.radii, self.config, self.cutoff, smooth=self.smooth)
        self._last, self._ws = pairs, None
        idx = np.flatnonzero(pairs.active)
        if idx.size:
            J, drift = self.jacobians(state.q, state.v, pairs.link[idx], pairs.point[idx])
            nrm = pairs.normal[idx]
            rows = np.einsum("ri,rin->rn", nrm, J)
            hdot = rows @ state.v
            d = pairs.distance[idx]
            soft = pairs.soft[idx]
            vs = self.config.soft_speed
            # rigid inside the margin: away at min(k₀/k₁ (m − d), v_s), not at k₀/k₁ (m − d), with gain k_r
            away = np.minimum(self.k0 / self.k1 * (self.margin - d), vs)
            rigid = np.where(d < self.margin, -self.recovery_gain * (hdot - away),
                             -self.k1 * hdot - self.k0 * (d - self.margin))
            rhs = np.where(soft, -self.k1 * (hdot + vs) - self.k0 * np.maximum(d - self.soft_margin, 0.0),
                           rigid) - np.einsum("ri,ri->r", nrm, drift)
            if self.torque is not None:  # rigid rows inside the margin: within reach of the torque window
                inside = np.flatnonzero(~soft & (d < self.margin))
                if inside.size:
                    rhs[inside] = np.minimum(rhs[inside], reach_cap(state, rows[inside], torque=self.torque))
            C[idx] = rows
            lower[idx] = rhs
        # the soft speed rows: the point's velocity h ahead along u no faster than b
        p, u, b, _ = self.speed_points(snap, state.segments, state.q, state.v)
        sp = np.flatnonzero(np.isfinite(b))
        if sp.size:
            J, drift = self.jacobians(state.q, state.v, sp // 2, p[sp])
            uJ = np.einsum("ri,rin->rn", u[sp], J)
            C[P + sp] = -uJ
            lower[P + sp] = (uJ @ state.v - b[sp]) / self.horizon + np.einsum("ri,ri->r", u[sp], drift)
        return Inequality(C, lower, upper)
