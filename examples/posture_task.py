"""Add a posture task to the QP: keep the Panda's redundant joints near a home posture.

The Panda has 7 joints for a 3-coordinate task (the gripper's position), so 4 directions of
self-motion that the task does not fix. Without a posture task they drift (the paper's null-space
term only damps them); ``PostureTask(q_ref, weight)`` adds ½w‖q̈ − q̈_p‖², q̈_p = K_p(q_ref − q) − K_d q̇,
to the QP's cost. The end-effector task is a hard equality, so the posture acts only in the null
space — tracking is unaffected.

    python examples/posture_task.py [DURATION_S]      (or QPCTL_EXAMPLE_DURATION=0.2)
"""

from __future__ import annotations

import os
import sys

import numpy as np
import pinocchio as pin

from qpctl import LawGains, PostureTask, QPController, Simulator, WaypointPath, panda


def main(duration: float) -> dict[str, float]:
    robot = panda()
    data = robot.model.createData()
    pin.framesForwardKinematics(robot.model, data, robot.q_home)
    x0 = data.oMf[robot.ee_frame_id].translation.copy()  # the gripper at the home posture [m]
    path = WaypointPath([x0, x0 + [0.25, 0.25, -0.1], x0 + [0.25, -0.25, 0.1]], durations=[1.0, 1.0])

    drift = {}
    for label, weight in (("without posture task", 0.0), ("with PostureTask(q_home, weight=10)", 10.0)):
        controller = QPController(robot, path, obstacles=[], gains=LawGains(kn=20.0))
        if weight:
            controller.add_task(PostureTask(robot.q_home, weight=weight))
        traj = Simulator(controller, dt=1e-3, duration=duration).run(robot.q_home)
        drift[label] = float(np.max(np.abs(traj.q - robot.q_home)))
        error = np.linalg.norm(traj.x_ref - traj.x, axis=1).max()
        print(f"{label:38s} max |q − q_home| {drift[label]:.2f} rad   max tracking error {error:.1e} m")
    return drift


if __name__ == "__main__":
    main(float(sys.argv[1]) if len(sys.argv) > 1 else float(os.environ.get("QPCTL_EXAMPLE_DURATION", "2.0")))
