"""Build a controller from a scenario's ``[controller]`` table."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from qpctl.controllers.base import Controller
from qpctl.errors import ConfigError
from qpctl.geometry.obstacles import Obstacle
from qpctl.law import LawGains
from qpctl.paths import WaypointPath
from qpctl.robot.model import RobotModel


def make_controller(cfg: dict[str, Any], robot: RobotModel, path: WaypointPath, obstacles: Sequence[Obstacle],
                    gains: LawGains, *, broadphase: bool | None = None, source: str = "") -> Controller:
    kind = cfg["kind"]
    if kind == "paper":
        from qpctl.controllers.closed_form import PaperController

        return PaperController(robot, path, obstacles, gains, broadphase=broadphase)
    if kind == "hsu":
        from qpctl.controllers.closed_form import HsuController

        return HsuController(robot, path, obstacles, gains, broadphase=broadphase)
    if kind == "qp":
        from qpctl.controllers.qp import QPController

        return QPController.from_config(cfg, robot, path, obstacles, gains, broadphase=broadphase)
    raise ConfigError(f"unknown controller {kind!r}; one of paper, hsu, qp", source=source or None,
                      key="controller.kind")
