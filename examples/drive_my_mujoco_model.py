"""Your own MJCF in MuJoCo, driven by a qpctl controller: its joint names, its geared motors.

``examples/my_arm.xml`` is a hand-written model of the paper's arm whose joints are called shoulder,
elbow and wrist (the controller's are joint1..3) and whose motor actuators have gear 100 and
ctrlrange ±5. Two ways to run it, which must agree with each other and with the built-in simulator:

* through the scenario file ``examples/my_arm.toml`` (``[sim] model = "my_arm.xml"``, ``joint_names``),
  what ``qpctl simulate examples/my_arm.toml`` does;
* through the API: ``MujocoSimulator(controller, model="my_arm.xml", joint_names=[...])``.

The adapter sends the torque through the motors' ``ctrl`` (τ / gear, clamped to ctrlrange and
reported if it is), switches off any servo actuator with a note, and checks the model's M(q) and bias
forces against the controller's; ``sim.notes`` says what it did.

    python examples/drive_my_mujoco_model.py [DURATION_S]      (or QPCTL_EXAMPLE_DURATION=0.2)
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

from qpctl import Scenario, Simulator, simulate
from qpctl.adapters.mujoco import MujocoSimulator

HERE = Path(__file__).resolve().parent


def main(duration: float) -> float:
    scenario = Scenario.load(HERE / "my_arm.toml", [f"sim.duration={duration}"])
    through_toml = simulate(scenario)  # sim.simulator = "mujoco", sim.model = "my_arm.xml"

    controller = scenario.build_controller()
    sim = MujocoSimulator(controller, dt=0.001, duration=duration, model=HERE / "my_arm.xml",
                          joint_names=["shoulder", "elbow", "wrist"])
    through_api = sim.run(scenario.q0(controller.robot))
    for note in sim.notes:
        print("mujoco:", note)

    builtin = Simulator(scenario.build_controller(), dt=0.001, duration=duration).run(scenario.q0(controller.robot))
    dq_toml = float(np.max(np.abs(through_toml.trajectory.q - builtin.q)))
    dq_api = float(np.max(np.abs(through_api.q - builtin.q)))
    print(f"{duration:g} s: max |Δq| against the built-in simulator {dq_toml:.1e} rad (TOML), "
          f"{dq_api:.1e} rad (API); ctrl clamped on {sim.counts['ctrl_clamped_ticks']} ticks")
    return max(dq_toml, dq_api)


if __name__ == "__main__":
    main(float(sys.argv[1]) if len(sys.argv) > 1 else float(os.environ.get("QPCTL_EXAMPLE_DURATION", "5.0")))
