"""Scene depth sources for the camera renderer's occlusion (robustbench3d.sensors.camera_depth and the exact
provider robustbench3d.synth.scene_depth)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from robustbench3d.errors import DataFormatError
from robustbench3d.kitti.calib import Calibration
from robustbench3d.sensors.camera_depth import DepthMap, camera_centre_rect, lidar_depth_map, pixel_rays_rect
from robustbench3d.synth.calibs import DAY_0926
from robustbench3d.synth.frame import generate_frame
from robustbench3d.synth.scene_depth import dataset_scene_depth, synth_scene_depth
from robustbench3d.testing import synth_dataset

_PERM = np.array([[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [1.0, 0.0, 0.0, 0.0]])


def small_calib() -> Calibration:
    p2 = np.array([[20.0, 0.0, 20.0, 0.0], [0.0, 20.0, 15.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
    return Calibration(P0=p2, P1=p2, P2=p2, P3=p2, R0_rect=np.eye(3), Tr_velo_to_cam=_PERM,
                       Tr_imu_to_velo=np.eye(3, 4))


def test_camera_centre_and_rays_project_back():
    calib = DAY_0926.calib
    c = camera_centre_rect(calib)
    np.testing.assert_allclose(calib.P2 @ np.append(c, 1.0), 0.0, atol=1e-9)
    u, v = np.array([0.0, 600.3, 1241.0]), np.array([0.0, 170.7, 374.0])
    p = c + 7.0 * pixel_rays_rect(calib, u, v)
    uv, _ = calib.rect_to_image(p)
    np.testing.assert_allclose(uv, np.column_stack([u, v]), atol=1e-9)


def test_depth_map_reads_the_pixel_containing_the_position():
    dmap = np.arange(12.0).reshape(3, 4)
    src = DepthMap(dmap)
    got = src.depth(np.array([0.0, 0.49, 0.51, 3.4, -0.6, 4.6]), np.array([0.0, 0.0, 1.49, 2.0, 0.0, 0.0]))
    np.testing.assert_array_equal(got, [0.0, 0.0, 5.0, 11.0, np.inf, np.inf])


def test_lidar_depth_map_fills_between_beams_only():
    calib = small_calib()

    def velo(u: float, v: float, z: float) -> list[float]:  # rect (x, y, z) -> velodyne (z, -x, -y)
        x, y = (u - 20.0) * z / 20.0, (v - 15.0) * z / 20.0
        return [z, -x, -y, 0.5]

    scan = np.array([velo(20, 10, 4.0), velo(20, 16, 5.0), velo(30, 20, 9.0)])
    d = lidar_depth_map(scan, calib, (40, 30), fill_rows=6, fill_cols=0, margin_m=0.25).depth_map
    assert d[10, 20] == 4.25 and d[16, 20] == 5.25
    np.testing.assert_array_equal(d[11:16, 20], 5.25)  # between the two points: the farther one
    assert np.isinf(d[9, 20]) and np.isinf(d[17, 20]) and np.isinf(d[13, 19])  # not beyond them
    assert d[20, 30] == 9.25 and np.isinf(d[19, 30])
    d = lidar_depth_map(scan, calib, (40, 30), fill_rows=6, fill_cols=3, margin_m=0.0).depth_map
    assert np.isinf(d[13, 19]) and np.isinf(d[13, 21])  # one column of points: nothing on both sides
    with pytest.raises(ValueError, match="field 'scan'"):
        lidar_depth_map(np.zeros(5), calib, (40, 30))


def test_exact_scene_depth_agrees_with_the_frame_scan():
    """A scan point's camera ray is free up to the point (or hidden by something nearer, parallax)."""
    frame = generate_frame(0, 3)
    src = synth_scene_depth(0, 3)
    np.testing.assert_array_equal(src.calib.P2, frame.calib.P2)
    calib = frame.calib
    uv, depth = calib.rect_to_image(calib.velo_to_rect_points(frame.scan[:, :3]))
    h, w, _ = frame.image.shape
    k = (depth > 1) & (uv[:, 0] > -0.5) & (uv[:, 0] < w - 0.5) & (uv[:, 1] > -0.5) & (uv[:, 1] < h - 0.5)
    assert k.sum() > 10000
    diff = src.depth(uv[k, 0], uv[k, 1]) - depth[k]
    assert np.mean(np.abs(diff) < 0.05) > 0.9  # the same surface, up to the LiDAR's range noise
    assert np.mean(diff < 0.1) > 0.999  # never farther than the point


def test_dataset_scene_depth_reads_the_manifest_and_checks_it(tmp_path):
    root = synth_dataset(tmp_path / "d", 1, seed=5)
    src = dataset_scene_depth(root, "000000")
    ref = synth_scene_depth(5, 0)
    u, v = np.array([100.0, 600.0, 900.0]), np.array([300.0, 200.0, 180.0])
    np.testing.assert_array_equal(src.depth(u, v), ref.depth(u, v))
    manifest = root / "synth_manifest.json"
    data = json.loads(manifest.read_text())
    manifest.write_text(json.dumps({**data, "version": 999}))
    with pytest.raises(DataFormatError, match=r"synth_manifest.json: field 'version'"):
        dataset_scene_depth(root, "000000")
    manifest.write_text(json.dumps({**data, "seed": 6}))
    with pytest.raises(DataFormatError, match=r"000000.txt(:1: field 'location'|: field 'P2')"):
        dataset_scene_depth(root, "000000")  # seed 6 rebuilds another scene
    manifest.unlink()
    with pytest.raises(DataFormatError, match=r"synth_manifest\.json: not found"):
        dataset_scene_depth(root, "000000")
