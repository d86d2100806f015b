"""Scan -> network inputs -> KITTI detections: the numpy glue shared by the torch and the ONNX victim.

The scan is cut to the camera's horizontal field of view (projected column u in [0, W), in front of
the camera) and to the pillar grid's region of interest; the network's (9, H, W) output is decoded at
the 3×3 heatmap peaks (see :mod:`.targets`) into velodyne boxes, converted to KITTI rows in the rect
frame (bottom centre, h w l, rotation_y, 2D box = the projected 3D box clipped to the image, score =
sigmoid of the peak's heatmap logit). Detections whose centre projects outside the image columns or
whose box misses the image are dropped.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from robustbench3d.errors import RobustBenchError
from robustbench3d.geometry import alpha_from_rotation_y, box_corners, project_boxes_to_image
from robustbench3d.kitti.calib import Calibration
from robustbench3d.kitti.labels import Labels
from robustbench3d.victims.pointpillars.config import PointPillarsConfig
from robustbench3d.victims.pointpillars.pillars import PillarGrid, pillarise
from robustbench3d.victims.pointpillars.targets import decode_cells, peaks, velo_boxes_to_rect

#: Range of the victim argument ``score_threshold``: a probability strictly inside (0, 1); 0.001 keeps
#: a ranking far below any useful operating point, 0.99 leaves almost nothing to rank.
SCORE_THRESHOLD_RANGE = (0.001, 0.99)
#: Range of ``max_detections`` per frame: a KITTI frame holds at most a few dozen cars.
MAX_DETECTIONS_RANGE = (1, 1000)

#: Near limit of the camera field of view (rect depth, m).
NEAR = 0.1


@dataclass(frozen=True)
class DecodeOptions:
    """score_threshold: lowest sigmoid score kept (0 < t < 1); max_detections per frame."""

    score_threshold: float = 0.05
    max_detections: int = 100

    @property
    def threshold_logit(self) -> float:
        t = self.score_threshold
        return float(np.log(t / (1 - t)))


def fov_mask_velo(points_velo: np.ndarray, calib: Calibration, image_size: tuple[int, int]) -> np.ndarray:
    """(N,) bool: velodyne points in front of the camera whose image column lies in [0, W)."""
    rect = calib.velo_to_rect_points(np.asarray(points_velo)[:, :3])
    uv, depth = calib.rect_to_image(rect)
    return (depth > NEAR) & (uv[:, 0] >= 0) & (uv[:, 0] < image_size[0])


def crop_mask(points: np.ndarray, calib: Calibration, image_size: tuple[int, int], grid: PillarGrid) -> np.ndarray:
    """(N,) bool: the rows of ``points`` (N, 3+ velodyne) in the grid's region and the camera's field of view."""
    from robustbench3d.victims.pointpillars.pillars import in_region

    keep = in_region(points, grid)
    keep[keep] = fov_mask_velo(points[keep], calib, image_size)
    return keep


def crop_scan(scan: np.ndarray, calib: Calibration, image_size: tuple[int, int], grid: PillarGrid) -> np.ndarray:
    """The rows of ``scan`` (N, 4 velodyne) in the camera's field of view and the grid's region (float32)."""
    scan = np.asarray(scan, dtype=np.float32)
    return scan[crop_mask(scan, calib, image_size, grid)]


NetworkFn = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]


def run_scan(network: NetworkFn, points: np.ndarray, cfg: PointPillarsConfig) -> np.ndarray:
    """(9, H, W) output of ``network(features, coords, mask)`` for the cropped velodyne ``points``."""
    feats, coords, mask = pillarise(points, cfg.grid)
    return network(feats, coords, mask)


def boxes_to_labels(boxes: np.ndarray, scores: np.ndarray, calib: Calibration, image_size: tuple[int, int],
                    type_name: str = "Car") -> Labels:
    """KITTI result rows of velodyne boxes (K, 7) with scores (K,), keeping those in the camera FOV."""
    loc, dims, ry = velo_boxes_to_rect(boxes, calib)
    centre = loc - np.stack([np.zeros(len(loc)), dims[:, 0] / 2, np.zeros(len(loc))], axis=1)
    uv, depth = calib.rect_to_image(centre) if len(loc) else (np.zeros((0, 2)), np.zeros(0))
    box2d, valid = project_boxes_to_image(box_corners(dims, loc, ry), calib, image_size, near=NEAR)
    keep = valid & (depth > NEAR) & (uv[:, 0] >= 0) & (uv[:, 0] < image_size[0])
    k = int(keep.sum())
    return Labels(type=np.array([type_name] * k, dtype=object), truncated=np.full(k, -1.0),
                  occluded=np.full(k, -1, dtype=np.int64),
                  alpha=alpha_from_rotation_y(ry[keep], loc[keep]) if k else np.zeros(0),
                  bbox=box2d[keep].reshape(k, 4), dimensions=dims[keep].reshape(k, 3),
                  location=loc[keep].reshape(k, 3), rotation_y=ry[keep].reshape(k),
                  score=np.asarray(scores, dtype=np.float64)[keep].reshape(k))


def sigmoid(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    return 1.0 / (1.0 + np.exp(-x))


def decode_output(out: np.ndarray, cfg: PointPillarsConfig, calib: Calibration, image_size: tuple[int, int],
                  options: DecodeOptions = DecodeOptions()) -> Labels:
    """KITTI detections of one (9, H, W) network output (peaks, decoding, FOV filter)."""
    rows, cols = peaks(out[0], options.threshold_logit, options.max_detections)
    boxes = decode_cells(out, rows, cols, cfg)
    return boxes_to_labels(boxes, sigmoid(np.asarray(out[0], dtype=np.float64)[rows, cols]), calib, image_size)


def check_args(score_threshold: object, max_detections: object) -> DecodeOptions:
    """The decoding options of the victim arguments, checked (one-line :class:`RobustBenchError` otherwise)."""
    from numbers import Integral, Real

    lo, hi = SCORE_THRESHOLD_RANGE
    if isinstance(score_threshold, bool) or not isinstance(score_threshold, Real) \
            or not lo <= float(score_threshold) <= hi:
        raise RobustBenchError(f"victim argument 'score_threshold': {score_threshold!r} is not a number in "
                               f"[{lo}, {hi}]")
    lo_n, hi_n = MAX_DETECTIONS_RANGE
    if isinstance(max_detections, bool) or not isinstance(max_detections, Integral) \
            or not lo_n <= int(max_detections) <= hi_n:
        raise RobustBenchError(f"victim argument 'max_detections': {max_detections!r} is not an integer in "
                               f"[{lo_n}, {hi_n}]")
    return DecodeOptions(float(score_threshold), int(max_detections))
