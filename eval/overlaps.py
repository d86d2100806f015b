"""Overlaps of every GT-detection pair sharing a frame, for all frames at once."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from robustbench3d.eval.iou import Criterion, bev_ratio, box3d_ratio, footprint_intersection, image_overlap
from robustbench3d.eval.table import ObjectTable

#: Overlap kinds: image boxes, BEV footprints (rect x-z), 3D boxes.
KINDS: tuple[str, ...] = ("2d", "bev", "3d")


def same_frame_pairs(frame_a: np.ndarray, frame_b: np.ndarray, n_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """All (i, j) with ``frame_a[i] == frame_b[j]``, sorted by i then j.

    Args:
        frame_a, frame_b: non-decreasing frame indices.
        n_frames: number of frames (upper bound of the indices).
    """
    count_b = np.bincount(frame_b, minlength=n_frames)
    start_b = np.cumsum(count_b) - count_b
    reps = count_b[frame_a]
    ia = np.repeat(np.arange(len(frame_a)), reps)
    first_of_run = np.repeat(np.cumsum(reps) - reps, reps)
    ib = start_b[frame_a[ia]] + (np.arange(len(ia)) - first_of_run)
    return ia, ib


@dataclass(frozen=True)
class PairOverlaps:
    """GT rows, detection rows and their overlap per kind (pairs sorted by GT row, then det row)."""

    gt: np.ndarray
    det: np.ndarray
    values: dict[str, np.ndarray]


def pair_overlaps(gt: ObjectTable, dt: ObjectTable, gt_rows: np.ndarray, det_rows: np.ndarray,
                  kinds: set[str], criterion: Criterion = "union") -> PairOverlaps:
    """Overlaps (det, gt) of all same-frame pairs among the given rows.

    Args:
        gt, dt: ground truth and detections of the same frames.
        gt_rows, det_rows: increasing row indices to pair up.
        kinds: subset of :data:`KINDS` to compute.
        criterion: "union" (IoU) or "det" (intersection over the detection's area/volume).
    """
    ia, ib = same_frame_pairs(gt.frame[gt_rows], dt.frame[det_rows], gt.n_frames)
    g, d = gt_rows[ia], det_rows[ib]
    values: dict[str, np.ndarray] = {}
    if "2d" in kinds:
        values["2d"] = image_overlap(dt.bbox[d], gt.bbox[g], criterion)
    if kinds & {"bev", "3d"}:
        bd, bg = dt.box3d[d], gt.box3d[g]
        inter, area_d, area_g = footprint_intersection(bd, bg)
        if "bev" in kinds:
            values["bev"] = bev_ratio(inter, area_d, area_g, criterion)
        if "3d" in kinds:
            values["3d"] = box3d_ratio(inter, area_d, area_g, bd, bg, criterion)
    return PairOverlaps(g, d, values)

