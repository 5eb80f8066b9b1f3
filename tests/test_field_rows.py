"""The depth map's rows in the compiled tick (qpctl.kernels.field_rows) against the Python path's
FieldBarrier.compute (qpctl.perception.rows): the same rows and bounds to 1e-12, rigid and soft rows
active, with the scene's primitives beside them; and the controller's torque on both paths."""

from __future__ import annotations

import numpy as np
import pytest

from qpctl import Scenario
from qpctl.perception import Perception, PerceptionConfig, PointCloud
from qpctl.perception.rows import FieldBarrier

CFG = PerceptionConfig(voxel=0.02, bounds_min=[-0.3, -0.6, 0.0], bounds_max=[1.1, 0.6, 1.1], truncation=0.3)


def _sphere_cloud(centre: np.ndarray, radius: float, rng: np.random.Generator, n: int = 3000) -> np.ndarray:
    d = rng.normal(size=(n, 3))
    return centre + radius * d / np.linalg.norm(d, axis=1, keepdims=True)


def _controller(rng: np.random.Generator, *, compiled: bool = True):  # type: ignore[no-untyped-def]
    scen = Scenario.load("panda_spheres")
    ctrl = scen.build_controller("qp")
    robot = ctrl.robot
    seg = ctrl.dynamics.compute(robot.q_home, np.zeros(robot.nv)).segments
    rigid = _sphere_cloud(0.5 * (seg[3, 0] + seg[3, 1]) + [0.0, 0.17, 0.0], 0.05, rng)
    soft = _sphere_cloud(seg[-1, 1] + [0.0, -0.12, -0.05], 0.05, rng)
    labels = np.r_[np.full(len(rigid), 1, np.uint8), np.full(len(soft), 2, np.uint8)]
    p = Perception(CFG, robot)
    p.submit(PointCloud(np.r_[rigid, soft], 0.0, labels=labels))
    bar = p.rows_for(ctrl)
    if not compiled:
        ctrl.remove_constraint(bar.name)
        bar = _PythonOnly(p, robot, CFG, d_safe=ctrl.gains.d_safe, cutoff=ctrl.cutoff,
                          k0=ctrl.config.barrier_k0, k1=ctrl.config.barrier_k1)
        ctrl.add_constraint(bar)
    return ctrl, bar


class _PythonOnly(FieldBarrier):
    """The same rows without a compiled form: the controller takes the Python formulation."""

    field_spec = None  # type: ignore[assignment]


def _states(ctrl, rng: np.random.Generator, k: int) -> list[tuple[np.ndarray, np.ndarray, float]]:  # type: ignore[no-untyped-def]
    q0 = ctrl.robot.q_home
    return [(q0 + rng.normal(0.0, 0.08, q0.size), rng.uniform(-0.6, 0.6, q0.size), 0.05 * i) for i in range(k)]


def test_compiled_field_rows_equal_the_python_rows() -> None:
    rng = np.random.default_rng(21)
    ctrl, bar = _controller(rng)
    ws = ctrl.workspace()
    assert ws.spec is not None and ws.spec.field is not None  # the compiled path, with the field
    rigid_active = soft_active = primitive_active = 0
    for q, v, t in _states(ctrl, rng, 10):
        ctrl.step(q, v, t)
        problem = ctrl.last_problem
        names = np.array(problem.row_names)
        rows = np.flatnonzero(names == bar.name)
        assert rows.size == bar.rows
        got_C, got_l = np.array(problem.C[rows]), np.array(problem.l[rows])
        # the soft rows' shared slack σ: the last column, 1 on the soft rows, 0 on the rigid ones
        assert np.array_equal(got_C[:, -1], np.repeat([0.0, 1.0], bar.rows // 2))
        assert not got_C[:, ctrl.n:-1].any()
        got_C = got_C[:, :ctrl.n]
        compiled = bar.last
        state = ctrl.dynamics.compute(q, v, t)
        want = bar.compute(state, None)  # type: ignore[arg-type]
        python = bar.last
        assert np.array_equal(compiled.active, python.active)
        assert compiled.distance == pytest.approx(python.distance, abs=1e-12)
        assert np.array_equal(np.isinf(got_l), np.isinf(want.lower))
        fin = np.isfinite(want.lower)
        assert np.abs(got_C - want.C).max() <= 1e-12
        assert np.abs(got_l[fin] - want.lower[fin]).max() <= 1e-12 * max(1.0, np.abs(want.lower[fin]).max())
        rigid_active += int((python.active & ~python.soft).any())
        soft_active += int((python.active & python.soft).any())
        obst = np.flatnonzero(names == "obstacles")
        primitive_active += int(np.isfinite(np.array(problem.l[obst])).any())
    assert rigid_active >= 5 and soft_active >= 5 and primitive_active >= 1
    assert problem.c[-1] == CFG.soft_weight and problem.lb[-1] == 0.0 and problem.ub[-1] == np.inf


def test_compiled_and_python_field_ticks_give_the_same_torque() -> None:
    fast, _ = _controller(np.random.default_rng(3))
    slow, _ = _controller(np.random.default_rng(3), compiled=False)
    assert fast.workspace().spec is not None and slow.workspace().spec is None
    rng = np.random.default_rng(4)
    for q, v, t in _states(fast, rng, 6):
        a, b = fast.step(q, v, t), slow.step(q, v, t)
        assert a.info.get("fallback") == b.info.get("fallback")
        assert np.allclose(a.tau, b.tau, rtol=1e-7, atol=1e-7 * np.abs(b.tau).max())


def _rushing_into_a_leaf(soft_weight: float):  # type: ignore[no-untyped-def]
    """The hand 3 cm from a soft blob, moving into it at 4 m/s: its soft rows ask more deceleration
    than the drives' torques give."""
    import dataclasses

    import pinocchio as pin

    scen = Scenario.load("panda_spheres")
    ctrl = scen.build_controller("qp", obstacles=[])
    robot = ctrl.robot
    q = robot.q_home.copy()
    seg = ctrl.dynamics.compute(q, np.zeros(robot.nv)).segments
    tip, axis = seg[-1, 1], seg[-1, 1] - seg[-1, 0]
    axis /= np.linalg.norm(axis)
    cfg = dataclasses.replace(CFG, soft_weight=soft_weight)
    p = Perception(cfg, robot)
    blob = _sphere_cloud(tip + (0.03 + robot.capsules[-1].radius + 0.05) * axis, 0.05, np.random.default_rng(5))
    p.submit(PointCloud(blob, 0.0, labels=np.full(len(blob), 2, np.uint8)))
    bar = p.rows_for(ctrl)
    data = robot.model.createData()
    pin.computeJointJacobians(robot.model, data, q)
    J = pin.getJointJacobian(robot.model, data, robot.capsules[-1].joint_id, pin.LOCAL_WORLD_ALIGNED)[:3]
    v = np.linalg.pinv(J) @ (4.0 * axis)
    return ctrl, bar, q, v


def test_the_soft_rows_slack_keeps_the_qp_feasible_where_a_leaf_cannot_be_stopped_for() -> None:
    hard_ctrl, _, q, v = _rushing_into_a_leaf(0.0)
    out = hard_ctrl.step(q, v, 0.0)
    assert hard_ctrl.workspace().spec is not None and hard_ctrl.last_problem.n_var == hard_ctrl.n + 6
    assert "fallback" in out.info and out.info["status"] == "primal_infeasible"  # the soft rows hard
    ctrl, bar, q, v = _rushing_into_a_leaf(CFG.soft_weight)
    out = ctrl.step(q, v, 0.0)
    assert "fallback" not in out.info and out.info["status"] == "solved"
    x = ctrl.last_solution.x
    sigma = x[-1]
    assert sigma > 1.0  # [m/s²] the leaf gives way
    problem = ctrl.last_problem
    rows = np.flatnonzero(np.array(problem.row_names) == bar.name)
    soft = rows[bar.rows // 2:]
    active = soft[np.isfinite(problem.l[soft])]
    assert active.size >= 1
    Cq = problem.C[active, :ctrl.n] @ x[:ctrl.n]
    assert np.all(Cq + sigma >= problem.l[active] - 1e-6)  # they hold with the slack
    assert np.any(Cq < problem.l[active] - 1.0)  # and only with it
