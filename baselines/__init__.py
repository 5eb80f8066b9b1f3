"""Closed-form baselines: the paper's inertia-weighted law and Hsu–Hauser–Sastry's unweighted law."""

from baselines.hsu import HsuController
from baselines.paper import PaperController

__all__ = ["HsuController", "PaperController"]
