"""Frustum extraction (reference §1.3-§1.4) on a real KITTI frame and on hand-made points."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from robustbench3d.geometry import box_corners, points_in_boxes, project_boxes_to_image
from robustbench3d.kitti.dataset import KittiDataset
from robustbench3d.victims.fpointnet.frustum import (
    extract_frustum,
    frustum_angle,
    perturb_box2d,
    project_rect_points,
    project_scan,
    resample_indices,
    rotate_from_frustum,
    rotate_to_frustum,
)
from robustbench3d.victims.fpointnet.model import rotate_to_frustum_torch


@pytest.fixture(scope="module")
def car_frame(kitti_samples):
    """Frame 000003: one Car at z = 13.2 m (680 scan points inside its 3D box)."""
    frame = KittiDataset(kitti_samples, split=None).frame("000003")
    car = frame.labels.select(frame.labels.type == "Car")
    assert len(car) == 1
    return frame, car


def test_fov_mask(car_frame):
    frame, _ = car_frame
    proj = project_scan(frame.scan, frame.calib, frame.image_size)
    w, h = frame.image_size
    u, v = proj.uv[proj.in_fov].T
    assert (u >= 0).all() and (u < w).all() and (v >= 0).all() and (v < h).all()
    assert (frame.scan[proj.in_fov, 0] > 2.0).all()
    # everything excluded is outside the image or within 2 m (velodyne x)
    out = ~proj.in_fov
    outside_image = (proj.uv[:, 0] < 0) | (proj.uv[:, 0] >= w) | (proj.uv[:, 1] < 0) | (proj.uv[:, 1] >= h)
    assert (outside_image[out] | (frame.scan[out, 0] <= 2.0)).all()
    # rect points are the calibration's transform of the scan; reflectance kept
    assert np.allclose(proj.points_rect[:, :3], frame.calib.velo_to_rect_points(frame.scan[:, :3]))
    assert np.array_equal(proj.points_rect[:, 3], frame.scan[:, 3].astype(np.float64))


def test_frustum_of_gt_box_contains_the_points_of_the_3d_box(car_frame):
    frame, car = car_frame
    proj = project_scan(frame.scan, frame.calib, frame.image_size)
    inside = points_in_boxes(proj.points_rect, car.dimensions, car.location, car.rotation_y)[:, 0] & proj.in_fov
    assert inside.sum() > 500
    # the 2D box of the projected 3D box: every in-box point is in the frustum
    box_proj, valid = project_boxes_to_image(box_corners(car.dimensions, car.location, car.rotation_y),
                                             frame.calib, frame.image_size)
    assert valid[0]
    fr = extract_frustum(proj, box_proj[0], frame.calib)
    assert np.isin(np.flatnonzero(inside), fr.indices).all()
    # the annotated 2D box: all but a handful (annotation is a pixel tighter)
    fr_label = extract_frustum(proj, car.bbox[0], frame.calib)
    assert np.isin(np.flatnonzero(inside), fr_label.indices).mean() > 0.99
    # frustum points are exactly the FOV points projecting into the half-open box
    x0, y0, x1, y1 = car.bbox[0]
    u, v = proj.uv[:, 0], proj.uv[:, 1]
    expect = np.flatnonzero(proj.in_fov & (u >= x0) & (u < x1) & (v >= y0) & (v < y1))
    assert np.array_equal(fr_label.indices, expect)
    assert np.array_equal(fr_label.points, proj.points_rect[expect])


def test_rotation_puts_the_box_centre_ray_on_plus_z(car_frame):
    frame, car = car_frame
    box = car.bbox[0]
    fr = extract_frustum(project_scan(frame.scan, frame.calib, frame.image_size), box, frame.calib)
    assert fr.rot_angle == pytest.approx(np.pi / 2 + frustum_angle(box, frame.calib))
    centre_px = np.array([[(box[0] + box[2]) / 2, (box[1] + box[3]) / 2]])
    # independent back-projection: the calibration's exact inverse of P2, at depth 20 m
    ray_point = frame.calib.image_to_rect(centre_px, np.array([20.0]))[0]
    rotated = rotate_to_frustum(ray_point, fr.rot_angle)
    assert abs(rotated[0]) < 5e-3  # x' = 0 up to P2[2,3] (ignored by the original formula)
    assert rotated[2] == pytest.approx(np.hypot(ray_point[0], ray_point[2]), abs=1e-6)
    assert rotated[1] == ray_point[1]
    # the car's centre lands near the +z axis too
    centre = rotate_to_frustum(car.location[0] - [0, car.dimensions[0, 0] / 2, 0], fr.rot_angle)
    assert abs(centre[0]) < 0.5 and centre[2] > 10


def test_rotation_matches_the_reference_formula_and_torch_twin():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(50, 4))
    a = 1.234
    out = rotate_to_frustum(pts, a)
    assert np.allclose(out[:, 0], pts[:, 0] * np.cos(a) - pts[:, 2] * np.sin(a))
    assert np.allclose(out[:, 2], pts[:, 0] * np.sin(a) + pts[:, 2] * np.cos(a))
    assert np.array_equal(out[:, [1, 3]], pts[:, [1, 3]])
    assert np.allclose(rotate_from_frustum(out, a), pts)
    t = rotate_to_frustum_torch(torch.from_numpy(pts), a)
    assert np.allclose(t.numpy(), out)


def test_resampling_is_seeded_uniform_and_with_replacement():
    a = resample_indices(10, 1024, np.random.default_rng(5))
    b = resample_indices(10, 1024, np.random.default_rng(5))
    assert np.array_equal(a, b)
    assert a.min() == 0 and a.max() == 9 and len(np.unique(a)) == 10  # all drawn, repeated
    assert len(np.unique(resample_indices(5000, 1024, np.random.default_rng(0)))) < 1024  # replacement
    with pytest.raises(ValueError):
        resample_indices(0, 8, np.random.default_rng(0))


def test_box_perturbation_bounds():
    rng = np.random.default_rng(0)
    box = np.array([100.0, 50.0, 300.0, 150.0])  # w 200, h 100
    out = np.stack([perturb_box2d(box, rng) for _ in range(2000)])
    w, h = out[:, 2] - out[:, 0], out[:, 3] - out[:, 1]
    cx, cy = (out[:, 0] + out[:, 2]) / 2, (out[:, 1] + out[:, 3]) / 2
    assert w.min() >= 180 and w.max() <= 220 and h.min() >= 90 and h.max() <= 110
    assert np.abs(cx - 200).max() <= 20 and np.abs(cy - 100).max() <= 10
    assert w.std() > 5 and np.abs(cx - 200).max() > 15  # really perturbed


def test_rect_points_path_matches_scan_path(car_frame):
    frame, car = car_frame
    a = project_scan(frame.scan, frame.calib, frame.image_size)
    b = project_rect_points(a.points_rect, frame.calib, frame.image_size)
    assert np.array_equal(extract_frustum(a, car.bbox[0], frame.calib).indices,
                          extract_frustum(b, car.bbox[0], frame.calib).indices)
