"""The one simulator interface (qpctl.adapters.SimulatorBase) and its registry.

A simulator is five methods; the recording loop is shared. The test writes a new simulator in a few
lines — semi-implicit Euler on Pinocchio's ABA, the interface's contract and nothing else — and
requires its recorded run to equal, bit for bit, the built-in simulator's with ``integrator="euler"``
(the same arithmetic), and every registered simulator to be a SimulatorBase reachable from the CLI.
"""

from __future__ import annotations

import importlib.util

import numpy as np
import pinocchio as pin
import pytest

from qpctl import ConfigError, Obstacle, Scenario, Simulator, WaypointPath
from qpctl.adapters import SIMULATORS, SimulatorBase, simulator_class
from qpctl.cli import build_parser


class EulerSimulator(SimulatorBase):
    """A new simulator, as a user would add one: semi-implicit Euler on ABA."""

    name = "euler-test"

    def reset(self, q0, v0=None):
        self.q, self.v = np.array(q0, float), np.zeros(self.robot.nv) if v0 is None else np.array(v0, float)
        self.tau, self.data = np.zeros(self.robot.nv), self.robot.model.createData()

    def read(self):
        return self.q.copy(), self.v.copy()

    def apply(self, tau):
        self.tau = np.array(tau, float)

    def step(self, t):
        self.v = self.v + self.dt * pin.aba(self.robot.model, self.data, self.q, self.v, self.tau)
        self.q = self.q + self.dt * self.v
        self._t = t + self.dt


def test_a_new_simulator_is_five_methods_and_records_like_the_builtin():
    scenario = Scenario.load("paper", ["sim.duration=0.3"])
    q0 = scenario.q0(scenario.build_robot())
    mine = EulerSimulator(scenario.build_controller("paper"), dt=1e-3, duration=0.3).run(q0)
    builtin = Simulator(scenario.build_controller("paper"), dt=1e-3, duration=0.3, integrator="euler").run(q0)
    for key in (*builtin.ARRAYS, "self_clearance"):
        if key != "tick_us":
            np.testing.assert_array_equal(getattr(mine, key), getattr(builtin, key), err_msg=key)
    assert np.max(np.abs(mine.q[-1] - q0)) > 1e-3


def test_every_registered_simulator_is_an_adapter_and_a_cli_choice():
    sim_action = next(a for a in build_parser()._subparsers._group_actions[0].choices["simulate"]._actions
                      if a.dest == "sim")
    assert list(sim_action.choices) == list(SIMULATORS)
    for name, (module, _, _) in SIMULATORS.items():
        if importlib.util.find_spec(SIMULATORS[name][2] or "numpy") is None:
            with pytest.raises(ConfigError, match=f"qpctl\\[{SIMULATORS[name][2]}\\]"):
                simulator_class(name)
            continue
        cls = simulator_class(name)
        assert issubclass(cls, SimulatorBase) and cls.name == name and cls.__module__ == module


def test_builtin_holds_moving_obstacles_where_the_scene_says(planar):
    from baselines.paper import PaperController

    moving = Obstacle("sphere", np.array([0.5, -0.5, 0.0]), radius=0.1, velocity=np.array([0.2, 0.0, 0.0]))
    ctrl = PaperController(planar, WaypointPath([[-1.0, -2.0], [-0.5, -1.5]], duration=1.0), [moving])
    sim = Simulator(ctrl, dt=1e-3, duration=0.1)
    traj = sim.run(planar.q_home)
    np.testing.assert_allclose(sim.obstacle_positions(), [moving.position_at(traj.t[-1])], atol=1e-12)
