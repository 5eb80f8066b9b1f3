"""Compile (or load from numba's on-disk cache) every entry point of the tick before a loop starts.

:func:`warmup` calls each kernel Python calls (:data:`qpctl.kernels.tick.__all__`) once, with the
argument types the controllers pass, on a small planar scene that takes every path: sphere, capsule
and box obstacles (one moving), the broad-phase grid, every QP row family, DAQP's C API on the
relaxed and the hard layout. It needs no controller: the controllers call it (``Controller.warmup``,
``qpctl warmup``). ``tests/test_warmup.py`` runs every controller path in a fresh process after it and
finds nothing left to compile.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from qpctl.constraints.constraints import TorqueLimit
from qpctl.geometry.obstacles import Obstacle
from qpctl.kernels import codes
from qpctl.kernels import tick as K
from qpctl.kernels.native_qp import new_native_qp, shortcut_scratch
from qpctl.law import LawGains
from qpctl.outcome import SOLUTION_RTOL
from qpctl.paths import WaypointPath
from qpctl.robot.model import planar_arm
from qpctl.solvers import daqp_native
from qpctl.tick import QPSpec, Workspace, WorldClearance

_WARM: dict[str, float] | None = None


def _spec(robot: Any, capacity: int) -> QPSpec:
    """Every row family of the compiled QP: torque window, joint bounds, obstacle barrier; a posture
    and a damping task (the types the controllers' specs have; the values matter little)."""
    n = robot.nv
    rows = [("torque_limits", n), ("obstacles", capacity)]
    return QPSpec(acc_weight=1.0, slack_l1=1e6, slack_l2=1e2, posture=(robot.q_home.astype(float), 1.0, 10.0, 5.0),
                  damping=(1e-3, 10.0), rows=rows, torque=TorqueLimit(robot.tau_max, robot.tau_rate_max),
                  joint_limits=(robot.q_min, robot.q_max, robot.v_max, 100.0, 20.0, 50.0, robot.qdd_max),
                  barrier=(capacity, 400.0, 40.0, False), row_names=[name for name, k in rows for _ in range(k)],
                  self_barrier=(400.0, 40.0, 0.02), row_kinds=["hard"] * (n + capacity))


def warmup() -> dict[str, float]:
    """Every entry point compiled or loaded (numba's cache beside :mod:`qpctl.kernels`, its user cache
    folder when that is read-only, or ``NUMBA_CACHE_DIR``), so that no code path compiles or loads in
    the middle of a control loop. Once per process; returns the seconds each part took (a warm cache:
    well under a second in all; a cold one: 15–25 s)."""
    global _WARM
    if _WARM is not None:
        return _WARM
    times: dict[str, float] = {}
    robot = planar_arm(tau_max=500.0)
    path = WaypointPath([[-1.0, -2.0], [1.0, -1.5]], duration=1.0)
    scene = [Obstacle("sphere", np.array([-0.7, -1.5, 0.0]), radius=0.1),
             Obstacle("capsule", np.array([-1.3, -1.2, 0.0]), radius=0.05, length=0.4, axis=np.array([0.0, 0.0, 1.0])),
             Obstacle("box", np.array([0.5, -0.5, 0.0]), size=np.array([0.1, 0.1, 0.1]),
                      velocity=np.array([0.0, 0.1, 0.0]))]
    q, v, t = robot.q_home.astype(float), np.array([0.1, -0.2, 0.3]), 0.1
    gains = LawGains(d_influence=0.5, d_safe=0.05)

    start = time.perf_counter()
    for shapes, grid in ((scene, True), (scene[:2], False)):  # python-fcl's box: the state Python finishes
        ws = Workspace(robot, shapes, path, gains, gains.d_influence, broadphase=grid, native_rigid=True)
        for weighted in (True, False):  # the whole tick, then its second half (after Python's part)
            ws.rigid(q, v)
            if K.tick_closed_form(ws.work, q, v, t, weighted, np.empty_like(ws.rec)) == codes.STATE_PYTHON:
                ws.finish_state(q, v, t)
            K.address_entry(K.tick_closed_form_at, ws.work, weighted=weighted, out=ws.rec)  # the common tick's
            K.closed_form_tick(ws.work, weighted)
    times["closed forms"] = time.perf_counter() - start

    start = time.perf_counter()
    ws = Workspace(robot, scene, path, gains, gains.d_influence, spec=_spec(robot, 12), broadphase=True,
                   native_rigid=True)
    hard, relaxed = ws.hard, ws.relaxed
    assert hard is not None and relaxed is not None
    ws.state(q, v, t)
    K.qp_terms_and_build(ws.work, hard.H, hard.f, hard.rows, hard.bu, hard.bl)
    K.qp_rebuild(ws.work, relaxed.H, relaxed.f, relaxed.rows, relaxed.bu, relaxed.bl)
    K.qp_build(ws.work, relaxed.H, relaxed.f, relaxed.rows, relaxed.bu, relaxed.bl)
    K.qp_finish(ws.work, relaxed.x, relaxed.rows, relaxed.bu, relaxed.bl, SOLUTION_RTOL, False)
    K.law_terms(ws.work, True)
    K.closed_form(ws.work, True)
    K.write_record(ws.work, False)
    K.finish_pairs(ws.work)
    K.set_field(ws.work, ws.fd_dist, ws.fd_grad, ws.fd_pairs)  # a depth map's snapshot arrives (the same array types)
    if daqp_native.available():
        nat_h = daqp_native.NativeDAQP(hard.H, hard.f, hard.rows, hard.bu, hard.bl, hard.sense)
        nat_r = daqp_native.NativeDAQP(relaxed.H, relaxed.f, relaxed.rows, relaxed.bu, relaxed.bl, relaxed.sense)
        nat_h.setup()
        nat_r.setup()
        K.native_solve(nat_r.dq)
        K.native_solve_finish(ws.work, relaxed.rows, relaxed.bu, relaxed.bl, nat_r.dq, nat_r.x, SOLUTION_RTOL)
        args = (*nat_h.kernel_args, nat_h.lam, *nat_r.kernel_args, SOLUTION_RTOL, 1e6, *shortcut_scratch(nat_h.x.shape[0], ws.n))
        packed = new_native_qp(ws.work, *args)
        for try_hard in (True, False):  # the whole tick, then its part after the state (Python's turn)
            ws.rigid(q, v)
            if K.tick_qp_native(ws.work, q, v, t, *nat_r.kernel_args, SOLUTION_RTOL) == codes.STATE_PYTHON:
                ws.finish_state(q, v, t)
            K.qp_tick_native(ws.work, *nat_r.kernel_args, SOLUTION_RTOL)
            ws.rigid(q, v)
            if K.tick_qp_native_hard_first(packed, q, v, t, try_hard)[0] == codes.STATE_PYTHON:
                ws.finish_state(q, v, t)
            K.qp_tick_native_hard_first(packed, try_hard)
            ws.rigid(q, v)
            K.tick_qp(packed, q, v, t, try_hard, np.empty_like(ws.rec))
        K.address_entry(K.tick_qp_at, packed, try_hard=True, out=ws.rec)  # the common tick's entry
        nat_h.free()
        nat_r.free()
    times["qp"] = time.perf_counter() - start

    start = time.perf_counter()
    WorldClearance(robot, scene)(q, t)
    times["clearance"] = time.perf_counter() - start
    _WARM = times
    return times
