"""Occupancy evaluation: voxel IoU / mIoU under the Occ3D and weakly supervised protocols."""

from dego.metrics.confusion import binary_occupancy_confusion, confusion_matrix
from dego.metrics.occupancy import WEAK_REMOVED_CLASSES, OccupancyMetrics
from dego.metrics.rayiou import RayIoU, RayIoUReport, lidar_origins
from dego.metrics.report import OccupancyReport, per_class_iou

__all__ = [
    "WEAK_REMOVED_CLASSES",
    "OccupancyMetrics",
    "OccupancyReport",
    "RayIoU",
    "RayIoUReport",
    "binary_occupancy_confusion",
    "confusion_matrix",
    "lidar_origins",
    "per_class_iou",
]
