"""The paper's law (baseline ``paper``): :class:`qpctl.controllers.closed_form.PaperController`."""

from qpctl.controllers.closed_form import PaperController

__all__ = ["PaperController"]
