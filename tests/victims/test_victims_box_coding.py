"""F-PN heading/size coding against hand-computed bins (reference §1.4-§1.5)."""

from __future__ import annotations

import numpy as np
import pytest

from robustbench3d.geometry import box_corners
from robustbench3d.victims.fpointnet.box_coding import (
    MEAN_SIZES,
    NUM_HEADING_BIN,
    NUM_SIZE_CLUSTER,
    SIZE_TYPES,
    angle_to_class,
    car_one_hot,
    class_to_angle,
    class_to_size,
    corners_from_center,
    one_hot,
    size_to_class,
)

D = np.pi / 180


@pytest.mark.parametrize(("deg", "cls", "res_deg"), [
    (0.0, 0, 0.0),        # centre of bin 0
    (14.0, 0, 14.0),
    (15.0, 1, -15.0),     # bin boundary belongs to the upper bin, residual -15 deg
    (16.0, 1, -14.0),
    (30.0, 1, 0.0),
    (90.0, 3, 0.0),
    (180.0, 6, 0.0),
    (-10.0, 0, -10.0),    # 350 deg -> shifted 5 deg -> bin 0
    (345.0, 0, -15.0),    # 345 + 15 = 360 -> 0 -> bin 0, residual -15
    (-90.0, 9, 0.0),      # 270 deg
    (400.0, 1, 10.0),     # 40 deg
])
def test_heading_bins_hand_computed(deg, cls, res_deg):
    c, r = angle_to_class(deg * D)
    assert int(c) == cls
    assert float(r) == pytest.approx(res_deg * D, abs=1e-9)


def test_heading_round_trip_and_ranges():
    rng = np.random.default_rng(0)
    a = rng.uniform(-4 * np.pi, 4 * np.pi, 10_000)
    c, r = angle_to_class(a)
    assert c.min() >= 0 and c.max() <= NUM_HEADING_BIN - 1
    assert (r >= -np.pi / 12 - 1e-12).all() and (r < np.pi / 12 + 1e-12).all()
    back = class_to_angle(c, r)
    assert (back > -np.pi - 1e-12).all() and (back <= np.pi + 1e-12).all()
    assert np.allclose(np.cos(back), np.cos(a)) and np.allclose(np.sin(back), np.sin(a))
    # just below 2*pi does not overflow into a 13th bin
    c, r = angle_to_class(np.nextafter(2 * np.pi, 0))
    assert int(c) == 0 and abs(float(r)) < 1e-9


def test_size_table_and_coding():
    assert NUM_SIZE_CLUSTER == len(SIZE_TYPES) == len(MEAN_SIZES) == 8
    # values typed from the reference table (l, w, h in m)
    assert MEAN_SIZES[0] == pytest.approx([3.88311640418, 1.62856739989, 1.52563191462])
    assert MEAN_SIZES[SIZE_TYPES.index("Cyclist")] == pytest.approx([1.76282397, 0.59706367, 1.73698127])
    assert MEAN_SIZES[SIZE_TYPES.index("Tram")] == pytest.approx([16.17150617, 2.53246914, 3.53079012])
    cls, res = size_to_class(np.array([[3.9, 1.6, 1.5], [0.8, 0.6, 1.8]]), ["Car", "Pedestrian"])
    assert cls.tolist() == [0, 3]
    assert res[0] == pytest.approx([3.9 - 3.88311640418, 1.6 - 1.62856739989, 1.5 - 1.52563191462])
    assert res[1] == pytest.approx([0.8 - 0.84422524, 0.6 - 0.66068622, 1.8 - 1.76255119])
    assert class_to_size(cls, res) == pytest.approx(np.array([[3.9, 1.6, 1.5], [0.8, 0.6, 1.8]]))
    with pytest.raises(KeyError):
        size_to_class(np.ones((1, 3)), ["DontCare"])


def test_one_hot():
    assert one_hot(["Car", "Pedestrian", "Cyclist", "Van"]).tolist() == [
        [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, 0]]
    cars = car_one_hot(2)
    assert cars.dtype == np.float32 and cars.tolist() == [[1, 0, 0], [1, 0, 0]]
    assert car_one_hot(0).shape == (0, 3)


def test_corners_match_the_kitti_box_of_the_same_object():
    """corners_from_center(geometric centre) equals geometry.box_corners(bottom centre), corner by corner."""
    rng = np.random.default_rng(1)
    for _ in range(20):
        h, w, l = rng.uniform(1, 5, 3)
        bottom = rng.uniform(-10, 10, 3)
        ry = rng.uniform(-np.pi, np.pi)
        centre = bottom - np.array([0.0, h / 2, 0.0])
        ours = corners_from_center(centre[None], np.array([ry]), np.array([[l, w, h]]))
        ref = box_corners(np.array([[h, w, l]]), bottom[None], np.array([ry]))
        assert np.allclose(ours, ref)


def test_float32_network_outputs_decode_in_float64():
    """Heads arrive as float32 (torch, ONNX Runtime) and class ids may sit in a float array; the
    decode is float64 arithmetic on the exact input values, by hand."""
    cls32, zero32 = np.array([11.0, 1.0], dtype=np.float32), np.zeros(2, dtype=np.float32)
    angle = class_to_angle(cls32, zero32, to_label_format=False)
    assert angle.dtype == np.float64
    assert angle.tolist() == pytest.approx([11 * np.pi / 6, np.pi / 6], rel=1e-15)   # float32 is off by ~2e-8
    assert class_to_angle(cls32, zero32).tolist() == pytest.approx([-np.pi / 6, np.pi / 6], rel=1e-14)
    assert class_to_size(np.array([3.0, 0.0]), np.zeros((2, 3))).tolist() == [
        [0.84422524, 0.66068622, 1.76255119], [3.88311640418, 1.62856739989, 1.52563191462]]
    h32 = np.float32(0.3)
    a = float(h32)                                           # the float32's exact value
    corners = corners_from_center(np.zeros((1, 3)), np.array([h32]), np.array([[4.0, 2.0, 1.0]]))
    assert corners.dtype == np.float64
    # corner 0: local (l/2, h/2, w/2) = (2, 0.5, 1) rotated by a about y
    assert corners[0, 0].tolist() == pytest.approx(
        [2 * np.cos(a) + np.sin(a), 0.5, -2 * np.sin(a) + np.cos(a)], rel=1e-13)
