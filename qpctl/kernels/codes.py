"""The tick's codes: where each setting, counter, flag and output sits in the workspace's arrays.

The kernels and the Python shell (:mod:`qpctl.tick`, the controllers) index :class:`TickWork`'s small
arrays by these constants (:mod:`qpctl.kernels.work` lists the arrays). A new setting is a new
constant here and a larger ``*_SIZE``; a new kind of obstacle a new ``KIND_*``.
"""

from __future__ import annotations

from numba import njit

# Obstacle kinds (TickWork.ob_kind): closed form in the kernels (spheres and capsules in
# qpctl.kernels.geometry, boxes and cylinders in qpctl.kernels.solids), or python-fcl's (KIND_FCL)
KIND_SPHERE, KIND_CAPSULE, KIND_FCL, KIND_BOX, KIND_CYLINDER = 0, 1, 2, 3, 4
# Pair states (TickWork.pr_state)
PAIR_OK, PAIR_FCL, PAIR_FAR = 0, 1, 2

# Float settings (TickWork.fpar)
FP_KP, FP_KV, FP_KN, FP_VREF, FP_DI, FP_DS, FP_GDAMP, FP_PINV_EPS, FP_CUTOFF = range(9)
FP_BK0, FP_BK1, FP_JK0, FP_JK1, FP_JKV, FP_SL1, FP_SL2, FP_WACC, FP_WPOST, FP_PKP, FP_PKD = range(9, 20)
FP_GRID_H, FP_CLEARANCE, FP_T, FP_DAMP, FP_DAMP_KD = 20, 21, 22, 23, 24
FP_SK0, FP_SK1, FP_SDS, FP_SELF_CLEARANCE, FP_SCUT = 25, 26, 27, 28, 29
# the depth map's field rows (qpctl.kernels.field_rows): voxel [m], truncation [m], rigid margin [m],
# soft_speed [m/s], cutoff [m], k0 [1/s²], k1 [1/s], the soft rows' margin [m]
FP_FD_VOXEL, FP_FD_TRUNC, FP_FD_MARGIN, FP_FD_VS, FP_FD_CUT, FP_FD_K0, FP_FD_K1, FP_FD_SMARGIN = range(30, 38)
# the braking-aware rows (qpctl.kernels.braking): the share of the drives' means, the margin [m], the period [s]
FP_BRK_SHARE, FP_BRK_MARGIN, FP_BRK_DT = 38, 39, 40
# the field's soft speed rows: where their bound reaches soft_speed [m], their horizon [s], the funnel's slope [1/s]
FP_FD_VMARGIN, FP_FD_HORIZON, FP_FD_VSLOPE = 41, 42, 43
FP_FD_KR = 44  # the rigid rows' recovery gain inside their margin [1/s]
# a time-scaled path's clock (qpctl.paths.TimeScaledPath, written by its advance): the path's time s [s] at
# the advance, κ, κ̇ [1/s], the time of the advance [s]
FP_TS = 45
FP_SIZE = 49
# Int settings (TickWork.ipar)
IP_JDOT_EN, IP_DRIFT_RIGID, IP_CAPACITY, IP_TORQUE_ROW0, IP_BARRIER_ROW0, IP_JOINT_LIMITS = range(6)
IP_POSTURE, IP_N_IN, IP_BDRIFT, IP_DAMPING, IP_SELF_ROW0 = range(6, 11)
IP_FIELD_ROW0, IP_FD_SAMPLES, IP_FD_RPL = range(11, 14)  # the field rows' first row (−1: none), samples, rows per link
IP_BRAKING = 14  # 1: the barrier and joint-limit rows are braking-aware too
IP_N_SIGMA = 15  # the constraints' own slack columns σ (after the task's s⁺, s⁻)
IP_TIME_SCALED = 16  # 1: the path is time-scaled (FP_TS … FP_TS + 3 its clock)
IP_SIZE = 17
# Counters (TickWork.cnt)
CNT_PAIRS, CNT_FCL, CNT_LOOKAHEAD, CNT_DROPPED = range(4)
CNT_SIZE = 4
# Flags (TickWork.flags)
FLAG_SINGULAR_TERMS, FLAG_SINGULAR_CF, FLAG_CLIPPED = range(3)
FLAG_SIZE = 3

# The output record (TickWork.rec): tau, qdd (n), x_d, ẋ_d, ẍ_d, x (m), e_N (n), then scalars
#   clearance [m], singular (0/1), pairs, pairs dropped (beyond the barrier's rows), slack norm,
#   active rows, the answer's largest relative violation, the torque clip [N·m], solver iterations,
#   stage times [µs] (state kernel, law and rows, solve), active families (bit 0: a torque-limit row,
#   bit 1: an obstacle-barrier row, bit 2: a depth-map field row), joints whose torque moved by its whole
#   rate limit, the rigid-body pass's time [µs] when the compiled tick ran it (qpctl.kernels.pin_native)
R_CLEARANCE, R_SINGULAR, R_PAIRS, R_DROPPED, R_SLACK, R_ACTIVE, R_VIOLATION, R_CLIPPED = range(8)
R_ITERATIONS, R_STATE_US, R_BUILD_US, R_SOLVE_US, R_ACTIVE_MASK, R_RATE_HITS, R_RIGID_US = range(8, 15)
R_SCALARS = 15

# What the state kernel returns when Python must finish the state (python-fcl's pairs, or a
# look-ahead barrier drift) before the law: the tick's entry points pass it on (qpctl.kernels.tick)
STATE_PYTHON = 5
# What the one-call QP tick returns when q or v does not have the robot's n joints
BAD_SHAPE = -2

@njit(cache=True)
def record_scalars(n: int, m: int) -> int:
    """Offset of the record's scalars: after τ, q̈, x_d, ẋ_d, ẍ_d, x and e_N."""
    return 3 * n + 4 * m
