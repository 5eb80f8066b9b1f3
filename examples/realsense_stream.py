"""Your own depth camera: frames in, the QP's rows out (docs/perception.md, "A user's own camera").

A generator stands in for a RealSense stream (``pipeline.wait_for_frames()``: a uint16 depth image
in millimetres, the camera's intrinsics and its pose in the robot's base frame, a stamp); the map is
built in a worker thread beside the 1 kHz loop, which only ever reads the newest snapshot.

    python examples/realsense_stream.py [DURATION_S]      (or QPCTL_EXAMPLE_DURATION=0.3)
"""

from __future__ import annotations

import os
import sys

import numpy as np

from qpctl import Obstacle, QPController, Simulator, WaypointPath, panda
from qpctl.perception import Intrinsics, Perception, PerceptionConfig
from qpctl.perception.synthetic import Sphere, look_at, render

K = Intrinsics.from_fov(424, 240, 58.0)  # a D435 at 424×240
POSE = look_at([1.5, 0.0, 0.9], [0.45, 0.0, 0.5])  # fixed beside the arm, in the base frame
BRANCH = (0.45, 0.12, 0.62)  # where the unseen obstacle is [m]


def realsense_frames(rate: float = 30.0):  # stands in for pyrealsense2: (depth uint16 [mm], stamp [s])
    k = 0
    while True:
        frame = render(POSE, [Sphere(BRANCH, 0.05)], K, stamp=k / rate, noise=0.004)
        yield np.nan_to_num(frame.depth * 1000.0, nan=0.0).astype(np.uint16), k / rate
        k += 1


def main(duration: float) -> dict[str, float]:
    robot = panda()
    controller = QPController(robot, WaypointPath([[0.307, 0.0, 0.487], [0.45, 0.0, 0.65]], duration=2.0))
    config = PerceptionConfig(bounds_min=[-0.2, -0.6, 0.0], bounds_max=[1.2, 0.6, 1.2], depth_noise=0.02)
    with Perception(config, robot, threaded=True) as perception:
        perception.rows_for(controller)  # the map's barrier rows in the QP
        world = [Obstacle("sphere", np.array(BRANCH), radius=0.05)]  # the simulator's truth only
        sim, dt, camera = Simulator(controller, dt=1e-3, duration=duration, obstacles=world), 1e-3, realsense_frames()
        sim.reset(robot.q_home)
        clearance = np.inf
        for k in range(round(duration / dt)):
            t = k * dt
            q, v = sim.read()
            perception.record(t, q)  # the self-filter's joint history
            if k % 33 == 0:  # a frame arrives (30 Hz): hand it over, never wait
                depth, stamp = next(camera)
                perception.update_map(depth, K, POSE, stamp, depth_scale=0.001)
            sim.apply(controller.torque(q, v, t))
            sim.step(t)
            clearance = min(clearance, sim.clearance(q, t))
        built = perception.worker.built if perception.worker else 0
    print(f"{built} maps built, min clearance {clearance:.3f} m to the unseen branch")
    return {"clearance": clearance, "built": built}


if __name__ == "__main__":
    main(float(sys.argv[1]) if len(sys.argv) > 1 else float(os.environ.get("QPCTL_EXAMPLE_DURATION", "2.0")))
