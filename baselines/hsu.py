"""Hsu–Hauser–Sastry's law (baseline ``hsu``): :class:`qpctl.controllers.closed_form.HsuController`."""

from qpctl.controllers.closed_form import HsuController

__all__ = ["HsuController"]
