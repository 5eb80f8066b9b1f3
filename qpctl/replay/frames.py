"""The replay's frames: the recorded run sampled at the display rate, and what each frame shows.

Frame k is shown from ``k / fps`` [s] (and the run's last sample at its end); it shows the last
recorded sample at or before that time — the recorded data themselves, never an interpolation or a
filtered copy. Per frame: each moving joint's pose (Pinocchio's forward kinematics of the recorded
q), each link capsule's least distance to the obstacles (python-fcl, :class:`DistanceEngine
<qpctl.geometry.distance.DistanceEngine>`, up to a cutoff), the obstacles' positions and the task
point's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from qpctl.errors import ConfigError
from qpctl.geometry.distance import DistanceEngine
from qpctl.geometry.obstacles import Obstacle
from qpctl.robot.model import RobotModel

DEFAULT_FPS = 30.0  # [frames/s] the display rate
MAX_FPS = 240.0  # [frames/s] beyond a screen's refresh rate, frames are never shown


@dataclass(frozen=True)
class Frames:
    """F display frames of a run (arrays in the world frame, [m]).

    Attributes:
        times: (F,) when each frame is shown [s], increasing from 0.
        ticks: (F,) the recorded sample each frame shows (an index into the trajectory's arrays).
        joints: the Pinocchio joint ids whose poses are given, in ``poses``' order.
        poses: (F, J, 7) each joint's placement: position (3) then orientation as (w, x, y, z).
        link_clearance: (F, L) each link capsule's least distance to any obstacle [m]; inf where no
            obstacle is within the cutoff.
        obstacle_positions: (F, O, 3) each obstacle's centre.
        task_point: (F, 3) the task frame's origin (the end effector).
    """

    times: np.ndarray
    ticks: np.ndarray
    joints: tuple[int, ...]
    poses: np.ndarray
    link_clearance: np.ndarray
    obstacle_positions: np.ndarray
    task_point: np.ndarray


def display_ticks(t: np.ndarray, fps: float = DEFAULT_FPS) -> tuple[np.ndarray, np.ndarray]:
    """(times [s], ticks): one frame every 1/fps from t[0] to t[-1] (t[-1] itself last), each showing
    the last recorded sample at or before its time."""
    t = np.asarray(t, float)
    if t.size == 0:
        return np.zeros(0), np.zeros(0, int)
    if not (np.isfinite(fps) and 0 < fps <= MAX_FPS):
        raise ConfigError(f"the display rate must be a number of frames per second in (0, {MAX_FPS:g}], got {fps}",
                          key="fps")
    span = float(t[-1] - t[0])
    count = int(np.floor(span * fps + 1e-9)) + 1
    times = np.arange(count) / fps
    if span - times[-1] > 1e-9:  # the run's end, shown as its own (last) frame
        times = np.append(times, span)
    ticks = np.searchsorted(t - t[0], times + 1e-12, side="right") - 1
    return times, np.clip(ticks, 0, t.size - 1)


def task_point_positions(robot: RobotModel, q: np.ndarray) -> np.ndarray:
    """(T, 3) world position [m] of the task frame's origin at each configuration (Pinocchio)."""
    data = robot.model.createData()
    out = np.empty((len(q), 3))
    for k, qk in enumerate(q):
        pin.framesForwardKinematics(robot.model, data, qk)
        out[k] = data.oMf[robot.ee_frame_id].translation
    return out


def sample(robot: RobotModel, obstacles: list[Obstacle], t: np.ndarray, q: np.ndarray, joints: tuple[int, ...],
           *, fps: float = DEFAULT_FPS, cutoff: float = np.inf) -> Frames:
    """The display frames of a run recorded at times ``t`` [s] with configurations ``q``; ``joints``:
    the joints whose poses the page moves; ``cutoff`` [m]: the link clearances beyond it are inf."""
    from qpctl.simulation.trajectory import link_segments

    times, ticks = display_ticks(t, fps)
    model, data = robot.model, robot.model.createData()
    poses = np.zeros((len(ticks), len(joints), 7))
    task = np.zeros((len(ticks), 3))
    for k, i in enumerate(ticks):
        pin.framesForwardKinematics(model, data, q[i])
        for n, j in enumerate(joints):
            M = data.oMi[j]
            poses[k, n, :3] = M.translation
            poses[k, n, 3:] = pin.Quaternion(M.rotation).coeffs()[[3, 0, 1, 2]]  # (x, y, z, w) → (w, x, y, z)
        task[k] = data.oMf[robot.ee_frame_id].translation
    L = len(robot.capsules)
    clearance = np.full((len(ticks), L), np.inf)
    positions = np.array([[o.position_at(float(t[i])) for o in obstacles] for i in ticks]).reshape(len(ticks), -1, 3)
    if obstacles and L:
        engine = DistanceEngine([c.radius for c in robot.capsules], obstacles, broadphase=False)
        segments = link_segments(robot, q[ticks])
        for k, i in enumerate(ticks):
            engine.update(segments[k], float(t[i]))
            pairs = engine.pairs(cutoff)
            np.minimum.at(clearance[k], pairs.link, pairs.distance)
    return Frames(times, ticks, tuple(joints), poses, clearance, positions, task)
