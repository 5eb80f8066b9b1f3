"""Obstacles and link–obstacle distances, computed by python-fcl."""

from qpctl.geometry.distance import DistanceEngine, PairSet
from qpctl.geometry.obstacles import Obstacle

__all__ = ["DistanceEngine", "Obstacle", "PairSet"]
