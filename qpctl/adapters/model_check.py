"""Is the simulated robot the robot the controller believes in? M(q) and the bias forces compared.

The laws compute M(q) and N(q, q̇) = C(q, q̇)q̇ + G(q) from their own Pinocchio model; a simulator
loaded from the user's own file may hold other inertias, another gravity, armature. That is not
forbidden (it is what robustness to model error means), but it must be seen: :func:`check_dynamics`
compares the simulator's terms with Pinocchio's on a few seeded random states and reports the
largest differences, and the adapters put its sentence in their ``notes`` (``metrics.json``'s
``simulator_notes``) whenever it exceeds round-off.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import pinocchio as pin

from qpctl.errors import ConfigError
from qpctl.robot.model import RobotModel

if TYPE_CHECKING:
    from qpctl.simulation.loop import SimulatorBase

ROUND_OFF = 1e-9  # relative difference below which two models are the same model
FORWARD_TOLERANCE = 1e-9  # relative q̈ difference above which a simulator's forward dynamics are reported
Terms = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class DynamicsCheck:
    """Largest differences simulator − controller's model over ``states`` random states.

    Attributes:
        m_abs: max |ΔM| [kg·m²]; m_rel: that over max |M|.
        bias_abs: max |ΔN| [N·m]; bias_rel: that over max(|N|, 1 N·m).
        states: how many states were compared.
    """

    m_abs: float
    m_rel: float
    bias_abs: float
    bias_rel: float
    states: int

    @property
    def same(self) -> bool:
        """Both differences at round-off level (:data:`ROUND_OFF`)."""
        return self.m_rel <= ROUND_OFF and self.bias_rel <= ROUND_OFF

    def sentence(self, what: str) -> str:
        verdict = "match the controller's model" if self.same else "DIFFER from the controller's model"
        return (f"{what}: M(q) and the bias forces {verdict} on {self.states} random states: "
                f"max |ΔM| = {self.m_abs:.2g} kg·m² ({self.m_rel:.2g} relative), max |ΔN| = "
                f"{self.bias_abs:.2g} N·m ({self.bias_rel:.2g} relative)")


def random_states(robot: RobotModel, count: int = 5, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """Seeded (q (a configuration), v [rad/s]) within the joint limits (±π where unlimited), |v| ≤ 1 rad/s."""
    rng = np.random.default_rng(seed)
    lo = np.where(np.isfinite(robot.q_min), robot.q_min, -np.pi)
    hi = np.where(np.isfinite(robot.q_max), robot.q_max, np.pi)
    return [(robot.random_configuration(rng, lo, hi), rng.uniform(-1.0, 1.0, robot.nv)) for _ in range(count)]


def check_dynamics(robot: RobotModel, terms: Terms, count: int = 5, seed: int = 0) -> DynamicsCheck:
    """Compare ``terms(q, v) → (M (n, n), N (n,))`` of a simulator (controller's joint order) with
    Pinocchio's CRBA and ``nonLinearEffects`` on ``count`` seeded random states."""
    data = robot.model.createData()
    m_abs = m_ref = b_abs = 0.0
    b_ref = 1.0
    states = random_states(robot, count, seed)
    for q, v in states:
        M = pin.crba(robot.model, data, q)
        M = np.triu(M) + np.triu(M, 1).T
        N = pin.nonLinearEffects(robot.model, data, q, v)
        M_sim, N_sim = terms(q, v)
        m_abs = max(m_abs, float(np.max(np.abs(M_sim - M))))
        m_ref = max(m_ref, float(np.max(np.abs(M))))
        b_abs = max(b_abs, float(np.max(np.abs(N_sim - N))))
        b_ref = max(b_ref, float(np.max(np.abs(N))))
    return DynamicsCheck(m_abs, m_abs / m_ref, b_abs, b_abs / b_ref, len(states))


def forward_difference(sim: SimulatorBase) -> float:
    """Largest relative difference between a simulator's q̈ — its first step's Δv/dt from each of
    :func:`random_states`, τ = 0, through its own reset/apply/step/read — and Pinocchio's ABA."""
    robot = sim.robot
    data = robot.model.createData()
    worst = 0.0
    for q, v in random_states(robot):
        sim.reset(q, v)
        sim.apply(np.zeros(robot.nv))
        sim.step(0.0)
        a_sim = (sim.read()[1] - v) / sim.dt
        a = pin.aba(robot.model, data, q, v, np.zeros(robot.nv))
        worst = max(worst, float(np.max(np.abs(a_sim - a)) / max(np.max(np.abs(a)), 1.0)))
    return worst


def check_simulator(sim: SimulatorBase, terms: Terms, what: str, *, by_order: bool) -> tuple[DynamicsCheck, float]:
    """The start-up checks of an adapter that loaded a model: :func:`check_dynamics` and
    :func:`forward_difference`, their sentences added to ``sim.notes`` when they differ (or the joints
    were matched by order); ``what`` names the model ("the PyBullet model").

    Raises:
        ConfigError (``sim.joint_names``): joints matched by order whose dynamics differ.
    """
    dynamics = check_dynamics(sim.robot, terms)
    if by_order and not dynamics.same:
        raise ConfigError("joints matched by order, but " + dynamics.sentence(what)
                          + "; name the joints with sim.joint_names (or fix the model)", key="sim.joint_names")
    if not dynamics.same or by_order:
        sim.notes.append(dynamics.sentence(what))
    forward = forward_difference(sim)
    if forward > FORWARD_TOLERANCE:
        sim.notes.append(f"{what}'s forward dynamics (one step from {len(random_states(sim.robot))} random states, "
                         f"τ = 0) differ from Pinocchio's ABA by {forward:.2g} relative in q̈")
    return dynamics, forward
