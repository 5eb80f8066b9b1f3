"""Drive MuJoCo with a qpctl controller from your own loop.

The whole contract is ``tau = controller.torque(q, v, t)``: joint positions [rad] and velocities
[rad/s] in the order of ``controller.robot.joint_names``, time [s] on the path's clock, torques
[N·m] back in the same order, held constant until the next call (zero-order hold). Here MuJoCo's
state is read and written by joint name, so any MJCF with those joint names would do; this one is
generated from the controller's own robot model.

    python examples/drive_mujoco_loop.py [DURATION_S]      (or QPCTL_EXAMPLE_DURATION=0.2)
"""

from __future__ import annotations

import os
import sys

import mujoco
import numpy as np

from qpctl import Scenario
from qpctl.adapters.mujoco import build_model


def main(duration: float) -> float:
    scenario = Scenario.load("paper")  # the paper's planar 3-link arm, two obstacles
    controller = scenario.build_controller("paper")  # or "hsu", or "qp"
    robot = controller.robot

    model = build_model(robot, controller.obstacles, timestep=0.001)  # RK4, contacts off
    data = mujoco.MjData(model)
    qpos = [model.joint(name).qposadr[0] for name in robot.joint_names]  # model order → MuJoCo addresses
    dofs = [model.joint(name).dofadr[0] for name in robot.joint_names]
    data.qpos[qpos] = scenario.q0(robot)
    mujoco.mj_forward(model, data)
    controller.warmup()  # compile or load the tick's kernels now, not in the loop's first tick

    for k in range(round(duration / model.opt.timestep)):
        t = k * model.opt.timestep
        tau = controller.torque(data.qpos[qpos], data.qvel[dofs], t)
        data.qfrc_applied[dofs] = tau  # held over the whole step, all four RK4 stages
        mujoco.mj_step(model, data)

    error = float(np.linalg.norm(controller.last.ref.x - controller.last.x))
    print(f"t = {data.time:.3f} s, tracking error {error:.2e} m, τ = {np.round(controller.last.tau, 2)} N·m")
    return error


if __name__ == "__main__":
    main(float(sys.argv[1]) if len(sys.argv) > 1 else float(os.environ.get("QPCTL_EXAMPLE_DURATION", "5.0")))
