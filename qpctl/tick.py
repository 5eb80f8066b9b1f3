"""The tick's workspace: fixed-shape arrays laid out once per controller, run by compiled kernels.

DESIGN.md §5. A :class:`Workspace` owns its own ``pin.Data`` and binds Pinocchio's arrays as numpy
views (:func:`rigid_pass` refreshes them in place), allocates every array the kernels of
:mod:`qpctl.kernels.tick` write (rigid-body terms, link–obstacle pairs at their full capacity,
law terms, the QP in DAQP's layout, the output record), and runs a tick as a handful of calls:

    rigid_pass (crba, nonLinearEffects; inside the one-call kernels on the native library) → kernels.state → [python-fcl for other shapes] → law kernel → [solve]

Spheres, capsules, boxes and cylinders are in closed form in the kernels. Obstacles of any other
shape (a mesh, a shape a user registers) are the only per-pair Python work: python-fcl's queries and
the look-ahead difference of their barrier drift (and of capsule pairs whose axes meet or run
parallel). Everything the kernels compute has a
reference implementation elsewhere in the package (:class:`qpctl.dynamics.Dynamics`'s Pinocchio and
python-fcl path, :mod:`qpctl.law`, :class:`qpctl.formulation.Formulation`) that the tests compare.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pinocchio as pin

from qpctl.errors import ConfigError
from qpctl.geometry.distance import DistanceEngine, PairSet
from qpctl.geometry.frames import rotation_z_to
from qpctl.geometry.obstacles import Obstacle
from qpctl.kernels import codes
from qpctl.kernels import tick as K
from qpctl.kernels.lie import joint_angles
from qpctl.kernels.pin_native import rigid_at
from qpctl.kernels.work import FIELDS, SJ_ROWS, SV_ROWS, new_tick_work
from qpctl.law import LawGains, LawTerms
from qpctl.native.rigid import NativeRigid, float_view
from qpctl.paths import PosePath, Reference, TimeScaledPath, WaypointPath
from qpctl.qp import Problem
from qpctl.robot.model import RobotModel
from qpctl.state import SelfPairState, TickState

GRID_MIN_OBSTACLES = 32  # the broad-phase grid is used above this many static obstacles (broadphase=None)
GRID_MAX_CELLS = 2_000_000


_crba, _nle, _WORLD = pin.crba, pin.nonLinearEffects, pin.Convention.WORLD


def rigid_pass(model: pin.Model, data: pin.Data, q: np.ndarray, v: np.ndarray) -> None:
    """Every rigid-body quantity the tick reads, by Pinocchio, into ``data``: ``crba`` in the world
    convention (the placements oMi, the joint Jacobians J and M's upper triangle) and
    ``nonLinearEffects`` (nle = C(q, q̇)q̇ + G(q), and a_gf: the joints' q̈ = 0 accelerations with the
    world accelerating at −g). The two calls take 2.6 µs on the Panda where ``computeAllTerms``, which
    also computes the centre of mass, its Jacobian and the energies, takes 3.6 µs (docs/performance.md).
    Every tick path calls it (the controllers' fast and general paths, :meth:`Workspace.state`, warm-up).
    The kernels give gravity back from ``model.gravity`` itself (:func:`bind_pinocchio`'s live view), so
    a gravity changed after the controller was built counts from the next tick."""
    _crba(model, data, q, _WORLD)
    _nle(model, data, q, v)


def bind_pinocchio(model: pin.Model, data: pin.Data) -> dict[str, np.ndarray]:
    """Numpy views of ``data``'s placements, accelerations (a_gf), Jacobians, inertia and bias forces,
    and of ``model``'s gravity (its linear part, the world acceleration a_gf omits).

    Checked against Pinocchio's own accessors once, on a random state after :func:`rigid_pass`: a
    Pinocchio build that lays its ``Data`` out otherwise, or whose ``rigid_pass`` leaves a view stale,
    raises here rather than returning wrong numbers later.
    """
    nj, n = model.njoints, model.nv
    placements = float_view(data.oMi[0].rotation.__array_interface__["data"][0], (nj, 12))
    accelerations = float_view(data.a_gf[0].linear.__array_interface__["data"][0], (nj, 6))
    gravity = model.gravity.linear  # Pinocchio returns the model's own memory (checked below)
    views = {"oMi": placements, "acc_gf": accelerations, "Jt": data.J.T, "Mt": data.M.T, "nle": data.nle,
             "gravity": gravity}
    rng = np.random.default_rng(0)
    q = pin.randomConfiguration(model, -np.ones(model.nq), np.ones(model.nq)) if model.nq else np.zeros(0)
    v = rng.uniform(-1, 1, n)
    rigid_pass(model, data, q, v)
    full = model.createData()
    pin.computeAllTerms(model, full, q, v)
    for j in range(nj):
        H = full.oMi[j].homogeneous
        ok = np.array_equal(placements[j, :9].reshape(3, 3).T, H[:3, :3]) and np.array_equal(placements[j, 9:],
                                                                                            H[:3, 3])
        ok = ok and np.array_equal(accelerations[j], data.a_gf[j].vector)
        if not ok:
            raise RuntimeError("this Pinocchio build lays out pin.Data differently from what qpctl's tick expects")
    for name in ("Jt", "Mt", "nle", "gravity"):
        if views[name].flags["OWNDATA"] or not views[name].flags["C_CONTIGUOUS"]:
            raise RuntimeError(f"pin.Data's {name} is not a contiguous view in this Pinocchio build")
    if gravity.__array_interface__["data"][0] != model.gravity.linear.__array_interface__["data"][0]:
        raise RuntimeError("this Pinocchio build returns a copy of model.gravity, not the model's own memory")
    if not (np.array_equal(data.J, full.J) and np.allclose(np.triu(data.M), np.triu(full.M), rtol=1e-12, atol=1e-12)
            and np.allclose(data.nle, full.nle, rtol=1e-12, atol=1e-12)):
        raise RuntimeError("Pinocchio's crba and nonLinearEffects disagree with its computeAllTerms in this build")
    return views


#: The obstacle shapes the kernels compute in closed form; every other shape is python-fcl's (KIND_FCL).
KINDS = {"sphere": codes.KIND_SPHERE, "capsule": codes.KIND_CAPSULE, "box": codes.KIND_BOX,
         "cylinder": codes.KIND_CYLINDER}


def _half_extents(obstacle: Obstacle) -> tuple[float, float, float]:
    """A box's half extents, a cylinder's (radius, radius, half length) [m]; zeros for other shapes."""
    if obstacle.shape == "box" and obstacle.size is not None:
        hx, hy, hz = (0.5 * float(s) for s in obstacle.size)
        return hx, hy, hz
    if obstacle.shape == "cylinder":
        return obstacle.radius, obstacle.radius, 0.5 * obstacle.length
    return 0.0, 0.0, 0.0


def _bounding_capsule(obstacle: Obstacle, rot: np.ndarray, half: np.ndarray) -> tuple[np.ndarray, float]:
    """(axis vector s [m], radius [m]) of the capsule the kernels compute for this obstacle: a
    capsule's own; a sphere's (s = 0); for a box or cylinder the capsule that contains it (about its
    longest axis, the cross radius), whose distance bounds the exact one from below (the pair loop's
    cheap test before :mod:`qpctl.kernels.solids`); zero for python-fcl's shapes."""
    if obstacle.shape == "capsule":
        return obstacle.length * obstacle.axis / np.linalg.norm(obstacle.axis), obstacle.radius
    if obstacle.shape == "sphere":
        return np.zeros(3), obstacle.radius
    if obstacle.shape == "cylinder":
        return 2.0 * half[2] * rot[:, 2], float(half[0])
    if obstacle.shape == "box":
        k = int(np.argmax(half))
        others = [half[c] for c in range(3) if c != k]
        return 2.0 * half[k] * rot[:, k], float(np.hypot(*others))
    return np.zeros(3), 0.0


def _supports(model: pin.Model, joint: int) -> np.ndarray:
    """(n,) 1 where joint velocity k moves joint ``joint``'s body."""
    mask = np.zeros(model.nv)
    for k in model.supports[joint]:
        if k > 0:
            jm = model.joints[k]
            mask[jm.idx_v : jm.idx_v + jm.nv] = 1.0
    return mask


@dataclass
class FieldSpec:
    """The depth map's field rows in the compiled QP (:mod:`qpctl.kernels.field_rows`): where the
    newest snapshot is read (``source.snapshot``, every tick), the rows' settings, and the constraint
    that owns them (told of the workspace, whose arrays then hold its pairs: ``owner.bind(ws)``)."""

    source: Any
    owner: Any
    rows: int  # 2 channels × links × rows_per_link pairs, then 2 soft speed rows per link
    samples: int
    rows_per_link: int
    margin: float  # the rigid rows' margin [m]
    soft_speed: float  # [m/s]
    cutoff: float  # [m]
    k0: float  # [1/s²]
    k1: float  # [1/s]
    soft_margin: float = 0.0  # the soft rows' margin [m]
    speed_margin: float = 0.0  # within this of a leaf's voxels the soft speed rows bound soft_speed [m]
    horizon: float = 1e-3  # the soft speed rows' horizon [s]
    funnel: float = 10.0  # the slope of their bound beyond speed_margin [1/s]
    recovery_gain: float = 10.0  # a rigid row inside its margin: ḧ ≥ −k_r(ḣ − v_a) [1/s]


@dataclass
class QPSpec:
    """What the compiled QP assembly needs from a controller's tasks and constraints (one of each
    standard kind; see :func:`qpctl.controllers.qp.compiled_spec`)."""

    acc_weight: float
    slack_l1: float
    slack_l2: float
    posture: tuple[np.ndarray, float, float, float] | None  # (q_ref, weight, kp, kd)
    damping: tuple[float, float] | None  # (relative weight ρ, gain K_d)
    rows: list[tuple[str, int]]  # (constraint name, its row count), in the constraints' order
    torque: Any  # the TorqueLimit (its limits, and the last commanded torque the workspace shares), or None
    joint_limits: tuple[Any, ...] | None  # q_min, q_max, v_max (arrays), k0, k1, kv (floats), qdd_max
    barrier: tuple[int, float, float, bool] | None  # capacity, k0, k1, rigid drift
    row_names: list[str]
    self_barrier: tuple[float, float, float] | None = None  # k0, k1, d_safe of the self-collision rows
    task_weights: np.ndarray | None = None  # (m,) the task rows' weights (None: 1)
    row_kinds: list[str] | None = None  # one per row: its constraint's kind (Constraint.kind)
    braking: Any = None  # the Braking of the braking-aware rows (qpctl.constraints.braking), or None
    field: FieldSpec | None = None  # the depth map's field rows
    # the constraints' slack columns (Constraint.slack_columns), after the task's: (first row, the column's
    # entries in its rows, ℓ₁, ℓ₂), in both layouts
    slack_columns: list[tuple[int, np.ndarray, float, float]] | None = None

    @property
    def n_in(self) -> int:
        """The QP's inequality rows, every constraint's."""
        return sum(r for _, r in self.rows)


class QPBuffers:
    """One QP layout in DAQP's convention, and a :class:`~qpctl.qp.Problem` of views onto it.

    x = [q̈ (n), s⁺ (k), s⁻ (k), σ (the constraints' slack columns, Constraint.slack_columns)] with k slack
    rows (0 for the hard layout); rows = [C; A],
    bu = [ub; u; b], bl = [lb; l; b], sense marks the equality rows. The tick-independent entries
    (slack columns, costs and bounds, inactive rows' infinite bounds) are set here, once.
    """

    def __init__(self, n: int, m: int, spec: QPSpec, *, relax: bool) -> None:
        soft = relax and (spec.slack_l1 > 0 or spec.slack_l2 > 0)
        k = m if soft else 0
        cols = spec.slack_columns or []
        nv = n + 2 * k + len(cols)
        n_in = spec.n_in
        self.n, self.nv, self.n_in, self.n_eq, self.relaxed = n, nv, n_in, m, soft
        self.H = np.zeros((nv, nv))
        self.f = np.zeros(nv)
        self.rows = np.zeros((n_in + m, nv))
        self.bu = np.full(nv + n_in + m, np.inf)
        self.bl = np.full(nv + n_in + m, -np.inf)
        self.sense = np.zeros(nv + n_in + m, dtype=np.int32)
        self.sense[nv + n_in :] = 5  # equality
        if k:
            self.rows[n_in:, n : n + k] = np.eye(k)
            self.rows[n_in:, n + k : n + 2 * k] = -np.eye(k)
            self.f[n : n + 2 * k] = spec.slack_l1
            self.H[np.arange(n, n + 2 * k), np.arange(n, n + 2 * k)] = max(spec.slack_l2, 1e-9)
            self.bl[n : n + 2 * k] = 0.0  # s⁺, s⁻ ≥ 0
        for j, (r0, col, l1, l2) in enumerate(cols):  # a constraint's σ ≥ 0, its rows' entries set once
            c = n + 2 * k + j
            self.rows[r0 : r0 + col.size, c] = col
            self.f[c], self.H[c, c], self.bl[c] = l1, max(l2, 1e-9), 0.0
        self.x = np.zeros(nv)
        self.problem = Problem(self.H, self.f, self.rows[n_in:], self.bu[nv + n_in :], self.rows[:n_in],
                               self.bl[nv : nv + n_in], self.bu[nv : nv + n_in], self.bl[:nv], self.bu[:nv], n,
                               list(spec.row_names), list(spec.row_kinds or ()))


class RecordLayout:
    """Where each output sits in the tick's record (one float64 row, copied once per tick)."""

    def __init__(self, n: int, m: int) -> None:
        self.n, self.m = n, m
        self.tau = slice(0, n)
        self.qdd = slice(n, 2 * n)
        self.x_ref = slice(2 * n, 2 * n + m)
        self.xd_ref = slice(2 * n + m, 2 * n + 2 * m)
        self.xdd_ref = slice(2 * n + 2 * m, 2 * n + 3 * m)
        self.x = slice(2 * n + 3 * m, 2 * n + 4 * m)
        self.e_null = slice(2 * n + 4 * m, 3 * n + 4 * m)
        self.scalars = 3 * n + 4 * m
        self.size = self.scalars + codes.R_SCALARS


class Workspace:
    """The arrays of one controller's tick and the :class:`TickWork` its kernels receive.

    Args:
        robot, obstacles, path: the controller's.
        gains: its :class:`~qpctl.law.LawGains` (None: state only, no law).
        cutoff: pairs farther than this [m] are not listed (the influence distance).
        spec: the QP's layout, or None for the closed forms.
        broadphase: a uniform grid over the static obstacles (None: above GRID_MIN_OBSTACLES).
        barrier_drift: compute every pair's barrier drift (the QP's spec implies it unless its drift
            is "rigid").
        native_rigid: the one-call kernels run Pinocchio's rigid-body pass themselves, on the native
            library (:mod:`qpctl.native.rigid`; the controllers' workspaces), where it is available and
            the configuration is a vector space; ``data`` is then not the views' memory.
    """

    def __init__(self, robot: RobotModel, obstacles: Sequence[Obstacle], path: object, gains: LawGains | None,
                 cutoff: float, *, spec: QPSpec | None = None, broadphase: bool | None = None,
                 barrier_drift: bool = False, self_pairs: Sequence[tuple[int, int]] = (),
                 self_cutoff: float = math.inf, native_rigid: bool = False) -> None:
        model = robot.model
        self.robot, self.model = robot, model
        self.data = model.createData()
        self.obstacles = list(obstacles)
        self.path = path
        self.spec = spec
        n, m, L, O = model.nv, robot.m, len(robot.capsules), len(self.obstacles)
        self.n, self.m = n, m
        # a configuration of nq ≠ nv entries (continuous, planar joints): the kernels read one coordinate
        # per degree of freedom (joint_view), the posture's error comes from pin.difference
        self.nq, self.lie = model.nq, robot.lie
        self.q_config, self.q_angles = np.zeros(model.nq), np.zeros(n)
        self.posture_config: np.ndarray | None = None
        f = self.__dict__
        f.update(bind_pinocchio(model, self.data))
        # the compiled tick's own rigid-body pass (qpctl.native.rigid): the views then read its Data
        self._native = NativeRigid.create(model) if native_rigid else None
        self.pin_native = np.zeros(2, np.int64)
        if self._native is not None:
            f.update(self._native.views)
            self.pin_native[:] = self._native.address, self._native.handle
        #: True where Python's rigid_pass fills the views before a kernel; False where the one-call
        #: kernels run the pass themselves (and rigid() calls it for the other paths)
        self.py_rigid = self._native is None
        # robot
        self.cap_joint = np.array([c.joint_id for c in robot.capsules], dtype=np.int64)
        self.cap_local = np.array([[c.p0, c.p1] for c in robot.capsules], float).reshape(L, 2, 3)
        self.cap_radius = np.array([c.radius for c in robot.capsules], float)
        self.cap_support = np.array([_supports(model, c.joint_id) for c in robot.capsules]).reshape(L, n)
        frame = model.frames[robot.ee_frame_id]
        self.ee_joint = int(frame.parentJoint)
        self.ee_local = np.array(frame.placement.translation, float)
        self.ee_support = _supports(model, self.ee_joint)
        # every task frame (several arms: robot.task_frames), its rows along task_axes stacked in order
        self.axes = np.tile(np.array(robot.task_axes, dtype=np.int64), len(robot.frames))
        tk = [model.frames[f] for f in robot.task_frame_ids]
        self.tk_joint = np.array([int(f.parentJoint) for f in tk], dtype=np.int64)
        self.tk_local = np.array([f.placement.translation for f in tk], float).reshape(len(tk), 3)
        self.tk_support = np.array([_supports(model, int(f.parentJoint)) for f in tk]).reshape(len(tk), n)
        # the oriented task frames' rows, frame after frame (ee_frame's alone with one: the first)
        oriented = list(robot.oriented_frames) or [0]
        specs = [robot.frame_orientation(i) for i in oriented]
        codes_of = [o.codes() for o in specs]
        self.ori_rows = np.concatenate(codes_of).astype(np.int64)
        self.ori_start = np.concatenate([[0], np.cumsum([c.size for c in codes_of])]).astype(np.int64)
        self.ori_tk = np.array(oriented, dtype=np.int64)
        self.ee_rot = np.array([robot.frame_rotation(i) for i in oriented], float)
        self.ori_basis = np.array([o.basis() for o in specs], float)
        self.ori_axis = np.array([o.approach_axis for o in specs], float)
        self.ee_R, self.ee_w = np.tile(np.eye(3), (len(oriented), 1, 1)), np.zeros((len(oriented), 6))
        self.task_w = np.ones(m)
        if spec is not None and spec.task_weights is not None:
            if spec.task_weights.shape != (m,):
                raise ConfigError(f"needs {m} weights (one per task row), got {spec.task_weights.size}",
                                  key="controller.task_weights")
            self.task_w = np.asarray(spec.task_weights, float).copy()
        P = len(self_pairs)
        self.sc_pairs = np.array(self_pairs, dtype=np.int64).reshape(P, 2)
        self.sc_d, self.sc_n, self.sc_row = np.full(P, np.inf), np.zeros((P, 3)), np.zeros((P, n))
        self.sc_hdot, self.sc_drift = np.zeros(P), np.zeros(P)
        m_p = robot.m_position
        # scene
        self.ob_kind = np.array([KINDS.get(o.shape, codes.KIND_FCL) for o in self.obstacles], dtype=np.int64)
        self.ob_bound = np.array([o.bounding_radius() for o in self.obstacles], float)
        self.ob_rot = np.array([rotation_z_to(o.axis) for o in self.obstacles], float).reshape(O, 3, 3)
        self.ob_half = np.array([_half_extents(o) for o in self.obstacles], float).reshape(O, 3)
        capsules = [_bounding_capsule(o, R, h) for o, R, h in zip(self.obstacles, self.ob_rot, self.ob_half)]
        self.ob_axis = np.array([c[0] for c in capsules], float).reshape(O, 3)
        self.ob_radius = np.array([c[1] for c in capsules], float)
        self.ob_pos0 = np.array([o.position for o in self.obstacles], float).reshape(O, 3)
        self.ob_vel0 = np.array([o.velocity for o in self.obstacles], float).reshape(O, 3)
        self.ob_amp = np.array([o.amplitude for o in self.obstacles], float).reshape(O, 3)
        self.ob_omega = np.array([2 * np.pi * o.frequency for o in self.obstacles], float)
        self.ob_vref = np.array([np.nan if o.v_ref is None else float(o.v_ref) for o in self.obstacles], float)
        self.moving = np.array([j for j, o in enumerate(self.obstacles) if o.moving], dtype=np.int64)
        self.ob_c = np.array([o.position_at(0.0) for o in self.obstacles], float).reshape(O, 3)
        self.ob_v = np.array([o.velocity_at(0.0) for o in self.obstacles], float).reshape(O, 3)
        self.ob_a = np.array([o.acceleration_at(0.0) for o in self.obstacles], float).reshape(O, 3)
        self.has_fcl = bool(np.any(self.ob_kind == codes.KIND_FCL))
        self._fcl = DistanceEngine(self.cap_radius, self.obstacles, broadphase=False) if self.has_fcl else None
        self._probe_data = model.createData() if self.has_fcl else None
        self.pin_s = self.state_s = 0.0  # the last tick's stage wall times [s]
        self.drift_step = 2e-3  # [s] look-ahead of the barrier drift's finite difference (python-fcl shapes)
        self.fpar = np.zeros(codes.FP_SIZE)
        self.ipar = np.zeros(codes.IP_SIZE, dtype=np.int64)
        self._grid(broadphase, cutoff)
        # path (None: state only); a time-scaled WaypointPath in the kernel too, its clock bound to fpar
        scaled = path if isinstance(path, TimeScaledPath) and path.compiled else None
        base = scaled.path if scaled is not None else path
        self.path_in_kernel = isinstance(base, WaypointPath) or path is None
        if isinstance(base, WaypointPath):
            self.path_pts, self.path_t0, self.path_T = (np.ascontiguousarray(a, dtype=float)
                                                        for a in (base.points, base.starts, base.durations))
            if scaled is not None:
                self.ipar[codes.IP_TIME_SCALED] = 1
                scaled.bind(self.fpar[codes.FP_TS:codes.FP_TS + 4])
        else:  # None, or any callable t → Reference (evaluated in Python each tick)
            self.path_pts, self.path_t0, self.path_T = np.zeros((2, m_p)), np.zeros(1), np.ones(1)
        if isinstance(path, PosePath):
            if len(self.ori_rows):
                path.check_frames(len(self.ori_tk))
            self.rot_pts = np.ascontiguousarray(path.frame_rotations)
            self.rot_theta = np.ascontiguousarray(path.frame_theta)
        else:
            F = len(self.ori_tk)
            self.rot_pts, self.rot_theta = np.tile(np.eye(3), (F, 2, 1, 1)), np.zeros((F, 1, 3))
            if len(self.ori_rows) and path is not None:
                raise ConfigError("an orientation task needs a PosePath (a rotation at every point)",
                                  key="path.orientations")
        # gains and settings
        fp, ip = self.fpar, self.ipar
        g = gains if gains is not None else LawGains()
        fp[codes.FP_KP], fp[codes.FP_KV], fp[codes.FP_KN], fp[codes.FP_VREF] = g.kp, g.kv, g.kn, g.v_ref
        fp[codes.FP_DI], fp[codes.FP_DS], fp[codes.FP_GDAMP] = g.d_influence, g.d_safe, g.g_damping
        fp[codes.FP_PINV_EPS], fp[codes.FP_CUTOFF] = g.pinv_eps, cutoff
        ip[codes.IP_JDOT_EN] = int(bool(g.jdot_en))
        ip[codes.IP_BDRIFT] = int(barrier_drift)
        if g.obstacle_v_ref:
            self.ob_vref = np.asarray(g.obstacle_v_ref, float).copy()
        # a whole tick in one kernel call when the law needs nothing from Python between state and law
        self.fast = self.path_in_kernel and not g.jdot_en
        self.q_ref, self.tau_max, self.tau_rate = np.zeros(n), np.full(n, np.inf), np.full(n, np.inf)
        self.tau_prev, self.t_prev = np.full(n, np.nan), np.full(1, np.nan)
        self.q_min, self.q_max, self.v_max = np.full(n, -np.inf), np.full(n, np.inf), np.full(n, np.inf)
        self.qdd_max = np.full(n, np.inf)
        ip[codes.IP_TORQUE_ROW0] = ip[codes.IP_BARRIER_ROW0] = ip[codes.IP_SELF_ROW0] = ip[codes.IP_FIELD_ROW0] = -1
        self.fpar[codes.FP_SELF_CLEARANCE] = np.inf
        self.fpar[codes.FP_SCUT] = self_cutoff  # self pairs farther apart have no row (SelfCollisionBarrier.cutoff)
        capacity = 0
        if spec is not None:
            capacity = self._settings(spec)
        # per tick
        self.q, self.v = np.zeros(n), np.zeros(n)
        self.M, self.N, self.x, self.xdot = np.zeros((n, n)), np.zeros(n), np.zeros(m), np.zeros(m)
        self.J, self.drift, self.Jdot = np.zeros((m, n)), np.zeros(m), np.zeros((m, n))
        self.segments, self.body_vel = np.zeros((L, 2, 3)), np.zeros((L, 6))
        self.acc_off, self.acc_K, self.link_jac = np.zeros((L, 3)), np.zeros((L, 3, 3)), np.zeros((L, 3, n))
        self.ref = np.zeros((3, m))
        KC = max(L * O, 1)
        self.pr_link, self.pr_obs = np.zeros(KC, np.int64), np.zeros(KC, np.int64)
        self.pr_d, self.pr_n, self.pr_pl, self.pr_po = np.zeros(KC), np.zeros((KC, 3)), np.zeros((KC, 3)), np.zeros((KC, 3))
        self.pr_state = np.zeros(KC, np.int64)
        self.pr_jac, self.pr_drift = np.zeros((KC, 3, n)), np.zeros((KC, 3))
        self.pr_bdrift, self.pr_bok = np.zeros(KC), np.zeros(KC, np.int64)
        self.order = np.zeros(max(capacity, KC, 1), np.int64)
        self.cnt = np.zeros(codes.CNT_SIZE, np.int64)
        self.e, self.edot, self.a = np.zeros(m), np.zeros(m), np.zeros(m)
        self.g, self.e_null, self.qdd0 = np.zeros(n), np.zeros(n), np.zeros(n)
        self.Jb, self.Jp, self.qdd, self.tau = np.zeros((n, m)), np.zeros((n, m)), np.zeros(n), np.zeros(n)
        self.Lm, self.Lb, self.S = np.zeros((n, n)), np.zeros((n, n)), np.zeros((n, n))
        self.Bt, self.Vm = np.zeros((n, m)), np.zeros((m, m))
        self.Gm = np.zeros((m, m + 2))
        self.gA = np.zeros((n, 3 * max(KC, L)))
        self.w1, self.w2, self.w3 = np.zeros(n), np.zeros(n), np.zeros(max(n, 6))
        self.sv, self.sj, self.ts = np.zeros((SV_ROWS, 6)), np.zeros((SJ_ROWS, 3, n)), np.zeros(2, np.int64)
        self.cx = np.zeros(max(spec.n_in if spec is not None else 0, 1))
        self.flags = np.zeros(codes.FLAG_SIZE, np.int64)
        self._field_arrays(spec.field if spec is not None else None, L, n)
        self.layout = RecordLayout(n, m)
        self.rec = np.zeros(self.layout.size)
        self.fpar[codes.FP_CLEARANCE] = np.inf
        # the kernels' view holds these arrays borrowed (qpctl.kernels.borrow: no reference counts in the
        # kernels); this tuple keeps each alive as long as the workspace, whatever its attributes become
        self._pinned = tuple(f[name] for name in FIELDS)
        self.work = new_tick_work(*self._pinned)
        # the QP's layouts: with the task slack, and hard (the "on_failure" relaxation's first try)
        self.relaxed = QPBuffers(n, m, spec, relax=True) if spec is not None else None
        self.hard = QPBuffers(n, m, spec, relax=False) if spec is not None else None
        self.sync_field()

    def _field_arrays(self, fs: FieldSpec | None, L: int, n: int) -> None:
        """The field rows' arrays (one-voxel placeholders without a field: the kernels' types stay)."""
        self._field, self._field_snap = fs, None
        if fs is None:
            shape, origin, R, S, rpl = (1, 1, 1), np.zeros(3), 2 * L, 2, 1
        else:
            snap = fs.source.snapshot
            shape, origin = tuple(snap.grid.shape), np.asarray(snap.grid.origin, float).copy()
            R, S, rpl = 2 * L * fs.rows_per_link, fs.samples, fs.rows_per_link
            if fs.rows != R + 2 * L:
                raise ValueError(f"the field's {fs.rows} rows are not 2 channels × {L} links × {rpl} and 2 × {L} speed rows")
            fp, ip = self.fpar, self.ipar
            fp[codes.FP_FD_VOXEL], fp[codes.FP_FD_TRUNC] = snap.grid.voxel, snap.truncation
            fp[codes.FP_FD_MARGIN], fp[codes.FP_FD_VS], fp[codes.FP_FD_CUT] = fs.margin, fs.soft_speed, fs.cutoff
            fp[codes.FP_FD_K0], fp[codes.FP_FD_K1], fp[codes.FP_FD_SMARGIN] = fs.k0, fs.k1, fs.soft_margin
            fp[codes.FP_FD_VMARGIN], fp[codes.FP_FD_HORIZON], fp[codes.FP_FD_VSLOPE] = fs.speed_margin, fs.horizon, \
                fs.funnel
            fp[codes.FP_FD_KR] = fs.recovery_gain
            ip[codes.IP_FD_SAMPLES], ip[codes.IP_FD_RPL] = S, rpl
        self.fd_dist = np.zeros((2, *shape), np.float32)
        self.fd_grad = np.zeros((2, *shape, 3), np.float32)
        self.fd_pairs = np.zeros((*shape, 2), np.float32)
        for a in (self.fd_dist, self.fd_grad, self.fd_pairs):
            a.flags.writeable = False  # a snapshot's arrays are read-only
        self.fd_origin = origin
        self.fd_d, self.fd_n, self.fd_p = np.zeros(R), np.zeros((R, 3)), np.zeros((R, 3))
        self.fd_s, self.fd_ds = np.zeros(R), np.zeros((2, S))
        self.fd_jac, self.fd_drift = np.zeros((R, 3, n)), np.zeros((R, 3))
        self.fd_vp, self.fd_vu, self.fd_vb, self.fd_vd = np.zeros((2 * L, 3)), np.zeros((2 * L, 3)), np.zeros(2 * L), \
            np.zeros(2 * L)
        self.fd_vjac = np.zeros((3, n))
        if fs is None:
            self.ipar[codes.IP_FD_RPL], self.ipar[codes.IP_FD_SAMPLES] = rpl, S

    def sync_field(self) -> None:
        """The newest snapshot's grids into the kernels' view (a reference swap when it changed; none
        without a field). :class:`ValueError` when its grid is not the workspace's."""
        fs = self._field
        if fs is None:
            return
        fs.owner.bind(self)  # its pairs are this tick's, in these arrays
        snap = fs.source.snapshot
        if snap is self._field_snap:
            return
        if snap.dist.shape != self.fd_dist.shape or not np.array_equal(snap.grid.origin, self.fd_origin):
            raise ValueError(f"a snapshot of grid {snap.dist.shape[1:]} at {snap.grid.origin} in a workspace of "
                             f"{self.fd_dist.shape[1:]} at {self.fd_origin}")
        K.set_field(self.work, snap.dist, snap.grad, snap.pairs)
        self.fd_dist, self.fd_grad, self.fd_pairs = snap.dist, snap.grad, snap.pairs
        self._field_snap = snap

    def field_state(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The last tick's field pairs (copies): distances (R,) [m], normals (R, 3), witness points (R, 3) [m]."""
        return self.fd_d.copy(), self.fd_n.copy(), self.fd_p.copy()

    # -- construction helpers -------------------------------------------------------------------
    def _settings(self, spec: QPSpec) -> int:
        fp, ip = self.fpar, self.ipar
        fp[codes.FP_WACC], fp[codes.FP_SL1], fp[codes.FP_SL2] = spec.acc_weight, spec.slack_l1, spec.slack_l2
        if spec.posture is not None:
            q_ref, w, kp, kd = spec.posture
            self.q_ref = np.asarray(q_ref, float).copy()
            if self.lie:  # q_ref is a configuration; the kernel's (nv) is written each tick by joint_view
                self.posture_config, self.q_ref = self.q_ref, np.zeros(self.n)
            ip[codes.IP_POSTURE] = 1
            fp[codes.FP_WPOST], fp[codes.FP_PKP], fp[codes.FP_PKD] = w, kp, kd
        if spec.damping is not None:
            ip[codes.IP_DAMPING] = 1
            fp[codes.FP_DAMP], fp[codes.FP_DAMP_KD] = spec.damping
        row = 0
        capacity = 0
        for name, count in spec.rows:
            if name == "torque_limits":
                ip[codes.IP_TORQUE_ROW0] = row
            elif name == "obstacles":
                ip[codes.IP_BARRIER_ROW0] = row
                capacity = count
            elif spec.field is not None and name == spec.field.owner.name:
                ip[codes.IP_FIELD_ROW0] = row
            elif name == "self_collision":
                if count != len(self.sc_pairs):
                    raise ValueError("the self-collision rows and the workspace's pairs differ")
                ip[codes.IP_SELF_ROW0] = row
            row += count
        ip[codes.IP_N_IN] = row
        ip[codes.IP_N_SIGMA] = len(spec.slack_columns or ())
        if spec.torque is not None:
            self.tau_max, self.tau_rate = spec.torque.tau_max.copy(), spec.torque.tau_rate_max.copy()
            self.tau_prev, self.t_prev = spec.torque.previous, spec.torque.t_previous  # shared: the same arrays
        if spec.joint_limits is not None:
            q_min, q_max, v_max, k0, k1, kv, qdd_max = spec.joint_limits
            self.q_min, self.q_max, self.v_max, self.qdd_max = (np.asarray(a, float).copy()
                                                                for a in (q_min, q_max, v_max, qdd_max))
            fp[codes.FP_JK0], fp[codes.FP_JK1], fp[codes.FP_JKV] = k0, k1, kv
            ip[codes.IP_JOINT_LIMITS] = 1
        if spec.self_barrier is not None:
            fp[codes.FP_SK0], fp[codes.FP_SK1], fp[codes.FP_SDS] = spec.self_barrier
        if spec.braking is not None:  # the braking-aware rows (qpctl.kernels.braking)
            b = spec.braking
            ip[codes.IP_BRAKING] = 1
            fp[codes.FP_BRK_SHARE], fp[codes.FP_BRK_MARGIN], fp[codes.FP_BRK_DT] = b.share, b.margin, b.dt
            if spec.joint_limits is None:
                self.qdd_max = np.asarray(b.qdd_max, float).copy()
        if spec.barrier is not None:
            cap, bk0, bk1, rigid = spec.barrier
            ip[codes.IP_CAPACITY] = cap
            fp[codes.FP_BK0], fp[codes.FP_BK1] = bk0, bk1
            ip[codes.IP_DRIFT_RIGID] = int(rigid)
            ip[codes.IP_BDRIFT] = int(not rigid or ip[codes.IP_BDRIFT])
        return capacity

    def _grid(self, broadphase: bool | None, cutoff: float) -> None:
        """A uniform grid over the static obstacles' bounding spheres (CSR: cell → obstacles)."""
        static = [j for j, o in enumerate(self.obstacles) if not o.moving]
        use = len(static) > GRID_MIN_OBSTACLES if broadphase is None else bool(broadphase)
        use = use and bool(static) and math.isfinite(cutoff)
        self.grid_dims = np.zeros(3, np.int64)
        self.grid_lo = np.zeros(3)
        self.grid_start = np.zeros(1, np.int64)
        self.grid_items = np.zeros(0, np.int64)
        self.stamp = np.zeros(max(len(self.obstacles), 1), np.int64)
        if not use:
            return
        centres, radii = self.ob_c[static], self.ob_bound[static]
        lo, hi = (centres - radii[:, None]).min(axis=0), (centres + radii[:, None]).max(axis=0)
        h = max(cutoff + 2.0 * float(self.cap_radius.max(initial=0.0)), 1e-3)
        dims = np.maximum(np.floor((hi - lo) / h).astype(np.int64) + 1, 1)
        while int(np.prod(dims)) > GRID_MAX_CELLS:
            h *= 2.0
            dims = np.maximum(np.floor((hi - lo) / h).astype(np.int64) + 1, 1)
        cells: list[list[int]] = [[] for _ in range(int(np.prod(dims)))]
        for j, c, r in zip(static, centres, radii):
            a = np.clip(np.floor((c - r - lo) / h).astype(np.int64), 0, dims - 1)
            b = np.clip(np.floor((c + r - lo) / h).astype(np.int64), 0, dims - 1)
            for cx in range(a[0], b[0] + 1):
                for cy in range(a[1], b[1] + 1):
                    for cz in range(a[2], b[2] + 1):
                        cells[(cx * dims[1] + cy) * dims[2] + cz].append(j)
        self.grid_dims, self.grid_lo = dims, lo
        self.fpar[codes.FP_GRID_H] = h
        self.grid_start = np.concatenate([[0], np.cumsum([len(c) for c in cells])]).astype(np.int64)
        self.grid_items = np.array([j for c in cells for j in c], dtype=np.int64)

    # -- the tick -------------------------------------------------------------------------------
    def joint_view(self, q: np.ndarray) -> np.ndarray:
        """What the kernels take as q: ``q`` itself where nq == nv; else its angles (one per degree
        of freedom, :meth:`RobotModel.angles`), with the posture target written so that the kernel's
        q_ref − q is pin.difference(q, q_ref). Computed once per tick, before the state kernel."""
        if not self.lie:
            return q
        self.q_config[:] = q
        r, qa = self.robot, self.q_angles
        joint_angles(q, r._plain_q, r._plain_v, r._rot_q, r._rot_v, qa)  # RobotModel.angles, compiled
        if self.posture_config is not None:
            self.q_ref[:] = qa + pin.difference(self.model, q, self.posture_config)
        return qa

    def rigid(self, q: np.ndarray, v: np.ndarray) -> None:
        """The rigid-body pass at (q, v) into the views: :func:`rigid_pass`, or the native pass
        (float64 vectors: the callers have checked the state)."""
        if self.py_rigid:
            rigid_pass(self.model, self.data, q, v)
            return
        code = rigid_at(self.work, q, v)
        if code == 2:
            raise ValueError(f"q and v must have shapes ({self.nq},) and ({self.n},), got {np.shape(q)} and {np.shape(v)}")
        if code:
            raise RuntimeError(f"Pinocchio's rigid-body pass failed: {self._native.error()}")  # type: ignore[union-attr]

    def before_kernel(self, q: np.ndarray, v: np.ndarray) -> None:
        """What a one-call kernel needs before it runs: :func:`rigid_pass`, unless the kernel runs the
        pass itself (the native pass)."""
        if self.py_rigid:
            rigid_pass(self.model, self.data, q, v)

    def state(self, q: np.ndarray, v: np.ndarray, t: float) -> int:
        """:meth:`rigid` and the state kernel (and python-fcl's pairs, if any); −1 if the dynamics
        overflow at this state (or q, v are not finite), else 0. Records Pinocchio's and the kernel's wall
        times [s] in ``pin_s`` and ``state_s``."""
        start = time.perf_counter()
        self.rigid(q, v)
        mid = time.perf_counter()
        status = K.state(self.work, self.joint_view(q), v, t)
        if status != 0:
            if status < 0:
                return -1
            self._fcl_pairs(t)
        if not self.path_in_kernel:
            ref = self.path(t)  # type: ignore[operator]
            self.ref[0], self.ref[1], self.ref[2] = ref.x, ref.xd, ref.xdd
        if self.cnt[codes.CNT_LOOKAHEAD]:
            self._look_ahead(q, v, t)
        self.pin_s, self.state_s = mid - start, time.perf_counter() - mid
        return 0

    def finish_state(self, q: np.ndarray, v: np.ndarray, t: float) -> None:
        """What the state kernel left to Python (it returned STATE_PYTHON): python-fcl's pairs, then
        the look-ahead drift of the pairs without a closed form."""
        start = time.perf_counter()
        if self.cnt[codes.CNT_FCL]:
            self._fcl_pairs(t)
        if self.cnt[codes.CNT_LOOKAHEAD]:
            self._look_ahead(q, v, t)
        self.rec[self.layout.scalars + codes.R_STATE_US] += (time.perf_counter() - start) * 1e6

    def _fcl_pairs(self, t: float) -> None:
        """python-fcl for the pairs the kernel could not do in closed form (boxes, cylinders)."""
        engine = self._fcl
        assert engine is not None
        k = int(self.cnt[codes.CNT_PAIRS])
        pending = np.flatnonzero(self.pr_state[:k] == codes.PAIR_FCL)
        links = sorted(set(self.pr_link[pending].tolist()))
        engine.update(self.segments, t, links=links)
        cutoff = float(self.fpar[codes.FP_CUTOFF])
        for r in pending.tolist():
            out = engine._query(int(self.pr_link[r]), int(self.pr_obs[r]), cutoff)
            if out is None:
                self.pr_state[r] = codes.PAIR_FAR
                continue
            self.pr_d[r], self.pr_n[r], self.pr_pl[r], self.pr_po[r] = out
            self.pr_state[r] = codes.PAIR_OK
        K.finish_pairs(self.work)

    def _look_ahead(self, q: np.ndarray, v: np.ndarray, t: float) -> None:
        """∂ḣ/∂q q̇ + ∂ḣ/∂t of the pairs without a closed-form drift, by a forward difference of ḣ
        along the motion (q + δq̇, t + δ), witness points and normal recomputed by python-fcl there;
        δ = ``drift_step`` balances truncation (O(δ)) and the distance query's noise (O(1e-8/δ))."""
        engine = self._fcl
        data = self._probe_data
        if engine is None or data is None:  # closed-form shapes only: meeting or parallel axes
            engine = self._fcl = DistanceEngine(self.cap_radius, self.obstacles, broadphase=False)
            data = self._probe_data = self.model.createData()
        k = int(self.cnt[codes.CNT_PAIRS])
        idx = np.flatnonzero(self.pr_bok[:k] == 0)
        delta = self.drift_step
        pin.forwardKinematics(self.model, data, self.robot.integrate(q, delta * v), v)
        seg = np.empty_like(self.segments)
        for i, jid in enumerate(self.cap_joint.tolist()):
            seg[i, 0] = data.oMi[jid].act(self.cap_local[i, 0])
            seg[i, 1] = data.oMi[jid].act(self.cap_local[i, 1])
        links = self.pr_link[idx]
        engine.update(seg, t + delta, links=sorted(set(links.tolist())))
        for r in idx.tolist():
            i, j = int(self.pr_link[r]), int(self.pr_obs[r])
            hdot0 = float(self.pr_n[r] @ (self.pr_jac[r] @ v - self.ob_v[j]))
            _, normal, p_link, _ = engine.pair(i, j)
            body = pin.getVelocity(self.model, data, int(self.cap_joint[i]), pin.WORLD)
            v_point = body.linear + np.cross(body.angular, p_link)
            hdot1 = float(normal @ (v_point - engine.obstacle_velocities(np.array([j]))[0]))
            self.pr_bdrift[r] = (hdot1 - hdot0) / delta

    # -- snapshots for the Python paths ---------------------------------------------------------
    def snapshot(self) -> TickState:
        """The state of the last tick as a :class:`~qpctl.state.TickState` of copies."""
        k = int(self.cnt[codes.CNT_PAIRS])
        pairs = PairSet(self.pr_link[:k].copy(), self.pr_obs[:k].copy(), self.pr_d[:k].copy(), self.pr_n[:k].copy(),
                        self.pr_pl[:k].copy(), self.pr_po[:k].copy(), self.ob_v[self.pr_obs[:k]],
                        self.ob_a[self.pr_obs[:k]])
        bdrift = self.pr_bdrift[:k].copy() if self.ipar[codes.IP_BDRIFT] else None
        q = self.q_config if self.lie else self.q  # the configuration (the kernels hold its angles)
        return TickState(float(self.fpar[codes.FP_T]), q.copy(), self.v.copy(), self.M.copy(), self.N.copy(),
                         self.x.copy(), self.xdot.copy(), self.J.copy(), self.drift.copy(), self.link_jac.copy(),
                         self.segments.copy(), pairs, self.pr_jac[:k].copy(), self.pr_drift[:k].copy(),
                         float(self.fpar[codes.FP_CLEARANCE]), _barrier_drift=bdrift,
                         _jdot=self.Jdot.copy() if self.ipar[codes.IP_JDOT_EN] else None,  # Controller._state's
                         rotations=self.ee_R.copy() if len(self.ori_rows) else None,
                         self_pairs=SelfPairState(self.sc_d.copy(), self.sc_n.copy(), self.sc_row.copy(),
                                                  self.sc_hdot.copy(), self.sc_drift.copy())
                         if len(self.sc_pairs) else None)

    def reference(self) -> Reference:
        """x_d, ẋ_d, ẍ_d of the last tick (copies)."""
        return Reference(self.ref[0].copy(), self.ref[1].copy(), self.ref[2].copy())

    def terms(self) -> LawTerms:
        """The law's terms of the last tick (copies), as :func:`qpctl.law.law_terms` returns them."""
        return LawTerms(self.reference(), self.e.copy(), self.edot.copy(), self.a.copy(), self.g.copy(),
                        self.e_null.copy(), self.qdd0.copy(), bool(self.flags[codes.FLAG_SINGULAR_TERMS]))


class WorldClearance:
    """The exact least distance [m] between any link and any obstacle, every pair, no cutoff: what a
    simulator records as the world's clearance (negative when penetrating). Closed form for spheres
    and capsules (:func:`qpctl.kernels.clearance.min_distance`), python-fcl for the other shapes."""

    def __init__(self, robot: RobotModel, obstacles: Sequence[Obstacle],
                 self_pairs: Sequence[tuple[int, int]] = ()) -> None:
        self.ws = Workspace(robot, obstacles, None, None, math.inf, self_pairs=self_pairs)
        others = [o for o in obstacles if o.shape not in KINDS]
        self._fcl = DistanceEngine(self.ws.cap_radius, others, broadphase=False) if others else None
        self.any = bool(obstacles)
        self.self_clearance = math.inf  # [m] between the self pairs' capsules, at the last call
        # an owner's count of the evaluations (:meth:`at`), e.g. the verified backup's bound on its check
        # (qpctl.safety.backup.Meter: ``spend()`` at each evaluation, which may raise to end the check's work)
        self.meter: Any = None

    def __call__(self, q: np.ndarray, t: float) -> float:
        if not self.any and not len(self.ws.sc_pairs):
            return math.inf
        self.pose(q)
        return self.at(t)

    def pose(self, q: np.ndarray) -> None:
        """Place the links at q [rad] (Pinocchio's forward kinematics) for :meth:`at`."""
        pin.forwardKinematics(self.ws.model, self.ws.data, np.asarray(q, float))

    def at(self, t: float) -> float:
        """The clearance [m] of the links as last posed (:meth:`pose`) with the obstacles at t [s]: an arm
        held still against moving obstacles needs its kinematics once."""
        ws = self.ws
        if self.meter is not None:
            self.meter.spend()
        best = float(K.min_distance(ws.work, float(t)))
        if len(ws.sc_pairs):
            self.self_clearance = float(K.min_self_distance(ws.work))
        if self._fcl is not None:
            self._fcl.update(ws.segments, t)
            best = min(best, self._fcl.min_distance())
        return best
