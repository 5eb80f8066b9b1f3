"""Closed-form baselines: the paper's inertia-weighted law and Hsu–Hauser–Sastry's unweighted law.

They live in the library (:mod:`qpctl.controllers.closed_form`, also ``from qpctl import
PaperController, HsuController``); this package names them as the paper reproduction does.
"""

from baselines.hsu import HsuController
from baselines.paper import PaperController

__all__ = ["HsuController", "PaperController"]
