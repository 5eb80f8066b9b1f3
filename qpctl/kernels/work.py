"""The tick's workspace: every fixed-shape array the compiled kernels read and write, in one object.

A :class:`TickWork` is a numba structref: the kernels receive it as one argument (about 0.8 µs to
pass, whatever the number of fields; forty separate arrays would cost 3–5 µs of dispatch per call),
while Python keeps its own references to the same numpy arrays (:class:`qpctl.tick.Workspace`). The
structref holds them borrowed (:mod:`qpctl.kernels.borrow`: no memory info, so no kernel pays an
atomic reference count to read one); the Workspace's references are what keep them alive.
Its fields are declared once here, in :data:`FIELDS`, grouped by who writes them:

* bound once: Pinocchio's arrays as numpy views (:func:`qpctl.tick.rigid_pass`, or the compiled tick's
  native pass, refreshes them in place);
* built once: the robot's capsules and task frame, the scene, the path, gains and QP settings;
* written every tick: the rigid-body terms, the pairs (fixed capacity: every link × obstacle pair),
  the law's terms, and the output record.
"""

from __future__ import annotations

from numba import njit
from numba.core import types
from numba.experimental import structref

from qpctl.kernels.borrow import borrow_all
from qpctl.kernels.lend import LentProxy


@structref.register
class TickWorkType(types.StructRef):  # type: ignore[name-defined]  # numba is untyped
    def preprocess_fields(self, fields: tuple[tuple[str, types.Type], ...]) -> tuple[tuple[str, types.Type], ...]:
        return tuple((name, types.unliteral(typ)) for name, typ in fields)  # type: ignore[attr-defined]


class TickWork(LentProxy):
    """The compiled kernels' view of a :class:`qpctl.tick.Workspace` (fields: :data:`FIELDS`)."""


FIELDS = (
    # -- Pinocchio's data, bound once as views (n joints, nj = n + 1 joint frames) --------------------
    "oMi",  # (nj, 12) joint placements: rotation column-major (9), then translation (3)
    "acc_gf",  # (nj, 6) joint accelerations at q̈ = 0 in their own frames (linear, angular), minus gravity
    #            (Pinocchio's a_gf: the world frame accelerating at −g, qpctl.tick.rigid_pass)
    "Jt",  # (n, 6) data.J transposed: world Jacobian column of each joint
    "Mt",  # (n, n) data.M transposed: its lower triangle holds the inertia matrix
    "nle",  # (n,) C(q, q̇)q̇ + G(q)
    "gravity",  # (3,) model.gravity's linear part [m/s²], a live view of the model: what a_gf omits
    "pin_native",  # (2,) int: the native rigid pass's function address and handle (qpctl.kernels.pin_native;
    #                0: Python's rigid_pass fills the views above before the kernels run)
    # -- robot, built once (L capsules, m task coordinates) ------------------------------------------
    "cap_joint",  # (L,) int: the joint whose body carries capsule i
    "cap_local",  # (L, 2, 3) capsule axis end points in that joint's frame [m]
    "cap_radius",  # (L,) [m]
    "cap_support",  # (L, n) 1 where joint k moves capsule i's body
    "ee_joint",  # int: the task frame's parent joint
    "ee_local",  # (3,) task point in that joint's frame [m]
    "ee_support",  # (n,)
    "axes",  # (m_p,) int: the world axes of the task's position rows (task_axes once per task frame)
    "tk_joint",  # (F,) int: each task frame's parent joint (the first: ee_joint)
    "tk_local",  # (F, 3) its task point in that joint's frame [m]
    "tk_support",  # (F, n) 1 where joint k moves it
    "ee_rot",  # (Fo, 3, 3) each oriented task frame's rotation in its parent joint's frame (Fo ≥ 1)
    "ori_rows",  # (m_o,) int: the orientation rows after the position rows, 0–2 a pose's world axis,
    #              3–4 an approach's row k = 1, 2 (qpctl.orientation), oriented frame after frame
    "ori_start",  # (Fo + 1,) int: oriented frame f's rows are ori_rows[ori_start[f]:ori_start[f + 1]]
    "ori_tk",  # (Fo,) int: its task frame (an index into tk_*)
    "ori_basis",  # (Fo, 2, 3) b_1, b_2 ⟂ its approach axis, in its task frame
    "ori_axis",  # (Fo, 3) its approach axis c in its task frame
    # -- scene, built once (O obstacles) -------------------------------------------------------------
    "ob_kind",  # (O,) int: KIND_SPHERE, KIND_CAPSULE, KIND_BOX, KIND_CYLINDER or KIND_FCL (python-fcl's)
    "ob_radius",  # (O,) [m] (a box's or cylinder's: that of its bounding capsule, see ob_axis)
    "ob_bound",  # (O,) bounding-sphere radius [m]
    "ob_axis",  # (O, 3) capsule axis vector s (length × unit axis; zero for a sphere and python-fcl's
    #             shapes; for a box or cylinder the axis of the capsule containing it) [m]
    "ob_rot",  # (O, 3, 3) a box's or cylinder's axes in the world (columns; z along its axis)
    "ob_half",  # (O, 3) a box's half extents; a cylinder's (radius, radius, half length) [m]
    "ob_pos0",  # (O, 3) centre at t = 0 [m]
    "ob_vel0",  # (O, 3) constant velocity [m/s]
    "ob_amp",  # (O, 3) sway amplitude [m]
    "ob_omega",  # (O,) sway angular frequency 2πf [rad/s]
    "ob_vref",  # (O,) the obstacle's own v_ref [m/s] (NaN: the controller's)
    "moving",  # (Mo,) int: the obstacles that move
    "grid_lo",  # (3,) broad phase: lower corner of the static obstacles' grid [m]
    "grid_dims",  # (3,) int: cells along x, y, z (0: no grid, every obstacle is a candidate)
    "grid_start",  # (cells + 1,) int: CSR offsets into grid_items
    "grid_items",  # (entries,) int: static obstacles overlapping each cell
    "stamp",  # (O,) int: last link that saw obstacle j as a candidate (deduplicates grid hits)
    # -- path (WaypointPath: K segments with quintic timing) ----------------------------------------
    "path_pts",  # (K + 1, m_p) [m]
    "rot_pts",  # (Fo, K + 1, 3, 3) a PosePath's rotations per oriented frame (world; unused without)
    "rot_theta",  # (Fo, K, 3) its segments' rotation vectors log(R_{k+1} R_kᵀ) [rad]
    "path_t0",  # (K,) segment start times [s]
    "path_T",  # (K,) segment durations [s]
    # -- gains and settings --------------------------------------------------------------------------
    "fpar",  # (FP_SIZE,) float settings, indexed by the FP_* constants of qpctl.kernels.codes
    "ipar",  # (IP_SIZE,) int settings, indexed by the IP_* constants
    "q_ref",  # (n,) posture task target [rad]
    "tau_max",  # (n,) [N·m]
    "tau_rate",  # (n,) torque-rate limits [N·m/s]
    "tau_prev",  # (n,) the torque commanded last tick [N·m] (TorqueLimit.previous, shared; NaN: none)
    "t_prev",  # (1,) its time [s] (TorqueLimit.t_previous, shared; NaN: none)
    "qdd_max",  # (n,) joint acceleration limits [rad/s²]
    "q_min",  # (n,)
    "q_max",  # (n,)
    "v_max",  # (n,)
    # -- per tick: the state and the obstacles at t -----------------------------------------------
    "q",  # (n,) joint positions of this tick [rad]
    "v",  # (n,) joint velocities [rad/s]
    "ob_c",  # (O, 3) centres [m]
    "ob_v",  # (O, 3) velocities [m/s]
    "ob_a",  # (O, 3) accelerations [m/s²]
    # -- per tick: rigid-body terms ------------------------------------------------------------------
    "M",  # (n, n) symmetric inertia [kg·m²]
    "N",  # (n,) [N·m]
    "x",  # (m,) task point [m] (0 on orientation rows: coordinates centred at the current R)
    "xdot",  # (m,) [m/s] (ω's components [rad/s] on orientation rows)
    "J",  # (m, n)
    "drift",  # (m,) J̇q̇ [m/s²] ([rad/s²] on orientation rows)
    "ee_R",  # (Fo, 3, 3) each oriented task frame's rotation in the world
    "ee_w",  # (Fo, 6) its angular velocity ω [rad/s] and q̈ = 0 angular acceleration α₀ [rad/s²] (world)
    "task_w",  # (m,) the task rows' weights in the QP (EndEffectorTask.weights; 1 by default)
    "Jdot",  # (m, n) J̇, filled by Python only when the law's J̇e_N term is on
    "segments",  # (L, 2, 3) capsule axes in the world [m]
    "body_vel",  # (L, 6) their world spatial velocities (v at the origin, ω)
    "acc_off",  # (L, 3) q̈ = 0 acceleration field a(p) = acc_off + acc_K p of each body
    "acc_K",  # (L, 3, 3)
    "link_jac",  # (L, 3, n) Jacobians of the capsules' mid-points
    "ref",  # (3, m) x_d, ẋ_d, ẍ_d
    # -- per tick: link–obstacle pairs (capacity KC = L × O; the first cnt[CNT_PAIRS] are valid) ----
    "pr_link",  # (KC,) int
    "pr_obs",  # (KC,) int
    "pr_d",  # (KC,) signed distance [m]
    "pr_n",  # (KC, 3) unit normal, obstacle → link
    "pr_pl",  # (KC, 3) witness point on the link [m]
    "pr_po",  # (KC, 3) witness point on the obstacle [m]
    "pr_state",  # (KC,) int: PAIR_OK, PAIR_FCL (python-fcl to query), PAIR_FAR (dropped after it)
    "pr_jac",  # (KC, 3, n) Jacobians of the link witness points
    "pr_drift",  # (KC, 3) J̇_p q̇ of the link witness points [m/s²]
    "pr_bdrift",  # (KC,) ḧ at q̈ = 0 (the barrier's drift) [m/s²]
    "pr_bok",  # (KC,) int: 1 where pr_bdrift is in closed form, 0 where Python's look-ahead fills it
    "order",  # (KC,) int: pairs by distance, nearest first
    "cnt",  # (CNT_SIZE,) int counters, indexed by the CNT_* constants
    # -- self-collision pairs (P capsule pairs, fixed at build) ----------------------------------------
    "sc_pairs",  # (P, 2) int: capsule indices i < j
    "sc_d",  # (P,) distance between the capsules [m]
    "sc_n",  # (P, 3) unit normal from capsule j's axis to capsule i's
    "sc_row",  # (P, n) nᵀ(J_p − J_q): ḣ = sc_row q̇
    "sc_hdot",  # (P,) [m/s]
    "sc_drift",  # (P,) ḧ at q̈ = 0 [m/s²]
    # -- the depth map's field (qpctl.kernels.field_rows; R = 2 channels × L × rows per link) ----------
    "fd_dist",  # (2, nx, ny, nz) float32, read-only: the newest snapshot's distance grids [m] (set_field)
    "fd_grad",  # (2, nx, ny, nz, 3) float32, read-only: their gradients
    "fd_pairs",  # (nx, ny, nz, 2) float32, read-only: fd_dist with the channels side by side (the samples' reads)
    "fd_origin",  # (3,) the grid's lower corner [m]
    "fd_d",  # (R,) per tick: the field pairs' distances from the capsules' surfaces [m]
    "fd_n",  # (R, 3) unit normals, away from the obstacle (zero: no pair)
    "fd_p",  # (R, 3) witness points on the links [m]
    "fd_s",  # (R,) scratch: axis parameters
    "fd_ds",  # (2, samples) scratch: both channels' distances along one axis
    "fd_jac",  # (R, 3, n) witness points' Jacobians (active rows)
    "fd_drift",  # (R, 3) their J̇_p q̇ [m/s²]
    "fd_vp",  # (2L, 3) the soft speed rows' points [m] (qpctl.kernels.field.speed_points)
    "fd_vu",  # (2L, 3) the unit directions of their velocities
    "fd_vb",  # (2L,) their speed bounds [m/s] (inf: no row)
    "fd_vd",  # (2L,) the field's distance there [m]
    "fd_vjac",  # (3, n) scratch: a speed point's Jacobian
    # -- per tick: law terms -------------------------------------------------------------------------
    "e",  # (m,) x_d − x [m]
    "edot",  # (m,) [m/s]
    "a",  # (m,) task acceleration target [m/s²]
    "g",  # (n,) obstacle reference joint velocity [rad/s]
    "e_null",  # (n,) null-space velocity error [rad/s]
    "qdd0",  # (n,) null-space acceleration target [rad/s²]
    "Jb",  # (n, m) J_b⁺ (Ryu-weighted, or Moore–Penrose for Hsu), formed only where damped (law._null_error)
    "Jp",  # (n, m) J_M⁺ of the closed form
    "qdd",  # (n,) commanded acceleration [rad/s²]
    "tau",  # (n,) commanded torque [N·m]
    "Lm",  # (n, n) Cholesky factor of M
    "Lb",  # (n, n) Cholesky factor of W_b (or of g's normal matrix, reused)
    "S",  # (n, n) scratch
    "Bt",  # (n, m) scratch: the transposed weighted Jacobian
    "Vm",  # (m, m) scratch: Jacobi rotations
    "Gm",  # (m, m + 2) scratch: the normal equations' Gram matrix and vectors (qpctl.kernels.small.normal_factor)
    "gA",  # (n, 3 max(KC, L)) scratch: the weighted rows of g's and W_b's normal matrices, packed
    "w1",  # (n,) scratch
    "w2",  # (n,) scratch
    "w3",  # (max(n, 3),) scratch
    "sv",  # (SV_ROWS, 6) scratch vectors of the state kernels (rows SV_*: no allocation per tick)
    "sj",  # (SJ_ROWS, 3, n) scratch point Jacobians of the state kernels (SJ_*)
    "ts",  # (2,) int: the clock's timespec (qpctl.kernels.clock.now_us)
    "cx",  # (max(n_in, 1),) scratch: C x of the QP's inequality rows (qp_finish)
    "flags",  # (FLAG_SIZE,) int: per-tick flags, indexed by the FLAG_* constants
    "rec",  # (record size,) the tick's output record (qpctl.tick.RecordLayout)
)


# Rows of the scratch arrays sv and sj: rigid_terms' (a body's spatial velocity, the task point, its
# acceleration; its Jacobian) and self_pairs' (the witness points; their Jacobians). The kernels pass
# rows by index (point_jacobian(ws, S, si, P, pi, out, oi)), not as views: a view taken in a loop costs
# an atomic reference count increment and decrement each time.
SV_VEL, SV_P, SV_A3, SV_SP, SV_SQ = range(5)
SV_ROWS = 5
SJ_TASK, SJ_SP, SJ_SQ = range(3)
SJ_ROWS = 3


def _make_proxy() -> None:
    structref.define_proxy(TickWork, TickWorkType, list(FIELDS))


_make_proxy()


@njit(cache=True)
def new_tick_work(*fields):  # type: ignore[no-untyped-def]
    """A TickWork of the arrays ``fields`` (in FIELDS order), built by a cached compiled constructor
    (TickWork(...) itself compiles its constructor anew in every process: ~3 s)."""
    return TickWork(*borrow_all(fields))
