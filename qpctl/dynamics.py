"""The state of one tick on demand: :class:`Dynamics` runs (q, v, t) through the compiled kernels of
a workspace of its own (:mod:`qpctl.tick`: one ``rigid_pass`` (crba, nonLinearEffects), then M, N = C q̇ + G, the
task and link Jacobians and drifts, and the link–obstacle pairs) and returns a
:class:`~qpctl.state.TickState` of copies, so states computed one after the other stay independent.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence

import numpy as np
import pinocchio as pin

from qpctl.errors import InvalidStateError
from qpctl.geometry.obstacles import Obstacle
from qpctl.robot.model import RobotModel
from qpctl.state import TickState, validate_state
from qpctl.tick import Workspace


class Dynamics:
    """Computes :class:`TickState` for one robot in one scene, with the tick's compiled kernels.

    A thin wrapper over a :class:`~qpctl.tick.Workspace` of its own: :meth:`compute` runs one tick's
    state (``rigid_pass``, the kernels, python-fcl for shapes without a closed form) and returns
    a snapshot (copies), so states computed one after the other stay independent. Controllers run
    their ticks on their own workspace and build a TickState only where a Python path needs one
    (custom tasks, the fallbacks).

    Args:
        robot: the robot model.
        obstacles: the scene.
        cutoff: pairs farther than this [m] are not reported (the largest influence distance).
        broadphase: see :class:`~qpctl.tick.Workspace`.
    """

    def __init__(self, robot: RobotModel, obstacles: Sequence[Obstacle] = (), cutoff: float = np.inf,
                 broadphase: bool | None = None) -> None:
        self.robot = robot
        self.model = robot.model
        self.obstacles = list(obstacles)
        self.cutoff = float(cutoff)
        self.broadphase = broadphase
        self.self_pairs: tuple[tuple[int, int], ...] = ()  # capsule pairs whose distances the state includes
        self.self_cutoff = math.inf  # [m] and, nearer than this, their rows and drifts
        self._workspace: Workspace | None = None
        self._jdot_data = robot.model.createData()

    @property
    def workspace(self) -> Workspace:
        """The :class:`~qpctl.tick.Workspace` :meth:`compute` runs on (built on first use)."""
        if self._workspace is None:
            self._workspace = Workspace(self.robot, self.obstacles, None, None, self.cutoff,
                                        broadphase=self.broadphase, barrier_drift=True, self_pairs=self.self_pairs,
                                        self_cutoff=self.self_cutoff)
        return self._workspace

    @property
    def data(self) -> pin.Data:
        """Pinocchio's data after the last :meth:`compute` (crba in the world convention and nonLinearEffects: no data.a, data.com)."""
        return self.workspace.data

    def compute(self, q: np.ndarray, v: np.ndarray, t: float = 0.0) -> TickState:
        """Everything at (q [rad], v [rad/s], t [s]); raises :class:`InvalidStateError` on bad input."""
        q, v, t = validate_state(q, v, t, self.model.nv, self.model.nq)
        start = time.perf_counter()
        if self.workspace.state(q, v, t) < 0:
            raise InvalidStateError(f"the dynamics overflow at this state: q={q.tolist()}, v={v.tolist()}")
        state = self.workspace.snapshot()
        state._jdot = self.task_jacobian_derivative(q, v)
        state.timing["state_us"] = (time.perf_counter() - start) * 1e6
        return state

    def task_jacobian_derivative(self, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        """J̇ (m, n) of the task points at (q, v) (every task frame's rows, stacked)."""
        data = self._jdot_data
        pin.computeJointJacobiansTimeVariation(self.model, data, q, v)
        axes = list(self.robot.task_axes)
        return np.concatenate([pin.getFrameJacobianTimeVariation(self.model, data, f, pin.LOCAL_WORLD_ALIGNED)[:3][axes]
                               for f in self.robot.task_frame_ids])

    def forward_dynamics(self, q: np.ndarray, v: np.ndarray, tau: np.ndarray) -> np.ndarray:
        """q̈ = M⁻¹(τ − N) by Pinocchio's ABA [rad/s²]."""
        return pin.aba(self.model, self._jdot_data, q, v, tau).copy()
