"""KITTI object-detection file formats and dataset layout."""

from robustbench3d.kitti.calib import CALIB_KEYS, Calibration, parse_calibration, read_calibration, write_calibration
from robustbench3d.kitti.dataset import Frame, KittiDataset
from robustbench3d.kitti.image import read_image, write_image
from robustbench3d.kitti.labels import KITTI_TYPES, Labels, parse_labels, read_labels, write_labels
from robustbench3d.kitti.splits import read_split, write_split
from robustbench3d.kitti.velodyne import read_scan, write_scan

__all__ = [
    "CALIB_KEYS", "KITTI_TYPES", "Calibration", "Frame", "KittiDataset", "Labels", "parse_calibration",
    "parse_labels", "read_calibration", "read_image", "read_labels", "read_scan", "read_split",
    "write_calibration", "write_image", "write_labels", "write_scan", "write_split",
]
