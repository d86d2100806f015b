"""Generated frames: loader round trip, labels consistent with the geometry, KITTI-like sensors."""

from __future__ import annotations

import numpy as np
import pytest

from robustbench3d.geometry import box_corners, points_in_boxes, project_boxes_to_image
from robustbench3d.kitti import KittiDataset, read_scan
from robustbench3d.sensors import LASER_ELEVATION_DEG, ring_ids_from_azimuth_wrap
from robustbench3d.synth.frame import SynthFrame, generate_frame
from robustbench3d.synth.writer import write_frame

SEED = 11
INDICES = (0, 1)


@pytest.fixture(scope="module")
def frames() -> list[SynthFrame]:
    return [generate_frame(SEED, i) for i in INDICES]


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    iw = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    ih = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = iw * ih
    area = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / area


def _labelled(frame: SynthFrame):
    """(label row, scene object index) of every non-DontCare label, matched through the annotations."""
    by_loc = {tuple(np.round(frame.scene.objects[a.index].location, 2)): a.index
              for a in frame.annotations if a.status == "label"}
    out = []
    for k in range(len(frame.labels)):
        if frame.labels.type[k] != "DontCare":
            out.append((k, by_loc[tuple(np.round(frame.labels.location[k], 2))]))
    return out


def test_loader_round_trip(frames, tmp_path):
    for i, frame in zip(INDICES, frames, strict=True):
        write_frame(tmp_path, i, frame)
    ds = KittiDataset(tmp_path, split=None)
    assert ds.frame_ids == [f"{i:06d}" for i in INDICES]
    for i, frame in zip(INDICES, frames, strict=True):
        loaded = ds.frame(f"{i:06d}")
        assert np.array_equal(loaded.image, frame.image)
        assert loaded.scan.dtype == np.float32 and np.array_equal(loaded.scan, frame.scan)
        for key in ("P0", "P1", "P2", "P3", "R0_rect", "Tr_velo_to_cam", "Tr_imu_to_velo"):
            assert np.array_equal(getattr(loaded.calib, key), getattr(frame.calib, key))
        a, b = loaded.labels, frame.labels
        assert list(a.type) == list(b.type)
        for name in ("truncated", "occluded", "alpha", "bbox", "dimensions", "location", "rotation_y"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), name
        assert loaded.image_size == frame.scene.image_size
    # DontCare lines are written exactly like KITTI's
    text = (tmp_path / "training" / "label_2" / "000000.txt").read_text()
    dc = [ln for ln in text.splitlines() if ln.startswith("DontCare")]
    assert dc and all(ln.split()[:4] == ["DontCare", "-1", "-1", "-10"] for ln in dc)
    assert all(ln.split()[8:] == ["-1", "-1", "-1", "-1000", "-1000", "-1000", "-10"] for ln in dc)


def test_boxes_contain_the_objects_lidar_points_and_nothing_else(frames):
    checked = 0
    for frame in frames:
        lab = frame.labels
        rect = frame.calib.velo_to_rect_points(frame.scan[:, :3])
        for k, obj in _labelled(frame):
            mine = frame.point_object == obj
            box = (lab.dimensions[k:k + 1], lab.location[k:k + 1], lab.rotation_y[k:k + 1])
            # range noise is clipped at 3 cm along the ray
            assert points_in_boxes(rect[mine], *box, margin=0.035)[:, 0].all()
            others = rect[~mine]
            dims = lab.dimensions[k:k + 1] - 0.2  # shrink 10 cm on every side
            inner = points_in_boxes(others, dims, lab.location[k:k + 1] - [0, 0.1, 0], lab.rotation_y[k:k + 1])
            assert not inner.any()
            checked += int(mine.sum() > 0)
    assert checked >= 10


def test_boxes_tightly_contain_the_meshes(frames):
    for frame in frames:
        lab = frame.labels
        for k, obj in _labelled(frame):
            verts = frame.calib.velo_to_rect_points(frame.scene.objects[obj].mesh.vertices)
            # mesh in box-local coordinates: x along the length, y up the height (negative), z across
            c, s = np.cos(lab.rotation_y[k]), np.sin(lab.rotation_y[k])
            rel = verts - lab.location[k]
            local = np.column_stack([c * rel[:, 0] - s * rel[:, 2], rel[:, 1], s * rel[:, 0] + c * rel[:, 2]])
            h, w, l = lab.dimensions[k]
            np.testing.assert_allclose(local.min(axis=0), [-l / 2, -h, -w / 2], atol=1e-6)
            np.testing.assert_allclose(local.max(axis=0), [l / 2, 0.0, w / 2], atol=1e-6)


def test_2d_boxes_agree_with_projected_3d_boxes(frames):
    ious = []
    for frame in frames:
        lab = frame.labels
        w, h = frame.scene.image_size
        for k, _ in _labelled(frame):
            assert 0 <= lab.bbox[k, 0] < lab.bbox[k, 2] <= w - 1 and 0 <= lab.bbox[k, 1] < lab.bbox[k, 3] <= h - 1
            if lab.type[k] != "Car" or lab.truncated[k] > 0 or lab.occluded[k] > 0:
                continue
            corners = box_corners(lab.dimensions[k:k + 1], lab.location[k:k + 1], lab.rotation_y[k:k + 1])
            proj, valid = project_boxes_to_image(corners, frame.calib, (w, h))
            assert valid[0]
            # the mesh lies inside its box, so its 2D box lies inside the projected box
            assert np.all(lab.bbox[k, :2] >= proj[0, :2] - 0.01) and np.all(lab.bbox[k, 2:] <= proj[0, 2:] + 0.01)
            ious.append(_iou(lab.bbox[k], proj[0]))
    assert len(ious) >= 3
    assert min(ious) > 0.75


def test_rendered_pixels_lie_inside_the_p2_projection(frames):
    """The camera casts rays consistent with P2: every pixel showing an object lies in its label box
    (the P2 projection of its mesh), up to the half-pixel sampling."""
    checked = 0
    for frame in frames:
        for k, obj in _labelled(frame):
            v, u = np.nonzero(frame.object_id == obj)
            box = frame.labels.bbox[k]
            assert u.min() >= box[0] - 1 and u.max() <= box[2] + 1
            assert v.min() >= box[1] - 1 and v.max() <= box[3] + 1
            checked += 1
    assert checked >= 10


def test_scans_look_like_kitti(frames):
    for frame in frames:
        scan = frame.scan
        assert 100_000 <= len(scan) <= 130_000
        refl = scan[:, 3]
        assert refl.min() >= 0 and refl.max() <= 0.99
        np.testing.assert_allclose(refl * 100, np.round(refl * 100), atol=1e-3)  # 0.01 steps like KITTI
        assert 0.02 < np.mean(refl == 0) < 0.3
        # ring order: the wrap heuristic recovers the lasers, and each traces its cone
        pts = scan.astype(np.float64)
        ring = ring_ids_from_azimuth_wrap(pts)
        assert ring.max() == 63
        rho = np.hypot(pts[:, 0], pts[:, 1])
        for k in (0, 20, 40, 63):
            m = (ring == k) & (rho > 2.5) & (rho < 70)
            coef = np.polyfit(rho[m], pts[m, 2], 1)
            assert np.degrees(np.arctan(coef[0])) == pytest.approx(LASER_ELEVATION_DEG[k], abs=0.01)
        r = np.linalg.norm(pts[:, :3], axis=1)
        assert r.max() <= 120.0 and np.percentile(r, 50) < 25.0


def test_sensor_frames_agree_with_real_kitti_geometry(frames, kitti_samples):
    """Ground returns sit 1.73 m below the sensor like in real scans, and the LiDAR origin in rect is
    the calibration's."""
    real = read_scan(kitti_samples / "training" / "velodyne" / "000004.bin")
    near = lambda s: s[(np.hypot(s[:, 0], s[:, 1]) < 8) & (np.abs(s[:, 1]) < 1.5) & (s[:, 0] > 4)]  # noqa: E731
    real_ground = np.median(near(real)[:, 2])
    for frame in frames:
        assert np.median(near(frame.scan)[:, 2]) == pytest.approx(real_ground, abs=0.1)
        origin = frame.calib.velo_to_rect_points(np.zeros((1, 3)))[0]
        assert -0.35 < origin[2] < -0.25 and -0.09 < origin[1] < -0.05


def test_image_matches_the_calibration_day(frames):
    for frame in frames:
        w, h = frame.scene.image_size
        assert frame.image.shape == (h, w, 3) and (w, h) in ((1242, 375), (1224, 370))
        assert frame.object_id.shape == (h, w)
        assert frame.image.std() > 20  # not a flat image
        # the top rows are mostly sky/buildings, the bottom rows road: different brightness statistics
        sky = frame.object_id[:20] == -1
        assert frame.object_id[-5:].min() >= 0 and sky.mean() < 1.0
