"""What a sensor sees: depth images and point clouds, turned into a distance field the tick reads.

DESIGN.md §6. :mod:`qpctl.perception.frames` holds the inputs (a depth image with its pinhole
intrinsics and camera pose, or a point cloud, each timestamped, optionally labelled per pixel or
point as rigid or soft) and checks them; the rest of the package builds the map from them.
"""

from qpctl.perception.frames import RIGID, SOFT, UNLABELED, DepthFrame, Intrinsics, PointCloud

__all__ = ["RIGID", "SOFT", "UNLABELED", "DepthFrame", "Intrinsics", "PointCloud"]
