"""Swap the QP solver: the same scenario and controller, once per installed solver.

The solver is a name in configuration (``controller.solver``, ``--solver``, or
``build_controller("qp", solver=...)``); ``controller.set_solver(name)`` swaps it on a live
controller. Each solver solves the same QP every tick, so the torques agree to the solvers'
tolerances; what differs is the time per tick.

    python examples/swap_solver.py [DURATION_S]      (or QPCTL_EXAMPLE_DURATION=0.2)
"""

from __future__ import annotations

import os
import sys

import numpy as np

from qpctl import Scenario, Simulator, available_solvers


def main(duration: float) -> dict[str, float]:
    scenario = Scenario.load("paper", [f"sim.duration={duration}"])
    dt = scenario.data["sim"]["dt"]
    reference = None
    spread = {}
    for name in available_solvers():
        controller = scenario.build_controller("qp", solver=name)
        traj = Simulator(controller, dt=dt, duration=duration).run(scenario.q0(controller.robot))
        reference = traj.tau if reference is None else reference
        spread[name] = float(np.max(np.abs(traj.tau - reference)))
        error = np.linalg.norm(traj.x_ref - traj.x, axis=1).max()
        print(f"{name:10s} tick median {np.median(traj.tick_us):7.0f} µs   "
              f"max tracking error {error:.2e} m   "
              f"max |τ − τ_{available_solvers()[0]}| {spread[name]:.1e} N·m")

    controller = scenario.build_controller("qp", solver="proxqp")
    controller.set_solver("osqp")  # on a live controller: its warm start begins afresh
    print(f"swapped a live controller to {controller.solver}")
    return spread


if __name__ == "__main__":
    main(float(sys.argv[1]) if len(sys.argv) > 1 else float(os.environ.get("QPCTL_EXAMPLE_DURATION", "1.0")))
