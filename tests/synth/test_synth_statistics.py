"""Dataset-level statistics of a few hundred generated frames, read back through the KITTI loader."""

from __future__ import annotations

import numpy as np
import pytest

from robustbench3d.kitti import KittiDataset
from robustbench3d.synth.annotate import difficulty
from robustbench3d.synth.writer import generate_dataset

FRAMES = 300


@pytest.mark.slow
def test_difficulty_groups_sizes_and_scans_over_300_frames(tmp_path):
    generate_dataset(tmp_path, FRAMES, seed=2024, val_fraction=0.5, workers=2, progress=False)
    ds = KittiDataset(tmp_path, split="trainval")
    assert len(ds) == FRAMES
    cars, dontcare, points = [], 0, []
    for fid in ds.frame_ids:
        labels = ds.labels(fid)
        cars.append(labels.select(labels.type == "Car"))
        dontcare += int(np.sum(labels.type == "DontCare"))
        points.append(ds.path("scan", fid).stat().st_size // 16)
    car = cars[0].concatenate(cars)
    height = car.bbox[:, 3] - car.bbox[:, 1]
    groups = np.bincount(difficulty(height, car.occluded, car.truncated), minlength=4) / len(car)
    # easy, moderate-only, hard-only, ignored at every level: each at least 10 % of the Car labels
    assert np.all(groups >= 0.10), groups
    assert dontcare >= 0.5 * FRAMES
    assert min(points) >= 100_000 and max(points) <= 130_000
    # sizes around the KITTI Car statistics (h, w, l = 1.53, 1.63, 3.88; sd 0.14, 0.10, 0.40)
    np.testing.assert_allclose(car.dimensions.mean(axis=0), [1.53, 1.63, 3.88], atol=0.08)
    np.testing.assert_allclose(car.dimensions.std(axis=0), [0.14, 0.10, 0.40], atol=0.06)
    depth = car.location[:, 2]
    assert depth.min() < 5.0 and depth.max() > 60.0
    # headings mostly along the road: KITTI ry = +-pi/2 is a car pointing along the camera axis
    along = np.abs(np.abs(car.rotation_y) - np.pi / 2) < np.radians(15)
    assert along.mean() > 0.6
    for level in (0, 1, 2):
        assert np.mean(car.occluded == level) > 0.1
    assert np.mean(car.truncated > 0) > 0.03
