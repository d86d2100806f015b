"""Silent corruption in the KITTI data layer: pixel formats converted exactly or refused, images
that cannot belong to their calibration, label values no object has. Hand-built files only."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from robustbench3d.errors import DataFormatError
from robustbench3d.eval import evaluate_dirs
from robustbench3d.kitti import KittiDataset, parse_labels, read_image, read_labels
from robustbench3d.kitti.image import check_image_fits_calibration
from robustbench3d.testing import SIMPLE_CALIB, write_kitti_frame


def _png(arr: np.ndarray, colour_type: int) -> bytes:
    """A 16-bit PNG written by hand (Pillow cannot write 16-bit colour): filter 0 on every row."""
    h, w = arr.shape[:2]
    raw = b"".join(b"\x00" + arr[y].astype(">u2").tobytes() for y in range(h))

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data))

    header = struct.pack(">IIBBBBB", w, h, 16, colour_type, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")


# ---- pixel formats ------------------------------------------------------------------------------
def test_16bit_grey_png_keeps_the_high_byte(tmp_path: Path) -> None:
    values = np.array([[0, 255, 256, 257, 511], [32767, 32768, 65280, 65534, 65535]], dtype=np.uint16)
    path = tmp_path / "grey16.png"
    Image.fromarray(values).save(path)
    assert Image.open(path).mode == "I;16"  # really a 16-bit file
    img = read_image(path)
    # v >> 8, by hand: 0 255 256 257 511 -> 0 0 1 1 1; 32767 32768 65280 65534 65535 -> 127 128 255 255 255
    expected = np.array([[0, 0, 1, 1, 1], [127, 128, 255, 255, 255]], dtype=np.uint8)
    assert img.dtype == np.uint8 and img.shape == (2, 5, 3)
    for c in range(3):
        np.testing.assert_array_equal(img[:, :, c], expected)


def test_8bit_widened_to_16bit_comes_back_unchanged(tmp_path: Path) -> None:
    v8 = np.arange(256, dtype=np.uint16).reshape(16, 16)
    path = tmp_path / "wide.png"
    Image.fromarray(v8 * 257).save(path)
    np.testing.assert_array_equal(read_image(path)[:, :, 1], v8.astype(np.uint8))


def test_16bit_colour_png_keeps_the_high_byte(tmp_path: Path) -> None:
    rgb = np.array([[[0, 257, 65535], [300, 511, 65280]]], dtype=np.uint16)
    path = tmp_path / "rgb16.png"
    path.write_bytes(_png(rgb, colour_type=2))
    np.testing.assert_array_equal(read_image(path), [[[0, 1, 255], [1, 1, 255]]])


def test_grey_and_palette_become_rgb_exactly(tmp_path: Path) -> None:
    grey = tmp_path / "l.png"
    Image.fromarray(np.array([[0, 7, 128, 255]], dtype=np.uint8)).save(grey)
    np.testing.assert_array_equal(read_image(grey), [[[0] * 3, [7] * 3, [128] * 3, [255] * 3]])

    pal = Image.new("P", (3, 1))
    pal.putpalette([10, 20, 30, 40, 50, 60, 70, 80, 90] + [0] * (768 - 9))
    pal.putdata([2, 0, 1])
    pal.save(tmp_path / "p.png")
    np.testing.assert_array_equal(read_image(tmp_path / "p.png"), [[[70, 80, 90], [10, 20, 30], [40, 50, 60]]])

    la = tmp_path / "la.png"
    Image.fromarray(np.array([[[9, 255], [200, 255]]], dtype=np.uint8), "LA").save(la)
    np.testing.assert_array_equal(read_image(la), [[[9] * 3, [200] * 3]])


def test_transparent_pixels_are_refused(tmp_path: Path) -> None:
    path = tmp_path / "rgba.png"
    Image.fromarray(np.array([[[1, 2, 3, 255], [4, 5, 6, 0]]], dtype=np.uint8), "RGBA").save(path)
    with pytest.raises(DataFormatError, match=r"rgba\.png: mode RGBA image has transparent pixels \(first at x=1, y=0"):
        read_image(path)


def test_cmyk_is_refused_naming_the_file(tmp_path: Path) -> None:
    path = tmp_path / "cmyk.tif"
    Image.new("CMYK", (4, 2), (0, 255, 0, 0)).save(path)
    with pytest.raises(DataFormatError, match=r"cmyk\.tif: pixel mode CMYK has no exact 8-bit RGB equivalent"):
        read_image(path)


def test_image_path_that_is_a_directory(tmp_path: Path) -> None:
    (tmp_path / "x.png").mkdir()
    with pytest.raises(DataFormatError, match=r"x\.png: is a directory, expected a file"):
        read_image(tmp_path / "x.png")


# ---- image size against the calibration --------------------------------------------------------
# SIMPLE_CALIB's principal point is (609.5593, 172.854): it must lie in [W/4, 3W/4] x [H/4, 3H/4].
@pytest.mark.parametrize(("size", "ok"), [
    ((1242, 375), True), ((1224, 370), True),
    ((813, 375), True), ((812, 375), False),  # 3 * 813 / 4 = 609.75 >= c_u; 3 * 812 / 4 = 609.0 < c_u
    ((2438, 375), True), ((2439, 375), False),  # 2438 / 4 = 609.5 <= c_u; 2439 / 4 = 609.75 > c_u
    ((1242, 231), True), ((1242, 230), False),  # 3 * 231 / 4 = 173.25 >= c_v; 172.5 < c_v
    ((1242, 691), True), ((1242, 692), False),  # 691 / 4 = 172.75 <= c_v; 173.0 > c_v
    ((621, 187), False),  # a half-size image
])
def test_principal_point_band(size: tuple[int, int], ok: bool) -> None:
    if ok:
        check_image_fits_calibration(size, SIMPLE_CALIB, "img.png")
    else:
        with pytest.raises(DataFormatError, match=r"img\.png: field 'size': image \d+x\d+ does not match"):
            check_image_fits_calibration(size, SIMPLE_CALIB, "img.png")


def _one_frame(root: Path, image: np.ndarray, labels: str = "") -> KittiDataset:
    write_kitti_frame(root, "000000", scan=np.zeros((3, 4), dtype=np.float32), labels=labels)
    Image.fromarray(image).save(root / "training" / "image_2" / "000000.png")  # replaces the default image
    return KittiDataset(root, split=None)


def test_dataset_refuses_an_image_of_the_wrong_size(tmp_path: Path) -> None:
    ds = _one_frame(tmp_path, np.zeros((187, 621, 3), dtype=np.uint8))
    msg = r"image_2/000000\.png: field 'size': image 621x187 does not match its calibration \(000000\.txt\)"
    with pytest.raises(DataFormatError, match=msg):
        ds.image("000000")
    with pytest.raises(DataFormatError, match=msg):
        ds.frame("000000")


def test_dataset_frame_converts_16bit_image(tmp_path: Path) -> None:
    grey = np.full((375, 1242), 40000, dtype=np.uint16)
    ds = _one_frame(tmp_path, grey)
    frame = ds.frame("000000")
    assert frame.image.shape == (375, 1242, 3) and np.all(frame.image == 40000 >> 8)  # 156, not 255


# ---- label values ------------------------------------------------------------------------------
CAR = "Car 0.00 0 -1.57 500.00 150.00 700.00 250.00 1.50 1.60 3.90 0.00 1.65 15.00 -1.57"
DONTCARE = "DontCare -1 -1 -10 503.89 169.71 590.61 190.13 -1 -1 -1 -1000 -1000 -1000 -10"


def test_dontcare_and_no_3d_placeholder_rows_are_accepted() -> None:
    no3d = "Car 0.00 0 -10 500.00 150.00 700.00 250.00 -1 -1 -1 -1000 -1000 -1000 -10"
    labels = parse_labels("\n".join([CAR, DONTCARE, no3d]) + "\n", scored=False)
    np.testing.assert_array_equal(labels.dimensions, [[1.5, 1.6, 3.9], [-1, -1, -1], [-1, -1, -1]])


@pytest.mark.parametrize(("row", "field", "message"), [
    ("Car 0.00 0 -1.57 500 150 700 250 1.50 -1.60 3.90 0 1.65 15 -1.57", "dimensions",
     "height, width, length must be >= 0 (or -1 -1 -1 for no 3D box), got 1.50 -1.60 3.90"),
    ("Car 0.00 0 -1.57 500 150 700 250 -1 -1 -2 0 1.65 15 -1.57", "dimensions", "got -1 -1 -2"),
    ("DontCare -1 -1 -10 500 150 700 250 -0.5 1 1 -1000 -1000 -1000 -10", "dimensions", "got -0.5 1 1"),
    ("Car 1.50 0 -1.57 500 150 700 250 1.5 1.6 3.9 0 1.65 15 -1.57", "truncated",
     "expected a fraction in 0..1 (or -1 for unknown), got 1.50"),
    ("Car 0.00 0 -1.57 700 150 500 250 1.5 1.6 3.9 0 1.65 15 -1.57", "bbox",
     "expected left <= right and top <= bottom, got 700 150 500 250"),
    ("Car 0.00 0 -1.57 500 150 700 250 nan 1.6 3.9 0 1.65 15 -1.57", "height", "expected a finite number, got 'nan'"),
])
def test_impossible_ground_truth_values_name_file_line_field(tmp_path: Path, row: str, field: str,
                                                            message: str) -> None:
    path = tmp_path / "000007.txt"
    path.write_text(f"{CAR}\n{DONTCARE}\n{row}\n")
    with pytest.raises(DataFormatError) as info:
        read_labels(path, scored=False)
    text = str(info.value)
    assert text.startswith(f"{path}:3: field '{field}': ") and text.endswith(message)


def test_result_rows_are_not_held_to_ground_truth_rules() -> None:
    """A detector's negative size is a bad prediction to score, not a broken file."""
    labels = parse_labels("Car -1 -1 -1.57 500 150 700 250 1.5 -0.2 3.9 0 1.65 15 -1.57 0.9\n", scored=True)
    assert labels.dimensions[0, 1] == -0.2


def test_eval_fast_path_refuses_what_the_data_layer_refuses(tmp_path: Path) -> None:
    gt, pred = tmp_path / "gt", tmp_path / "pred"
    gt.mkdir()
    pred.mkdir()
    (gt / "000000.txt").write_text(f"{CAR}\n")
    (gt / "000001.txt").write_text(f"{DONTCARE}\nCar 0.00 0 -1.57 500 150 700 250 1.5 1.6 -3.9 0 1.65 15 -1.57\n")
    with pytest.raises(DataFormatError, match=r"000001\.txt:2: field 'dimensions': .*got 1\.5 1\.6 -3\.9"):
        evaluate_dirs(gt, pred)
