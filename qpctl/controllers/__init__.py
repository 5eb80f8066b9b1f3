"""Controllers: one interface, ``tau = controller.torque(q, v, t)``."""

from qpctl.controllers.base import ControlOutput, Controller

__all__ = ["ControlOutput", "Controller"]
