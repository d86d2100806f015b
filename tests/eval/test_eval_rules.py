"""Each devkit rule on a small hand-built case whose AP is worked out by hand in the comments.

Facts used throughout (devkit semantics): precision is sampled at one score threshold per
pass-1 true positive (at most 41), padded with zeros, then made non-increasing from the right;
R40 averages samples 1..40, R11 samples 0, 4, ..., 40. So N perfect detections of N counted GT
give R40 = 100 (N - 1) / 40 and R11 = 100 ceil(N / 4) / 11 for N <= 41, and 100 from N = 41 on.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import pytest

from robustbench3d.eval import evaluate
from robustbench3d.eval.precision import average_precision, interpolate, ratio, score_thresholds
from robustbench3d.kitti import Labels

N = 41  # frames per case: enough GT for AP to reach 100


def obj(type_: str = "Car", box: Sequence[float] = (100, 100, 200, 200), trunc: float = 0.0, occ: int = 0,
        alpha: float = 0.0, x: float = 0.0, y: float = 1.7, z: float = 20.0, ry: float = 0.0,
        dims: Sequence[float] = (1.5, 1.6, 3.9), score: float | None = None) -> dict:
    return dict(type=type_, box=box, trunc=trunc, occ=occ, alpha=alpha, loc=(x, y, z), ry=ry, dims=dims,
                score=score)


def frame(*objs: dict, scored: bool = False) -> Labels:
    if not objs:
        return Labels.empty(with_score=scored)
    return Labels(
        type=np.array([o["type"] for o in objs], dtype=object),
        truncated=np.array([o["trunc"] for o in objs], dtype=np.float64),
        occluded=np.array([o["occ"] for o in objs], dtype=np.int64),
        alpha=np.array([o["alpha"] for o in objs], dtype=np.float64),
        bbox=np.array([o["box"] for o in objs], dtype=np.float64),
        dimensions=np.array([o["dims"] for o in objs], dtype=np.float64),
        location=np.array([o["loc"] for o in objs], dtype=np.float64),
        rotation_y=np.array([o["ry"] for o in objs], dtype=np.float64),
        score=np.array([o["score"] for o in objs], dtype=np.float64) if scored else None,
    )


def det(**kw) -> dict:
    kw.setdefault("score", 0.9)
    return obj(**kw)


def run(gt: list[tuple[dict, ...]], dt: list[tuple[dict, ...]], **kw) -> dict:
    return evaluate([frame(*g) for g in gt], [frame(*d, scored=True) for d in dt], **kw)


def ap(result: dict, metric: str, recall: str = "R40", cls: str = "Car") -> list[float]:
    return [result[cls][metric][recall][d] for d in ("easy", "moderate", "hard")]


# ---- sampling, R11 / R40 ------------------------------------------------------------------------
@pytest.mark.parametrize(("n", "r40", "r11"), [(1, 0.0, 100 / 11), (3, 5.0, 100 / 11), (5, 10.0, 200 / 11),
                                               (40, 97.5, 1000 / 11), (41, 100.0, 100.0), (90, 100.0, 100.0)])
def test_perfect_detections_follow_the_sampling_formula(n: int, r40: float, r11: float) -> None:
    r = run([(obj(),)] * n, [(det(),)] * n)
    for metric in ("2d", "aos", "bev", "3d"):
        assert ap(r, metric) == pytest.approx([r40] * 3, abs=1e-9)
        assert ap(r, metric, "R11") == pytest.approx([r11] * 3, abs=1e-9)


def test_r40_and_r11_from_samples() -> None:
    samples = interpolate(np.array([1.0] * 21 + [0.5] * 20))
    assert average_precision(samples) == pytest.approx({"R40": 75.0, "R11": (6 + 5 * 0.5) / 11 * 100})
    # interpolation: max over the tail, zeros beyond the last threshold
    np.testing.assert_array_equal(interpolate(np.array([0.5, 1.0, 0.2]))[:4], [1.0, 1.0, 0.2, 0.0])


# ---- thresholds (getThresholds) --------------------------------------------------------------------
def test_thresholds_hand_cases() -> None:
    # Every TP gets a threshold while recall steps (1/n_gt) exceed the 1/40 sampling step.
    assert score_thresholds(np.array([0.1, 0.5, 0.3, 0.9, 0.7]), 5).tolist() == [0.9, 0.7, 0.5, 0.3, 0.1]
    # 80 TPs of 80 GT: recall 1/80 per TP; taken when the left recall is the better approximation of
    # 0, 1/40, 2/40, ...: indices 0, 1, 3, 5, ..., 79.
    scores = 1 - np.arange(80) / 100
    assert score_thresholds(scores, 80).tolist() == scores[[0, *range(1, 80, 2)]].tolist()
    # 41 x 0.9 then 41 x 0.8 with 82 GT: take k lands on index ceil(2.05 k - 1.5): k <= 20 -> 0.9.
    t = score_thresholds(np.array([0.9] * 41 + [0.8] * 41), 82)
    assert t.tolist() == [0.9] * 21 + [0.8] * 20
    assert score_thresholds(np.array([]), 10).size == 0
    assert score_thresholds(np.array([0.5]), 0).size == 0


def test_thresholds_stop_at_41_and_are_float64() -> None:
    # 100 TPs of 10 GT: each left recall (i + 1) / 10 is ahead of the step c = k / 40, so every score
    # is taken in order until the devkit's 41 samples are full.
    scores = 1 - np.arange(100) / 200
    t = score_thresholds(scores, 10)
    assert t.tolist() == scores[:41].tolist()
    # devkit doubles whatever the input type (thresholds are compared with float64 scores)
    for given in (np.array([3, 1, 2]), np.array([0.75, 0.25, 0.5], dtype=np.float32)):
        t = score_thresholds(given, 3)
        assert t.dtype == np.float64 and t.tolist() == sorted(given.tolist(), reverse=True)


def test_ratio_is_zero_where_the_denominator_is_zero() -> None:
    assert ratio(np.array([1, 2, 3]), np.array([2, 0, 4])).tolist() == [0.5, 0.0, 0.75]
    # broadcasting either way: (2, 1) / (3,) and (3,) / (2, 1)
    assert ratio(np.array([[1.0], [2.0]]), np.array([1.0, 0.0, 4.0])).tolist() == [[1.0, 0.0, 0.25],
                                                                                 [2.0, 0.0, 0.5]]
    assert ratio(np.array([1.0, 0.0, 4.0]), np.array([[2.0], [0.0]])).tolist() == [[0.5, 0.0, 2.0],
                                                                                 [0.0, 0.0, 0.0]]
    # zeros written, not left uninitialised: the result reuses freshly freed memory full of 7s
    num, den = np.ones(64), np.zeros(64)
    junk = np.full(64, 7.0)
    del junk
    assert not ratio(num, den).any()


# ---- difficulty: height, occlusion, truncation boundaries ----------------------------------------------
def test_gt_height_boundary_is_inclusive_ignore() -> None:
    # GT counts only if bottom - top > MIN_HEIGHT: exactly 40 px is ignored at easy, 25 at moderate/hard.
    gt = [(obj(box=(0, 100, 50, 140)),), (obj(box=(0, 100, 50, 140.5)),),
          (obj(box=(0, 100, 50, 125)),), (obj(box=(0, 100, 50, 125.25)),)]
    counted = run(gt, [()] * 4)["meta"]["gt_counted"]["Car"]
    assert counted == {"easy": 1, "moderate": 3, "hard": 3}


def test_detection_height_boundary_and_int_truncation() -> None:
    # GT 41 px high counts at every level. A detection 40 px high counts at easy; 39.99 px is cut to
    # 39 (int32) and ignored at easy: it is still matched (so no FN), but is no TP -> easy AP 0.
    gt = [(obj(box=(100, 100, 200, 141)),)] * N
    for height, easy in ((40.0, 100.0), (40.9, 100.0), (39.99, 0.0)):
        r = run(gt, [(det(box=(100, 100, 200, 100 + height)),)] * N, metrics=("2d",))
        assert ap(r, "2d") == pytest.approx([easy, 100.0, 100.0]), height


@pytest.mark.parametrize(("trunc", "occ", "expected"), [
    (0.15, 0, (1, 1, 1)), (0.1500001, 0, (0, 1, 1)), (0.0, 1, (0, 1, 1)),
    (0.3, 1, (0, 1, 1)), (0.3000001, 0, (0, 0, 1)), (0.0, 2, (0, 0, 1)),
    (0.5, 2, (0, 0, 1)), (0.5000001, 0, (0, 0, 0)), (0.0, 3, (0, 0, 0)),
])
def test_occlusion_and_truncation_limits(trunc: float, occ: int, expected: tuple[int, int, int]) -> None:
    counted = run([(obj(trunc=trunc, occ=occ),)], [()])["meta"]["gt_counted"]["Car"]
    assert tuple(counted.values()) == expected


# ---- neighbour classes -------------------------------------------------------------------------------
@pytest.mark.parametrize(("cls", "neighbour", "other"), [("Car", "Van", "Truck"),
                                                         ("Pedestrian", "Person_sitting", "Cyclist")])
def test_neighbour_class_is_ignored_not_a_false_positive(cls: str, neighbour: str, other: str) -> None:
    # Per frame: a perfectly detected GT of the class (score 0.9) and a second object 300 px away
    # carrying a detection of the class scored 0.95. On a neighbour it is ignored -> AP 100; on any
    # other type it is an FP above every threshold (all 0.9) -> precision 41 / 82 -> AP 50.
    dims = (1.5, 1.6, 3.9)
    for second, expected in ((neighbour, 100.0), (other, 50.0)):
        gt = [(obj(cls, dims=dims), obj(second, box=(400, 100, 500, 200), x=8.0, dims=dims))] * N
        dt = [(det(type_=cls, dims=dims), det(type_=cls, box=(400, 100, 500, 200), x=8.0, score=0.95, dims=dims))] * N
        r = run(gt, dt, classes=(cls,))
        for metric in ("2d", "bev", "3d"):
            assert ap(r, metric, cls=cls) == pytest.approx([expected] * 3), (second, metric)


def test_undetected_neighbours_are_no_false_negatives() -> None:
    r = run([(obj(), obj("Van", box=(400, 100, 500, 200), x=8.0))] * N, [(det(),)] * N)
    assert ap(r, "2d") == [100.0] * 3


# ---- DontCare ----------------------------------------------------------------------------------------
DC_KITTI = obj("DontCare", box=(380, 80, 560, 230), trunc=-1, occ=-1, alpha=-10, x=-1000, y=-1000, z=-1000,
               ry=-10, dims=(-1, -1, -1))


def test_dontcare_suppresses_false_positives_in_2d_only_with_kitti_lines() -> None:
    # FP (score 0.95) lies inside a DontCare image region: intersection / detection area = 1 > 0.7.
    # KITTI's DontCare lines have no 3D box (-1000), so in BEV/3D the FP stays: precision 1/2 -> 50.
    gt = [(obj(), DC_KITTI)] * N
    dt = [(det(), det(box=(400, 100, 500, 200), x=8.0, score=0.95))] * N
    r = run(gt, dt)
    assert ap(r, "2d") == [100.0] * 3
    assert ap(r, "bev") == [50.0] * 3 and ap(r, "3d") == [50.0] * 3


def test_dontcare_uses_intersection_over_detection_area() -> None:
    # The region covers 60 % of the FP's image box (IoU 0.6 as well): 0.6 < 0.7 -> FP counts -> 50.
    partial = dict(DC_KITTI, box=(400, 100, 460, 200))
    r = run([(obj(), partial)] * N, [(det(), det(box=(400, 100, 500, 200), x=8.0, score=0.95))] * N, metrics=("2d",))
    assert ap(r, "2d") == [50.0] * 3
    # A region 5x larger than the FP has IoU 0.2 but contains it: intersection / det area = 1 -> 100.
    huge = dict(DC_KITTI, box=(300, 0, 800, 300))
    r = run([(obj(), huge)] * N, [(det(), det(box=(400, 100, 500, 200), x=8.0, score=0.95))] * N, metrics=("2d",))
    assert ap(r, "2d") == [100.0] * 3


def test_dontcare_uses_the_metrics_own_overlap_in_bev_and_3d() -> None:
    # A DontCare line with a real 3D box around the FP's footprint: suppressed in BEV and 3D too,
    # while its image box (away from the FP) leaves the 2D FP counting.
    dc = obj("DontCare", box=(900, 100, 1000, 200), trunc=-1, occ=-1, alpha=-10, x=8.0, y=1.8, z=20.0,
             dims=(2.0, 3.0, 6.0))
    r = run([(obj(), dc)] * N, [(det(), det(box=(400, 100, 500, 200), x=8.0, score=0.95))] * N)
    assert ap(r, "2d") == [50.0] * 3
    assert ap(r, "bev") == [100.0] * 3 and ap(r, "3d") == [100.0] * 3


def test_detections_assigned_to_gt_are_not_taken_by_dontcare() -> None:
    # The TP lies inside a DontCare region too; it is assigned first, so it stays a TP.
    r = run([(obj(), dict(DC_KITTI, box=(50, 50, 250, 250)))] * N, [(det(),)] * N, metrics=("2d",))
    assert ap(r, "2d") == [100.0] * 3


# ---- greedy matching in GT order ---------------------------------------------------------------------
# Image boxes share rows 100..200; along x: GT A [0, 100], GT B [20, 120], D1 [12, 112], D2 [35, 135].
# IoU(D1, A) = 88/112 = 0.786, IoU(D1, B) = 92/108 = 0.852, IoU(D2, B) = 85/115 = 0.739,
# IoU(D2, A) = 65/135 = 0.481 (no candidate).
A, B = obj(box=(0, 100, 100, 200)), obj(box=(20, 100, 120, 200))


def _d1_d2(s1: float, s2: float) -> tuple[dict, dict]:
    return det(box=(12, 100, 112, 200), score=s1), det(box=(35, 100, 135, 200), score=s2)


def test_greedy_matching_follows_gt_file_order() -> None:
    # Scores D1 0.8, D2 0.9. Order A, B: A takes D1, B takes D2 in both passes -> AP 100.
    r = run([(A, B)] * N, [_d1_d2(0.8, 0.9)] * N, metrics=("2d",))
    assert ap(r, "2d") == [100.0] * 3
    # Order B, A. Pass 1 (highest score): B takes D2, A takes D1 -> 82 TP scores (41 x 0.9, 41 x 0.8),
    # thresholds 21 x 0.9 then 20 x 0.8 (see test_thresholds_hand_cases). Pass 2 (largest overlap):
    # at 0.9, D1 is removed, B takes D2: precision 1; at 0.8, B takes D1 (0.852 > 0.739), A is left
    # without a candidate, D2 is an FP: precision 1/2. R40 = (20 + 20 / 2) / 40, R11 = (6 + 5 / 2) / 11.
    r = run([(B, A)] * N, [_d1_d2(0.8, 0.9)] * N, metrics=("2d",))
    assert ap(r, "2d") == pytest.approx([75.0] * 3)
    assert ap(r, "2d", "R11") == pytest.approx([(6 + 2.5) / 11 * 100] * 3)


def test_pass_one_takes_the_highest_score_even_an_ignored_detection() -> None:
    # GT 30 px high (moderate). A Car detection on it scores 0.5; a Pedestrian detection 24 px high
    # (ignored at moderate: too small, whatever its class) scores 0.9 with IoU 0.8. Pass 1 gives the
    # GT the higher-scored ignored detection, so no TP score is collected: moderate AP 0.
    gt = [(obj(box=(100, 100, 200, 130)),)] * N
    car = det(box=(100, 100, 200, 130), score=0.5)
    small_ped = det(type_="Pedestrian", box=(100, 100, 200, 124), score=0.9)
    assert ap(run(gt, [(car,)] * N, metrics=("2d",)), "2d")[1] == 100.0
    assert ap(run(gt, [(small_ped, car)] * N, metrics=("2d",)), "2d")[1] == 0.0


# ---- AOS ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize(("delta", "expected"), [(0.0, 100.0), (math.pi / 2, 50.0), (math.pi, 0.0),
                                                 (math.pi / 3, 75.0)])
def test_aos_similarity_is_one_plus_cos_over_two(delta: float, expected: float) -> None:
    r = run([(obj(alpha=0.3),)] * N, [(det(alpha=0.3 + delta),)] * N, metrics=("2d", "aos"))
    assert ap(r, "2d") == [100.0] * 3
    assert ap(r, "aos") == pytest.approx([expected] * 3, abs=1e-9)


def test_aos_is_skipped_when_a_detection_has_no_orientation() -> None:
    r = run([(obj(),)] * N, [(det(), det(type_="Pedestrian", box=(500, 100, 540, 200), alpha=-10.0))] * N)
    assert "aos" not in r["Car"]
    assert {"class": "Car", "metric": "aos"}.items() <= r["meta"]["skipped"][0].items()


# ---- which metrics and classes are evaluated ------------------------------------------------------
def test_metrics_without_boxes_are_skipped_like_the_devkit() -> None:
    no3d = det(x=-1000.0, y=-1000.0, z=-1000.0, dims=(-1, -1, -1))
    r = run([(obj(),)] * N, [(no3d,)] * N)
    assert ap(r, "2d") == [100.0] * 3 and "bev" not in r["Car"] and "3d" not in r["Car"]
    assert {s["metric"] for s in r["meta"]["skipped"]} == {"bev", "3d"}
    no2d = det(box=(-1, 100, -1, 200))
    r = run([(obj(),)] * N, [(no2d,)] * N)
    assert "2d" not in r["Car"] and "aos" not in r["Car"] and ap(r, "bev") == [100.0] * 3



@pytest.mark.parametrize(("change", "skipped"), [
    (dict(box=(0, 100, 100, 200)), set()),  # 2D box with left exactly 0: usable (left >= 0)
    (dict(x=-1000.0), {"bev", "3d"}),  # x alone unlocated: no BEV footprint
    (dict(z=-1000.0), {"bev", "3d"}),  # z alone
    (dict(y=-1000.0), {"3d"}),  # y alone: the footprint stays
    (dict(dims=(1.5, 0.0, 3.9)), {"bev", "3d"}),  # w = 0 (dims are h, w, l)
    (dict(dims=(1.5, 1.6, 0.0)), {"bev", "3d"}),  # l = 0
    (dict(dims=(0.0, 1.6, 3.9)), {"3d"}),  # h = 0
    (dict(dims=(0.5, 1.6, 3.9)), set()),  # a low box is still a box
])
def test_each_box_field_decides_which_metrics_are_evaluated(change: dict, skipped: set) -> None:
    """The devkit's usable-box rules one field at a time: 2D needs left >= 0, BEV x, z != -1000 and w, l > 0,
    3D also y != -1000 and h > 0; a skipped metric is listed in meta and absent from the class's table."""
    r = run([(obj(),)], [(det(**change),)])
    assert {s["metric"] for s in r["meta"]["skipped"]} == skipped
    assert set(r["Car"]) == {"2d", "aos", "bev", "3d"} - skipped



def test_skipped_entries_notes_and_meta_text_exactly() -> None:
    no_boxes = det(x=-1000.0, alpha=-10.0)  # no footprint, and no orientation
    r = run([(obj(),)], [(no_boxes,)])
    no_bev = "no detection of the class has a BEV box (x, z != -1000, w, l > 0), so the devkit skips it"
    no_3d = "no detection of the class has a 3D box (x, y, z != -1000, h, w, l > 0), so the devkit skips it"
    assert r["meta"]["skipped"] == [
        {"class": "Car", "metric": "aos", "reason": "a detection has alpha = -10 (no orientation), as in the devkit"},
        {"class": "Car", "metric": "bev", "reason": no_bev}, {"class": "Car", "metric": "3d", "reason": no_3d}]
    assert run([(obj(),)], [(no_boxes,)], metrics=("2d",))["meta"]["skipped"] == []  # AOS not asked for
    meta = r["meta"]
    assert meta["evaluator"] == "robustbench3d.eval"
    assert meta["reference"] == "KITTI object devkit cpp/evaluate_object.cpp (2019+)"
    assert meta["metrics"] == ["2d", "aos", "bev", "3d"] and meta["n_thresholds"] == {"Car": {"2d": [1, 1, 1]}}
    # one car 30 px high: not counted at easy (40 px), counted once at moderate and hard
    low = obj(box=(100, 100, 200, 130))
    notes = run([(low,)], [(det(box=(100, 100, 200, 130)),)])["meta"]["notes"]
    few = ("only 1 counted GT objects; the devkit samples precision at one score threshold per TP, so AP stays "
           "below 100 with fewer than 41")
    assert notes == ["Car easy: no counted GT objects; AP is 0", f"Car moderate: {few}", f"Car hard: {few}"]
    assert run([(obj(),)] * 40, [(det(),)] * 40)["meta"]["notes"] == [
        f"Car {d}: only 40 counted GT objects; the devkit samples precision at one score threshold per TP, so AP "
        "stays below 100 with fewer than 41" for d in ("easy", "moderate", "hard")]
    assert run([(obj(),)] * 41, [(det(),)] * 41)["meta"]["notes"] == []
    # every class's notes, in class order; the difficulty table; curves only on request
    ped = obj("Pedestrian", box=(400, 100, 440, 200), x=5.0)
    r = run([(low, ped)], [(det(box=(100, 100, 200, 130)),)], classes=("Car", "Pedestrian"))
    assert [n.split(":")[0] for n in r["meta"]["notes"]] == [
        "Car easy", "Car moderate", "Car hard", "Pedestrian easy", "Pedestrian moderate", "Pedestrian hard"]
    assert r["meta"]["difficulty"] == {"names": ["easy", "moderate", "hard"], "min_height_px": [40, 25, 25],
                                       "max_occlusion": [0, 1, 2], "max_truncation": [0.15, 0.3, 0.5]}
    assert "curves" not in r["meta"]



def test_a_detection_scored_at_the_no_detection_sentinel_is_never_matched() -> None:
    """The devkit matches a detection only if its score exceeds NO_DETECTION = -1e7: perfect boxes scored
    exactly -1e7 find nothing (AP 0), scored just above it they are all TPs (AP 100)."""
    at = run([(obj(),)] * N, [(det(score=-1e7),)] * N, metrics=("2d",))
    above = run([(obj(),)] * N, [(det(score=-9999999.0),)] * N, metrics=("2d",))
    assert ap(at, "2d") == [0.0] * 3 and ap(above, "2d") == [100.0] * 3


def test_empty_candidate_pairs_keep_their_empty_arrays() -> None:
    from robustbench3d.eval.matching import CandidatePairs

    none = np.zeros(0, dtype=np.int64)
    pairs = CandidatePairs.build(none, none, np.zeros(0), np.zeros(3, dtype=np.int64))
    assert pairs.gt.shape == pairs.det.shape == pairs.overlap.shape == (0,)
    assert pairs.rank_slices == [] and pairs.group_starts == []


def test_evaluate_tables_rejects_mismatched_frames_and_unscored_detections() -> None:
    from robustbench3d.eval.kitti_eval import evaluate_tables
    from robustbench3d.eval.table import ObjectTable

    gt = ObjectTable.from_labels([frame(obj())], scored=False)
    two = ObjectTable.from_labels([frame(det(), scored=True)] * 2, scored=True)
    with pytest.raises(ValueError, match=r"^1 GT frames but 2 detection frames$"):
        evaluate_tables(gt, two)
    with pytest.raises(ValueError, match=r"^detections need scores$"):
        evaluate_tables(gt, gt)


def test_overlap_exactly_at_the_threshold_is_not_enough() -> None:
    """The devkit needs overlap > 0.7 (Car) for a TP, and > 0.7 of a detection inside DontCare to drop it as
    FP. A 2D box 70 x 100 px inside the 100 x 100 GT box: IoU exactly 0.7, an FP (2D AP 0); 71 px: a TP."""
    gt_box = (100, 100, 200, 200)
    exact = run([(obj(box=gt_box),)] * N, [(det(box=(100, 100, 170, 200)),)] * N, metrics=("2d",))
    above = run([(obj(box=gt_box),)] * N, [(det(box=(100, 100, 171, 200)),)] * N, metrics=("2d",))
    assert ap(exact, "2d") == [0.0] * 3 and ap(above, "2d") == [100.0] * 3
    # a higher-scored extra detection with 70 of its 100 px (exactly 0.7) inside a DontCare region stays an FP:
    # precision 1/2 at every threshold; 71 px inside: dropped
    dc = obj("DontCare", box=(530, 100, 700, 200), trunc=-1, occ=-1, alpha=-10, x=-1000, y=-1000, z=-1000,
             dims=(-1, -1, -1), ry=-10)
    extra = {70: det(box=(500, 100, 600, 200), score=0.95), 71: det(box=(501, 100, 601, 200), score=0.95)}
    at = run([(obj(box=gt_box), dc)] * N, [(det(box=gt_box), extra[70])] * N, metrics=("2d",))
    inside = run([(obj(box=gt_box), dc)] * N, [(det(box=gt_box), extra[71])] * N, metrics=("2d",))
    assert ap(at, "2d") == pytest.approx([50.0] * 3) and ap(inside, "2d") == [100.0] * 3


def test_no_detections_give_zero_ap_and_default_classes() -> None:
    r = run([(obj(),)] * N, [()] * N, classes=None)
    assert r["meta"]["classes"] == ["Car"]
    for metric in ("2d", "aos", "bev", "3d"):
        assert ap(r, metric) == [0.0] * 3 and ap(r, metric, "R11") == [0.0] * 3
    r = run([(obj(), obj("Pedestrian", box=(400, 100, 440, 200), x=5.0))] * N,
            [(det(type_="Pedestrian", box=(400, 100, 440, 200), x=5.0),)] * N, classes=None)
    assert r["meta"]["classes"] == ["Pedestrian"]


def test_bad_arguments_are_rejected() -> None:
    with pytest.raises(ValueError, match="unknown class"):
        run([()], [()], classes=("Bus",))
    with pytest.raises(ValueError, match="unknown metric"):
        run([()], [()], metrics=("map",))
    with pytest.raises(ValueError, match="frames"):
        evaluate([frame()], [])
    with pytest.raises(ValueError, match="scores"):
        evaluate([frame(obj())], [frame(obj())])
    with pytest.raises(ValueError, match="frame 1: non-finite"):
        evaluate([frame(), frame()], [frame(det(), scored=True), frame(det(score=math.nan), scored=True)])


def test_missed_objects_cap_recall() -> None:
    # 41 frames found perfectly, 41 frames (some with empty detection lists) missed: 82 GT, 41 TP.
    # Recall stops at 1/2: 21 thresholds (recall 0 .. 20/40) with precision 1, zeros beyond.
    r = run([(obj(),)] * 82, [(det(),)] * 41 + [()] * 41)
    assert ap(r, "bev") == pytest.approx([50.0] * 3)
    assert ap(r, "bev", "R11") == pytest.approx([600 / 11] * 3)


def test_each_box_metric_runs_alone() -> None:
    # Perfect detections of 41 GT per frame set: every metric alone gives 100, and only it is reported.
    for metric in ("3d", "bev", "2d"):
        r = run([(obj(),)] * N, [(det(),)] * N, metrics=(metric,))
        assert ap(r, metric) == [100.0] * 3
        assert "3d" not in r["Car"] or metric == "3d"


def test_name_errors_are_exact() -> None:
    with pytest.raises(ValueError) as info:
        run([()], [()], classes=("car", "Bus"))
    assert str(info.value) == "unknown class 'Bus'; expected some of Car, Pedestrian, Cyclist"
    with pytest.raises(ValueError) as info:
        run([()], [()], metrics=())
    assert str(info.value) == "no metric requested"


def test_difficulty_status_codes_by_hand() -> None:
    """gt_status / det_status / detection_height_px on one frame, every code worked out by hand
    (MIN_HEIGHT 40/25/25 px, MAX_OCCLUSION 0/1/2, MAX_TRUNCATION 0.15/0.3/0.5)."""
    from robustbench3d.eval.difficulty import det_status, detection_height_px, gt_status
    from robustbench3d.eval.table import ObjectTable

    gt = ObjectTable.from_labels([frame(
        obj(box=(0, 100, 10, 150)),                        # h 50, visible: counts everywhere
        obj(box=(0, 100, 10, 130), occ=1, trunc=0.2),      # h 30, partly occluded: not easy
        obj(box=(0, 100, 10, 140)),                        # h exactly 40: ignored in easy (needs > 40)
        obj("Van"),                                        # neighbour class: ignored
        obj("Pedestrian"),                                 # other class: not involved
        obj("DontCare", trunc=-1, occ=-1, dims=(-1, -1, -1)),
        obj(occ=3),                                        # occlusion unknown: ignored everywhere
        obj(trunc=0.5),                                    # truncated exactly 0.5: hard only
    )], scored=False)
    status = gt_status(gt, "Car")
    assert status.dtype == np.int8 and status.shape == (3, 8)
    assert status.tolist() == [[0, 1, 1, 1, -1, -1, 1, 1],
                               [0, 0, 0, 1, -1, -1, 1, 1],
                               [0, 0, 0, 1, -1, -1, 1, 0]]
    dt = ObjectTable.from_labels([frame(
        det(box=(0, 100, 10, 139.9)),                      # 39.9 -> 39 px: too small for easy only
        det(box=(0, 100, 10, 140)),                        # exactly 40 px: counts
        det(type_="Pedestrian", box=(0, 100, 10, 200)),          # other class: not involved
        det(type_="Pedestrian", box=(0, 100, 10, 124.99)),       # 24 px: ignored whatever the class
        det(box=(0, 200, 10, 100)),                        # top below bottom: |h| = 100
        scored=True)], scored=True)
    assert detection_height_px(dt).tolist() == [39, 40, 100, 24, 100]
    status = det_status(dt, "Car")
    assert status.dtype == np.int8 and status.shape == (3, 5)
    assert status.tolist() == [[1, 0, -1, 1, 0], [0, 0, -1, 1, 0], [0, 0, -1, 1, 0]]
    # the devkit's int32 cast: up to 2^31 - 1 truncated, from 2^31 on INT32_MIN (x86)
    huge = ObjectTable.from_labels([frame(*(det(box=(0, 0, 10, b)) for b in
                                            (2.0**31 - 0.5, 2.0**31, 3e9, 1e10, 1e300)), scored=True)],
                                   scored=True)
    heights = detection_height_px(huge)
    assert heights.dtype == np.int64 and heights.tolist() == [2**31 - 1] + [-(2**31)] * 4


def test_object_table_columns_dtypes_and_errors() -> None:
    from robustbench3d.eval.table import ObjectTable

    table = ObjectTable.from_labels([frame(obj(occ=2, trunc=0.25)), frame(), frame(obj("Van"), obj())], scored=False)
    assert table.frame.tolist() == [0, 2, 2] and table.type.tolist() == [0, 1, 0] and table.n_frames == 3
    assert table.occluded.tolist() == [2, 0, 0] and table.truncated.tolist() == [0.25, 0.0, 0.0]
    assert table.frame.dtype == table.type.dtype == table.occluded.dtype == np.int64
    assert table.box3d[0].tolist() == [1.5, 1.6, 3.9, 0.0, 1.7, 20.0, 0.0] and table.score is None
    for frames in ([], [frame(), frame()]):
        for scored in (False, True):
            empty = ObjectTable.from_labels(frames, scored=scored)
            assert len(empty) == 0 and empty.n_frames == len(frames) and empty.truncated.shape == (0,)
            assert empty.type.dtype == empty.occluded.dtype == np.int64 and empty.box3d.shape == (0, 7)
            assert (empty.score is None) != scored
    with pytest.raises(ValueError) as info:
        ObjectTable.from_labels([frame(obj())], scored=True)
    assert str(info.value) == "detections must carry scores (16-column results)"
    with pytest.raises(ValueError) as info:
        ObjectTable.from_labels([frame(obj("Bus"), obj("Auto"))], scored=False)
    assert str(info.value) == "unknown object type(s) ['Auto', 'Bus']; expected KITTI types"
    # from_columns keeps the documented int64 columns for narrower index arrays too
    numeric = np.arange(14.0)[None].repeat(2, axis=0)
    cols = ObjectTable.from_columns(np.array([0, 1], np.int32), np.array([3, 8], np.int32), numeric, 2, False)
    assert cols.frame.dtype == cols.type.dtype == cols.occluded.dtype == np.int64
    assert cols.type.tolist() == [3, 8] and cols.occluded.tolist() == [1, 1] and cols.bbox[0].tolist() == [3, 4, 5, 6]
