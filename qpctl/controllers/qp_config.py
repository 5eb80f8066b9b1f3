"""The QP controller's settings: :class:`QPConfig` (the ``[controller]`` keys the QP reads, units in
brackets) and :func:`braking_model` (the brake its braking-aware rows assume). Re-exported by
:mod:`qpctl.controllers.qp`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from qpctl.config import check_fields, setting
from qpctl.constraints.braking import Braking
from qpctl.errors import ConfigError
from qpctl.fallbacks import BRAKE, CLOSED_FORM, FALLBACKS, SAFE_STOP
from qpctl.robot.model import RobotModel
from qpctl.solvers.base import DEFAULT_SOLVER
from qpctl.tasks.tasks import DEFAULT_DAMPING

__all__ = ["BUILT_IN_FALLBACKS", "FALLBACK_BRAKE", "FALLBACK_CLOSED_FORM", "FALLBACK_SAFE_STOP", "QPConfig",
           "braking_model"]

FALLBACK_CLOSED_FORM = CLOSED_FORM  # the fallback chain's built-in strategies (qpctl.fallbacks)
FALLBACK_BRAKE = BRAKE
FALLBACK_SAFE_STOP = SAFE_STOP
BUILT_IN_FALLBACKS = tuple(FALLBACKS)


@dataclass
class QPConfig:
    """Settings of the QP controller (the ``[controller]`` keys of a scenario; units in brackets).

    solver: a name from ``qpctl solvers``; solver_settings: passed to it (tolerances, max_iter...).
    torque_limits / joint_limits: include those constraints when the robot has finite limits.
    barrier_k0 [1/s²], barrier_k1 [1/s]: obstacle barrier gains; barrier_drift: "exact" (default:
    closed form for sphere and capsule obstacles, a look-ahead finite difference of ḣ for the others)
    or "rigid" (nᵀJ̇_p q̇ only, DESIGN.md §2's approximation); joint_k0, joint_k1: joint-position
    barrier gains; velocity_gain [1/s]: joint-speed barrier gain.
    slack_l1, slack_l2: task slack weights (ℓ₁ exact penalty, ℓ₂ regulariser).
    task_relaxation: "always" — solve with the task slack every tick; "on_failure" — solve with the
    task hard first and with the slack only when that fails or its answer is not the relaxed QP's;
    "auto" — "on_failure" for osqp (ADMM converges slowly and its polishing fails with the ℓ₁ slack),
    the task hard first inside DAQP's compiled tick (a smaller QP, same answer), "always" otherwise.
    max_pairs: obstacle rows (0: 4 per link, at most links × obstacles).
    fallback: the failure policy — what produces the torque when the solver fails (infeasible,
    iteration or time limit, numerical error, non-finite data), tried in order:

    * a solver name (``qpctl solvers``), e.g. ``"daqp"``: that solver on the same tick's QP (with the
      task slack), skipped once the tick budget is spent;
    * ``"closed-form"`` — the paper law (eq. 19) when it is safe, i.e. no link is within d_safe of an
      obstacle and its q̈ meets every obstacle-barrier row of the tick's QP; otherwise on down the
      chain (status ``within_d_safe`` or ``barrier_violated``);
    * ``"safe-stop"`` — the brake below corrected by a small QP (DAQP, tens of µs) that keeps the
      barrier rows as well as the torque limits allow: where they cannot all hold it decelerates the
      approach as hard as the limits allow (:class:`qpctl.fallbacks.SafeStop`);
    * ``"brake"`` — q̈ = k_v (g − q̇): come to rest, except that links within d_influence back away
      along the obstacle sensor's reference velocity g (g = 0 when no obstacle is near), k_v the
      task's velocity gain [1/s].

    ``"brake"`` always produces a torque, so entries after it are never used; when every entry fails,
    the brake is used. Any fallback's q̈ is clipped to the joint-limit bounds and its torque to ±τ_max
    (the brake and the closed form scaled toward gravity compensation, direction kept). The tick's
    ``info`` records ``fallback`` (what produced the torque), ``fallback_reason`` (the QP's status)
    and ``fallback_tried`` ("name:status" of the entries that failed); the run's metrics count
    ``qp_fallbacks`` by name.
    tick_budget_us: wall-time budget of a tick [µs] (0: none), from the start of
    :meth:`QPController.step` (state, QP build and every solver attempt). Each solver attempt gets
    what is left as its time limit (osqp, clarabel, daqp: their own; proxqp: an iteration cap from its
    measured cost per iteration; quadprog: cannot be stopped, the clock is checked after);
    once it is spent no further solver is tried and the chain goes on with its built-in entries
    (``"closed-form"``, ``"safe-stop"``, ``"brake"``: tens of µs each). ``info["budget_exhausted"]``
    marks such ticks.
    posture / posture_weight: an optional PostureTask.
    damping [1], damping_gain [1/s]: the DampingTask's relative weight ρ and gain K_d (ρ = 0: none,
    the QP then reduces exactly to the paper law where no inequality is active).
    task_weights: one per task row (> 0): how much more a row's slack costs (EndEffectorTask).
    self_collision: keep the arm's own links ``self_d_safe`` [m] apart (a SelfCollisionBarrier on
    the pairs :func:`qpctl.geometry.self_collision.self_collision_pairs` keeps, or on
    ``self_collision_pairs``, pairs of link names), with the obstacle barrier's gains.
    braking: braking-aware obstacle and joint-limit rows (issue 22; :mod:`qpctl.kernels.braking`):
    ``"on"``, ``"off"`` (the default: measured, they do not yet lower the soak's collisions,
    docs/reliability.md) or ``"auto"`` (on where the robot has a finite torque-rate limit and torque
    limits); braking_share (0, 1]: the share of the drives' means at a point the brake is assumed to
    have; braking_margin [m]: kept at rest beyond d_safe; braking_period [s]: the control period
    (0: the scenario's sim.dt, 1 ms for a controller built in code); braking_reach [m]: pairs are
    found this far beyond d_influence (they have only the braking bound there).
    """

    solver: str = DEFAULT_SOLVER
    solver_settings: dict[str, Any] = field(default_factory=dict)
    torque_limits: bool = True
    joint_limits: bool = True
    barrier_k0: float = setting(400.0, valid="positive", unit="1/s²")
    barrier_k1: float = setting(40.0, valid="positive", unit="1/s")
    barrier_drift: str = "exact"
    joint_k0: float = setting(100.0, valid="positive", unit="1/s²")
    joint_k1: float = setting(20.0, valid="positive", unit="1/s")
    velocity_gain: float = setting(50.0, valid="positive", unit="1/s")
    slack_l1: float = setting(1e6, valid="nonnegative")
    slack_l2: float = setting(1e2, valid="nonnegative")
    max_pairs: int = 0
    task_relaxation: str = "auto"
    fallback: list[str] = field(default_factory=lambda: [FALLBACK_CLOSED_FORM, FALLBACK_SAFE_STOP])
    tick_budget_us: float = setting(0.0, valid="nonnegative", unit="µs")
    posture: list[float] | None = None
    posture_weight: float = setting(0.0, valid="nonnegative")
    damping: float = setting(DEFAULT_DAMPING, valid="nonnegative")
    damping_gain: float = setting(10.0, valid="nonnegative", unit="1/s")
    task_weights: list[float] | None = None
    self_collision: bool = True
    self_d_safe: float = 0.02
    self_collision_pairs: list[list[str]] | None = None
    braking: str = setting("off", choices=("auto", "on", "off"))
    braking_share: float = setting(0.5, valid="positive", unit="1")
    braking_margin: float = setting(0.0, valid="nonnegative", unit="m")
    braking_period: float = setting(0.0, valid="nonnegative", unit="s")
    braking_reach: float = setting(0.5, valid="nonnegative", unit="m")

    def __post_init__(self) -> None:
        if isinstance(self.fallback, str) or not all(isinstance(x, str) for x in self.fallback):
            raise ConfigError(f"must be a list of names, got {self.fallback!r}", key="controller.fallback")
        self.fallback = list(self.fallback)
        check_fields(self, "controller")
        if isinstance(self.max_pairs, bool) or not isinstance(self.max_pairs, int) or self.max_pairs < 0:
            raise ConfigError(f"must be an integer >= 0, got {self.max_pairs!r}", key="controller.max_pairs")

    @classmethod
    def from_dict(cls, cfg: dict[str, Any]) -> QPConfig:
        keys = cls.__dataclass_fields__.keys()
        return cls(**{k: v for k, v in cfg.items() if k in keys})




def braking_model(cfg: QPConfig, robot: RobotModel) -> Braking | None:
    """The brake the braking-aware rows assume (``controller.braking``), or None where they are off."""
    rate = np.broadcast_to(np.asarray(robot.tau_rate_max, float), (robot.nv,))
    limited = bool(np.all(np.isfinite(robot.tau_max)) and np.any(np.isfinite(rate)))
    if cfg.braking == "off" or (cfg.braking == "auto" and not (limited and cfg.torque_limits)):
        return None
    if not (cfg.torque_limits and np.all(np.isfinite(robot.tau_max))):
        raise ConfigError("braking-aware rows need the torque limits (robot.tau_max finite, "
                          "controller.torque_limits = true)", key="controller.braking")
    if cfg.braking_share > 1:
        raise ConfigError(f"must be in (0, 1], got {cfg.braking_share}", key="controller.braking_share")
    qdd = np.broadcast_to(np.asarray(robot.qdd_max, float), (robot.nv,))
    return Braking(np.asarray(robot.tau_max, float).copy(), rate.copy(), qdd.copy(), cfg.braking_share,
                   cfg.braking_margin, cfg.braking_period or 1e-3)
