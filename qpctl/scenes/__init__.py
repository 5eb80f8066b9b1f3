"""Scenes grown in code and seeded: the canopies a depth camera sees (:mod:`qpctl.scenes.canopy`)."""

from qpctl.scenes.canopy import Canopy, CanopyConfig, Fruit, generate_canopy

__all__ = ["Canopy", "CanopyConfig", "Fruit", "generate_canopy"]
