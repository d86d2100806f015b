"""The example plugin (examples/lidar_cluster_victim), found through its entry point.

Install it with ``pip install -c constraints.txt -e examples/lidar_cluster_victim``; the tests
skip with that hint otherwise.
"""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from robustbench3d.geometry import box_corners, points_in_boxes
from robustbench3d.kitti.dataset import Frame, KittiDataset
from robustbench3d.testing import SIMPLE_CALIB
from robustbench3d.victims import VICTIMS, create_victim
from robustbench3d.victims.base import Detector, FrustumSegmentationOracle, ImageObjectnessOracle

pytestmark = pytest.mark.skipif(
    importlib.util.find_spec("rb3d_lidar_cluster") is None,
    reason="example plugin not installed: pip install -c constraints.txt -e examples/lidar_cluster_victim",
)



def synthetic_scene(rng: np.random.Generator) -> tuple[Frame, np.ndarray, float]:
    """Flat ground at velodyne z = -1.73 and one car-sized box (surface points of the two faces
    seen from the sensor). Returns the frame, the box centre (velodyne x, y) and its yaw."""
    gx, gy = np.meshgrid(np.arange(3.0, 40.0, 0.3), np.arange(-15.0, 15.0, 0.3))
    ground = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, -1.73)], axis=1)
    ground[:, 2] += rng.normal(0, 0.02, len(ground))
    centre, yaw, (l, w, h) = np.array([15.0, 2.0]), np.deg2rad(25.0), (4.2, 1.7, 1.5)
    u = rng.uniform(-0.5, 0.5, (3000, 2))
    z = rng.uniform(-1.73 + 0.05, -1.73 + h, 3000)
    rear = np.stack([np.full(1500, -l / 2), u[:1500, 1] * w], axis=1)        # face towards the sensor
    side = np.stack([u[1500:, 0] * l, np.full(1500, -w / 2)], axis=1)       # right side (facing -y)
    local = np.concatenate([rear, side])
    rot = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
    car = np.concatenate([local @ rot.T + centre, z[:, None]], axis=1)
    scan = np.concatenate([ground, car]).astype(np.float32)
    scan = np.concatenate([scan, np.full((len(scan), 1), 0.3, np.float32)], axis=1)
    image = np.zeros((375, 1242, 3), dtype=np.uint8)
    return Frame("000000", image, scan, SIMPLE_CALIB, None), centre, yaw


def test_plugin_is_registered_from_its_entry_point():
    entry = VICTIMS.entry("lidar-cluster")
    assert entry.origin.startswith("plugin rb3d-lidar-cluster")
    cap = VICTIMS.get("lidar-cluster").info.capabilities
    assert cap.modalities == ("lidar",) and not cap.gradients and cap.backend == "other"
    victim = create_victim("lidar-cluster")
    assert isinstance(victim, Detector)
    assert not isinstance(victim, ImageObjectnessOracle) and not isinstance(victim, FrustumSegmentationOracle)
    with pytest.raises(ValueError, match="LiDAR-only"):
        victim.detect([], proposals="gt")


def test_plugin_finds_the_synthetic_car():
    frame, centre, yaw = synthetic_scene(np.random.default_rng(0))
    victim = create_victim("lidar-cluster")
    dets = victim.detect([frame])[0]
    assert dets.has_score and len(dets) == 1
    # back to velodyne to compare with the scene definition
    loc_velo = SIMPLE_CALIB.rect_to_velo_points(dets.location)[0]
    assert np.hypot(*(loc_velo[:2] - centre)) < 0.3
    assert abs(loc_velo[2] - (-1.73)) < 0.1  # bottom centre on the ground
    h, w, l = dets.dimensions[0]
    assert abs(l - 4.2) < 0.3 and abs(w - 1.7) < 0.2 and abs(h - 1.5) < 0.15
    # rect rotation_y of a velodyne yaw: heading (cos, sin, 0)_velo = (-sin, 0, cos)_rect -> ry = -yaw - pi/2
    err = (dets.rotation_y[0] - (-yaw - np.pi / 2)) % np.pi
    assert min(err, np.pi - err) < np.deg2rad(3)
    # every car point lies inside the detected box (grown by 5 cm)
    car_rect = SIMPLE_CALIB.velo_to_rect_points(frame.scan[-3000:, :3])
    assert points_in_boxes(car_rect, dets.dimensions, dets.location, dets.rotation_y, margin=0.05).all()
    assert np.isfinite(box_corners(dets.dimensions, dets.location, dets.rotation_y)).all()
    assert victim.detect([frame])[0].to_text() == dets.to_text()  # deterministic


def test_plugin_on_a_real_frame(kitti_samples):
    frame = KittiDataset(kitti_samples, split=None).frame("000003")
    car = frame.labels.select(frame.labels.type == "Car")
    dets = create_victim("lidar-cluster").detect([frame])[0]
    dist = np.hypot(*(dets.location[:, [0, 2]] - car.location[0, [0, 2]]).T)
    assert dist.min() < 0.5  # the 13 m car is found
