"""Scalar metrics of a run (DESIGN.md §4, ``metrics.json``)."""

from __future__ import annotations

from collections import Counter
from typing import Any

import numpy as np

from qpctl.simulation.simulator import Trajectory


def _finite_or_none(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


#: An arm is at rest when every joint speed is at most this [rad/s] (qpctl.safety.oracle's REST_SPEED).
REST_SPEED = 1e-2


def contact_onsets(clearance: np.ndarray) -> np.ndarray:
    """The ticks at which a contact begins: the clearance [m] below 0 there and not on the tick before
    (a run that starts in contact begins one at tick 0)."""
    inside = np.asarray(clearance) < 0.0
    return np.flatnonzero(inside & ~np.concatenate([[False], inside[:-1]]))


def collisions_at_rest(traj: Trajectory) -> int:
    """How many contacts (:func:`contact_onsets`) began with every joint speed ≤ REST_SPEED [rad/s]
    (issue 22, item 4: a moving obstacle catching a stopped arm; a stop cannot avoid it)."""
    return int(sum(bool(np.all(np.abs(traj.v[k]) <= REST_SPEED)) for k in contact_onsets(traj.clearance)))


def backup_metrics(infos: list[dict[str, Any]]) -> dict[str, Any]:
    """The verified backup's counts: ticks checked, on the stored brake, unverified (the guarantee
    holds for a run without one; of them on the arm's unverified stop: ``backup_stop_ticks``, of those on
    the way to a carried search's anchor: ``backup_carried_ticks``), the carried searches' retreats stored,
    and the check's cost per checked tick [µs]."""
    us = [float(i["backup_check_us"]) for i in infos if "backup_check_us" in i]
    return {"backup_checked_ticks": sum(bool(i["backup_checked"]) for i in infos),
            "backup_ticks": sum("backup" in i for i in infos),
            "backup_retreat_ticks": sum("backup" in i and "backup_retreat" in i for i in infos),
            "backup_unverified_ticks": sum(bool(i.get("backup_unverified")) for i in infos),
            "backup_check_us_median": float(np.median(us)) if us else 0.0,
            "backup_check_us_p99": float(np.percentile(us, 99)) if us else 0.0,
            "backup_out_of_steps_ticks": sum(bool(i.get("backup_out_of_steps")) for i in infos),
            "backup_hold_lapsed_ticks": sum(bool(i.get("backup_hold_lapsed")) for i in infos),
            "backup_stop_ticks": sum("backup_stop" in i for i in infos),
            # under a check limit: ticks on the stop to a carried search's anchor; the carried retreats stored
            "backup_carried_ticks": sum(bool(i.get("backup_carried")) for i in infos),
            "backup_carried_adopted": sum(bool(i.get("backup_carried_adopted")) for i in infos)}


def rms_jerk(t: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(n,) each joint's root-mean-square jerk [rad/s³] over a run sampled at the ticks t (T,) [s] with
    joint velocities v (T, n) [rad/s]: q̈ over each tick by the velocity's difference, the jerk by the
    difference of consecutive q̈. On ``panda_canopy`` (6 s) 267 on the first joint and 2,357 on the
    last; a joint whose acceleration flips between its bounds tick after tick (a 2-tick chatter) gives
    2q̈_max/Δt on the ticks it flips (40,000 rad/s³ for ±20 rad/s² at 1 kHz). Zeros for fewer than
    3 ticks."""
    if t.size < 3:
        return np.zeros(v.shape[1])
    dt = np.diff(t)
    qdd = np.diff(v, axis=0) / dt[:, None]
    jerk = np.diff(qdd, axis=0) / (0.5 * (dt[1:] + dt[:-1]))[:, None]
    return np.sqrt(np.mean(jerk**2, axis=0))


def compute_metrics(traj: Trajectory, *, d_safe: float = 0.0, frames: int = 1) -> dict[str, Any]:
    """Tracking [m], torque [N·m] and torque rate [N·m/s], joint jerk [rad/s³] (:func:`rms_jerk`),
    clearance [m], compute time [µs], QP stats.
    With several task frames (``frames``, their position rows stacked in x) the tracking errors are
    over all of them, and ``max_tracking_error_per_task``, ``final_tracking_error_per_task`` give each's."""
    err = np.linalg.norm(traj.x_ref - traj.x, axis=1)
    dt = float(np.median(np.diff(traj.t))) if traj.t.size > 1 else 1.0
    rate = np.abs(np.diff(traj.tau, axis=0)) / dt if traj.t.size > 1 else np.zeros((1, traj.tau.shape[1]))
    min_clear = float(np.min(traj.clearance)) if traj.clearance.size else float("inf")
    jerk = rms_jerk(traj.t, traj.v)
    tick = traj.tick_us
    out: dict[str, Any] = {
        "rms_tracking_error": float(np.sqrt(np.mean(err**2))),
        "max_tracking_error": float(np.max(err)),
        "final_tracking_error": float(err[-1]),
        "max_abs_torque": float(np.max(np.abs(traj.tau))),
        "max_abs_torque_per_joint": np.max(np.abs(traj.tau), axis=0).tolist(),
        "max_abs_torque_rate": float(np.max(rate)),
        "max_abs_torque_rate_per_joint": np.max(rate, axis=0).tolist(),
        "rms_jerk_per_joint": jerk.tolist(),
        "min_clearance": _finite_or_none(min_clear),
        "collided": bool(min_clear < 0.0),
        # contacts that began with the arm at rest: an obstacle caught a stopped arm, which no brake avoids
        "collisions_at_rest": collisions_at_rest(traj),
        "safety_violated": bool(min_clear < d_safe - 1e-9),
        "final_null_space_error": float(np.linalg.norm(traj.e_null[-1])),
        "singular_ticks": int(np.count_nonzero(traj.singular)),
        "tick_us_median": float(np.median(tick)),
        "tick_us_p99": float(np.percentile(tick, 99)),
        "tick_us_max": float(np.max(tick)),
        "duration_s": float(traj.t[-1]),
        "ticks": int(traj.t.size),
    }
    if frames > 1:  # each task frame's own position rows (the orientation rows are not in x)
        per = np.linalg.norm((traj.x_ref - traj.x).reshape(len(traj.t), frames, -1), axis=2)
        out["max_tracking_error_per_task"] = per.max(axis=0).tolist()
        out["final_tracking_error_per_task"] = per[-1].tolist()
    if traj.self_clearance is not None:  # between the arm's own links (qpctl.geometry.self_collision's pairs)
        out["min_self_clearance"] = _finite_or_none(float(np.min(traj.self_clearance)))
    if traj.orientation_error_deg is not None:  # an orientation task (pose: the whole rotation; approach: the axis)
        out["max_orientation_error_deg"] = float(np.max(traj.orientation_error_deg))
        out["final_orientation_error_deg"] = float(traj.orientation_error_deg[-1])
    if traj.orientation_error_deg_per_task is not None:  # several oriented task frames: each's
        out["max_orientation_error_deg_per_task"] = traj.orientation_error_deg_per_task.max(axis=0).tolist()
        out["final_orientation_error_deg_per_task"] = traj.orientation_error_deg_per_task[-1].tolist()
    if traj.infos and "backup_checked" in traj.infos[0]:  # behind the verified backup (qpctl.safety.BackupGuard)
        out.update(backup_metrics(traj.infos))
    qp = [i for i in traj.infos if "status" in i]
    if qp:
        out["qp_status_counts"] = dict(Counter(str(i["status"]) for i in qp))
        out["qp_iterations_max"] = int(max(int(i.get("iterations", 0)) for i in qp))
        out["qp_slack_max"] = float(max(float(i.get("slack_norm", 0.0)) for i in qp))
        out["qp_active_max"] = int(max(int(i.get("active", 0)) for i in qp))
        for stage in ("state_us", "build_us", "solve_us"):
            vals = [float(i[stage]) for i in qp if stage in i]
            if vals:
                out[f"{stage[:-3]}_us_median"] = float(np.median(vals))
        fb = [i.get("fallback") for i in qp if i.get("fallback")]
        out["qp_fallbacks"] = dict(Counter(str(f) for f in fb))
        # ticks at which a joint's torque moved by its whole rate limit (the drives' limit binding)
        out["torque_rate_limit_hits"] = sum(1 for i in qp if i.get("rate_limited"))
    return out
