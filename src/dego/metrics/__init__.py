"""Occupancy evaluation: voxel IoU / mIoU under the Occ3D, weakly supervised and SurroundOcc
protocols."""

from dego.metrics.confusion import binary_occupancy_confusion, confusion_matrix
from dego.metrics.occupancy import (
    SURROUNDOCC_REMOVED_CLASSES,
    WEAK_REMOVED_CLASSES,
    OccupancyMetrics,
)
from dego.metrics.rayiou import RayIoU, RayIoUReport, lidar_origins
from dego.metrics.report import OccupancyReport, per_class_iou

__all__ = [
    "SURROUNDOCC_REMOVED_CLASSES",
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
