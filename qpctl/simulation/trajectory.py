"""What a run records: :class:`Trajectory` (DESIGN.md §4's arrays), and the helpers every simulator
shares to fill it (the tick budget of a run, the self-collision pairs it measures, the orientation
columns added after the run)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

from qpctl.controllers.base import Controller
from qpctl.errors import ConfigError
from qpctl.robot.model import RobotModel


@dataclass
class Trajectory:
    """Recorded arrays (DESIGN.md §4); T samples, n joints (degrees of freedom), m task coordinates;
    q is Pinocchio's configuration (T × nq: nq > n with continuous or planar joints, then ``angles``
    holds one number per degree of freedom)."""

    t: np.ndarray
    q: np.ndarray
    v: np.ndarray
    tau: np.ndarray
    x: np.ndarray
    x_ref: np.ndarray
    xd_ref: np.ndarray
    xdd_ref: np.ndarray
    clearance: np.ndarray
    e_null: np.ndarray
    tick_us: np.ndarray
    singular: np.ndarray
    infos: list[dict[str, Any]] = field(default_factory=list, repr=False)
    # with an orientation task: the task frame's orientation and its reference, quaternions (x, y, z, w)
    quat: np.ndarray | None = None
    quat_ref: np.ndarray | None = None
    orientation_error_deg: np.ndarray | None = None  # (T,) the angle between them (approach: the axis's)
    # with several oriented task frames (quat, quat_ref: the first's; orientation_error_deg: the largest)
    orientation_error_deg_per_task: np.ndarray | None = None  # (T, F) each oriented frame's angle [deg]
    self_clearance: np.ndarray | None = None  # (T,) least distance between the self-collision pairs [m]
    tau_command: np.ndarray | None = None  # (T, n) the controller's command, with faults (tau: what acted)
    # with the QP: each tick's SolveStatus ("solved", "infeasible", ...) and the fallback that gave the
    # torque ("" where the QP's own answer did), from the ticks' infos (the replay's status panel)
    qp_status: np.ndarray | None = None
    qp_fallback: np.ndarray | None = None
    # (T, n) one number per degree of freedom beside Pinocchio's configuration q (T, nq), where they
    # differ (continuous joints' angles in (−π, π], a planar base's x, y, θ: RobotModel.angles)
    angles: np.ndarray | None = None
    # with a depth camera: the map's occupied voxel centres (K, 3) [m], both channels, at some of its
    # snapshots, and each point's snapshot stamp (K,) [s] (the replay draws them: qpctl.replay.record)
    map_points: np.ndarray | None = None
    map_stamps: np.ndarray | None = None

    ARRAYS = ("t", "q", "v", "tau", "x", "x_ref", "xd_ref", "xdd_ref", "clearance", "e_null", "tick_us",
              "singular")
    OPTIONAL = ("quat", "quat_ref", "orientation_error_deg", "orientation_error_deg_per_task", "self_clearance",
                "tau_command", "qp_status", "qp_fallback", "angles", "map_points", "map_stamps")

    def save(self, path: str | Path) -> None:
        arrays = {k: getattr(self, k) for k in self.ARRAYS}
        arrays.update({k: getattr(self, k) for k in self.OPTIONAL if getattr(self, k) is not None})
        np.savez_compressed(path, **arrays)

    @classmethod
    def load(cls, path: str | Path) -> Trajectory:
        with np.load(path) as data:
            return cls(**{k: data[k] for k in cls.ARRAYS + cls.OPTIONAL if k in data.files})


MAX_TICKS = 5_000_000  # one run's recorded ticks (the trajectory is kept in memory: ~1 GB for the Panda)


def check_ticks(duration: float, dt: float) -> None:
    """:class:`ConfigError` (``sim.duration``) if a run of ``duration`` [s] at ``dt`` [s] would record
    more than MAX_TICKS ticks."""
    if not (np.isfinite(dt) and dt > 0):
        return  # the step's own check reports it
    ticks = duration / dt
    if not ticks <= MAX_TICKS:
        raise ConfigError(f"{duration} s at dt = {dt} s is {ticks:.3g} ticks; one run records at most "
                          f"{MAX_TICKS:,} (split it, or raise sim.dt)", key="sim.duration")


def measured_self_pairs(controller: Controller) -> tuple[tuple[int, int], ...]:
    """The link pairs whose distance a simulator records as the self clearance: the controller's
    self-collision pairs, or those a default SelfCollisionBarrier would keep (for every law)."""
    from qpctl.constraints.constraints import SelfCollisionBarrier
    from qpctl.geometry.self_collision import self_collision_pairs

    for c in getattr(controller, "constraints", ()):
        if isinstance(c, SelfCollisionBarrier):
            return c.pairs
    if len(controller.robot.capsules) < 3:
        return ()
    return self_collision_pairs(controller.robot, SELF_D_SAFE).pairs


SELF_D_SAFE = 0.02  # [m] QPConfig.self_d_safe's default, for the pairs measured under other laws


def finish_trajectory(traj: Trajectory, controller: Controller) -> Trajectory:
    """The task's position columns only in x, x_ref, ẋ_ref, ẍ_ref (the orientation rows' coordinates are
    centred at each tick's orientation: not a trajectory), and, with an orientation task, the frame's
    orientation and its reference as quaternions and the angle between them, from the recorded q
    and the path (after the run, outside the tick's timing); with the QP, its status and fallback per tick."""
    if traj.infos and all("status" in i for i in traj.infos):
        traj.qp_status = np.array([str(getattr(s, "value", s)) for s in
                                   (i.get("solve_status", i["status"]) for i in traj.infos)])
        traj.qp_fallback = np.array([str(i.get("fallback") or "") for i in traj.infos])
    robot = controller.robot
    if robot.lie:
        traj.angles = robot.angles(traj.q).copy()
    if not robot.m_orientation:
        return traj
    from qpctl.orientation import orientation_error_deg

    m_p = robot.m_position
    for name in ("x", "x_ref", "xd_ref", "xdd_ref"):
        setattr(traj, name, np.ascontiguousarray(getattr(traj, name)[:, :m_p]))
    model, data = robot.model, robot.model.createData()
    T, oriented = traj.t.size, robot.oriented_frames
    traj.quat, traj.quat_ref = np.zeros((T, 4)), np.zeros((T, 4))
    errors = np.zeros((T, len(oriented)))
    for k in range(T):
        pin.framesForwardKinematics(model, data, traj.q[k])
        for j, f in enumerate(oriented):
            R = data.oMf[robot.task_frame_ids[f]].rotation
            R_d = controller.path.orientation(float(traj.t[k]), j)[0]  # type: ignore[attr-defined]
            if j == 0:
                traj.quat[k] = pin.Quaternion(R).coeffs()
                traj.quat_ref[k] = pin.Quaternion(R_d).coeffs()
            errors[k, j] = orientation_error_deg(robot, R, R_d, frame=f)
    traj.orientation_error_deg = errors.max(axis=1)
    if len(oriented) > 1:
        traj.orientation_error_deg_per_task = errors
    return traj


def link_segments(controller: Controller | RobotModel, q: np.ndarray) -> np.ndarray:
    """(T, L, 2, 3) link capsule axes [m] for each configuration (a controller's robot, or a robot)."""
    robot = controller if isinstance(controller, RobotModel) else controller.robot
    data = robot.model.createData()
    out = np.empty((len(q), len(robot.capsules), 2, 3))
    for k, qk in enumerate(q):
        pin.forwardKinematics(robot.model, data, qk)
        for i, c in enumerate(robot.capsules):
            out[k, i] = data.oMi[c.joint_id].act(c.p0), data.oMi[c.joint_id].act(c.p1)
    return out
