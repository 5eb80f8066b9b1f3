"""The controller kinds (``controller.kind``) and how a scenario's ``[controller]`` table builds one.

A kind is a :class:`~qpctl.controllers.base.Controller` subclass registered here by name: one file
for the class, one line in :data:`CONTROLLERS` (or :func:`register_controller` from outside the
package). Its classmethod ``from_config(cfg, robot, path, obstacles, gains, *, broadphase)`` builds it
from the validated ``[controller]`` table (the base class's takes the law gains only; the QP's reads
its :class:`~qpctl.controllers.qp.QPConfig` from the table too).
"""

from __future__ import annotations

import importlib
from collections.abc import Sequence
from typing import Any

from qpctl.controllers.base import Controller
from qpctl.errors import ConfigError
from qpctl.geometry.obstacles import Obstacle
from qpctl.law import LawGains
from qpctl.paths import WaypointPath
from qpctl.robot.model import RobotModel

# kind → the class, or "module:Class" imported on first use (the laws import this module's package)
CONTROLLERS: dict[str, type[Controller] | str] = {
    "paper": "qpctl.controllers.closed_form:PaperController",
    "hsu": "qpctl.controllers.closed_form:HsuController",
    "qp": "qpctl.controllers.qp:QPController",
}


def register_controller(kind: str, cls: type[Controller] | str) -> None:
    """Make ``controller.kind = kind`` build ``cls`` (a Controller subclass, or "module:Class")."""
    if not isinstance(kind, str) or not kind:
        raise ConfigError(f"a controller kind must be a non-empty name, got {kind!r}")
    if not isinstance(cls, str) and not (isinstance(cls, type) and issubclass(cls, Controller)):
        raise ConfigError(f"controller {kind!r} must be a Controller subclass, got {cls!r}")
    CONTROLLERS[kind] = cls


def controller_kinds() -> tuple[str, ...]:
    """The registered kinds, in registration order."""
    return tuple(CONTROLLERS)


def unknown_kind(kind: Any, source: str | None = None) -> ConfigError:
    return ConfigError(f"unknown controller {kind!r}; one of {', '.join(CONTROLLERS)}", source=source,
                       key="controller.kind")


def controller_class(kind: str, source: str | None = None) -> type[Controller]:
    """The class registered as ``kind``; :class:`ConfigError` naming the registered ones otherwise."""
    if kind not in CONTROLLERS:
        raise unknown_kind(kind, source)
    entry = CONTROLLERS[kind]
    if isinstance(entry, str):
        module, _, name = entry.partition(":")
        entry = getattr(importlib.import_module(module), name)
        CONTROLLERS[kind] = entry
    assert isinstance(entry, type)
    return entry


def make_controller(cfg: dict[str, Any], robot: RobotModel, path: WaypointPath, obstacles: Sequence[Obstacle],
                    gains: LawGains, *, broadphase: bool | None = None, source: str = "") -> Controller:
    """The controller ``cfg["kind"]`` names, built from the validated ``[controller]`` table ``cfg``."""
    cls = controller_class(cfg["kind"], source or None)
    return cls.from_config(cfg, robot, path, obstacles, gains, broadphase=broadphase)
