"""Put a qpctl controller into a Drake diagram of your own: one LeafSystem, two connections.

``QpctlController`` reads the plant's state output for the arm's model instance (``estimated_state``)
and feeds the plant's actuation input for it (``actuation``), joints matched by name. Beside a discrete
plant it computes the torque when the plant's step asks for it (one call per step, no delay); beside a
continuous plant give it ``period=dt`` (a zero-order hold). Here the plant is the Panda as
``add_robot`` builds it (STL collision meshes replaced by qpctl's capsules, actuators added, root
welded), the canopy's branches and leaves are SceneGraph geometry (``add_obstacles``: shown by a
Meshcat visualiser if you add one, never in contact), and a logger records the arm's state.

    python examples/drake_diagram.py [DURATION_S]      (or QPCTL_EXAMPLE_DURATION=0.2)
"""

from __future__ import annotations

import os
import sys

import numpy as np
from pydrake.multibody.plant import AddMultibodyPlantSceneGraph
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import LogVectorOutput

from qpctl import Scenario
from qpctl.adapters.drake import QpctlController, add_obstacles, add_robot
from qpctl.tick import WorldClearance


def main(duration: float) -> float:
    scenario = Scenario.load("panda_canopy")  # the Panda picking three fruits among branches and leaves
    controller = scenario.build_controller("qp")  # or "paper", "hsu"
    robot = controller.robot

    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlantSceneGraph(builder, time_step=0.001)
    arm = add_robot(plant, scene_graph, robot).instance
    plant.Finalize()
    add_obstacles(builder, scene_graph, controller.obstacles)

    qpctl_system = builder.AddSystem(QpctlController(controller, plant, arm))
    builder.Connect(plant.get_state_output_port(arm), qpctl_system.get_input_port())
    builder.Connect(qpctl_system.get_output_port(), plant.get_actuation_input_port(arm))
    logger = LogVectorOutput(plant.get_state_output_port(arm), builder, publish_period=0.01)

    simulator = Simulator(builder.Build())
    context = plant.GetMyMutableContextFromRoot(simulator.get_mutable_context())
    plant.SetPositions(context, arm, scenario.q0(robot))  # the Panda's joints are in the controller's order
    simulator.AdvanceTo(duration)

    log = logger.FindLog(simulator.get_context())
    world = WorldClearance(robot, controller.obstacles)
    clearance = min(world(x[:robot.nv], t) for x, t in zip(log.data().T, log.sample_times()))
    error = float(np.linalg.norm(controller.last.ref.x - controller.last.x))
    print(f"t = {duration:.3f} s, tracking error {error:.2e} m, min clearance {clearance:.4f} m "
          f"over {len(log.sample_times())} logged states")
    return error


if __name__ == "__main__":
    main(float(sys.argv[1]) if len(sys.argv) > 1 else float(os.environ.get("QPCTL_EXAMPLE_DURATION", "6.0")))
