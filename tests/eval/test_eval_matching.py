"""The vectorised matching equals a straightforward per-threshold transcription of the devkit.

``reference_curves`` below follows ``evaluate_object.cpp`` loop by loop: ``cleanData``, then
``computeStatistics`` once to collect TP scores, ``getThresholds``, and ``computeStatistics`` again
for every frame and every threshold. Only the overlaps come from the library (they are checked
on their own in test_eval_iou.py).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from eval_fixture_generator import load_generator

from robustbench3d.eval.iou import bev_overlap, box3d_overlap, image_overlap
from robustbench3d.eval.kitti_eval import evaluate_tables
from robustbench3d.eval.loading import load_dirs
from robustbench3d.eval.precision import score_thresholds
from robustbench3d.kitti import Labels, read_labels

MIN_HEIGHT, MAX_OCC, MAX_TRUNC = (40, 25, 25), (0, 1, 2), (0.15, 0.3, 0.5)
THRESH = {"Car": 0.7, "Pedestrian": 0.5, "Cyclist": 0.5}
NEIGHBOUR = {"Car": "Van", "Pedestrian": "Person_sitting"}




GEN = load_generator()


# ---- literal reference -----------------------------------------------------------------------
def _boxes7(lab: Labels) -> np.ndarray:
    return np.concatenate([lab.dimensions, lab.location, lab.rotation_y[:, None]], axis=1)


def overlap_matrix(det: Labels, gt: Labels, kind: str, criterion: str) -> np.ndarray:
    """(D, G) overlaps, detection first as in the devkit's boxoverlap(det, gt, criterion)."""
    out = np.zeros((len(det), len(gt)))
    for j in range(len(det)):
        for i in range(len(gt)):
            if kind == "2d":
                out[j, i] = image_overlap(det.bbox[j:j + 1], gt.bbox[i:i + 1], criterion)[0]
            else:
                f = bev_overlap if kind == "bev" else box3d_overlap
                out[j, i] = f(_boxes7(det)[j:j + 1], _boxes7(gt)[i:i + 1], criterion)[0]
    return out


def clean_data(cls: str, gt: Labels, det: Labels, d: int) -> tuple[list[int], list[int], list[int], int]:
    ignored_gt, dontcare, ignored_det, n_gt = [], [], [], 0
    for i in range(len(gt)):
        height = gt.bbox[i, 3] - gt.bbox[i, 1]
        if gt.type[i] == cls:
            valid = 1
        elif NEIGHBOUR.get(cls) == gt.type[i]:
            valid = 0
        else:
            valid = -1
        ignore = gt.occluded[i] > MAX_OCC[d] or gt.truncated[i] > MAX_TRUNC[d] or height <= MIN_HEIGHT[d]
        if valid == 1 and not ignore:
            ignored_gt.append(0)
            n_gt += 1
        elif valid == 0 or (ignore and valid == 1):
            ignored_gt.append(1)
        else:
            ignored_gt.append(-1)
    dontcare = [i for i in range(len(gt)) if gt.type[i] == "DontCare"]
    for j in range(len(det)):
        height = int(abs(det.bbox[j, 1] - det.bbox[j, 3]))
        if height < MIN_HEIGHT[d]:
            ignored_det.append(1)
        elif det.type[j] == cls:
            ignored_det.append(0)
        else:
            ignored_det.append(-1)
    return ignored_gt, dontcare, ignored_det, n_gt


def compute_statistics(ov: np.ndarray, ov_dc: np.ndarray, gt: Labels, det: Labels, ignored_gt: list[int],
                       dontcare: list[int], ignored_det: list[int], thr: float, compute_fp: bool,
                       compute_aos: bool, thresh: float = 0.0) -> tuple[int, int, float, list[float]]:
    """(tp, fp, similarity, tp_scores) of one frame."""
    no_detection = -10000000.0
    assigned = [False] * len(det)
    below = [compute_fp and det.score[j] < thresh for j in range(len(det))]
    tp = fp = 0
    scores, delta = [], []
    for i in range(len(gt)):
        if ignored_gt[i] == -1:
            continue
        det_idx, valid, max_overlap, assigned_ignored = -1, no_detection, 0.0, False
        for j in range(len(det)):
            if ignored_det[j] == -1 or assigned[j] or below[j]:
                continue
            o = ov[j, i]
            if not compute_fp and o > thr and det.score[j] > valid:
                det_idx, valid = j, det.score[j]
            elif compute_fp and o > thr and (o > max_overlap or assigned_ignored) and ignored_det[j] == 0:
                max_overlap, det_idx, valid, assigned_ignored = o, j, 1.0, False
            elif compute_fp and o > thr and valid == no_detection and ignored_det[j] == 1:
                det_idx, valid, assigned_ignored = j, 1.0, True
        if valid == no_detection:
            continue
        if ignored_gt[i] == 1 or ignored_det[det_idx] == 1:
            assigned[det_idx] = True
        else:
            tp += 1
            scores.append(det.score[det_idx])
            delta.append(gt.alpha[i] - det.alpha[det_idx])
            assigned[det_idx] = True
    similarity = 0.0
    if compute_fp:
        for j in range(len(det)):
            if not (assigned[j] or ignored_det[j] in (-1, 1) or below[j]):
                fp += 1
        stuff = 0
        for k in range(len(dontcare)):
            for j in range(len(det)):
                if assigned[j] or ignored_det[j] in (-1, 1) or below[j]:
                    continue
                if ov_dc[j, k] > thr:
                    assigned[j] = True
                    stuff += 1
        fp -= stuff
        if compute_aos:
            similarity = sum((1.0 + math.cos(x)) / 2.0 for x in delta)
    return tp, fp, similarity, scores


def get_thresholds(v: list[float], n_gt: int) -> list[float]:
    v = sorted(v, reverse=True)
    t, current = [], 0.0
    for i in range(len(v)):
        left = (i + 1) / n_gt
        right = (i + 2) / n_gt if i < len(v) - 1 else left
        if (right - current) < (current - left) and i < len(v) - 1:
            continue
        t.append(v[i])
        current += 1.0 / 40.0
    return t


def reference_curves(gts: list[Labels], dets: list[Labels], cls: str, kind: str, compute_aos: bool) -> dict:
    thr = THRESH[cls]
    ovs = [overlap_matrix(d, g, kind, "union") for g, d in zip(gts, dets, strict=True)]
    ov_dcs = [overlap_matrix(d, g.select(g.type == "DontCare"), kind, "det") for g, d in zip(gts, dets, strict=True)]
    out: dict = {"precision": [], "aos": []}
    for d in range(3):
        cleaned = [clean_data(cls, g, t, d) for g, t in zip(gts, dets, strict=True)]
        n_gt = sum(c[3] for c in cleaned)
        v: list[float] = []
        for f in range(len(gts)):
            ig, dc, idet, _ = cleaned[f]
            v += compute_statistics(ovs[f], ov_dcs[f], gts[f], dets[f], ig, dc, idet, thr, False, False)[3]
        thresholds = get_thresholds(v, n_gt) if n_gt else []
        precision, aos = [0.0] * 41, [0.0] * 41
        for k, t in enumerate(thresholds[:41]):
            tp = fp = 0
            sim = 0.0
            for f in range(len(gts)):
                ig, dc, idet, _ = cleaned[f]
                a, b, s, _ = compute_statistics(ovs[f], ov_dcs[f], gts[f], dets[f], ig, dc, idet, thr, True,
                                                compute_aos, t)
                tp, fp, sim = tp + a, fp + b, sim + s
            precision[k] = tp / (tp + fp) if tp + fp else 0.0
            aos[k] = sim / (tp + fp) if tp + fp else 0.0
        out["precision"].append([max(precision[k:]) for k in range(41)])
        out["aos"].append([max(aos[k:]) for k in range(41)])
    return out


# ---- tests -------------------------------------------------------------------------------------
SPECS = {
    "mixed": GEN.SetSpec(seed=101, frames=30, gt_per_frame=5.0, boundary=0.6, small_other=0.3, duplicate=0.3,
                         score_decimals=1, dontcare_3d=0.5, fp_in_dontcare=0.8),
    "crowded": GEN.SetSpec(seed=102, frames=12, gt_per_frame=12.0, jitter2d=0.08, jitter3d=0.5, duplicate=0.4,
                           fp_per_frame=4.0, det_type_swap=0.4),
    "peds": GEN.SetSpec(seed=103, frames=25, type_weights={"Pedestrian": 0.5, "Person_sitting": 0.2,
                                                           "Cyclist": 0.2, "DontCare": 0.1}),
}


@pytest.mark.parametrize("name", sorted(SPECS))
def test_vectorised_matching_equals_per_threshold_reference(name: str, tmp_path: Path) -> None:
    ids, gt, dt = GEN.make_set(SPECS[name])
    GEN.write_set(tmp_path, ids, gt, dt)
    loaded = load_dirs(tmp_path / "label_2", tmp_path / "results", tmp_path / "frames.txt")
    ours = evaluate_tables(loaded.gt, loaded.dt, ("Car", "Pedestrian", "Cyclist"), with_curves=True)
    gts = [read_labels(tmp_path / "label_2" / f"{i}.txt", scored=False) for i in ids]
    dets = [read_labels(tmp_path / "results" / f"{i}.txt", scored=True) if i in dt else Labels.empty(True)
            for i in ids]
    compute_aos = not any((d.alpha == -10).any() for d in dets)
    checked = 0
    for cls in ("Car", "Pedestrian", "Cyclist"):
        for kind in ("2d", "bev", "3d"):
            ref = reference_curves(gts, dets, cls, kind, compute_aos)
            curves = ours["meta"]["curves"][cls]
            for d, diff in enumerate(("easy", "moderate", "hard")):
                np.testing.assert_allclose(curves[kind][diff], ref["precision"][d], rtol=0, atol=1e-12,
                                           err_msg=f"{cls} {kind} {diff}")
                if kind == "2d":
                    np.testing.assert_allclose(curves["aos"][diff], ref["aos"][d], rtol=0, atol=1e-12)
                checked += int(max(ref["precision"][d]) > 0)
    assert checked >= 6  # the sets produce non-trivial curves


@pytest.mark.parametrize("seed", range(30))
def test_thresholds_equal_the_literal_loop(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n_gt = int(rng.integers(1, 400))
    m = int(rng.integers(0, n_gt + 1))
    scores = np.round(rng.random(m), int(rng.integers(1, 4)))  # with ties
    assert score_thresholds(scores, n_gt).tolist() == get_thresholds(list(scores), n_gt)[:41]


def test_pass_two_by_hand_on_direct_pairs() -> None:
    """Pass 2 on hand-made pairs of one frame (GTs in file order g0, g1, g2): a counting candidate beats an
    ignored one whatever its overlap (0.3 here; the matching takes any pairs), a GT with only an ignored
    candidate takes it, a detection not involved (-1) is never taken; the counts are (K,) int64 / float64
    also when the last configuration (threshold 0.95) keeps no detection."""
    from robustbench3d.eval.matching import CandidatePairs, assign_at_thresholds, count_at_thresholds

    # detections: d0 ignored (0.9), d1 counting (0.8), d2 not involved (0.7), d3 counting, unpaired (0.6)
    det_status = np.tile([1, 0, -1, 0], (3, 1))
    score = np.array([0.9, 0.8, 0.7, 0.6])
    pairs = CandidatePairs.build(np.array([0, 0, 1, 2]), np.array([0, 1, 0, 2]), np.array([0.9, 0.3, 0.8, 0.95]),
                                 np.zeros(3, dtype=np.int64))
    diff, thr = np.array([0, 0]), np.array([0.0, 0.95])
    a = assign_at_thresholds(pairs, diff, thr, det_status, score)
    assert sorted(zip(a.config.tolist(), a.gt.tolist(), a.det.tolist(), strict=True)) == [(0, 0, 1), (0, 1, 0)]
    c = count_at_thresholds(pairs, diff, thr, np.zeros((3, 3), dtype=np.int64), det_status, score,
                            np.zeros(3), np.full(4, 0.5), np.ones(4, dtype=bool))
    assert c.tp.dtype == np.int64 and c.tp.tolist() == [1, 0]
    assert c.similarity.dtype == np.float64 and c.similarity == pytest.approx([(1 + math.cos(0.5)) / 2, 0.0])
    assert c.assigned_counting.dtype == np.int64 and c.assigned_counting.tolist() == [1, 0]
