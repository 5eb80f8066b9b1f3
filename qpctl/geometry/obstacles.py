"""Obstacles: python-fcl shapes with a pose that may move in time.

Shapes and sizes (all in metres) are the registered shapes of :mod:`qpctl.geometry.shapes`:

* ``sphere``: ``radius``. In the planar scenarios a sphere centred in the plane is a circle.
* ``box``: ``size`` = full extents (x, y, z).
* ``capsule`` / ``cylinder``: ``radius`` and ``length`` (of the axis), axis along ``axis``
  (a unit vector, default z — in the planar scenarios a z-axis cylinder is a disc in the plane).

``material`` is ``"rigid"`` (stems, branches, trunk, wires: hard barrier rows, and the run's
``min_clearance``) or ``"soft"`` (leaves: slack-penalised rows a link may pass no faster than the
controller's ``soft_speed``). ``perceived = true`` puts the obstacle in the world only (the simulator,
its clearance metrics and its simulated depth camera have it): the controller knows it only through
the depth map (DESIGN.md §6), not as a primitive.

``v_ref`` [m/s] optionally overrides the controller's obstacle reference velocity for this obstacle
(the paper's Fig. 4 sweeps area B's while area A's stays fixed).

Motion: constant ``velocity`` [m/s] and/or a sinusoidal sway ``amplitude`` [m] at
``frequency`` [Hz]: p(t) = p₀ + v t + A sin(2π f t).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import fcl
import numpy as np

from qpctl.errors import ConfigError
from qpctl.geometry.shapes import SHAPES, Shape, shape_of

__all__ = ["MATERIALS", "SHAPES", "Obstacle", "quaternion_z_to", "rotation_z_to"]

MATERIALS = ("rigid", "soft")  # Obstacle.material


def _vec3(value: Sequence[float] | np.ndarray, key: str) -> np.ndarray:
    arr = np.asarray(value, dtype=float).reshape(-1)
    if arr.shape == (2,):
        arr = np.append(arr, 0.0)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ConfigError(f"must be 2 or 3 finite numbers, got {value!r}", key=key)
    return arr


def quaternion_z_to(x: float, y: float, z: float) -> tuple[float, float, float, float]:
    """(w, x, y, z) of the shortest rotation taking the z axis onto the non-zero direction (x, y, z).

    With a = (x, y, z)/‖·‖ and c = a_z: q = (1 + c, z × a)/√(2(1 + c)), z × a = (−a_y, a_x, 0); a
    half turn about x when a = −z. Plain floats: it runs for every link capsule at every tick.
    """
    norm = math.sqrt(x * x + y * y + z * z)
    c = z / norm
    if c > 1 - 1e-12:
        return (1.0, 0.0, 0.0, 0.0)
    if c < -1 + 1e-12:
        return (0.0, 1.0, 0.0, 0.0)
    w = 1.0 + c
    s = math.sqrt(2.0 * w) * norm
    return (w * norm / s, -y / s, x / s, 0.0)


def rotation_z_to(axis: np.ndarray) -> np.ndarray:
    """A rotation matrix taking the z axis onto the unit vector ``axis`` (see :func:`quaternion_z_to`)."""
    w, x, y, z = quaternion_z_to(*(float(c) for c in axis))
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


@dataclass
class Obstacle:
    """An obstacle for python-fcl distance queries (see module docstring for shapes and units)."""

    shape: str
    position: np.ndarray
    radius: float = 0.0
    size: np.ndarray | None = None
    length: float = 0.0
    axis: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    amplitude: np.ndarray = field(default_factory=lambda: np.zeros(3))
    frequency: float = 0.0
    name: str = ""
    v_ref: float | None = None  # [m/s] this obstacle's reference velocity (None: the controller's)
    material: str = "rigid"  # "rigid" or "soft" (module docstring)
    perceived: bool = False  # True: in the world only; the controller sees it through the depth map

    def __post_init__(self) -> None:
        key = f"obstacles.{self.name}" if self.name else "obstacles"
        kind = shape_of(self.shape, f"{key}.shape")
        self.position = _vec3(self.position, f"{key}.position")
        self.velocity = _vec3(self.velocity, f"{key}.velocity")
        self.amplitude = _vec3(self.amplitude, f"{key}.amplitude")
        self.axis = _vec3(self.axis, f"{key}.axis")
        if np.linalg.norm(self.axis) == 0:
            raise ConfigError("axis must be non-zero", key=f"{key}.axis")
        if self.v_ref is not None and not (np.isfinite(self.v_ref) and self.v_ref >= 0):
            raise ConfigError(f"must be a number >= 0, got {self.v_ref}", key=f"{key}.v_ref")
        if self.material not in MATERIALS:
            raise ConfigError(f"must be {' or '.join(MATERIALS)}, got {self.material!r}", key=f"{key}.material")
        if not (np.isfinite(self.frequency) and self.frequency >= 0):
            raise ConfigError(f"must be >= 0, got {self.frequency}", key=f"{key}.frequency")
        kind.check(self, key)
        self._rotation = rotation_z_to(self.axis)

    @property
    def moving(self) -> bool:
        return bool(np.any(self.velocity) or (np.any(self.amplitude) and self.frequency > 0))

    @property
    def kind(self) -> Shape:
        """The registered shape this obstacle is (:mod:`qpctl.geometry.shapes`)."""
        return shape_of(self.shape)

    def geometry(self) -> fcl.CollisionGeometry:
        """A new python-fcl geometry for this shape."""
        return self.kind.geometry(self)

    def transform(self, t: float) -> fcl.Transform:
        return fcl.Transform(self._rotation, self.position_at(t))

    def position_at(self, t: float) -> np.ndarray:
        """Centre position [m] at time t [s]."""
        w = 2 * np.pi * self.frequency
        return self.position + self.velocity * t + self.amplitude * np.sin(w * t)

    def velocity_at(self, t: float) -> np.ndarray:
        """Velocity [m/s] at time t [s] (the obstacle translates; it does not rotate)."""
        w = 2 * np.pi * self.frequency
        return self.velocity + self.amplitude * w * np.cos(w * t)

    def acceleration_at(self, t: float) -> np.ndarray:
        """Acceleration [m/s²] at time t [s]."""
        w = 2 * np.pi * self.frequency
        return -self.amplitude * w * w * np.sin(w * t)

    def bounding_radius(self) -> float:
        """Radius [m] of a sphere about the centre that contains the shape."""
        return self.kind.bounding_radius(self)
