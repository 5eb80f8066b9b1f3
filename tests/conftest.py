"""Shared fixtures: the paper's planar arm, the Panda, seeded random states, the paper scenario.

Also the independent reference models the tests compare the library against (written here from
first principles, not from the library): thin-rod kinematics and dynamics of an n-link planar arm.
"""

from __future__ import annotations

import os
import socket
from collections.abc import Callable

import numpy as np
import pytest

os.environ.setdefault("MPLBACKEND", "Agg")

from qpctl import Scenario, panda, planar_arm
from qpctl.robot.model import RobotModel

SEED = 20240611


@pytest.fixture
def rng() -> np.random.Generator:
    """A fresh seeded generator per test, so each test is reproducible on its own."""
    return np.random.default_rng(SEED)


@pytest.fixture(scope="session")
def planar() -> RobotModel:
    """The paper's arm: 3 unit rods of 10 kg in the vertical x–y plane, gravity −y."""
    return planar_arm()


@pytest.fixture(scope="session")
def panda_robot() -> RobotModel:
    return panda()


@pytest.fixture
def random_states(rng: np.random.Generator) -> Callable[[RobotModel, int], list[tuple[np.ndarray, np.ndarray]]]:
    """``random_states(robot, k)``: k (q, v) pairs, q inside the joint limits, |v| ≲ 1.5 rad/s."""

    def make(robot: RobotModel, k: int) -> list[tuple[np.ndarray, np.ndarray]]:
        lo = np.where(np.isfinite(robot.q_min), robot.q_min, -np.pi)
        hi = np.where(np.isfinite(robot.q_max), robot.q_max, np.pi)
        margin = 0.05 * (hi - lo)
        return [(rng.uniform(lo + margin, hi - margin), rng.uniform(-1.5, 1.5, robot.nv)) for _ in range(k)]

    return make


@pytest.fixture
def paper_scenario() -> Scenario:
    return Scenario.load("paper")


@pytest.fixture
def no_network(monkeypatch: pytest.MonkeyPatch) -> None:
    """Any attempt to open a network connection fails the test."""

    def refuse(*_args: object, **_kwargs: object) -> None:
        raise AssertionError("network access attempted")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket, "create_connection", refuse)


# ------------------------------------------------------------------------------------------------
# Independent thin-rod model of an n-link planar arm (revolute joints about z, link k along its
# absolute angle θ_k = q_1 + … + q_k, length l, mass m, centre of mass at mid-link,
# I_c = m l²/12, gravity g along −y). Derived by hand from the Lagrangian; written so that it also
# accepts complex q (complex-step derivatives of M give exact Christoffel symbols).
# ------------------------------------------------------------------------------------------------
class ThinRodArm:
    def __init__(self, n: int = 3, length: float = 1.0, mass: float = 10.0, g: float = 9.81) -> None:
        self.n, self.l, self.m, self.g = n, length, mass, g
        self.I = mass * length**2 / 12.0

    def angles(self, q: np.ndarray) -> np.ndarray:
        return np.cumsum(q)

    def joint_positions(self, q: np.ndarray) -> np.ndarray:
        """(n+1, 2): base, joints 2…n, tip."""
        th = self.angles(q)
        steps = self.l * np.stack([np.cos(th), np.sin(th)], axis=1)
        return np.vstack([np.zeros((1, 2), dtype=steps.dtype), np.cumsum(steps, axis=0)])

    def ee(self, q: np.ndarray) -> np.ndarray:
        return self.joint_positions(q)[-1]

    def point_jacobian(self, q: np.ndarray, k: int, s: float) -> np.ndarray:
        """(2, n) Jacobian of the point at distance s along link k (0-based)."""
        th = self.angles(q)
        J = np.zeros((2, self.n), dtype=np.result_type(q, float))
        for i in range(k + 1):  # joint i moves every link from i on
            for j in range(i, k + 1):
                r = self.l if j < k else s
                J[:, i] += r * np.array([-np.sin(th[j]), np.cos(th[j])])
        return J

    def ee_jacobian(self, q: np.ndarray) -> np.ndarray:
        return self.point_jacobian(q, self.n - 1, self.l)

    def com(self, q: np.ndarray, k: int) -> np.ndarray:
        th = self.angles(q)
        return self.joint_positions(q)[k] + 0.5 * self.l * np.array([np.cos(th[k]), np.sin(th[k])])

    def mass_matrix(self, q: np.ndarray) -> np.ndarray:
        """M_ij = Σ_k m (J_ck,i · J_ck,j) + I_c [i, j ≤ k]."""
        M = np.zeros((self.n, self.n), dtype=np.result_type(q, float))
        for k in range(self.n):
            Jc = self.point_jacobian(q, k, 0.5 * self.l)
            M = M + self.m * Jc.T @ Jc
            M[: k + 1, : k + 1] += self.I
        return M

    def gravity(self, q: np.ndarray) -> np.ndarray:
        """G = ∂V/∂q with V = Σ_k m g y_ck."""
        return sum(self.m * self.g * self.point_jacobian(q, k, 0.5 * self.l)[1] for k in range(self.n))

    def potential(self, q: np.ndarray) -> float:
        return float(sum(self.m * self.g * self.com(q, k)[1] for k in range(self.n)))

    def dM(self, q: np.ndarray) -> np.ndarray:
        """∂M/∂q_k (n, n, n), last index k, by complex step (exact to rounding)."""
        h = 1e-30
        out = np.empty((self.n, self.n, self.n))
        for k in range(self.n):
            dq = np.zeros(self.n, complex)
            dq[k] = 1j * h
            out[:, :, k] = self.mass_matrix(q + dq).imag / h
        return out

    def coriolis_vector(self, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        """(C q̇)_i = Σ_jk Γ_ijk q̇_j q̇_k, Γ_ijk = ½(∂M_ij/∂q_k + ∂M_ik/∂q_j − ∂M_jk/∂q_i)."""
        dM = self.dM(q)
        gamma = 0.5 * (dM + dM.transpose(0, 2, 1) - dM.transpose(2, 0, 1))
        return np.einsum("ijk,j,k->i", gamma, v, v)


@pytest.fixture(scope="session")
def thin_rod() -> ThinRodArm:
    """The hand-derived model of the paper's arm (3 unit rods, 10 kg, g = 9.81 along −y)."""
    return ThinRodArm()
