"""What a sensor sees: depth images and point clouds, turned into a distance field the tick reads.

DESIGN.md §6. :mod:`qpctl.perception.frames` holds the inputs (a depth image with its pinhole
intrinsics and camera pose, or a point cloud, each timestamped, optionally labelled per pixel or
point as rigid or soft) and checks them; :class:`DepthMap` (:mod:`qpctl.perception.depth_map`)
filters, self-filters and integrates them into a robot-local voxel map with rigid and soft channels
and computes its distance field as an immutable :class:`MapSnapshot`; :class:`PerceptionConfig` is
the scenario's ``[perception]`` table.
"""

from qpctl.perception.config import PerceptionConfig
from qpctl.perception.depth_map import DepthMap, FrameReport
from qpctl.perception.frames import RIGID, SOFT, UNLABELED, DepthFrame, Intrinsics, PointCloud
from qpctl.perception.perception import Perception
from qpctl.perception.self_filter import JointHistory
from qpctl.perception.snapshot import MapSnapshot, VoxelGrid
from qpctl.perception.stale import StalePolicy, TimeScaledPath
from qpctl.perception.worker import MapWorker

__all__ = [
           "RIGID",
           "SOFT",
           "UNLABELED",
           "DepthFrame",
           "DepthMap",
           "FrameReport",
           "Intrinsics",
           "JointHistory",
           "MapSnapshot",
           "MapWorker",
           "Perception",
           "PerceptionConfig",
           "PointCloud",
           "StalePolicy",
           "TimeScaledPath",
           "VoxelGrid",
]
