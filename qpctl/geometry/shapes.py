"""Obstacle shapes: each owns its size check, its python-fcl geometry, its MuJoCo geom and its plot.

An :class:`~qpctl.geometry.obstacles.Obstacle` names its shape (``shape = "box"``) and this registry
says what that shape is. Adding one is one file with a :class:`Shape` subclass plus one registry
line (a line in :data:`SHAPES`, or :func:`register_shape` from outside the package); every method
below is abstract, so a shape that lacks one cannot be registered, and a shape nobody registered is
a :class:`~qpctl.errors.ConfigError` when an obstacle names it — never a silent capsule or circle.

Sizes are the obstacle's ``radius``, ``length`` (along ``axis``) and ``size`` [m]. Distances to a
new shape go through python-fcl (the compiled kernels have closed forms for the four shapes here:
spheres and capsules in :mod:`qpctl.kernels.geometry`, boxes and cylinders in
:mod:`qpctl.kernels.solids`); the PyBullet adapter draws it from its MuJoCo geom (sphere, box,
capsule, cylinder).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, NamedTuple, Protocol

import fcl
import numpy as np

from qpctl.errors import ConfigError
from qpctl.geometry.frames import rotation_z_to, vec3


class Obstacle(Protocol):
    """What a shape reads of an obstacle (:class:`qpctl.geometry.obstacles.Obstacle` is one): its
    sizes [m] and axis (the shape's z), which :meth:`Shape.check` may normalise."""

    radius: float
    length: float
    size: np.ndarray | None
    axis: np.ndarray


class Geom(NamedTuple):
    """A MuJoCo geom: ``type`` (MJCF's name: "sphere", "box", ...), ``size`` (MJCF's meaning, 1–3
    numbers [m]) and orientation ``rotation`` (3×3, world frame; None: the body's own, left out of the
    MJCF)."""

    type: str
    size: tuple[float, ...]
    rotation: np.ndarray | None = None


def _axis_rotation(obs: Obstacle) -> np.ndarray:
    return rotation_z_to(obs.axis)


def _positive(value: float, what: str, key: str) -> None:
    if not (np.isfinite(value) and value > 0):
        raise ConfigError(f"{what} must be positive, got {value}", key=key)


class Shape(ABC):
    """What an obstacle shape owns; ``key`` is the obstacle's dotted key for error messages."""

    name: str = ""

    @abstractmethod
    def check(self, obs: Obstacle, key: str) -> None:
        """Raise :class:`ConfigError` (``key.<size key>``) unless the obstacle's sizes make this shape;
        may normalise them (e.g. ``size`` to a 3-vector)."""

    @abstractmethod
    def geometry(self, obs: Obstacle) -> fcl.CollisionGeometry:
        """A new python-fcl geometry, centred on the obstacle's position, its z along ``obs.axis``."""

    @abstractmethod
    def bounding_radius(self, obs: Obstacle) -> float:
        """Radius [m] of a sphere about the centre that contains the shape."""

    @abstractmethod
    def mujoco_geom(self, obs: Obstacle) -> Geom:
        """Its MuJoCo geom (the MJCF of :func:`qpctl.adapters.mujoco.robot_mjcf` and a user's model)."""

    @abstractmethod
    def patch(self, obs: Obstacle, centre: np.ndarray, **style: Any) -> Any:
        """A matplotlib patch of its section in the x–y plane about ``centre`` [m] (figures)."""


class Sphere(Shape):
    """``radius``. In the planar scenarios a sphere centred in the plane is a circle."""

    name = "sphere"

    def check(self, obs: Obstacle, key: str) -> None:
        _positive(obs.radius, "radius", f"{key}.radius")

    def geometry(self, obs: Obstacle) -> fcl.CollisionGeometry:
        return fcl.Sphere(obs.radius)

    def bounding_radius(self, obs: Obstacle) -> float:
        return obs.radius

    def mujoco_geom(self, obs: Obstacle) -> Geom:
        return Geom("sphere", (obs.radius,))

    def patch(self, obs: Obstacle, centre: np.ndarray, **style: Any) -> Any:
        import matplotlib.pyplot as plt

        return plt.Circle((centre[0], centre[1]), obs.radius, **style)


class Box(Shape):
    """``size`` = full extents (x, y, z) along the box's own axes: the world's, turned by the rotation
    taking z onto ``axis`` (default z: axis-aligned), as python-fcl places every shape."""

    name = "box"

    def check(self, obs: Obstacle, key: str) -> None:
        if obs.size is None:
            raise ConfigError("a box needs size = [x, y, z]", key=f"{key}.size")
        obs.size = vec3(obs.size, f"{key}.size")
        if np.any(obs.size <= 0):
            raise ConfigError(f"box size must be positive, got {obs.size.tolist()}", key=f"{key}.size")

    def geometry(self, obs: Obstacle) -> fcl.CollisionGeometry:
        assert obs.size is not None
        return fcl.Box(*obs.size)

    def bounding_radius(self, obs: Obstacle) -> float:
        assert obs.size is not None
        return float(np.linalg.norm(obs.size) / 2)

    def mujoco_geom(self, obs: Obstacle) -> Geom:
        assert obs.size is not None
        return Geom("box", tuple(float(s) / 2 for s in obs.size), _axis_rotation(obs))

    def patch(self, obs: Obstacle, centre: np.ndarray, **style: Any) -> Any:
        import matplotlib.pyplot as plt

        assert obs.size is not None
        return plt.Rectangle((centre[0] - obs.size[0] / 2, centre[1] - obs.size[1] / 2), obs.size[0], obs.size[1],
                             **style)


class Cylinder(Shape):
    """``radius`` and ``length`` (of the axis), axis along ``axis`` (in the planar scenarios a z-axis
    cylinder is a disc in the plane)."""

    name = "cylinder"

    def check(self, obs: Obstacle, key: str) -> None:
        _positive(obs.radius, "radius", f"{key}.radius")
        _positive(obs.length, "length", f"{key}.length")

    def geometry(self, obs: Obstacle) -> fcl.CollisionGeometry:
        return fcl.Cylinder(obs.radius, obs.length)

    def bounding_radius(self, obs: Obstacle) -> float:
        return float(np.hypot(obs.radius, obs.length / 2))

    def mujoco_geom(self, obs: Obstacle) -> Geom:
        return Geom(self.name, (obs.radius, obs.length / 2), _axis_rotation(obs))

    def patch(self, obs: Obstacle, centre: np.ndarray, **style: Any) -> Any:
        import matplotlib.pyplot as plt

        return plt.Circle((centre[0], centre[1]), obs.radius, **style)


class Capsule(Cylinder):
    """A cylinder with hemispherical caps: ``radius``, ``length`` of the axis segment, ``axis``."""

    name = "capsule"

    def geometry(self, obs: Obstacle) -> fcl.CollisionGeometry:
        return fcl.Capsule(obs.radius, obs.length)

    def bounding_radius(self, obs: Obstacle) -> float:
        return float(np.hypot(obs.radius, obs.length / 2) + obs.radius)


# The registry: name → shape. One line per shape.
SHAPES: dict[str, Shape] = {
    "sphere": Sphere(),
    "box": Box(),
    "capsule": Capsule(),
    "cylinder": Cylinder(),
}


def register_shape(shape: Shape) -> Shape:
    """Add ``shape`` under its ``name`` (replacing one of that name); returns it."""
    if not isinstance(shape, Shape) or not shape.name:
        raise ConfigError(f"an obstacle shape must be a Shape with a name, got {shape!r}")
    SHAPES[shape.name] = shape
    return shape


def shape_of(name: str, key: str = "obstacles.shape") -> Shape:
    """The registered shape called ``name``; :class:`ConfigError` listing the registered ones."""
    try:
        return SHAPES[name]
    except (KeyError, TypeError):
        raise ConfigError(f"unknown shape {name!r}; one of {', '.join(SHAPES)}", key=key) from None
