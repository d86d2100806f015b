"""Box geometry: hand-computed cases, brute-force references and real KITTI frames."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import Delaunay

from robustbench3d.geometry import (
    alpha_from_rotation_y,
    box_corners,
    points_in_boxes,
    project_boxes_to_image,
    wrap_angle,
)
from robustbench3d.kitti import Calibration, KittiDataset


def _iou_2d(a: np.ndarray, b: np.ndarray) -> float:
    w = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    h = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = w * h
    return inter / ((a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter)


def test_corners_hand_computed() -> None:
    # h=1, w=2, l=4 at the origin, ry=0: length along x, width along z, top at y=-1.
    c = box_corners([[1.0, 2.0, 4.0]], [[0.0, 0.0, 0.0]], [0.0])[0]
    np.testing.assert_allclose(c[0], [2, 0, 1])
    np.testing.assert_allclose(c[2], [-2, 0, -1])
    np.testing.assert_allclose(c[4], [2, -1, 1])
    # ry = +pi/2: R maps local +x to rect -z (x' = c x + s z, z' = -s x + c z).
    c = box_corners([[1.0, 2.0, 4.0]], [[10.0, 1.5, 20.0]], [np.pi / 2])[0]
    np.testing.assert_allclose(c[0], [10 + 1, 1.5, 20 - 2], atol=1e-12)
    assert c[:, 1].max() == pytest.approx(1.5) and c[:, 1].min() == pytest.approx(0.5)


def test_points_in_boxes_matches_convex_hull_reference() -> None:
    rng = np.random.default_rng(3)
    dims = rng.uniform([0.5, 0.5, 0.5], [3, 3, 6], size=(5, 3))
    loc = rng.uniform(-5, 5, size=(5, 3))
    ry = rng.uniform(-np.pi, np.pi, size=5)
    pts = rng.uniform(-9, 9, size=(4000, 3))
    inside = points_in_boxes(pts, dims, loc, ry)
    corners = box_corners(dims, loc, ry)
    for k in range(5):
        ref = Delaunay(corners[k]).find_simplex(pts) >= 0
        # Points within 1e-9 of a face may differ by rounding; there are none at this density.
        assert np.array_equal(inside[:, k], ref)
    assert inside.any()


def test_alpha_and_wrap() -> None:
    # A car straight ahead (x=0) has alpha == ry; one to the right at 45 degrees: alpha = ry - pi/4.
    np.testing.assert_allclose(alpha_from_rotation_y([0.3, 0.3], [[0, 1, 10], [10, 1, 10]]),
                               [0.3, 0.3 - np.pi / 4])
    np.testing.assert_allclose(wrap_angle([np.pi, -np.pi, 3 * np.pi + 0.1]), [-np.pi, -np.pi, -np.pi + 0.1])


def _simple_calib() -> Calibration:
    p = np.array([[700.0, 0, 600, 0], [0, 700.0, 180, 0], [0, 0, 1, 0]])
    eye = np.eye(3, 4)
    return Calibration(P0=p, P1=p, P2=p, P3=p, R0_rect=np.eye(3), Tr_velo_to_cam=eye, Tr_imu_to_velo=eye)


def test_projection_hand_computed_and_clipped() -> None:
    calib = _simple_calib()
    # Axis-aligned box (ry=0) 2 m wide in x, 1 m high, 2 m deep, bottom centre at (0, 1, 10).
    corners = box_corners([[1.0, 2.0, 2.0]], [[0.0, 1.0, 10.0]], [0.0])
    boxes, valid = project_boxes_to_image(corners, calib, (1242, 375))
    # Nearest face z=9: u = 600 +- 700*1/9; top y=0 -> v=180 at any depth, bottom y=1 at z=9.
    np.testing.assert_allclose(boxes[0], [600 - 700 / 9, 180, 600 + 700 / 9, 180 + 700 / 9])
    assert valid[0]
    # Far to the right: clipped to W-1; entirely outside: invalid.
    corners = box_corners([[1.0, 2.0, 2.0], [1.0, 2.0, 2.0]], [[9.0, 1.0, 10.0], [80.0, 1.0, 10.0]], [0.0, 0.0])
    boxes, valid = project_boxes_to_image(corners, calib, (1242, 375))
    assert boxes[0, 2] == 1241 and valid.tolist() == [True, False]


def test_projection_of_box_reaching_behind_camera_uses_near_plane() -> None:
    calib = _simple_calib()
    # A long box beside the car spanning z in [-3, 5] at x = 3: only its z >= 0.1 part is seen.
    corners = box_corners([[1.5, 2.0, 8.0]], [[3.0, 1.5, 1.0]], [np.pi / 2])
    boxes, valid = project_boxes_to_image(corners, calib, (1242, 375))
    assert valid[0]
    # The near-plane cut at z=0.1 makes the box reach the right image border and the bottom.
    assert boxes[0, 2] == 1241 and boxes[0, 3] == 374
    # Its far end (z=5, x from 2 to 4) sets the left edge: u = 600 + 700*2/5.
    assert boxes[0, 0] == pytest.approx(600 + 700 * 2 / 5)
    # Entirely behind the camera: invalid.
    behind = box_corners([[1.5, 2.0, 4.0]], [[0.0, 1.5, -10.0]], [0.0])
    assert not project_boxes_to_image(behind, calib, (1242, 375))[1][0]


def test_real_projected_boxes_agree_with_label_boxes(kitti_samples: Path) -> None:
    ds = KittiDataset(kitti_samples, split=None)
    n = 0
    for fid in ds.frame_ids:
        labels, calib = ds.labels(fid), ds.calib(fid)
        keep = labels.type != "DontCare"
        corners = box_corners(labels.dimensions[keep], labels.location[keep], labels.rotation_y[keep])
        from robustbench3d.kitti.image import image_size

        boxes, valid = project_boxes_to_image(corners, calib, image_size(ds.path("image", fid)))
        assert valid.all()
        for box, ref in zip(boxes, labels.bbox[keep], strict=True):
            assert _iou_2d(box, ref) > 0.75, (fid, box, ref)
            n += 1
    assert n == 10


def test_real_car_and_pedestrian_boxes_contain_lidar_points(kitti_samples: Path) -> None:
    ds = KittiDataset(kitti_samples, split=None)
    checked = 0
    for fid in ds.frame_ids:
        labels, calib = ds.labels(fid), ds.calib(fid)
        keep = np.isin(labels.type, ["Car", "Pedestrian"])
        if not keep.any():
            continue
        rect = calib.velo_to_rect_points(ds.scan(fid)[:, :3])
        inside = points_in_boxes(rect, labels.dimensions[keep], labels.location[keep], labels.rotation_y[keep])
        counts = inside.sum(axis=0)
        assert (counts > 0).all(), (fid, counts)
        checked += len(counts)
    assert checked == 7  # 5 cars + 2 pedestrians in the samples
