"""Drive PyBullet with a qpctl controller from your own loop.

The same contract as with MuJoCo: ``tau = controller.torque(q, v, t)`` with q [rad], v [rad/s] in
``controller.robot.joint_names``' order, the torque [N·m] held over the control period. PyBullet
needs three things undone first: each joint's default velocity motor (it holds the joint still) is
switched off by a VELOCITY_CONTROL command of zero force, and the links' default damping is set to
zero; then TORQUE_CONTROL applies the torque for exactly one stepSimulation (it is cleared after a
step, so it is re-applied every tick). The URDF here is the paper arm's, written from the controller's
own model (any URDF with these joint names would do: load it with URDF_USE_INERTIA_FROM_FILE).

    python examples/drive_pybullet_loop.py [DURATION_S]      (or QPCTL_EXAMPLE_DURATION=0.2)
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

import numpy as np
import pybullet

from qpctl import Scenario
from qpctl.adapters.pybullet import robot_urdf


def main(duration: float) -> float:
    scenario = Scenario.load("paper")  # the paper's planar 3-link arm, two obstacle areas
    controller = scenario.build_controller("paper")  # or "hsu", or "qp"
    robot = controller.robot
    dt = 0.001

    client = pybullet.connect(pybullet.DIRECT)
    pybullet.setGravity(*robot.model.gravity.linear)
    pybullet.setTimeStep(dt)
    with tempfile.TemporaryDirectory() as tmp:
        urdf = Path(tmp) / "arm.urdf"
        urdf.write_text(robot_urdf(robot))
        arm = pybullet.loadURDF(str(urdf), useFixedBase=True, flags=pybullet.URDF_USE_INERTIA_FROM_FILE)
    names = [pybullet.getJointInfo(arm, i)[1].decode() for i in range(pybullet.getNumJoints(arm))]
    joints = [names.index(name) for name in robot.joint_names]  # model order → PyBullet joint indices
    for link in [-1, *joints]:
        pybullet.changeDynamics(arm, link, linearDamping=0.0, angularDamping=0.0, jointDamping=0.0)
    pybullet.setJointMotorControlArray(arm, joints, pybullet.VELOCITY_CONTROL, forces=[0.0] * len(joints))
    for j, qj in zip(joints, scenario.q0(robot)):
        pybullet.resetJointState(arm, j, qj, 0.0)
    controller.warmup()  # compile or load the tick's kernels now, not in the loop's first tick

    for k in range(round(duration / dt)):
        states = pybullet.getJointStates(arm, joints)
        q, v = np.array([s[0] for s in states]), np.array([s[1] for s in states])
        tau = controller.torque(q, v, k * dt)
        pybullet.setJointMotorControlArray(arm, joints, pybullet.TORQUE_CONTROL, forces=tau.tolist())
        pybullet.stepSimulation()  # semi-implicit Euler, one control period
    pybullet.disconnect(client)

    error = float(np.linalg.norm(controller.last.ref.x - controller.last.x))
    print(f"t = {duration:.3f} s, tracking error {error:.2e} m, τ = {np.round(controller.last.tau, 2)} N·m")
    return error


if __name__ == "__main__":
    main(float(sys.argv[1]) if len(sys.argv) > 1 else float(os.environ.get("QPCTL_EXAMPLE_DURATION", "5.0")))
