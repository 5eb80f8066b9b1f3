"""Tasks: the paper's law as QP costs and rows (DESIGN.md §2, "QP law").

* :class:`AccelerationTask` — ½‖M(q̈ − q̈₀)‖², the inertia-weighted acceleration cost (= ½‖τ − τ₀‖²
  with τ₀ = M q̈₀ + N): its minimiser under the task rows is the paper's J_M⁺ law (eq. 6, 19).
* :class:`EndEffectorTask` — J q̈ = a (eq. 3 with a from eq. 7), softened by an exact ℓ₁ slack
  so that obstacles and torque limits (hard) win when they conflict with the path.
* :class:`PostureTask` — ½ w ‖q̈ − (K_p(q_ref − q) − K_d q̇)‖², an optional extra.
* :class:`DampingTask` — ½ w ‖q̈ + K_d q̇‖² with w relative to M: damps the redundant self-motion
  that the paper's local torque minimisation leaves free (on by default in the QP).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence

import numpy as np

from qpctl.errors import ConfigError
from qpctl.law import LawTerms
from qpctl.qp import Equality, Objective
from qpctl.state import TickState


class Task(ABC):
    """A task reads the tick's state and law terms and returns a cost or rows on q̈."""

    name: str = "task"

    @abstractmethod
    def compute(self, state: TickState, terms: LawTerms) -> Objective | Equality:
        """The task's contribution at this tick."""


class AccelerationTask(Task):
    """½ w ‖M(q̈ − q̈₀)‖² [w·(N·m)²]: stay as close as possible, in torque, to the null-space target q̈₀."""

    name = "acceleration"

    def __init__(self, weight: float = 1.0) -> None:
        if not (np.isfinite(weight) and weight > 0):
            raise ConfigError(f"weight must be positive, got {weight}", key="AccelerationTask.weight")
        self.weight = float(weight)

    def compute(self, state: TickState, terms: LawTerms) -> Objective:
        W = self.weight * (state.M.T @ state.M)
        return Objective(W, -W @ terms.qdd0)


class EndEffectorTask(Task):
    """J q̈ = a [m/s²] (a includes the PD feedback and −J̇q̇), with slack weights ℓ₁ and ℓ₂.

    ``slack_l1`` [(N·m)²/(m/s²)] must exceed the task's multiplier for the slack to vanish when the
    problem is feasible; ``slack_l1 = slack_l2 = 0`` makes the rows hard. ``weights`` (one per task
    row, > 0; default 1) scale the rows, so where the task cannot all be met (a constraint binds) a
    row of weight w gives way as if its slack cost w times more: e.g. the position over the
    orientation. Where the task can be met the weights change nothing.
    """

    name = "end_effector"

    def __init__(self, slack_l1: float = 1e6, slack_l2: float = 1e2, weights: Sequence[float] | None = None) -> None:
        for key, val in (("slack_l1", slack_l1), ("slack_l2", slack_l2)):
            if not (np.isfinite(val) and val >= 0):
                raise ConfigError(f"must be a number >= 0, got {val}", key=f"controller.{key}")
        self.slack_l1 = float(slack_l1)
        self.slack_l2 = float(slack_l2)
        self.weights = None if weights is None else np.asarray(weights, float).reshape(-1)
        if self.weights is not None and not (np.all(np.isfinite(self.weights)) and np.all(self.weights > 0)):
            raise ConfigError(f"must be positive numbers, got {self.weights.tolist()}", key="controller.task_weights")

    def compute(self, state: TickState, terms: LawTerms) -> Equality:
        if self.weights is None:
            return Equality(state.J, terms.a, self.slack_l1, self.slack_l2)
        if self.weights.shape != terms.a.shape:
            raise ConfigError(f"needs {terms.a.size} weights (one per task row), got {self.weights.size}",
                              key="controller.task_weights")
        return Equality(self.weights[:, None] * state.J, self.weights * terms.a, self.slack_l1, self.slack_l2)


class PostureTask(Task):
    """½ w ‖q̈ − q̈_p‖², q̈_p = K_p (q_ref − q) − K_d q̇: pull the joints towards ``q_ref`` [rad].

    ``weight`` is in the units of the acceleration cost ((N·m)²/(rad/s²)² when combined with
    :class:`AccelerationTask`), so useful values scale with ‖M‖².
    """

    name = "posture"

    def __init__(self, q_ref: Sequence[float] | np.ndarray, weight: float = 1.0, kp: float = 25.0,
                 kd: float = 10.0, *, difference: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None) -> None:
        self.q_ref = np.asarray(q_ref, float).reshape(-1)
        # q_ref ⊖ q on a configuration space that is not a vector space (RobotModel.difference): then
        # q_ref is a configuration (nq) and the error a velocity (nv)
        self.difference = difference
        if not np.all(np.isfinite(self.q_ref)):
            raise ConfigError("q_ref must be finite", key="PostureTask.q_ref")
        for key, val in (("weight", weight), ("kp", kp), ("kd", kd)):
            if not (np.isfinite(val) and val >= 0):
                raise ConfigError(f"must be a number >= 0, got {val}", key=f"PostureTask.{key}")
        self.weight, self.kp, self.kd = float(weight), float(kp), float(kd)

    def compute(self, state: TickState, terms: LawTerms) -> Objective:
        if self.q_ref.shape != state.q.shape:
            raise ConfigError(f"q_ref has {self.q_ref.size} entries, the robot {state.n}", key="PostureTask.q_ref")
        error = self.q_ref - state.q if self.difference is None else self.difference(state.q, self.q_ref)
        target = self.kp * error - self.kd * state.v
        return Objective(self.weight * np.eye(state.n), -self.weight * target)


DEFAULT_DAMPING = 1.0  # the QP's DampingTask weight ρ by default (README, "Drive limits": measured)


class DampingTask(Task):
    """½ w ‖q̈ + K_d q̇‖², w = ρ · tr(MᵀM)/n: a pull of every joint's acceleration toward −K_d q̇.

    The task rows are equalities, so this shapes only the null space: it damps the self-motion that
    the paper's cost ½‖M(q̈ − q̈₀)‖² (a local torque minimisation) lets fall under gravity and swing
    — the cause of the QP's torque chatter at an active barrier and of joint speeds and
    accelerations beyond what real drives allow. ``weight`` ρ is relative to the acceleration cost
    (the mean diagonal of MᵀM, per tick, so one value suits a planar arm of 10 kg links and the
    Panda alike); ``gain`` K_d [1/s]. ρ = 0 leaves the paper's law exact.
    """

    name = "damping"

    def __init__(self, weight: float = DEFAULT_DAMPING, gain: float = 10.0) -> None:
        for key, val in (("damping", weight), ("damping_gain", gain)):
            if not (np.isfinite(val) and val >= 0):
                raise ConfigError(f"must be a number >= 0, got {val}", key=f"controller.{key}")
        self.weight, self.gain = float(weight), float(gain)

    def compute(self, state: TickState, terms: LawTerms) -> Objective:
        w = self.weight * float(np.sum(state.M * state.M)) / state.n
        return Objective(w * np.eye(state.n), w * self.gain * state.v)
