"""KITTI calibration and label files on hand-written text (no real data needed): the frame
transforms against pencil-and-paper values, the file formats, and the errors' file:line: field."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robustbench3d.errors import DataFormatError
from robustbench3d.kitti.calib import Calibration, parse_calibration, read_calibration, write_calibration
from robustbench3d.kitti.labels import Labels, impossible_rows, parse_labels, read_labels, write_labels

# P2: f = 700, c = (600, 180), P2[:, 3] = (70, 14, 0.5); R0_rect: 90° about y (x -> -z, z -> x);
# Tr_velo_to_cam: the axis permutation (-y, -z, x) plus a shift of (0.1, -0.2, 0.3).
CALIB_TEXT = """P0: 1 0 0 0 0 1 0 0 0 0 1 0
P1: 2 0 0 0 0 2 0 0 0 0 2 0
P2: 700 0 600 70 0 700 180 14 0 0 1 0.5
P3: 3 0 0 0 0 3 0 0 0 0 3 0
R0_rect: 0 0 1 0 1 0 -1 0 0
Tr_velo_to_cam: 0 -1 0 0.1 0 0 -1 -0.2 1 0 0 0.3
Tr_imu_to_velo: 1 0 0 4 0 1 0 5 0 0 1 6
"""


def test_calibration_values_and_transforms_by_hand():
    c = parse_calibration(CALIB_TEXT)
    assert c.P1[0, 0] == 2 and c.P3[2, 2] == 3 and c.Tr_imu_to_velo[:, 3].tolist() == [4, 5, 6]
    assert c.intrinsics == (700.0, 700.0, 600.0, 180.0)
    # velodyne (1, 2, 3) -> cam (-2 + 0.1, -3 - 0.2, 1 + 0.3) = (-1.9, -3.2, 1.3) -> R0: (1.3, -3.2, 1.9)
    rect = c.velo_to_rect_points(np.array([[1.0, 2.0, 3.0, 99.0]]))
    assert rect == pytest.approx(np.array([[1.3, -3.2, 1.9]]))
    assert c.rect_to_velo_points(rect) == pytest.approx(np.array([[1.0, 2.0, 3.0]]))
    assert c.velo_to_rect @ c.rect_to_velo == pytest.approx(np.eye(4))
    assert c.velo_to_image == pytest.approx(c.P2 @ c.velo_to_rect)
    # rect (1, 2, 10): (700 + 6000 + 70, 1400 + 1800 + 14, 10.5) -> u = 6770/10.5, v = 3214/10.5
    uv, depth = c.rect_to_image(np.array([[1.0, 2.0, 10.0]]))
    assert uv == pytest.approx(np.array([[6770 / 10.5, 3214 / 10.5]])) and depth == pytest.approx([10.5])
    # back-projection at rect depth 10 inverts P2, P2[2, 3] included
    assert c.image_to_rect(uv, np.array([10.0])) == pytest.approx(np.array([[1.0, 2.0, 10.0]]))
    assert not c.velo_to_rect.flags.writeable and not c.rect_to_velo.flags.writeable
    assert not c.velo_to_image.flags.writeable
    with pytest.raises(ValueError, match="P2 has shape"):
        Calibration(**{**{k: getattr(c, k) for k in ("P0", "P1", "P3", "R0_rect", "Tr_velo_to_cam",
                                                      "Tr_imu_to_velo")}, "P2": np.eye(3)})


def test_calibration_text_round_trip(tmp_path):
    c = parse_calibration(CALIB_TEXT)
    text = c.to_text()
    lines = text.split("\n")
    assert lines[2] == "P2: " + " ".join(f"{v:.12e}" for v in (700, 0, 600, 70, 0, 700, 180, 14, 0, 0, 1, 0.5))
    assert lines[0].startswith("P0: 1.000000000000e+00 ") and text.endswith("\n\n") and len(lines) == 9
    write_calibration(tmp_path / "c.txt", c)
    back = read_calibration(tmp_path / "c.txt")
    for key in ("P0", "P1", "P2", "P3", "R0_rect", "Tr_velo_to_cam", "Tr_imu_to_velo"):
        assert np.array_equal(getattr(back, key), getattr(c, key))
    # blank lines and surrounding spaces are tolerated
    assert parse_calibration("\n  " + CALIB_TEXT.replace("\n", "  \n\n")).P2[2, 3] == 0.5


@pytest.mark.parametrize(("old", "new", "line", "field", "problem"), [
    ("P1: 2", "P9: 2", 2, "P9",
     "unknown calibration matrix; expected one of P0, P1, P2, P3, R0_rect, Tr_velo_to_cam, Tr_imu_to_velo"),
    ("P3: 3 0 0 0 0 3 0 0 0 0 3 0\n", "", None, "P3", "missing calibration matrix P3"),
    ("P3: 3 0 0 0 0 3 0 0 0 0 3 0\nR0_rect: 0 0 1 0 1 0 -1 0 0\n", "", None, "P3",
     "missing calibration matrix P3, R0_rect"),
    ("P3: 3", "P2: 3", 4, "P2", "matrix given twice"),
    ("R0_rect: 0 0 1 0 1 0 -1 0 0", "R0_rect: 0 0 1 0 1 0 -1 0", 5, "R0_rect", "expected 9 values, got 8"),
    ("0 0 1 0.5", "0 0 1", 3, "P2", "expected 12 values, got 11"),
    ("0 0 1 0.5", "0 0 1 x", 3, "P2", "expected a number, got 'x'"),
    ("0 0 1 0.5", "0 0 : 1", 3, "P2", "expected a number, got ':'"),   # the key ends at the first colon
    ("0 0 1 0.5", "0 0 1 nan", 3, "P2", "non-finite value"),
    ("Tr_imu_to_velo:", "Tr_imu_to_velo", 7, None, "expected 'KEY: v1 v2 ...'"),
])
def test_calibration_errors_name_line_and_field(old, new, line, field, problem):
    with pytest.raises(DataFormatError) as info:
        parse_calibration(CALIB_TEXT.replace(old, new, 1), "calib/000007.txt")
    err = info.value
    assert (err.line, err.field, err.problem) == (line, field, problem)
    assert str(err).startswith("calib/000007.txt" + (f":{line}" if line else "") + ": ")


LABEL_TEXT = ("Car 0.12 1 -1.57 100.50 50.25 200.00 150.00 1.50 1.60 3.90 -2.00 1.70 20.00 -1.62\n"
              "\n"
              "Pedestrian 0.00 0 0.30 300.00 60.00 320.00 120.00 1.80 0.60 0.80 4.00 1.60 15.50 0.57   \n")


def test_label_columns_by_hand():
    lab = parse_labels(LABEL_TEXT, "label_2/000001.txt")
    assert len(lab) == 2 and not lab.has_score and lab.score is None
    assert lab.type.tolist() == ["Car", "Pedestrian"]
    assert lab.truncated.tolist() == [0.12, 0.0] and lab.occluded.tolist() == [1, 0]
    assert lab.occluded.dtype == np.int64
    assert lab.alpha.tolist() == [-1.57, 0.3]
    assert lab.bbox[0].tolist() == [100.5, 50.25, 200.0, 150.0]
    assert lab.dimensions[0].tolist() == [1.5, 1.6, 3.9]           # h, w, l
    assert lab.location[1].tolist() == [4.0, 1.6, 15.5]
    assert lab.rotation_y.tolist() == [-1.62, 0.57]
    assert lab.to_text() == LABEL_TEXT.replace("\n\n", "\n").replace("   \n", "\n")
    assert lab.to_text(precision=3).split()[1:3] == ["0.120", "1"]
    scored = parse_labels("Car -1 -1 0.5 1 2 3 4 1.5 1.6 3.9 1 2 30 0.25 0.123456789012345\n", scored=True)
    assert scored.has_score and scored.score.tolist() == [0.123456789012345] and scored.occluded.tolist() == [-1]
    assert scored.to_text().endswith(" 0.25 0.123456789012345\n")   # the score keeps every digit
    assert parse_labels("").to_text() == "" and len(parse_labels("\n  \n")) == 0


def test_label_selection_and_concatenation():
    lab = parse_labels(LABEL_TEXT)
    ped = lab.select(lab.type == "Pedestrian")
    assert len(ped) == 1 and ped.location[0].tolist() == [4.0, 1.6, 15.5]
    both = Labels.concatenate([ped, lab.select(np.array([0]))])
    assert both.type.tolist() == ["Pedestrian", "Car"] and both.bbox[1].tolist() == [100.5, 50.25, 200.0, 150.0]
    assert len(Labels.concatenate([])) == 0 and len(Labels.empty(with_score=True).score) == 0
    scored = parse_labels("Car -1 -1 0.5 1 2 3 4 1.5 1.6 3.9 1 2 30 0.25 0.9\n")
    with pytest.raises(ValueError, match="scored and unscored"):
        Labels.concatenate([lab, scored])
    assert Labels.concatenate([scored, scored]).score.tolist() == [0.9, 0.9]
    with pytest.raises(ValueError, match="bbox has shape"):
        Labels(type=lab.type, truncated=lab.truncated, occluded=lab.occluded, alpha=lab.alpha,
               bbox=lab.bbox[:1], dimensions=lab.dimensions, location=lab.location, rotation_y=lab.rotation_y)


GOOD = "Car 0.00 0 0.50 1.00 2.00 3.00 4.00 1.50 1.60 3.90 1.00 2.00 30.00 0.25"


@pytest.mark.parametrize(("text", "scored", "line", "field", "problem"), [
    (GOOD.replace("Car", "Bus"), None, 1, "type", "unknown object type 'Bus'"),
    (GOOD + " 0.9 7", None, 1, None, "expected 15 or 16 columns, got 17"),
    (GOOD + "\n" + GOOD + " 0.9", None, 2, None, "expected 15 columns like the lines above, got 16"),
    (GOOD, True, 1, None, "expected 16 columns, got 15"),
    (GOOD + " 0.9", False, 1, None, "expected 15 columns, got 16"),
    (GOOD.replace("0.50", "abc"), None, 1, "alpha", "expected a number, got 'abc'"),
    (GOOD.replace("30.00", "inf"), None, 1, "z", "expected a finite number, got 'inf'"),
    ("\n" + GOOD.replace(" 0 0.50", " 4 0.50"), None, 2, "occluded", "expected an integer in -1..3, got '4'"),
    (GOOD.replace(" 0 0.50", " 1.5 0.50"), None, 1, "occluded", "expected an integer in -1..3, got '1.5'"),
])
def test_label_errors_name_line_and_field(text, scored, line, field, problem):
    with pytest.raises(DataFormatError) as info:
        parse_labels(text, "label_2/000003.txt", scored=scored)
    assert (info.value.line, info.value.field) == (line, field) and info.value.problem.startswith(problem)


def test_label_files(tmp_path):
    lab = parse_labels(LABEL_TEXT)
    write_labels(tmp_path / "a.txt", lab, precision=4)
    back = read_labels(tmp_path / "a.txt", scored=False)
    assert back.to_text(4) == lab.to_text(4) and math.isclose(back.bbox[0, 1], 50.25)
    with pytest.raises(DataFormatError, match=r"a\.txt"):
        read_labels(tmp_path / "a.txt", scored=True)
    with pytest.raises(DataFormatError):
        read_labels(tmp_path / "missing.txt")


def test_calibration_edge_inputs(tmp_path):
    c = parse_calibration(CALIB_TEXT)
    listed = Calibration(**{k: getattr(c, k).astype(int).tolist() for k in ("P0", "P1", "P3", "R0_rect")},
                         P2=c.P2, Tr_velo_to_cam=c.Tr_velo_to_cam, Tr_imu_to_velo=c.Tr_imu_to_velo)
    assert listed.P0.dtype == listed.R0_rect.dtype == np.float64
    # (N, 4) points with reflectance: the fourth column is ignored by every transform
    p4 = np.array([[1.3, -3.2, 1.9, 0.7]])
    assert c.rect_to_velo_points(p4) == pytest.approx(np.array([[1.0, 2.0, 3.0]]))
    assert c.rect_to_image(p4)[0] == pytest.approx(c.rect_to_image(p4[:, :3])[0])
    # depth near zero: a point at depth 0.25 projects normally; one at depth 0 is guarded (no inf/NaN)
    uv, depth = c.rect_to_image(np.array([[0.0, 0.0, -0.25], [1.0, 0.0, -0.5]]))
    assert depth == pytest.approx([0.25, 0.0]) and uv[0] == pytest.approx([(-150 + 70) / 0.25, (-45 + 14) / 0.25])
    assert np.isfinite(uv).all() and abs(uv[1, 0]) > 1e12
    bad = tmp_path / "calib.txt"
    bad.write_text(CALIB_TEXT.replace("P1: 2", "P9: 2"))
    with pytest.raises(DataFormatError, match=r"calib\.txt:2: field 'P9'"):
        read_calibration(bad)


def test_label_edge_cases():
    empty = Labels.empty()
    assert empty.score is None and empty.type.dtype == object and empty.occluded.dtype == np.int64
    scored = parse_labels("Car -1 -1 0.5 1 2 3 4 1.5 1.6 3.9 1 2 30 0.25 0.9\n")
    assert Labels.concatenate([scored]).score.tolist() == [0.9]
    with pytest.raises(ValueError, match=r"^cannot concatenate scored and unscored Labels$"):
        Labels.concatenate([parse_labels(LABEL_TEXT), scored])
    with pytest.raises(DataFormatError) as info:
        parse_labels(GOOD.replace(" 0 0.50", " -2 0.50"))
    assert info.value.field == "occluded"
    with pytest.raises(DataFormatError) as info:
        parse_labels(GOOD.replace("Car", "Bus"))
    assert info.value.problem == ("unknown object type 'Bus'; expected one of Car, Van, Truck, Pedestrian, "
                                  "Person_sitting, Cyclist, Tram, Misc, DontCare")


# ---- ground-truth value rules at their boundaries (labels._value_checks / _check_values) -------
TRUNC_RULE = "expected a fraction in 0..1 (or -1 for unknown)"
BBOX_RULE = "expected left <= right and top <= bottom"
DIMS_RULE = "height, width, length must be >= 0 (or -1 -1 -1 for no 3D box)"


def _gt_row(t: str = "0.25", bbox: str = "10 20 30 40", dims: str = "1.5 1.6 3.9") -> str:
    """A ground-truth row: type, truncated, occluded 0, alpha 0.5, bbox, dims, location, rotation_y."""
    return f"Car {t} 0 0.5 {bbox} {dims} 1 2 30 0.25"


@pytest.mark.parametrize(("row", "column", "value"), [
    (_gt_row(t="0"), "truncated", [0.0]),
    (_gt_row(t="1"), "truncated", [1.0]),
    (_gt_row(t="1.00"), "truncated", [1.0]),
    (_gt_row(t="-1"), "truncated", [-1.0]),
    (_gt_row(bbox="10 20 10 40"), "bbox", [10.0, 20.0, 10.0, 40.0]),      # left == right
    (_gt_row(bbox="10 20 30 20"), "bbox", [10.0, 20.0, 30.0, 20.0]),      # top == bottom
    (_gt_row(bbox="7 7 7 7"), "bbox", [7.0, 7.0, 7.0, 7.0]),
    (_gt_row(dims="0 0 0"), "dimensions", [0.0, 0.0, 0.0]),
    (_gt_row(dims="0 1.6 3.9"), "dimensions", [0.0, 1.6, 3.9]),
    (_gt_row(dims="-1 -1 -1"), "dimensions", [-1.0, -1.0, -1.0]),       # KITTI's "no 3D box"
])
def test_ground_truth_boundary_values_are_accepted(row, column, value):
    lab = parse_labels(row + "\n", scored=False)
    assert np.atleast_1d(getattr(lab, column)[0]).tolist() == value


@pytest.mark.parametrize(("row", "field", "problem"), [
    (_gt_row(t="1.5"), "truncated", f"{TRUNC_RULE}, got 1.5"),
    (_gt_row(t="1.01"), "truncated", f"{TRUNC_RULE}, got 1.01"),
    (_gt_row(t="-0.01"), "truncated", f"{TRUNC_RULE}, got -0.01"),
    (_gt_row(t="-1.5"), "truncated", f"{TRUNC_RULE}, got -1.5"),
    (_gt_row(bbox="31 20 30 40"), "bbox", f"{BBOX_RULE}, got 31 20 30 40"),   # left > right only
    (_gt_row(bbox="10 41 30 40"), "bbox", f"{BBOX_RULE}, got 10 41 30 40"),   # top > bottom only
    (_gt_row(dims="-0.01 1.6 3.9"), "dimensions", f"{DIMS_RULE}, got -0.01 1.6 3.9"),
    (_gt_row(dims="1.5 1.6 -3.9"), "dimensions", f"{DIMS_RULE}, got 1.5 1.6 -3.9"),
    (_gt_row(dims="-1 -1 0"), "dimensions", f"{DIMS_RULE}, got -1 -1 0"),     # not the placeholder
    (_gt_row(dims="-2 -1 -1"), "dimensions", f"{DIMS_RULE}, got -2 -1 -1"),
    (_gt_row(dims="-1 -1 -1.5"), "dimensions", f"{DIMS_RULE}, got -1 -1 -1.5"),
])
def test_ground_truth_value_errors_exact_message(row, field, problem):
    # the bad row is the second non-blank row, on line 4
    text = f"\n{_gt_row()}\n\n{row}\n"
    with pytest.raises(DataFormatError) as info:
        parse_labels(text, "label_2/000009.txt", scored=False)
    assert str(info.value) == f"label_2/000009.txt:4: field '{field}': {problem}"
    assert (info.value.line, info.value.field, info.value.problem) == (4, field, problem)
    with pytest.raises(DataFormatError) as info:             # the default file name
        parse_labels(row)
    assert str(info.value) == f"<string>:1: field '{field}': {problem}"


@pytest.mark.parametrize(("rows", "line", "field", "got"), [
    # one row breaking several rules: the first rule (truncated, bbox, dimensions) is named
    ([_gt_row(t="2", bbox="30 20 10 40")], 1, "truncated", "2"),
    ([_gt_row(t="2", dims="1 -1 1")], 1, "truncated", "2"),
    ([_gt_row(bbox="30 20 10 40", dims="1 -1 1")], 1, "bbox", "30 20 10 40"),
    # several bad rows: the first row is named, whatever rule it breaks
    ([_gt_row(), _gt_row(dims="1 -1 1"), _gt_row(t="2"), _gt_row(bbox="30 20 10 40")], 2, "dimensions", "1 -1 1"),
    ([_gt_row(bbox="30 20 10 40"), _gt_row(t="2"), _gt_row(t="3")], 1, "bbox", "30 20 10 40"),
    ([_gt_row(), _gt_row(t="3"), _gt_row(t="2"), _gt_row(bbox="30 20 10 40")], 2, "truncated", "3"),
])
def test_ground_truth_first_bad_row_then_first_rule_is_named(rows, line, field, got):
    with pytest.raises(DataFormatError) as info:
        parse_labels("\n".join(rows), "gt.txt")
    assert (info.value.line, info.value.field) == (line, field)
    assert info.value.problem.endswith(f", got {got}")


def test_result_rows_skip_the_ground_truth_rules():
    bad = _gt_row(t="2", bbox="30 20 10 40", dims="-1 -2 -3")
    for scored in (True, None):
        lab = parse_labels(bad + " 0.75\n", scored=scored)
        assert lab.truncated.tolist() == [2.0] and lab.dimensions.tolist() == [[-1.0, -2.0, -3.0]]
    with pytest.raises(DataFormatError, match=r"^<string>:1: field 'truncated': "):
        parse_labels(bad)


def test_impossible_rows_by_hand():
    rows = [_gt_row(), _gt_row(t="1.5"), _gt_row(bbox="30 20 10 40"), _gt_row(dims="1 -1 1"),
            _gt_row(t="-1", dims="-1 -1 -1"), _gt_row(t="1", bbox="5 5 5 5", dims="0 0 0"),
            _gt_row(t="2", bbox="30 20 10 40", dims="1 -1 1")]
    numeric = np.array([[float(v) for v in row.split()[1:]] for row in rows])
    assert impossible_rows(numeric).tolist() == [False, True, True, True, False, False, True]
    assert impossible_rows(numeric[:1]).tolist() == [False] and impossible_rows(numeric[:0]).tolist() == []


def test_write_labels_default_is_the_devkit_two_decimals(tmp_path):
    write_labels(tmp_path / "b.txt", parse_labels(LABEL_TEXT))
    assert (tmp_path / "b.txt").read_text() == LABEL_TEXT.replace("\n\n", "\n").replace("   \n", "\n")
