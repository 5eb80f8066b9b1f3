"""Controllers: one interface, ``tau = controller.torque(q, v, t)``."""

from qpctl.controllers.base import Controller, ControlOutput

__all__ = ["ControlOutput", "Controller"]
