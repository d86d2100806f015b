"""Attacked cells against the clean cell: AP drop and attack success rate, computed by hand on
hand-written result files (robustbench3d.runner.effect, robustbench3d.eval.matches)."""

from __future__ import annotations

import copy
import csv
import io

import pytest
from cell_builders import hand_cell

from robustbench3d.eval.matches import best_f1_threshold, matched_ground_truth
from robustbench3d.kitti.labels import parse_labels
from robustbench3d.results import CellResult, long_csv_text, long_rows, validate_summary
from robustbench3d.runner.config import RunConfig
from robustbench3d.runner.effect import attach_effects, with_clean_cells
from robustbench3d.runner.table import summary_table

SHA = "a" * 64
FRAMES = ["000000", "000001"]


def car(x: float, z: float, score: float | None = None, bbox=(100, 100, 200, 180), kind: str = "Car") -> str:
    """A label/result row: a 1.5 x 1.6 x 4.0 m car at rect (x, 1.6, z), yaw 0, 80 px tall (moderate)."""
    row = f"{kind} 0.00 0 0.00 {bbox[0]} {bbox[1]} {bbox[2]} {bbox[3]} 1.50 1.60 4.00 {x} 1.60 {z} 0.00"
    return row + ("" if score is None else f" {score}")


# Ground truth: frame 0 has cars A1 (x=-4) and A2 (x=4); frame 1 has B1 (x=-4) and B2 (x=4).
GT = {"000000": [car(-4, 20), car(4, 20)], "000001": [car(-4, 30), car(4, 30)]}
# Clean: A1 0.9, A2 0.8, B1 0.7 exact; B2 missed; a false positive far away at 0.95 and one at 0.1.
CLEAN = {"000000": [car(-4, 20, 0.9), car(4, 20, 0.8), car(0, 60, 0.95)],
         "000001": [car(-4, 30, 0.7), car(12, 50, 0.1)]}
# Attacked: A1 moved 1.5 m sideways (BEV IoU 0.03 < 0.7) -> missed; A2 unchanged -> matched;
# B1 found at 0.65 < the clean threshold 0.7 -> missed; B2 found at 0.99 (not matched clean: no effect).
ATTACKED = {"000000": [car(-2.5, 20, 0.9), car(4, 20, 0.8), car(0, 60, 0.95)],
            "000001": [car(-4, 30, 0.65), car(4, 30, 0.99)]}


def labels(rows: dict[str, list[str]], scored: bool) -> list:
    return [parse_labels("\n".join(rows[f]) + "\n", f"{f}.txt", scored=scored) for f in FRAMES]


def test_best_f1_threshold_and_matched_cars_by_hand():
    gt, clean, attacked = labels(GT, False), labels(CLEAN, True), labels(ATTACKED, True)
    # F1 = 2TP / (2TP + FP + FN), FP = the 0.95 detection: t=0.9: 2/6, t=0.8: 4/7, t=0.7: 6/8 (best).
    assert best_f1_threshold(gt, clean) == 0.7
    before = matched_ground_truth(gt, clean, 0.7)
    assert [m.tolist() for m in before.matched] == [[True, True], [True, False]]
    assert [c.tolist() for c in before.counted] == [[True, True], [True, True]]
    after = matched_ground_truth(gt, attacked, 0.7)
    assert [m.tolist() for m in after.matched] == [[False, True], [False, True]]
    # At a lower threshold B1 (0.65) is matched again.
    assert [m.tolist() for m in matched_ground_truth(gt, attacked, 0.6).matched] == [[False, True], [True, True]]
    # No true positive at all: no threshold, nothing matched.
    empty = labels({"000000": [car(0, 60, 0.5)], "000001": []}, True)
    assert best_f1_threshold(gt, empty) is None
    assert not any(m.any() for m in matched_ground_truth(gt, empty, None).matched)



def frame_labels(frames: list[list[str]], scored: bool) -> list:
    """Labels of frames 000000, 000001, ... from their rows."""
    return [parse_labels("".join(r + "\n" for r in rows), f"{i:06d}.txt", scored=scored)
            for i, rows in enumerate(frames)]


# One frame, two moderate cars G1 (x=-4) and G2 (x=4) at z=20; false positives far from both (z=60).
TWO_CARS = [[car(-4, 20), car(4, 20)]]


def test_best_f1_threshold_prefers_fewer_false_positives_by_hand():
    gt = frame_labels(TWO_CARS, False)
    # TPs G1 at 0.9 and G2 at 0.5 are the sampled thresholds; FPs at 0.8, 0.7, 0.6 (n_gt = 2).
    dt = frame_labels([[car(-4, 20, 0.9), car(4, 20, 0.5), car(0, 60, 0.8), car(10, 60, 0.7),
                        car(-10, 60, 0.6)]], True)
    # t=0.9: TP 1, FP 0, FN 1: F1 = 2/(2+0+1) = 2/3; t=0.5: TP 2, FP 3, FN 0: F1 = 4/(4+3) = 4/7 < 2/3.
    # (2TP * denominator, 2TP - FP + FN or 2/TP + FP + FN would pick 0.5.)
    assert best_f1_threshold(gt, dt) == 0.9
    # With one false positive fewer above 0.5 nothing changes at 0.9, 0.5 gives 4/(4+2) = 2/3: a tie, and
    # ties go to the highest threshold.
    tie = frame_labels([[car(-4, 20, 0.9), car(4, 20, 0.6), car(0, 60, 0.8), car(10, 60, 0.7)]], True)
    assert best_f1_threshold(gt, tie) == 0.9
    # With a single FP (0.8) the lower threshold wins: t=0.6: 4/(4+1) = 4/5 > 2/3.
    one_fp = frame_labels([[car(-4, 20, 0.9), car(4, 20, 0.6), car(0, 60, 0.8)]], True)
    assert best_f1_threshold(gt, one_fp) == 0.6


# G1 moderate (and easy), G2 occluded 2 (hard only), a Van (a neighbour class: never counted for Car).
MIXED = [[car(-4, 20), "Car 0.00 2 0.00 100 100 200 180 1.50 1.60 4.00 4 1.60 20 0.00", car(0, 40, kind="Van")]]
MIXED_DT = [[car(-4, 20, 0.9), car(4, 20, 0.8)]]


def test_best_f1_threshold_uses_the_requested_difficulty_only():
    gt, dt = frame_labels(MIXED, False), frame_labels(MIXED_DT, True)
    # Moderate: n_gt 1 (G1), the 0.8 detection of the ignored G2 is neither TP nor FP; thresholds [0.9]:
    # F1 = 2/(2+0+0) = 1 -> 0.9. (Taking the easy and hard thresholds instead: hard's t=0.8 has TP 2
    # with FN = 1 - 2, F1 = 4/3 -> 0.8.)
    assert best_f1_threshold(gt, dt) == 0.9
    assert best_f1_threshold(gt, dt, difficulty="easy") == 0.9
    # Hard: n_gt 2, thresholds [0.9, 0.8]: F1 = 2/(2+0+1) = 2/3, then 4/(4+0+0) = 1 -> 0.8.
    assert best_f1_threshold(gt, dt, difficulty="hard") == 0.8


def test_matched_ground_truth_counted_rows_and_threshold_by_hand():
    gt, dt = frame_labels(MIXED, False), frame_labels(MIXED_DT, True)
    # Moderate counts G1 only; at 0.8 G1 is matched (0.9), G2 is found but not counted, the Van neither.
    m = matched_ground_truth(gt, dt, 0.8)
    assert [x.tolist() for x in m.matched] == [[True, False, False]]
    assert [x.tolist() for x in m.counted] == [[True, False, False]]
    assert m.threshold == 0.8 and type(m.threshold) is float
    hard = matched_ground_truth(gt, dt, 0.8, difficulty="hard")
    assert [x.tolist() for x in hard.matched] == [[True, True, False]]
    assert [x.tolist() for x in hard.counted] == [[True, True, False]]
    # No threshold: nothing matched, the counted rows all the same.
    none = matched_ground_truth(gt, dt, None)
    assert [x.tolist() for x in none.matched] == [[False, False, False]]
    assert [x.tolist() for x in none.counted] == [[True, False, False]]
    assert none.threshold is None


def test_matched_ground_truth_splits_rows_per_frame():
    # Three frames with 1, 0 and 2 GT cars; frame 2's second car (x=4) is missed.
    gt = frame_labels([[car(-4, 20)], [], [car(-4, 30), car(4, 30)]], False)
    dt = frame_labels([[car(-4, 20, 0.9)], [], [car(-4, 30, 0.7)]], True)
    m = matched_ground_truth(gt, dt, 0.5)
    assert [x.tolist() for x in m.matched] == [[True], [], [True, False]]
    assert [x.tolist() for x in m.counted] == [[True], [], [True, True]]
    # No frames at all: empty lists, not one empty frame.
    for threshold in (None, 0.5):
        empty = matched_ground_truth([], [], threshold)
        assert (empty.matched, empty.counted, empty.threshold) == ([], [], threshold)
    assert best_f1_threshold([], []) is None


def test_frame_count_mismatch_is_an_error():
    gt, dt = labels(GT, False), labels(CLEAN, True)
    with pytest.raises(ValueError, match=r"^2 ground-truth frames but 1 detection frames$"):
        matched_ground_truth(gt, dt[:1], 0.7)
    with pytest.raises(ValueError, match=r"^1 ground-truth frames but 2 detection frames$"):
        best_f1_threshold(gt[:1], dt)


def ap_table(e: float, m: float, h: float) -> dict:
    return {"easy": e, "moderate": m, "hard": h}


def cell(attack: str, bev40: tuple[float, float, float], fingerprint: str = SHA) -> dict:
    metrics = {"Car": {"bev": {"R40": ap_table(*bev40), "R11": ap_table(50.0, 50.0, 50.0)}},
               "meta": {"evaluator": "robustbench3d.eval", "version": "1", "ap_unit": "percent", "frames": 2,
                        "classes": ["Car"], "metrics": ["bev"], "min_overlap": {"Car": {"bev": 0.7}}}}
    return hand_cell(attack, metrics, fingerprint, SHA)


def write_results(cell_dir, rows: dict[str, list[str]]) -> None:
    data = cell_dir / "data"
    data.mkdir(parents=True)
    for fid in FRAMES:
        (data / f"{fid}.txt").write_text("".join(r + "\n" for r in rows[fid]))


@pytest.fixture
def cells(tmp_path):
    write_results(tmp_path / "v+none+detector", CLEAN)
    write_results(tmp_path / "v+random-shape+detector", ATTACKED)
    return tmp_path, [cell("none", (80.0, 64.0, 0.0), "b" * 64), cell("random-shape", (60.0, 48.0, 10.0))]


def test_attach_effects_drop_relative_drop_and_success_rate(cells):
    cells_dir, summary = cells
    changed = attach_effects(summary, cells_dir, labels(GT, False), FRAMES)
    assert changed == [1]
    validate_summary(summary)
    assert "attack_effect" not in summary[0]  # the clean cell: no comparison, the cell is left as it was
    attacked = CellResult(summary[1])
    effect = attacked.effect
    assert effect["clean_cell"] == "v+none+detector" and effect["clean_fingerprint"] == "b" * 64
    assert attacked.clean_ap("Car", "bev", "R40", "easy") == 80.0
    assert attacked.drop("Car", "bev", "R40", "easy") == 20.0
    assert attacked.drop("Car", "bev", "R40", "moderate") == 16.0
    assert attacked.drop("Car", "bev", "R40", "moderate", relative=True) == 16.0 / 64.0
    assert attacked.drop("Car", "bev", "R40", "hard") == -10.0  # the attack helped: negative drop
    assert attacked.drop("Car", "bev", "R40", "hard", relative=True) is None  # clean AP 0: undefined
    assert attacked.drop("Car", "bev", "R11", "easy") == 0.0
    assert effect["success"] == {"class": "Car", "metric": "bev", "iou": 0.7, "difficulty": "moderate",
                                 "score_threshold": 0.7, "clean_matched": 3, "attacked_missed": 2, "rate": 2 / 3}
    assert attacked.attack_success_rate == 2 / 3
    with pytest.raises(LookupError, match="no clean-cell comparison"):
        CellResult(summary[0]).drop()
    # Unchanged inputs: nothing to rewrite.
    assert attach_effects(summary, cells_dir, labels(GT, False), FRAMES) == []


def test_no_ok_clean_cell_means_no_effect(cells):
    cells_dir, summary = cells
    summary[0].update(status="error", reason="boom", metrics=None)
    attach_effects(summary, cells_dir, labels(GT, False), FRAMES)
    assert summary[1]["attack_effect"] is None and CellResult(summary[1]).attack_success_rate is None


def test_csv_and_table_show_the_drop(cells):
    cells_dir, summary = cells
    attach_effects(summary, cells_dir, labels(GT, False), FRAMES)
    rows = list(csv.DictReader(io.StringIO(long_csv_text(long_rows(summary)))))
    clean_row = next(r for r in rows if r["attack"] == "none" and r["difficulty"] == "moderate")
    assert clean_row["clean_ap"] == clean_row["ap_drop"] == clean_row["attack_success_rate"] == ""
    row = next(r for r in rows if r["attack"] == "random-shape" and r["recall_points"] == "40"
               and r["difficulty"] == "moderate")
    assert (float(row["ap"]), float(row["clean_ap"]), float(row["ap_drop"])) == (48.0, 64.0, 16.0)
    assert float(row["relative_drop"]) == 0.25 and float(row["attack_success_rate"]) == 2 / 3
    hard = next(r for r in rows if r["attack"] == "random-shape" and r["recall_points"] == "40"
                and r["difficulty"] == "hard")
    assert hard["relative_drop"] == "" and float(hard["ap_drop"]) == -10.0
    table = summary_table(summary)
    line = next(t for t in table.splitlines() if "random-shape" in t)
    assert " 60.00(-20.00)  48.00(-16.00)  10.00(+10.00)" in line and "66.7" in line
    assert "(" not in next(t for t in table.splitlines() if "| none" in t or " none " in t)


def test_schema_rejects_a_bad_effect(cells):
    cells_dir, summary = cells
    attach_effects(summary, cells_dir, labels(GT, False), FRAMES)
    bad = copy.deepcopy(summary)
    bad[1]["attack_effect"]["success"]["rate"] = 1.5
    with pytest.raises(Exception, match="attack_effect"):
        validate_summary(bad)


def test_with_clean_cells_adds_none_first(tmp_path):
    config = RunConfig(victims=("v",), attacks=("random-shape",), proposals=("detector",), out=tmp_path)
    assert with_clean_cells(config).attacks == ("none", "random-shape")
    clean = RunConfig(victims=("v",), attacks=("random-shape", "none"), proposals=("detector",), out=tmp_path)
    assert with_clean_cells(clean) is clean
