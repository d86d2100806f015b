"""The frame picture draws labelled boxes where the calibration puts them."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from robustbench3d.cli import main
from robustbench3d.draw import CLASS_COLOURS, render
from robustbench3d.geometry import box_corners
from robustbench3d.kitti import KittiDataset, read_image


def test_render_draws_car_box_at_its_projection(kitti_samples: Path) -> None:
    frame = KittiDataset(kitti_samples, split=None).frame("000004")
    pic = render(frame)
    assert pic.shape[1] == 1242 and pic.shape[0] > 375
    cars = frame.labels.type == "Car"
    corners = box_corners(frame.labels.dimensions[cars], frame.labels.location[cars], frame.labels.rotation_y[cars])
    uv, _ = frame.calib.rect_to_image(corners.reshape(-1, 3))
    green = np.array(CLASS_COLOURS["Car"])
    hits = 0
    for u, v in uv:
        patch = pic[max(int(v) - 2, 0): int(v) + 3, max(int(u) - 2, 0): int(u) + 3].reshape(-1, 3)
        hits += bool((patch == green).all(axis=1).any())
    assert hits >= 0.9 * len(uv)
    # Pixels away from every box keep the camera image.
    np.testing.assert_array_equal(pic[5, 5], frame.image[5, 5])


def test_show_cli_writes_png(kitti_samples: Path, tmp_path: Path) -> None:
    out = tmp_path / "f.png"
    assert main(["show", str(kitti_samples), "000001", "--out", str(out),
                 "--pred", str(kitti_samples / "results/pointgnn_car_val/data")]) == 0
    assert read_image(out).shape[1] == 1242
