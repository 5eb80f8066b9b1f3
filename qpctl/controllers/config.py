"""The ``[controller]`` table: every key declared once, as a field of the dataclass that uses it.

* :class:`~qpctl.law.LawGains` — the laws' gains and obstacle sensor (``kp`` … ``jdot_en``);
* :class:`~qpctl.controllers.qp.QPConfig` — the QP's settings (``solver`` … ``self_collision_pairs``);
* :class:`ControllerConfig` — the keys the scenario itself reads to build a controller (below).

:func:`controller_schema` turns their fields into the table's schema (:func:`qpctl.config.schema_of`):
a new key is one field with its docstring line, in the class that reads it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from qpctl.config import Checker, check_fields, schema_of, setting


@dataclass(frozen=True)
class ControllerConfig:
    """The ``[controller]`` keys read by the scenario (:class:`qpctl.scenario.Scenario`), not by a law.

    kind: the controller (a name registered in :data:`qpctl.controllers.factory.CONTROLLERS`).
    task: "position", "pose" or "approach"; task_mask: for a pose task, 6 entries of 0/1 (x, y, z, rx,
    ry, rz) saying which rows are tracked; approach_axis: the tool axis an approach task points.
    barrier_design: "manual" (barrier_k0, barrier_k1, d_influence as written) or "drives" (derived from
    the robot's drive limits, :mod:`qpctl.barrier_design`); approach_speed [m/s] (or "auto"): the
    approach speed that design assumes.
    d_safe_margin [m] (or "auto": from the faults' noise levels): added to d_safe by the controllers.
    broadphase: "auto", "on" or "off" — the distance engine's grid over static obstacles.
    backup: the controller behind the verified backup (:class:`qpctl.safety.BackupGuard`, issue 22): its
    torque applied only where a brake from the state it leads to is verified by rollout, at ``sim.dt``;
    backup_margin [m]: the clearance kept all along the brake; backup_check_distance [m]: ticks whose
    world clearance is at least this are not checked (inf: every tick, the default); backup_check_steps:
    the rollout steps one check may spend on a proposal, all its gains together (inf: no limit, the
    default) — one not verified within them is refused and the stored brake continues;
    backup_check_evaluations: the world-clearance evaluations one check may spend, its rollouts' and its
    rest tests' together (inf: no limit, the default) — the evaluation past them ends the check's work as
    the steps do; with backup_check_steps a bound on the check's whole cost. Under either limit a
    retreat search from the state that does not fit a tick is carried over the ticks while the arm
    follows its stop (:mod:`qpctl.safety.backup`, "Carried search"; backup_carry: true, the default;
    false: searched within each tick, cut short by the limits);
    backup_tries_on_brake: the gains a check tries while the last tick applied the stored brake (2, the
    default: the stored one and the first other; inf: the whole family).
    backup_retreats: where no brake verifies from the state itself (a start inside a swaying obstacle's
    sweep), search a retreat to a rest clear of the sweeps (:mod:`qpctl.safety.retreat`; true, the default);
    backup_hold [s]: how long after its rest a brake's stop must stay clear of the drifting obstacles
    (their scene-given motion), re-verified every tick the arm rests (2, the default; 0: not tested).
    backup_unverified: what a tick with no verified backup applies — "stop" (the default): the proposal
    only if a rollout from its successor comes to rest before any contact, else the stop the arm is on,
    so that every contact begins at rest; "proposal": the proposal all the same.
    backup_retreat_proposals: a proposal refused only because its successor's stops end inside a swaying
    obstacle's sweep (or a drifting one's way) is applied if a retreat from that successor verifies
    (the search of ``backup_retreats``, every ``RETRY_TICKS`` ticks at most after a failed one): the QP
    may dodge through a swing's sweep with an escape verified (true, the default).
    backup_settle: a brake's rollout ends where the brake has settled into its exponential decay (torque
    and rate within 80 % of the limits along it) and its rest, bounded by 1.25 × its creep, passes the
    rest test — instead of rolling on to rest (:mod:`qpctl.safety.rollout`, "Settled"; true, the default;
    false: every rollout to rest, 6–30× more steps).
    """

    kind: str = "paper"
    task: str = setting("position", choices=("position", "pose", "approach"))
    task_mask: list[float] | None = None
    approach_axis: list[float] = field(default_factory=lambda: [0.0, 0.0, 1.0])
    barrier_design: str = setting("manual", choices=("manual", "drives"))
    approach_speed: float | str = setting("auto", valid="positive", unit="m/s")
    d_safe_margin: float | str = setting(0.0, valid="nonnegative", unit="m")
    broadphase: str = setting("auto", choices=("auto", "on", "off"))
    backup: bool = False
    backup_margin: float = setting(0.0, valid="nonnegative", unit="m")
    backup_check_distance: float = setting(float("inf"), valid="distance_or_inf", unit="m")
    backup_check_steps: float = setting(float("inf"), valid="count_or_inf")
    backup_check_evaluations: float = setting(float("inf"), valid="count_or_inf")
    backup_tries_on_brake: float = setting(2.0, valid="count_or_inf")
    backup_retreats: bool = True
    backup_hold: float = setting(2.0, valid="nonnegative", unit="s")
    backup_unverified: str = setting("stop", choices=("stop", "proposal"))
    backup_retreat_proposals: bool = True
    backup_settle: bool = True
    backup_carry: bool = True

    def __post_init__(self) -> None:
        check_fields(self, "controller")


def controller_schema() -> dict[str, tuple[Checker, Any]]:
    """``{key: (checker, default)}`` of the ``[controller]`` table, from the three classes' fields."""
    from qpctl.controllers.qp import QPConfig
    from qpctl.law import LawGains

    return schema_of(ControllerConfig, LawGains, QPConfig, skip=("obstacle_v_ref",))
