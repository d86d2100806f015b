"""The devkit's greedy GT-to-detection assignment (``computeStatistics``), vectorised.

The devkit walks the ground truth of a frame in file order; each GT takes one still unassigned
detection among those overlapping it by more than the class threshold, and keeps it:

* pass 1 (collecting scores for the thresholds): the candidate with the highest score;
* pass 2 (one run per score threshold t, detections scoring below t removed): the counting
  (status 0) candidate with the largest overlap, else the first ignored (status 1) one.

Only the order of GTs *within a frame* matters, and only GTs that have candidates at all can
take a detection. So GTs are ranked within their frame among those with candidates, and the
assignment runs rank by rank for all frames at once: the k-th candidate-holding GT of every
frame chooses simultaneously, which cannot conflict because frames share no detections. Every
configuration (difficulty x score threshold) is a row of the same arrays, so the 41 threshold
runs of all difficulties are one pass. Ties go to the detection that comes first in its file, as
in the devkit's strict comparisons.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from robustbench3d.eval.rules import NO_DETECTION


@dataclass(frozen=True)
class CandidatePairs:
    """GT-detection pairs overlapping by more than the threshold, laid out rank by rank.

    Attributes:
        gt: (P,) GT index of each pair.
        det: (P,) detection index of each pair.
        overlap: (P,) overlap of each pair.
        rank_slices: per rank r, the slice of pairs whose GT is the r-th candidate-holding GT of
            its frame; within a slice, pairs are grouped by GT, detections in file order.
        group_starts: per rank, the start offsets (relative to the slice) of the GT groups.
    """

    gt: np.ndarray
    det: np.ndarray
    overlap: np.ndarray
    rank_slices: list[slice]
    group_starts: list[np.ndarray]

    @classmethod
    def build(cls, gt: np.ndarray, det: np.ndarray, overlap: np.ndarray, gt_frame: np.ndarray) -> CandidatePairs:
        """Lay out pairs sorted by (GT, detection) with GT indices in frame-major file order.

        Args:
            gt, det, overlap: (P,) pairs, sorted by GT then detection index.
            gt_frame: frame of every GT index (non-decreasing).
        """
        if gt.size == 0:
            return cls(gt, det, overlap, [], [])
        holders, first = np.unique(gt, return_index=True)
        frames = gt_frame[holders]
        run_start = np.r_[0, np.flatnonzero(np.diff(frames)) + 1]
        run_len = np.diff(np.r_[run_start, len(holders)])
        holder_rank = np.arange(len(holders)) - np.repeat(run_start, run_len)
        pair_rank = np.repeat(holder_rank, np.diff(np.r_[first, len(gt)]))
        order = np.argsort(pair_rank, kind="stable")
        gt, det, overlap, pair_rank = gt[order], det[order], overlap[order], pair_rank[order]
        bounds = np.searchsorted(pair_rank, np.arange(pair_rank[-1] + 2))
        slices, starts = [], []
        for r in range(len(bounds) - 1):
            sl = slice(int(bounds[r]), int(bounds[r + 1]))
            g = gt[sl]
            slices.append(sl)
            starts.append(np.r_[0, np.flatnonzero(np.diff(g)) + 1])
        return cls(gt, det, overlap, slices, starts)


@dataclass(frozen=True)
class Assignments:
    """Chosen (configuration, GT, detection) triples, and which paired detections each config took."""

    config: np.ndarray
    gt: np.ndarray
    det: np.ndarray
    paired_dets: np.ndarray  # (Dp,) detection indices that occur in some pair
    assigned: np.ndarray  # (Dp, K) bool, rows follow paired_dets


def _greedy(pairs: CandidatePairs, n_config: int, key_of) -> Assignments:
    """Run the rank-by-rank greedy assignment.

    ``key_of(local_det, overlap, assigned)`` gives the (Pr, K) keys of a rank's pairs, where
    ``local_det`` indexes the rows of ``assigned``. Each GT group takes its maximal key (first pair
    on ties); -inf keys are not eligible.
    """
    paired, local = np.unique(pairs.det, return_inverse=True)
    local = local.reshape(-1)
    assigned = np.zeros((len(paired), n_config), dtype=bool)
    chosen_k, chosen_g, chosen_d = [], [], []
    for sl, starts in zip(pairs.rank_slices, pairs.group_starts, strict=True):
        loc = local[sl]
        key = key_of(loc, pairs.overlap[sl], assigned)
        n = key.shape[0]
        best = np.maximum.reduceat(key, starts, axis=0)  # (G, K)
        at_best = key == np.repeat(best, np.diff(np.r_[starts, n]), axis=0)
        first = np.minimum.reduceat(np.where(at_best, np.arange(n)[:, None], n), starts, axis=0)
        grp, k = np.nonzero(best > -np.inf)
        p = first[grp, k]
        assigned[loc[p], k] = True
        chosen_k.append(k)
        chosen_g.append(pairs.gt[p + sl.start])
        chosen_d.append(pairs.det[p + sl.start])
    cat = (lambda xs: np.concatenate(xs) if xs else np.empty(0, dtype=np.int64))  # noqa: E731
    return Assignments(cat(chosen_k), cat(chosen_g), cat(chosen_d), paired, assigned)


def collect_tp_detections(pairs: CandidatePairs, gt_status: np.ndarray, det_status: np.ndarray,
                          score: np.ndarray) -> list[np.ndarray]:
    """Pass 1 as detection indices: per difficulty, which detections are true positives (arguments as in
    :func:`collect_tp_scores`)."""
    n_diff = det_status.shape[0]
    paired = np.unique(pairs.det)
    usable = ((det_status[:, paired] != -1) & (score[paired] > NO_DETECTION)[None, :]).T  # (Dp, 3)
    paired_score = score[paired][:, None]

    def key_of(loc: np.ndarray, overlap: np.ndarray, assigned: np.ndarray) -> np.ndarray:
        return np.where(usable[loc] & ~assigned[loc], paired_score[loc], -np.inf)

    a = _greedy(pairs, n_diff, key_of)
    tp = (gt_status[a.config, a.gt] == 0) & (det_status[a.config, a.det] == 0)
    return [a.det[tp & (a.config == k)] for k in range(n_diff)]


def collect_tp_scores(pairs: CandidatePairs, gt_status: np.ndarray, det_status: np.ndarray,
                      score: np.ndarray) -> list[np.ndarray]:
    """Pass 1: per difficulty, the scores of the true positives (highest-score matching).

    Args:
        gt_status: (3, G) GT status (0 counts, 1 ignored) of the GT indices in ``pairs``.
        det_status: (3, D) detection status (0 counts, 1 ignored, -1 not involved).
        score: (D,) detection scores.
    Returns:
        Three arrays of TP scores (unsorted), easy, moderate, hard.
    """
    return [score[d] for d in collect_tp_detections(pairs, gt_status, det_status, score)]


def assign_at_thresholds(pairs: CandidatePairs, config_difficulty: np.ndarray, config_threshold: np.ndarray,
                         det_status: np.ndarray, score: np.ndarray) -> Assignments:
    """Pass 2's assignment for every configuration (difficulty x score threshold): each GT, in file
    order, takes the unassigned counting detection with the largest overlap, else the first ignored
    one; detections scoring below the configuration's threshold are removed (arguments as in
    :func:`count_at_thresholds`)."""
    paired = np.unique(pairs.det)
    status = det_status[:, paired].T[:, config_difficulty]  # (Dp, K)
    usable = (status != -1) & (score[paired][:, None] >= config_threshold[None, :])
    counting_status = status == 0

    def key_of(loc: np.ndarray, overlap: np.ndarray, assigned: np.ndarray) -> np.ndarray:
        ok = usable[loc] & ~assigned[loc]
        # Counting candidates rank by overlap (all > threshold > 0); ignored ones below them.
        return np.where(ok, np.where(counting_status[loc], overlap[:, None], -0.5), -np.inf)

    return _greedy(pairs, len(config_difficulty), key_of)


def true_positives(a: Assignments, config_difficulty: np.ndarray, gt_status: np.ndarray,
                   det_status: np.ndarray) -> np.ndarray:
    """(len(a.gt),) bool: which assigned pairs are true positives (counting GT and counting detection)."""
    d = config_difficulty[a.config]
    return (gt_status[d, a.gt] == 0) & (det_status[d, a.det] == 0)


@dataclass(frozen=True)
class ThresholdCounts:
    """Pass-2 totals per configuration (difficulty x score threshold)."""

    tp: np.ndarray  # (K,) int64 true positives
    similarity: np.ndarray  # (K,) float64 sum over TPs of (1 + cos(alpha_gt - alpha_det)) / 2
    assigned_counting: np.ndarray  # (K,) int64 assigned detections that would otherwise be FPs


def count_at_thresholds(pairs: CandidatePairs, config_difficulty: np.ndarray, config_threshold: np.ndarray,
                        gt_status: np.ndarray, det_status: np.ndarray, score: np.ndarray,
                        gt_alpha: np.ndarray, det_alpha: np.ndarray, fp_candidate: np.ndarray) -> ThresholdCounts:
    """Pass 2 for every configuration at once (largest-overlap matching, low scores removed).

    Args:
        config_difficulty: (K,) difficulty index of each configuration.
        config_threshold: (K,) score threshold; detections scoring below it are removed.
        gt_status, det_status, score: as in :func:`collect_tp_scores`.
        gt_alpha, det_alpha: (G,), (D,) observation angles, rad (for AOS).
        fp_candidate: (D,) bool, detections that count as FP when unassigned (not in DontCare).
    """
    n_config = len(config_difficulty)
    a = assign_at_thresholds(pairs, config_difficulty, config_threshold, det_status, score)
    counting_status = det_status[:, a.paired_dets].T[:, config_difficulty] == 0
    tp = true_positives(a, config_difficulty, gt_status, det_status)
    sim = (1.0 + np.cos(gt_alpha[a.gt[tp]] - det_alpha[a.det[tp]])) / 2.0
    counting = a.assigned & counting_status & fp_candidate[a.paired_dets][:, None]
    return ThresholdCounts(
        tp=np.bincount(a.config[tp], minlength=n_config).astype(np.int64),
        similarity=np.bincount(a.config[tp], weights=sim, minlength=n_config),
        assigned_counting=counting.sum(axis=0).astype(np.int64),
    )
