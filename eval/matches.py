"""Which ground-truth objects the evaluator counts as found: per-object true positives, for attack success rates.

A GT object is **matched** at (class, metric, difficulty, score threshold t) when it is a true positive of
the evaluator's own second pass (:func:`~robustbench3d.eval.matching.assign_at_thresholds`) for that
difficulty with every detection scoring below t removed: GTs are visited in label-file order and each
takes the still unassigned counting detection with the largest overlap above the class's minimum
overlap (BEV IoU > 0.7 for Car), else an ignored one; matched means a counting GT (status 0 for the
difficulty: the class, not a neighbour, within the difficulty's height/occlusion/truncation limits) got
a counting detection.

:func:`best_f1_threshold` picks t for a set of detections: among the evaluator's sampled score
thresholds of that difficulty (the at most 41 thresholds of its precision curve,
:func:`~robustbench3d.eval.precision.score_thresholds`), the one maximising
F1 = 2 TP / (2 TP + FP + FN) (FN = counted GT - TP; FP as in the AP computation: unassigned counting
detections at or above t, not in a DontCare region); on ties the highest threshold.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from robustbench3d.eval.kitti_eval import ClassEvaluation, ThresholdStats, class_overlaps
from robustbench3d.eval.matching import assign_at_thresholds, true_positives
from robustbench3d.eval.rules import DIFFICULTIES, OVERLAP_OF_METRIC, TARGET_CLASS
from robustbench3d.eval.table import ObjectTable
from robustbench3d.kitti.labels import Labels


@dataclass(frozen=True)
class GtMatches:
    """Per frame, (n_labels,) bool arrays over the frame's label rows (file order).

    Attributes:
        matched: the row is a matched GT object (a true positive, see the module doc).
        counted: the row is a counting GT object of the class and difficulty.
        threshold: the score threshold applied (None: no detection kept, nothing matched).
    """

    matched: list[np.ndarray]
    counted: list[np.ndarray]
    threshold: float | None


class _Matching:
    """The evaluator's state for one class and metric over the frames' GT and detections."""

    def __init__(self, gt: Sequence[Labels], dt: Sequence[Labels], cls: str, metric: str, difficulty: str):
        if len(gt) != len(dt):
            raise ValueError(f"{len(gt)} ground-truth frames but {len(dt)} detection frames")
        kind = OVERLAP_OF_METRIC[metric]
        self.d = DIFFICULTIES.index(difficulty)
        self.gt = ObjectTable.from_labels(gt, scored=False)
        dt_table = ObjectTable.from_labels(dt, scored=True)
        pairs, dontcare = class_overlaps(self.gt, dt_table, [cls], [kind])
        self.ce = ClassEvaluation(self.gt, dt_table, cls)
        self.stats: ThresholdStats = self.ce.threshold_counts(pairs, dontcare, kind)
        self.sizes = [len(g) for g in gt]

    def per_frame(self, rows: np.ndarray) -> list[np.ndarray]:
        """(n_labels,) bool per frame, True at the given GT table rows."""
        flat = np.zeros(sum(self.sizes), dtype=bool)
        flat[rows] = True
        return np.split(flat, np.cumsum(self.sizes)[:-1]) if self.sizes else []


def best_f1_threshold(gt: Sequence[Labels], dt: Sequence[Labels], cls: str = TARGET_CLASS, metric: str = "bev",
                      difficulty: str = "moderate") -> float | None:
    """The F1-maximising sampled score threshold (module doc); None without any true positive."""
    m = _Matching(gt, dt, cls, metric, difficulty)
    at = m.stats.config_difficulty == m.d
    tp = m.stats.counts.tp[at].astype(np.float64)
    if not len(tp):
        return None
    fn = float(m.ce.n_gt[m.d]) - tp
    f1 = 2 * tp / np.maximum(2 * tp + m.stats.fp[at] + fn, 1)
    return float(m.stats.config_threshold[at][int(np.argmax(f1))])


def matched_ground_truth(gt: Sequence[Labels], dt: Sequence[Labels], threshold: float | None, cls: str = TARGET_CLASS,
                         metric: str = "bev", difficulty: str = "moderate") -> GtMatches:
    """Which GT objects are matched with detections scoring at least ``threshold`` (module doc)."""
    m = _Matching(gt, dt, cls, metric, difficulty)
    counted = m.ce.gt_rows[m.ce.gt_status[m.d] == 0]
    if threshold is None:
        return GtMatches(m.per_frame(np.zeros(0, np.int64)), m.per_frame(counted), None)
    cfg_d, cfg_t = np.array([m.d], np.int64), np.array([float(threshold)])
    a = assign_at_thresholds(m.stats.pairs, cfg_d, cfg_t, m.ce.det_status, m.ce.score)
    rows = m.ce.gt_rows[a.gt[true_positives(a, cfg_d, m.ce.gt_status, m.ce.det_status)]]
    return GtMatches(m.per_frame(rows), m.per_frame(counted), float(threshold))


__all__ = ["GtMatches", "best_f1_threshold", "matched_ground_truth"]
