"""The task frames' orientation rows (:meth:`RobotModel.frame_orientation`), in Python.

The compiled tick computes the same rows in :mod:`qpctl.kernels.scene` (``tests/test_orientation.py``
holds the two together, and these against finite differences on SO(3)). Every row is in the form
the laws already use for positions, e = x_d − x, ė = ẋ_d − ẋ, a = ẍ_d + K_v ė + K_p e − J̇q̇, in
exponential coordinates centred at the current orientation R (so x = 0 on these rows and x_d is
the error):

* ``pose``, world axis i: x_d = log(R_d Rᵀ)_i, ẋ = ω_i, ẋ_d = ω_d,i, ẍ_d = ω̇_d,i, J = J_ω,i,
  J̇q̇ = α₀,i, where ω = J_ω q̇ is the frame's angular velocity and α₀ = J̇_ω q̇ its angular
  acceleration at q̈ = 0 (world frame, Pinocchio's LOCAL_WORLD_ALIGNED). The error's exact rate
  is J_l⁻¹(e)(ω_d − ω); with ω_d − ω in its place (as TSID does) the error still decays as
  s² + k_v s + k_p while small, and is monotone for large ones.
* ``approach``, rows k = 1, 2: with the approach axis c (task frame), z = R c, and v_k = R_d b_k
  where b_1, b_2 ⟂ c (:meth:`RobotModel.approach_basis`), the coordinates y_k = v_k·z vanish
  exactly when z = d = R_d c (in the half-space z·d > 0). x = y_k, x_d = 0, and, from ż = ω × z,
  v̇_k = ω_d × v_k: ẏ_k = (z × v_k)·(ω − ω_d), so J = (z × v_k)ᵀJ_ω, ẋ_d = (z × v_k)·ω_d,
  J̇q̇ = (z × v_k)·α₀ + (ż × v_k)·(ω − ω_d) + (z × v̇_k)·ω, ẍ_d = (z × v̇_k)·ω_d + (z × v_k)·ω̇_d —
  exact, so e → 0 as s² + k_v s + k_p. The roll about z is free.

Every function takes ``frame``, the task frame (an index into :attr:`RobotModel.frames`, 0 by
default: ``ee_frame``); with several oriented frames each has its own rows, stacked frame after frame
(:attr:`RobotModel.oriented_frames`) after every position row.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from qpctl.errors import ConfigError
from qpctl.robot.model import RobotModel


def frame_terms(robot: RobotModel, q: np.ndarray, v: np.ndarray, data: pin.Data | None = None, *,
                frame: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """R (3, 3), ω [rad/s], α₀ [rad/s²] (angular acceleration at q̈ = 0) and J_ω (3, n) of task frame
    ``frame``, world frame, from Pinocchio's frame functions."""
    model = robot.model
    data = data or model.createData()
    fid = robot.task_frame_ids[frame]
    pin.forwardKinematics(model, data, q, v, np.zeros(model.nv))
    pin.updateFramePlacements(model, data)
    R = data.oMf[fid].rotation.copy()
    omega = pin.getFrameVelocity(model, data, fid, pin.LOCAL_WORLD_ALIGNED).angular.copy()
    alpha = pin.getFrameAcceleration(model, data, fid, pin.LOCAL_WORLD_ALIGNED).angular.copy()
    J = pin.computeFrameJacobian(model, data, q, fid, pin.LOCAL_WORLD_ALIGNED)[3:].copy()
    return R, omega, alpha, J


def orientation_rows(robot: RobotModel, R: np.ndarray, omega: np.ndarray, alpha: np.ndarray,
                     J_omega: np.ndarray, R_d: np.ndarray,
                     omega_d: np.ndarray, *, frame: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(x, ẋ, J, J̇q̇) of task frame ``frame``'s orientation rows at its R, ω, α₀, J_ω and the
    reference's R_d, ω_d (the approach rows depend on the reference's orientation: see the module)."""
    o = robot.frame_orientation(frame)
    if o.kind == "pose":
        axes = list(o.axes)
        return np.zeros(len(axes)), omega[axes], J_omega[axes], alpha[axes]
    if o.kind != "approach":
        return np.zeros(0), np.zeros(0), np.zeros((0, J_omega.shape[1])), np.zeros(0)
    z = R @ np.asarray(o.approach_axis)
    zdot = np.cross(omega, z)
    x, xd, J, drift = np.zeros(2), np.zeros(2), np.zeros((2, J_omega.shape[1])), np.zeros(2)
    for k, b in enumerate(o.basis()):
        v = R_d @ b
        zv = np.cross(z, v)
        x[k], xd[k], J[k] = v @ z, zv @ omega, zv @ J_omega
        drift[k] = zv @ alpha + np.cross(zdot, v) @ (omega - omega_d) + np.cross(z, np.cross(omega_d, v)) @ omega
    return x, xd, J, drift


def orientation_reference(robot: RobotModel, R: np.ndarray, R_d: np.ndarray, omega_d: np.ndarray,
                          alpha_d: np.ndarray, *, frame: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(x_d, ẋ_d, ẍ_d) of task frame ``frame``'s orientation rows at its R and the reference R_d, ω_d, ω̇_d."""
    o = robot.frame_orientation(frame)
    if o.kind == "pose":
        axes = list(o.axes)
        return pin.log3(R_d @ R.T)[axes], omega_d[axes], alpha_d[axes]
    if o.kind != "approach":
        return np.zeros(0), np.zeros(0), np.zeros(0)
    z = R @ np.asarray(o.approach_axis)
    xd, xdd = np.zeros(2), np.zeros(2)
    for k, b in enumerate(o.basis()):
        v = R_d @ b
        zv = np.cross(z, v)
        xd[k] = zv @ omega_d
        xdd[k] = np.cross(z, np.cross(omega_d, v)) @ omega_d + zv @ alpha_d
    return np.zeros(2), xd, xdd


def rotation_error(robot: RobotModel, R: np.ndarray, R_d: np.ndarray, *, frame: int = 0) -> np.ndarray:
    """The rotation vector [rad] (world frame) between task frame ``frame`` and its reference:
    log(R_d Rᵀ) for a pose, the least rotation taking the approach axis z = R c onto d = R_d c for an
    approach."""
    o = robot.frame_orientation(frame)
    if o.kind == "pose":
        return pin.log3(R_d @ R.T)
    c = np.asarray(o.approach_axis, float)
    z, d = R @ c, R_d @ c
    w = np.cross(z, d)
    s, cos = float(np.linalg.norm(w)), float(z @ d)
    if s < 1e-12:
        return np.zeros(3) if cos > 0 else np.pi * (R @ o.basis()[0])
    return np.arctan2(s, cos) * w / s


def orientation_error_deg(robot: RobotModel, R: np.ndarray, R_d: np.ndarray, *, frame: int = 0) -> float:
    """The angle [deg] between task frame ``frame`` and its reference: the whole rotation for a pose
    task, the approach axis's for an approach task (its roll is free)."""
    return float(np.degrees(np.linalg.norm(rotation_error(robot, R, R_d, frame=frame))))


def approach_rotations(R0: np.ndarray, axis: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Rotations (k+1, 3, 3) for an approach path: R0 first, then each turned from the previous by
    the least rotation that takes its approach axis R_k c onto the next direction (so a slerp
    between them swings the axis along a great circle and adds no roll)."""
    c = np.asarray(axis, float) / np.linalg.norm(axis)
    out = [np.asarray(R0, float)]
    for k, d in enumerate(np.asarray(directions, float)):
        nd = np.linalg.norm(d)
        if not (np.all(np.isfinite(d)) and nd > 1e-9):
            raise ConfigError(f"approach direction {k} must be a non-zero 3-vector, got {d.tolist()}",
                              key="path.approach")
        d = d / nd
        z = out[-1] @ c
        w = np.cross(z, d)
        s = float(np.linalg.norm(w))
        if s < 1e-12 and z @ d < 0:  # a half turn: about any axis orthogonal to z
            perp = np.cross(z, np.eye(3)[int(np.argmin(np.abs(z)))])
            w, s = np.pi * perp / np.linalg.norm(perp), 1.0
            out.append(pin.exp3(w) @ out[-1])
            continue
        out.append(pin.exp3(np.arctan2(s, z @ d) * w / max(s, 1e-300)) @ out[-1] if s > 0 else out[-1].copy())
    return np.array(out)
