"""Faults of a real arm, applied by the simulator: what the controller measures, what the drives apply,
the robot it really is and the scene it really moves in (issue 12).

A :class:`Faults` is built from the scenario's ``[faults]`` table (every fault off by default) and
handed to :class:`~qpctl.simulation.Simulator`. Each fault draws from its own seeded random stream
(``seed`` and the fault's name), so switching one fault on does not change another's realisation.

Sensing (the controller sees only these; the recorded q, q̇, task point and clearance are the truth):

* ``q_noise`` [rad]: measured q = q + N(0, σ²) per joint and tick;
* ``q_quantum`` [rad]: encoder resolution: measured q = Δ·round((q + noise)/Δ);
* ``v_noise`` [rad/s]: measured q̇ = q̇ + N(0, σ_v²) per joint and tick;
* ``obstacle_noise`` [m]: the controller's map has every obstacle displaced by a constant offset
  N(0, σ²) along each of the task's world axes (a camera's calibration error, drawn once per run);
* ``obstacle_velocity`` [m/s]: the true obstacles drift at this speed, each in a seeded random
  direction within the task's axes, while the controller's map keeps them where they started.

Actuation (the torque that acts on the simulated robot; the chain below, in this order):

* ``miss_rate``: probability that a tick's command is lost (computed, but too late for the
  drive): the drive holds the last command it received;
* ``delay_ticks``: the drive applies the command received k ticks earlier (before the first k
  ticks have passed, the first command);
* ``torque_saturation`` [N·m] (scalar or per joint): the drives deliver at most this much, whatever
  the controller's own limits say;
* ``torque_lag`` [s]: a first-order lag T, T τ̇_a = u − τ_a, on the (saturated) command u held over
  the step: the drive's torque is sampled exactly at the ticks, τ_a ← u + (τ_a − u)·e^(−dt/T), and
  the torque held over the step is its exact mean, u + (τ_a − u)·(T/dt)(1 − e^(−dt/T)), so the
  impulse each step imparts is the lagged drive's; τ_a starts at the first command.

The robot (the simulated model; the controller keeps its nominal one):

* ``mass_error`` e (relative): every body's mass and rotational inertia scaled by 1 + ε_i,
  ε_i ~ U(−e, e) per body, its centre of mass unchanged;
* ``payload_mass`` [kg] from ``payload_time`` [s] on: a solid sphere of ``payload_radius`` [m]
  centred on the task frame (the fruit after the grasp), added to that frame's body with
  Pinocchio's spatial inertia algebra.
"""

from __future__ import annotations

import dataclasses
import math
import zlib
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pinocchio as pin

from qpctl.errors import ConfigError
from qpctl.geometry.obstacles import Obstacle
from qpctl.robot.config import RobotConfig
from qpctl.robot.model import RobotModel, arm_reach

#: Default radius [m] of the payload sphere (a fruit of 8 cm).
PAYLOAD_RADIUS = RobotConfig.payload_radius

def _stream(seed: int, name: str) -> np.random.Generator:
    """The random stream of one fault: seeded by ``seed`` and the fault's name (stable across runs)."""
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, zlib.crc32(name.encode())])


@dataclass(frozen=True)
class Faults:
    """What is not ideal in a run (module docstring); every field's default is "no fault". The fields
    are the keys of the scenario's ``[faults]`` table (:data:`qpctl.scenario.SCHEMA` reads them here)."""

    q_noise: float = 0.0  # [rad] σ of the measured joint positions
    q_quantum: float = 0.0  # [rad] encoder resolution (0: none)
    v_noise: float = 0.0  # [rad/s] σ of the measured joint velocities
    delay_ticks: int = 0  # the command acts this many ticks late
    miss_rate: float = 0.0  # probability that a tick's command is lost (the last one held)
    torque_lag: float = 0.0  # [s] first-order actuator time constant (0: none)
    torque_saturation: float | tuple[float, ...] | None = None  # [N·m] what the drives deliver at most
    mass_error: float = 0.0  # relative: masses and inertias × (1 + U(−e, e)) per body
    payload_mass: float = 0.0  # [kg] unknown payload at the task frame
    payload_time: float = 0.0  # [s] from when the payload is carried
    payload_radius: float = PAYLOAD_RADIUS  # [m] the payload is a solid sphere of this radius
    obstacle_noise: float = 0.0  # [m] σ of the offset of each obstacle in the controller's map
    obstacle_velocity: float = 0.0  # [m/s] drift speed of the true obstacles (unknown to the controller)
    seed: int = 0

    def __post_init__(self) -> None:
        def bad(key: str, message: str, value: Any) -> ConfigError:
            return ConfigError(f"{message}, got {value!r}", key=f"faults.{key}")

        for key in ("q_noise", "q_quantum", "v_noise", "torque_lag", "payload_mass", "payload_time",
                    "obstacle_noise", "obstacle_velocity"):
            val = getattr(self, key)
            if isinstance(val, bool) or not isinstance(val, (int, float)) or not (math.isfinite(val) and val >= 0):
                raise bad(key, "must be a finite number >= 0", val)
        for key in ("delay_ticks", "seed"):
            val = getattr(self, key)
            if isinstance(val, bool) or not isinstance(val, (int, np.integer)):
                raise bad(key, "must be an integer", val)
        if self.delay_ticks < 0:
            raise bad("delay_ticks", "must be an integer >= 0", self.delay_ticks)
        if not (isinstance(self.miss_rate, (int, float)) and 0 <= self.miss_rate < 1):
            raise bad("miss_rate", "must be a probability in [0, 1)", self.miss_rate)
        if not (isinstance(self.mass_error, (int, float)) and 0 <= self.mass_error < 1):
            raise bad("mass_error", "must be a relative error in [0, 1)", self.mass_error)
        if not (isinstance(self.payload_radius, (int, float)) and math.isfinite(self.payload_radius)
                and self.payload_radius > 0):
            raise bad("payload_radius", "must be a positive number of metres", self.payload_radius)
        sat = self.torque_saturation
        if sat is not None:
            arr = np.asarray(sat, float)
            if arr.ndim > 1 or arr.size == 0 or not np.all(arr > 0) or np.any(np.isnan(arr)):
                raise bad("torque_saturation", "must be a positive number or a list of them [N·m] (inf: none)", sat)
            object.__setattr__(self, "torque_saturation", float(arr) if arr.ndim == 0 else tuple(arr.tolist()))

    @classmethod
    def from_dict(cls, table: dict[str, Any]) -> Faults:
        """From a validated ``[faults]`` table (unknown keys are the scenario's to refuse)."""
        return cls(**{k: table[k] for k in FAULT_KEYS if k in table})

    # -- what is on --------------------------------------------------------------------------------
    @property
    def sensing(self) -> bool:
        """Whether the measured state differs from the true one."""
        return bool(self.q_noise or self.q_quantum or self.v_noise)

    @property
    def actuation(self) -> bool:
        """Whether the applied torque differs from the commanded one."""
        return bool(self.delay_ticks or self.miss_rate or self.torque_lag or self.torque_saturation is not None)

    @property
    def model_error(self) -> bool:
        """Whether the simulated robot differs from the controller's model."""
        return bool(self.mass_error or self.payload_mass)

    @property
    def scene_error(self) -> bool:
        """Whether the true obstacles differ from the controller's map."""
        return bool(self.obstacle_noise or self.obstacle_velocity)

    @property
    def active(self) -> bool:
        """Whether any fault is on (a run without any is the ideal one, bit for bit)."""
        return self.sensing or self.actuation or self.model_error or self.scene_error

    def kinds(self) -> list[str]:
        """The names of the faults that are on."""
        off = Faults()
        return [k for k in FAULT_KEYS if k not in ("seed", "payload_time", "payload_radius")
                and getattr(self, k) != getattr(off, k)]

    def replace(self, **changes: Any) -> Faults:
        """A copy with some fields changed (validated again)."""
        return dataclasses.replace(self, **changes)

    # -- the scene ---------------------------------------------------------------------------------
    def obstacle_offsets(self, count: int, axes: Sequence[int]) -> np.ndarray:
        """(count, 3) offsets [m] of the controller's map from the true obstacles: N(0, σ²) along ``axes``."""
        out = np.zeros((count, 3))
        if self.obstacle_noise and count:
            draw = _stream(self.seed, "obstacle_noise").normal(0.0, self.obstacle_noise, (count, 3))
            out[:, list(axes)] = draw[:, list(axes)]
        return out

    def obstacle_drifts(self, count: int, axes: Sequence[int]) -> np.ndarray:
        """(count, 3) velocities [m/s] added to the true obstacles: ``obstacle_velocity`` in a random
        direction within ``axes``."""
        out = np.zeros((count, 3))
        if self.obstacle_velocity and count:
            rng = _stream(self.seed, "obstacle_velocity")
            for j in range(count):
                d = np.zeros(3)
                d[list(axes)] = rng.normal(size=len(axes))
                out[j] = self.obstacle_velocity * d / max(float(np.linalg.norm(d)), 1e-300)
        return out

    def perceived(self, obstacles: Sequence[Obstacle], axes: Sequence[int]) -> list[Obstacle]:
        """The controller's map of the true ``obstacles``: each displaced by its offset, none drifting
        beyond what the scenario says (build the controller on this list)."""
        if not self.obstacle_noise:
            return list(obstacles)
        offsets = self.obstacle_offsets(len(obstacles), axes)
        return [dataclasses.replace(o, position=o.position + d) for o, d in zip(obstacles, offsets, strict=True)]

    def world(self, obstacles: Sequence[Obstacle], axes: Sequence[int]) -> list[Obstacle]:
        """The true obstacles as they move in the simulation: the scenario's, plus the unknown drift."""
        if not self.obstacle_velocity:
            return list(obstacles)
        drifts = self.obstacle_drifts(len(obstacles), axes)
        return [dataclasses.replace(o, velocity=o.velocity + d) for o, d in zip(obstacles, drifts, strict=True)]

    # -- the robot ---------------------------------------------------------------------------------
    def mass_factors(self, model: pin.Model) -> np.ndarray:
        """(njoints,) the factor 1 + ε_i of each body's mass and inertia (index 0, the universe: 1)."""
        out = np.ones(model.njoints)
        if self.mass_error:
            out[1:] += _stream(self.seed, "mass_error").uniform(-self.mass_error, self.mass_error, model.njoints - 1)
        return out

    def simulated_models(self, robot: RobotModel) -> tuple[pin.Model, pin.Model]:
        """The true robot before and after the payload is taken: copies of ``robot.model`` with the
        mass errors, the second with the payload on the task frame's body too."""
        before = robot.model.copy()
        if self.mass_error:
            for i, s in enumerate(self.mass_factors(before)):
                if i:
                    inertia = before.inertias[i]
                    before.inertias[i] = pin.Inertia(inertia.mass * s, inertia.lever.copy(), inertia.inertia * s)
        after = before.copy()
        if self.payload_mass:
            frame = after.frames[robot.ee_frame_id]
            sphere = pin.Inertia.FromSphere(self.payload_mass, self.payload_radius)
            after.inertias[frame.parentJoint] += frame.placement.act(sphere)  # as with_payload does
        return before, after

    # -- the controller's d_safe margin -----------------------------------------------------------------
    def margin(self, robot: RobotModel) -> float:
        """A d_safe margin [m] for what the controller cannot see: 3σ of an obstacle's offset along the
        normal, and the largest displacement of a link point that 3σ of joint noise plus half an encoder
        step can cause (each joint's error times the arm's reach, summed over the joints)."""
        reach = arm_reach(robot)
        lever = reach[1] if reach is not None else 1.0
        joint = (3.0 * self.q_noise + 0.5 * self.q_quantum) * lever * robot.nv
        return 3.0 * self.obstacle_noise + joint


def with_payload(robot: RobotModel, mass: float, radius: float = PAYLOAD_RADIUS) -> RobotModel:
    """A copy of ``robot`` carrying a solid sphere of ``mass`` [kg] and ``radius`` [m] centred on its task
    frame (added to that frame's body with Pinocchio's spatial-inertia algebra): a declared payload."""
    model = robot.model.copy()
    frame = model.frames[robot.ee_frame_id]
    model.inertias[frame.parentJoint] += frame.placement.act(pin.Inertia.FromSphere(mass, radius))
    return dataclasses.replace(robot, model=model, capsules=list(robot.capsules), joint_names=list(robot.joint_names),
                               urdf=None)  # the file lacks the payload: simulators generate from the model


#: The keys of ``[faults]``, in order.
FAULT_KEYS = tuple(f.name for f in dataclasses.fields(Faults))


class FaultState:
    """One run's faults as they unfold: the sensors' and the drives' state (the Simulator's). The first
    command always arrives; each later one is lost with probability ``miss_rate``."""

    def __init__(self, faults: Faults, n: int, dt: float, robot: RobotModel | None = None) -> None:
        self.faults, self.n, self.dt = faults, n, dt
        self.robot = robot if robot is not None and robot.lie else None  # the sensors read its angles
        self._q_rng = _stream(faults.seed, "q_noise")
        self._v_rng = _stream(faults.seed, "v_noise")
        self._miss_rng = _stream(faults.seed, "miss_rate")
        self._line: deque[np.ndarray] = deque(maxlen=faults.delay_ticks + 1)
        self._held: np.ndarray | None = None  # the last command the drive received
        self._lag_state: np.ndarray | None = None
        lag = faults.torque_lag
        self._decay = math.exp(-dt / lag) if lag else 0.0
        self._mean = lag / dt * -math.expm1(-dt / lag) if lag else 0.0  # (T/dt)(1 − e^(−dt/T))
        sat = faults.torque_saturation
        self._sat = None if sat is None else np.broadcast_to(np.asarray(sat, float), (n,)).copy()
        self.missed = 0  # commands lost so far
        self.saturated = 0  # ticks at which a drive saturated

    def measure(self, q: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(q, q̇) as the sensors report them."""
        f = self.faults
        robot = self.robot
        qa = q if robot is None else robot.angles(q)  # the encoders read one angle per degree of freedom
        qm = qa + self._q_rng.normal(0.0, f.q_noise, self.n) if f.q_noise else qa.copy()
        if f.q_quantum:
            qm = f.q_quantum * np.round(qm / f.q_quantum)
        vm = v + self._v_rng.normal(0.0, f.v_noise, self.n) if f.v_noise else v.copy()
        if robot is not None:
            qm = robot.configuration(qm) if (f.q_noise or f.q_quantum) else q.copy()
        return qm, vm

    def actuate(self, command: np.ndarray) -> np.ndarray:
        """The torque [N·m] the drives hold over the coming step, given this tick's command."""
        f = self.faults
        if self._held is None or not (f.miss_rate and self._miss_rng.random() < f.miss_rate):
            self._held = np.array(command, float)
        else:
            self.missed += 1
        line = self._line
        if not line:  # before any command: the pipeline holds the first one
            line.extend(self._held for _ in range(line.maxlen or 1))
        line.append(self._held)
        u = line[0]
        if self._sat is not None:
            clipped = np.clip(u, -self._sat, self._sat)
            self.saturated += bool(np.any(clipped != u))
            u = clipped
        if not f.torque_lag:
            return u
        if self._lag_state is None:
            self._lag_state = u.copy()
        gap = self._lag_state - u
        self._lag_state = u + gap * self._decay
        return u + gap * self._mean

    @property
    def drive_torque(self) -> np.ndarray | None:
        """The lagged drive's torque [N·m] at the coming tick (None without a lag, or before any command)."""
        return self._lag_state
