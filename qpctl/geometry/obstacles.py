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

from dataclasses import dataclass, field

import fcl
import numpy as np

from qpctl.errors import ConfigError
from qpctl.geometry.frames import quaternion_z_to, rotation_z_to, vec3
from qpctl.geometry.shapes import SHAPES, Shape, shape_of

__all__ = ["MATERIALS", "SHAPES", "Obstacle", "quaternion_z_to", "rotation_z_to"]

MATERIALS = ("rigid", "soft")  # Obstacle.material


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
        self.position = vec3(self.position, f"{key}.position")
        self.velocity = vec3(self.velocity, f"{key}.velocity")
        self.amplitude = vec3(self.amplitude, f"{key}.amplitude")
        self.axis = vec3(self.axis, f"{key}.axis")
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

    @property
    def speed_bound(self) -> float:
        """[m/s] a bound on the centre's speed at every time: |v| + 2πf|A|."""
        return float(np.linalg.norm(self.velocity) + 2 * np.pi * self.frequency * np.linalg.norm(self.amplitude))

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
