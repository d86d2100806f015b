"""KITTI file formats: real files, round trips, and errors that name file, line and field."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from robustbench3d.errors import DataFormatError
from robustbench3d.kitti import (
    CALIB_KEYS,
    KittiDataset,
    Labels,
    parse_calibration,
    parse_labels,
    read_calibration,
    read_image,
    read_labels,
    read_scan,
    read_split,
    write_calibration,
    write_image,
    write_labels,
    write_scan,
    write_split,
)
from robustbench3d.kitti.labels import type_mask

FRAMES = [f"{i:06d}" for i in range(6)]


# ---- labels ---------------------------------------------------------------------------
def test_real_labels_parse_and_match_text(kitti_samples: Path) -> None:
    path = kitti_samples / "training/label_2/000001.txt"
    labels = read_labels(path, scored=False)
    assert list(labels.type) == ["Truck", "Car", "Cyclist"] + ["DontCare"] * 4
    # Second line, column by column (hand-read from the file).
    assert labels.truncated[1] == 0.0 and labels.occluded[1] == 0 and labels.alpha[1] == 1.85
    np.testing.assert_array_equal(labels.bbox[1], [387.63, 181.54, 423.81, 203.12])
    np.testing.assert_array_equal(labels.dimensions[1], [1.67, 1.87, 3.69])
    np.testing.assert_array_equal(labels.location[1], [-16.53, 2.39, 58.49])
    assert labels.rotation_y[1] == 1.57 and labels.score is None
    assert labels.occluded[2] == 3  # Cyclist with 'unknown' occlusion


@pytest.mark.parametrize("frame", FRAMES)
def test_label_round_trip_is_exact(kitti_samples: Path, tmp_path: Path, frame: str) -> None:
    src = kitti_samples / "training/label_2" / f"{frame}.txt"
    labels = read_labels(src)
    write_labels(tmp_path / "x.txt", labels)
    again = read_labels(tmp_path / "x.txt")
    for field in ("truncated", "occluded", "alpha", "bbox", "dimensions", "location", "rotation_y"):
        np.testing.assert_array_equal(getattr(again, field), getattr(labels, field), err_msg=field)
    assert list(again.type) == list(labels.type)


def test_result_files_with_trailing_spaces_and_blank_lines(kitti_samples: Path) -> None:
    res = kitti_samples / "results/pointgnn_car_val/data"
    dets = read_labels(res / "000001.txt", scored=True)
    assert len(dets) == 2 and dets.has_score
    assert dets.score[0] == pytest.approx(4.10767303327915)
    assert dets.occluded.tolist() == [-1, -1]
    empty = read_labels(res / "000005.txt", scored=True)
    assert len(empty) == 0 and empty.has_score


def test_scored_round_trip_keeps_score_order(tmp_path: Path) -> None:
    row = "Car -1 -1 0 1 2 30 40 1.5 1.6 3.9 1 1.7 20 0.1 "
    text = row + "0.123456789\n" + row + "0.123456788\n"
    dets = parse_labels(text, scored=True)
    write_labels(tmp_path / "r.txt", dets)
    again = read_labels(tmp_path / "r.txt", scored=True)
    assert again.score[0] > again.score[1]


def test_labels_of_types_keeps_the_rows_of_those_types_in_order() -> None:
    rows = ["Car", "Van", "DontCare", "Car", "Pedestrian"]
    text = "".join(f"{t} 0.00 0 0.00 {i} 0 {i + 10} 10 1.5 1.6 3.9 0 1.7 {i} 0.0\n" for i, t in enumerate(rows))
    labels = parse_labels(text)
    assert type_mask(labels.type, ("Car", "Pedestrian")).tolist() == [True, False, False, True, True]
    assert type_mask(labels.type, iter(["Van"])).tolist() == [False, True, False, False, False]
    cars = labels.of_types(["Car"])
    assert cars.type.tolist() == ["Car", "Car"] and cars.bbox[:, 0].tolist() == [0.0, 3.0]
    assert len(labels.of_types([])) == 0 and len(Labels.empty().of_types(["Car"])) == 0


def test_result_text_has_two_decimals_and_exact_scores() -> None:
    row = "Car -1 -1 0.123 1.005 2 30 40 1.5 1.6 3.9 1 1.7 20 0.1 0.123456789\n"
    line = parse_labels(row, scored=True).to_text()
    assert line == "Car -1.00 -1 0.12 1.00 2.00 30.00 40.00 1.50 1.60 3.90 1.00 1.70 20.00 0.10 0.123456789\n"


GOOD = "Car 0.00 0 1.85 387.63 181.54 423.81 203.12 1.67 1.87 3.69 -16.53 2.39 58.49 1.57"


@pytest.mark.parametrize(
    ("text", "line", "field", "fragment"),
    [
        (GOOD + "\n" + GOOD.replace(" 1.57", ""), 2, None, "expected 15 columns like the lines above, got 14"),
        (GOOD.replace(" 1.57", ""), 1, None, "expected 15 or 16 columns, got 14"),
        (GOOD.replace("58.49", "5B.49"), 1, "z", "expected a number, got '5B.49'"),
        (GOOD.replace("387.63", "nan"), 1, "bbox_left", "finite"),
        (GOOD.replace("Car", "Bus"), 1, "type", "unknown object type 'Bus'"),
        (GOOD.replace(" 0 1.85", " 1.5 1.85"), 1, "occluded", "integer"),
        ("\n\n" + GOOD + " 0.9\n" + GOOD, 4, None, "expected 16 columns like the lines above, got 15"),
    ],
)
def test_label_errors_name_file_line_field(tmp_path: Path, text: str, line: int, field: str | None,
                                           fragment: str) -> None:
    path = tmp_path / "000007.txt"
    path.write_text(text)
    with pytest.raises(DataFormatError) as info:
        read_labels(path)
    err = info.value
    assert err.path == path and err.line == line and err.field == field
    assert fragment in str(err) and str(path) in str(err)


def test_scored_flag_is_enforced(tmp_path: Path) -> None:
    path = tmp_path / "a.txt"
    path.write_text(GOOD + "\n")
    with pytest.raises(DataFormatError, match="expected 16 columns, got 15"):
        read_labels(path, scored=True)
    path.write_text(GOOD + " 0.5\n")
    with pytest.raises(DataFormatError, match="expected 15 columns, got 16"):
        read_labels(path, scored=False)


def test_blank_and_whitespace_only_file_is_empty() -> None:
    assert len(parse_labels("\n   \n\t\n")) == 0


# ---- calibration ------------------------------------------------------------------------
@pytest.mark.parametrize("frame", FRAMES)
def test_calib_round_trip_is_byte_exact(kitti_samples: Path, tmp_path: Path, frame: str) -> None:
    src = kitti_samples / "training/calib" / f"{frame}.txt"
    calib = read_calibration(src)
    write_calibration(tmp_path / "c.txt", calib)
    assert (tmp_path / "c.txt").read_bytes() == src.read_bytes()
    again = read_calibration(tmp_path / "c.txt")
    for key in CALIB_KEYS:
        np.testing.assert_array_equal(getattr(again, key), getattr(calib, key))


def test_calib_values_and_transforms(kitti_samples: Path) -> None:
    calib = read_calibration(kitti_samples / "training/calib/000001.txt")
    fu, fv, cu, cv = calib.intrinsics
    assert (fu, fv, cu, cv) == (721.5377, 721.5377, 609.5593, 172.854)
    rng = np.random.default_rng(0)
    velo = rng.uniform([-50, -30, -3], [70, 30, 3], size=(500, 3))
    np.testing.assert_allclose(calib.rect_to_velo_points(calib.velo_to_rect_points(velo)), velo, atol=1e-9)
    rect = calib.velo_to_rect_points(velo[velo[:, 0] > 5])
    uv, _ = calib.rect_to_image(rect)
    np.testing.assert_allclose(calib.image_to_rect(uv, rect[:, 2]), rect, atol=1e-9)
    # Velodyne origin sits ~0.27 m behind and ~0.07 m above camera 0 (reference.md §4.5).
    origin = calib.velo_to_rect_points(np.zeros((1, 3)))[0]
    np.testing.assert_allclose(origin, [-0.003, -0.075, -0.272], atol=2e-3)


def _calib_text(kitti_samples: Path) -> str:
    return (kitti_samples / "training/calib/000001.txt").read_text()


def test_calib_missing_matrix(kitti_samples: Path, tmp_path: Path) -> None:
    text = "\n".join(line for line in _calib_text(kitti_samples).split("\n") if not line.startswith("R0_rect"))
    path = tmp_path / "c.txt"
    path.write_text(text)
    with pytest.raises(DataFormatError, match="missing calibration matrix R0_rect") as info:
        read_calibration(path)
    assert info.value.field == "R0_rect"


@pytest.mark.parametrize(
    ("mutate", "line", "field", "fragment"),
    [
        (lambda s: s.replace("P2: 7.215377000000e+02", "P2: 7.2x5377000000e+02"), 3, "P2", "expected a number"),
        (lambda s: s.replace("R0_rect: 9.999239000000e-01 ", "R0_rect: "), 5, "R0_rect", "expected 9 values, got 8"),
        (lambda s: s.replace("Tr_imu_to_velo", "Tr_imu_to_cam"), 7, "Tr_imu_to_cam", "unknown calibration matrix"),
        (lambda s: s.replace("P1:", "P0:"), 2, "P0", "matrix given twice"),
        (lambda s: "garbage line\n" + s, 1, None, "expected 'KEY: v1 v2 ...'"),
    ],
)
def test_calib_errors(kitti_samples: Path, tmp_path: Path, mutate, line: int, field: str | None,
                      fragment: str) -> None:
    path = tmp_path / "c.txt"
    path.write_text(mutate(_calib_text(kitti_samples)))
    with pytest.raises(DataFormatError) as info:
        read_calibration(path)
    assert info.value.line == line and info.value.field == field and fragment in str(info.value)


def test_parse_calibration_from_string_names_source() -> None:
    with pytest.raises(DataFormatError, match="<string>"):
        parse_calibration("P0: 1 2 3\n")


# ---- scans, images, splits ----------------------------------------------------------------
def test_real_scans(kitti_samples: Path) -> None:
    counts = [len(read_scan(kitti_samples / "training/velodyne" / f"{f}.bin")) for f in FRAMES]
    assert counts == [115384, 120268, 126891, 113110, 115976, 125086]  # SOURCE.md table


def test_scan_round_trip_and_bad_size(tmp_path: Path) -> None:
    scan = np.random.default_rng(1).normal(size=(1000, 4)).astype(np.float32)
    write_scan(tmp_path / "s.bin", scan)
    np.testing.assert_array_equal(read_scan(tmp_path / "s.bin"), scan)
    (tmp_path / "bad.bin").write_bytes(scan.tobytes()[:-4])
    with pytest.raises(DataFormatError, match="not a multiple of 16"):
        read_scan(tmp_path / "bad.bin")
    nan_scan = scan.copy()
    nan_scan[7, 2] = np.nan
    (tmp_path / "nan.bin").write_bytes(nan_scan.tobytes())
    with pytest.raises(DataFormatError, match="point 7"):
        read_scan(tmp_path / "nan.bin")


def test_both_image_sizes_load(kitti_samples: Path) -> None:
    shapes = {read_image(kitti_samples / "training/image_2" / f"{f}.png").shape for f in FRAMES}
    assert shapes == {(370, 1224, 3), (375, 1242, 3)}


def test_image_round_trip_and_unreadable(tmp_path: Path) -> None:
    img = np.random.default_rng(2).integers(0, 256, size=(37, 50, 3), dtype=np.uint8)
    write_image(tmp_path / "i.png", img)
    np.testing.assert_array_equal(read_image(tmp_path / "i.png"), img)
    (tmp_path / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 40)
    with pytest.raises(DataFormatError, match="unreadable image") as info:
        read_image(tmp_path / "broken.png")
    assert info.value.path == tmp_path / "broken.png"


def test_real_split_lists(kitti_samples: Path) -> None:
    train = read_split(kitti_samples / "ImageSets/train.txt")
    val = read_split(kitti_samples / "ImageSets/val.txt")
    assert (len(train), len(val)) == (3712, 3769)
    assert not set(train) & set(val) and len(set(train) | set(val)) == 7481
    assert val[:3] == ["000001", "000002", "000004"]


@pytest.mark.parametrize("final_newline", [True, False])
def test_split_with_or_without_final_newline(tmp_path: Path, final_newline: bool) -> None:
    path = tmp_path / "s.txt"
    path.write_text("000001\n000002" + ("\n" if final_newline else ""))
    assert read_split(path) == ["000001", "000002"]
    write_split(path, ["000003", "000004"])
    assert path.read_text() == "000003\n000004\n"


def test_split_bad_id(tmp_path: Path) -> None:
    path = tmp_path / "s.txt"
    path.write_text("000001\n12\n")
    with pytest.raises(DataFormatError) as info:
        read_split(path)
    assert info.value.line == 2 and info.value.field == "frame_id"


# ---- dataset ---------------------------------------------------------------------------------
def test_dataset_is_lazy_and_complete(kitti_samples: Path) -> None:
    ds = KittiDataset(kitti_samples, split=None)
    assert ds.frame_ids == FRAMES
    frame = ds[1]
    assert frame.frame_id == "000001" and frame.image_size == (1242, 375)
    assert frame.scan.dtype == np.float32 and frame.labels is not None and len(frame.labels) == 7
    val = KittiDataset(kitti_samples, split="val")
    assert len(val) == 3769  # only the list is read
    with pytest.raises(DataFormatError, match=r"007480\.png: file not found"):
        val.frame(val.frame_ids[-1])


def test_dataset_missing_root(tmp_path: Path) -> None:
    with pytest.raises(DataFormatError, match="KITTI layout"):
        KittiDataset(tmp_path / "nowhere")
