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
        assert not got_C[:, ctrl.n:].any()  # no slack on the field rows
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


def test_compiled_and_python_field_ticks_give_the_same_torque() -> None:
    fast, _ = _controller(np.random.default_rng(3))
    slow, _ = _controller(np.random.default_rng(3), compiled=False)
    assert fast.workspace().spec is not None and slow.workspace().spec is None
    rng = np.random.default_rng(4)
    for q, v, t in _states(fast, rng, 6):
        a, b = fast.step(q, v, t), slow.step(q, v, t)
        assert a.info.get("fallback") == b.info.get("fallback")
        assert np.allclose(a.tau, b.tau, rtol=1e-7, atol=1e-7 * np.abs(b.tau).max())
