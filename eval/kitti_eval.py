"""KITTI object-detection AP with the official devkit's semantics (``evaluate_object.cpp``, 2019+).

Entry points: :func:`evaluate` (in-memory, one :class:`~robustbench3d.kitti.Labels` per frame)
and :func:`evaluate_dirs` (a GT label directory and a result directory). Both return::

    {"Car": {"2d" | "aos" | "bev" | "3d": {"R40" | "R11": {"easy": ap, "moderate": ap, "hard": ap}}},
     ..., "meta": {...}}

with AP in percent. Rules (all from the devkit): per class and difficulty, GT of the class that
passes the height/occlusion/truncation limits counts, neighbour classes (Van for Car,
Person_sitting for Pedestrian) and filtered GT are ignored; detections lower than the minimum
height are ignored; unassigned detections overlapping a DontCare region by more than the
threshold (intersection over the detection, with the metric's own overlap) are not FPs. Matching
is greedy in GT file order. Precision is sampled at the devkit's up to 41 score thresholds,
interpolated (max over higher recall), and averaged over R40 (recall 1/40..1) or R11
(0, 0.1, ..., 1).

Deliberate differences, all in cases where the devkit misbehaves: precision with no TP and no
FP at a threshold is 0 (the devkit divides 0 by 0 and prints NaN); threshold picks beyond the
41st (an out-of-bounds write in the devkit) are dropped. A class without any detection scores
AP 0 on every metric (the devkit skips such a class silently); a metric for which the class's
detections carry no usable box (devkit: no 2D box with left >= 0, no BEV/3D box) is skipped and
listed in ``meta.skipped``, as is AOS when any detection has alpha = -10.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from robustbench3d.eval.difficulty import det_status, detection_height_px, gt_status
from robustbench3d.eval.loading import load_dirs
from robustbench3d.eval.matching import CandidatePairs, ThresholdCounts, collect_tp_scores, count_at_thresholds
from robustbench3d.eval.overlaps import PairOverlaps, pair_overlaps
from robustbench3d.eval.precision import average_precision, interpolate, ratio, score_thresholds
from robustbench3d.eval.rules import (
    CLASSES,
    DIFFICULTIES,
    EVALUATOR_VERSION,
    INVALID_ALPHA,
    INVALID_LOCATION,
    MAX_OCCLUSION,
    MAX_TRUNCATION,
    METRICS,
    MIN_HEIGHT,
    MIN_OVERLAP,
    N_SAMPLE_PTS,
    NEIGHBOURS,
    OVERLAP_OF_METRIC,
    RECALL_SAMPLES,
    TARGET_CLASS,
    normalise_names,
)
from robustbench3d.eval.table import TYPE_CODE, ObjectTable
from robustbench3d.kitti.labels import Labels


def _codes(names: Iterable[str]) -> list[int]:
    return [TYPE_CODE[n] for n in names]


def _usable_boxes(dt: ObjectTable, own: np.ndarray) -> dict[str, bool]:
    """Which overlap kinds the devkit would evaluate, judged on the class's detections."""
    b = dt.box3d
    located_xz = (b[:, 3] != INVALID_LOCATION) & (b[:, 5] != INVALID_LOCATION)
    return {
        "2d": bool(np.any(own & (dt.bbox[:, 0] >= 0))),
        "bev": bool(np.any(own & located_xz & (b[:, 1] > 0) & (b[:, 2] > 0))),
        "3d": bool(np.any(own & located_xz & (b[:, 4] != INVALID_LOCATION)
                          & (b[:, 0] > 0) & (b[:, 1] > 0) & (b[:, 2] > 0))),
    }


@dataclass(frozen=True)
class ThresholdStats:
    """Pass-2 results of one class and overlap kind (configurations: difficulty x sampled threshold).

    Attributes:
        pairs: the GT-detection candidate pairs (indices into the class's GT and detection rows).
        thresholds: per difficulty the sampled score thresholds (up to 41, descending).
        config_difficulty, config_threshold: (K,) each configuration's difficulty index and threshold.
        counts: TP totals per configuration; fp: (K,) false positives per configuration.
    """

    pairs: CandidatePairs
    thresholds: list[np.ndarray]
    config_difficulty: np.ndarray
    config_threshold: np.ndarray
    counts: ThresholdCounts
    fp: np.ndarray


class ClassEvaluation:
    """Everything of one class that does not depend on the overlap kind."""

    def __init__(self, gt: ObjectTable, dt: ObjectTable, cls: str):
        self.cls = cls
        status_gt = gt_status(gt, cls)
        status_dt = det_status(dt, cls)
        self.gt_rows = np.flatnonzero(status_gt[0] != -1)  # class or neighbour (same every difficulty)
        self.det_rows = np.flatnonzero((status_dt != -1).any(axis=0))
        self.gt_status = status_gt[:, self.gt_rows]
        self.det_status = status_dt[:, self.det_rows]
        self.gt_frame = gt.frame[self.gt_rows]
        self.gt_alpha = gt.alpha[self.gt_rows]
        self.det_alpha = dt.alpha[self.det_rows]
        self.score = dt.score[self.det_rows]
        self.n_gt = (self.gt_status == 0).sum(axis=1)

    def threshold_counts(self, pairs: PairOverlaps, dontcare: PairOverlaps, kind: str) -> ThresholdStats:
        """Both matching passes for one overlap kind: TP and FP at every sampled score threshold."""
        thr = MIN_OVERLAP[kind][self.cls]
        ov = pairs.values[kind]
        keep = (ov > thr) & np.isin(pairs.gt, self.gt_rows) & np.isin(pairs.det, self.det_rows)
        gi = np.searchsorted(self.gt_rows, pairs.gt[keep])
        di = np.searchsorted(self.det_rows, pairs.det[keep])
        cand = CandidatePairs.build(gi, di, ov[keep], self.gt_frame)

        tp_scores = collect_tp_scores(cand, self.gt_status, self.det_status, self.score)
        thresholds = [score_thresholds(tp_scores[d], int(self.n_gt[d])) for d in range(3)]
        cfg_diff = np.concatenate([np.full(len(t), d) for d, t in enumerate(thresholds)]).astype(np.int64)
        cfg_thr = np.concatenate(thresholds)

        in_dontcare = np.isin(self.det_rows, dontcare.det[dontcare.values[kind] > thr])
        counts = count_at_thresholds(cand, cfg_diff, cfg_thr, self.gt_status, self.det_status, self.score,
                                     self.gt_alpha, self.det_alpha, ~in_dontcare)
        # FP = counting detections at or above the threshold, minus those assigned to some GT.
        fp = np.empty(len(cfg_thr), dtype=np.int64)
        for d in range(3):
            scores = np.sort(self.score[(self.det_status[d] == 0) & ~in_dontcare])
            at = cfg_diff == d
            fp[at] = len(scores) - np.searchsorted(scores, cfg_thr[at], side="left")
        fp -= counts.assigned_counting
        return ThresholdStats(cand, thresholds, cfg_diff, cfg_thr, counts, fp)

    def curves(self, pairs: PairOverlaps, dontcare: PairOverlaps, kind: str, with_aos: bool) -> dict:
        """Interpolated precision (and AOS) samples per difficulty for one overlap kind."""
        st = self.threshold_counts(pairs, dontcare, kind)
        thresholds, cfg_diff, counts, fp = st.thresholds, st.config_difficulty, st.counts, st.fp
        precision = ratio(counts.tp, counts.tp + fp)
        similarity = ratio(counts.similarity, counts.tp + fp)
        out: dict = {"n_thresholds": [len(t) for t in thresholds],
                     "precision": [interpolate(precision[cfg_diff == d]) for d in range(3)]}
        if with_aos:
            out["aos"] = [interpolate(similarity[cfg_diff == d]) for d in range(3)]
        return out


def class_overlaps(gt: ObjectTable, dt: ObjectTable, classes: Sequence[str], kinds: Iterable[str]
                   ) -> tuple[PairOverlaps, PairOverlaps]:
    """Overlaps of the GT-detection pairs the evaluation of ``classes`` looks at (GT of the classes and
    their neighbours x the classes' detections and all too-small ones), and of the classes' detections
    with DontCare regions (intersection over the detection)."""
    gt_types = set(classes) | {n for c in classes for n in NEIGHBOURS[c]}
    gt_rows = np.flatnonzero(np.isin(gt.type, _codes(gt_types)))
    own_dets = np.isin(dt.type, _codes(classes))
    det_rows = np.flatnonzero(own_dets | (detection_height_px(dt) < max(MIN_HEIGHT)))
    pairs = pair_overlaps(gt, dt, gt_rows, det_rows, set(kinds))
    dontcare = pair_overlaps(gt, dt, np.flatnonzero(gt.of_type("DontCare")), np.flatnonzero(own_dets), set(kinds),
                             "det")
    return pairs, dontcare


def evaluate_tables(gt: ObjectTable, dt: ObjectTable, classes: Sequence[str] | None = (TARGET_CLASS,),
                    metrics: Sequence[str] = METRICS, with_curves: bool = False) -> dict:
    """Evaluate detection and GT tables of the same frames (see the module doc for the result).

    Args:
        gt: ground truth (15-column labels), one frame per index.
        dt: detections with scores, same frames.
        classes: any of "Car", "Pedestrian", "Cyclist"; None: every class with a detection (as the
            devkit), "Car" if there is none.
        metrics: any of "2d", "aos", "bev", "3d".
        with_curves: also return the 41 interpolated samples under ``meta["curves"]``.
    """
    if gt.n_frames != dt.n_frames:
        raise ValueError(f"{gt.n_frames} GT frames but {dt.n_frames} detection frames")
    if dt.score is None:
        raise ValueError("detections need scores")
    if classes is None:
        detected = [c for c in CLASSES if dt.of_type(c).any()]
        classes = detected or [TARGET_CLASS]
    classes = normalise_names(classes, CLASSES, "class")
    metrics = normalise_names(metrics, METRICS, "metric")
    kinds = {OVERLAP_OF_METRIC[m] for m in metrics}
    orientation_ok = not bool(np.any(dt.alpha == INVALID_ALPHA))

    pairs, dontcare = class_overlaps(gt, dt, classes, kinds)

    result: dict = {}
    skipped: list[dict] = []
    notes: list[str] = []
    curves: dict = {}
    n_thresholds: dict = {}
    gt_counted: dict = {}
    for cls in classes:
        ce = ClassEvaluation(gt, dt, cls)
        gt_counted[cls] = {diff: int(ce.n_gt[d]) for d, diff in enumerate(DIFFICULTIES)}
        result[cls], curves[cls], n_thresholds[cls] = _class_result(
            ce, dt, metrics, pairs, dontcare, orientation_ok, skipped)
        notes += _sample_size_notes(cls, ce.n_gt)
    result["meta"] = _meta(gt, dt, classes, metrics, skipped, notes)
    result["meta"]["gt_counted"] = gt_counted
    result["meta"]["n_thresholds"] = n_thresholds
    if with_curves:
        result["meta"]["curves"] = curves
    return result


def _class_result(ce: ClassEvaluation, dt: ObjectTable, metrics: tuple[str, ...], pairs: PairOverlaps,
                  dontcare: PairOverlaps, orientation_ok: bool, skipped: list[dict]) -> tuple[dict, dict, dict]:
    """AP tables, curves and threshold counts of one class; appends skipped metrics to ``skipped``."""
    own = dt.of_type(ce.cls)
    usable = _usable_boxes(dt, own)
    aps: dict = {}
    curves: dict = {}
    n_thresholds: dict = {}
    for kind in ("2d", "bev", "3d"):
        wanted = [m for m in metrics if OVERLAP_OF_METRIC[m] == kind]
        if not wanted:
            continue
        if not (usable[kind] or not own.any()):  # a class without detections scores 0, not "skipped"
            skipped.extend({"class": ce.cls, "metric": m, "reason": _NO_BOX_REASON[kind]} for m in wanted)
            continue
        with_aos = "aos" in wanted and orientation_ok
        if "aos" in wanted and not orientation_ok:
            skipped.append({"class": ce.cls, "metric": "aos",
                            "reason": "a detection has alpha = -10 (no orientation), as in the devkit"})
        c = ce.curves(pairs, dontcare, kind, with_aos)
        n_thresholds[kind] = c["n_thresholds"]
        for m in wanted:
            if m == "aos" and not with_aos:
                continue
            samples = c["aos" if m == "aos" else "precision"]
            aps[m] = _ap_table(samples)
            curves[m] = {diff: samples[d].tolist() for d, diff in enumerate(DIFFICULTIES)}
    return {m: aps[m] for m in metrics if m in aps}, curves, n_thresholds


def _sample_size_notes(cls: str, n_gt: np.ndarray) -> list[str]:
    notes = []
    for d, diff in enumerate(DIFFICULTIES):
        if 0 < n_gt[d] < N_SAMPLE_PTS:
            notes.append(f"{cls} {diff}: only {n_gt[d]} counted GT objects; the devkit samples precision at one "
                         f"score threshold per TP, so AP stays below 100 with fewer than {N_SAMPLE_PTS}")
        elif n_gt[d] == 0:
            notes.append(f"{cls} {diff}: no counted GT objects; AP is 0")
    return notes


_NO_BOX_REASON = {
    "2d": "no detection of the class has a 2D box (left >= 0), so the devkit skips it",
    "bev": "no detection of the class has a BEV box (x, z != -1000, w, l > 0), so the devkit skips it",
    "3d": "no detection of the class has a 3D box (x, y, z != -1000, h, w, l > 0), so the devkit skips it",
}


def _ap_table(samples: list[np.ndarray]) -> dict:
    aps = [average_precision(s) for s in samples]
    return {name: {diff: aps[d][name] for d, diff in enumerate(DIFFICULTIES)} for name in ("R40", "R11")}


def _meta(gt: ObjectTable, dt: ObjectTable, classes: tuple[str, ...], metrics: tuple[str, ...],
          skipped: list[dict], notes: list[str]) -> dict:
    return {
        "evaluator": "robustbench3d.eval",
        "version": EVALUATOR_VERSION,
        "reference": "KITTI object devkit cpp/evaluate_object.cpp (2019+)",
        "ap_unit": "percent",
        "frames": int(gt.n_frames),
        "classes": list(classes),
        "metrics": list(metrics),
        "gt_objects": gt.count_by_type(),
        "detections": dt.count_by_type(),
        "min_overlap": {c: {m: MIN_OVERLAP[OVERLAP_OF_METRIC[m]][c] for m in metrics} for c in classes},
        "difficulty": {
            "names": list(DIFFICULTIES),
            "min_height_px": list(MIN_HEIGHT),
            "max_occlusion": list(MAX_OCCLUSION),
            "max_truncation": list(MAX_TRUNCATION),
        },
        "recall_points": {name: [i / (N_SAMPLE_PTS - 1) for i in idx] for name, idx in RECALL_SAMPLES.items()},
        "skipped": skipped,
        "notes": notes,
    }


def evaluate(gt: Sequence[Labels], dt: Sequence[Labels], classes: Sequence[str] | None = (TARGET_CLASS,),
             metrics: Sequence[str] = METRICS) -> dict:
    """AP of detections ``dt`` against ground truth ``gt``, one :class:`Labels` per frame each.

    Frames pair up by position; detections must carry scores. See the module doc for the result.
    """
    if len(gt) != len(dt):
        raise ValueError(f"{len(gt)} ground-truth frames but {len(dt)} detection frames")
    return evaluate_tables(ObjectTable.from_labels(gt, scored=False), ObjectTable.from_labels(dt, scored=True),
                           classes, metrics)


def evaluate_dirs(gt_dir: str | Path, pred_dir: str | Path, split: str | Path | None = None,
                  classes: Sequence[str] | None = None, metrics: Sequence[str] = METRICS) -> dict:
    """AP of a result directory against a GT label directory (frame set: see :mod:`.loading`).

    ``classes=None`` evaluates every class with a detection (the devkit's rule), Car if none.
    """
    loaded = load_dirs(gt_dir, pred_dir, split)
    result = evaluate_tables(loaded.gt, loaded.dt, classes, metrics)
    meta = result["meta"]
    meta["gt_dir"] = str(gt_dir)
    meta["pred_dir"] = str(loaded.pred_dir)
    meta["split"] = None if split is None else str(split)
    meta["frames_without_results"] = loaded.frames_without_results
    meta["ignored_result_files"] = {"count": len(loaded.ignored_result_files),
                                    "examples": loaded.ignored_result_files[:10]}
    if loaded.ignored_result_files:
        meta["notes"].append(f"{len(loaded.ignored_result_files)} result files are not in the frame set and "
                             f"were ignored (e.g. {loaded.ignored_result_files[0]}.txt)")
    return result
