"""Generated scans against the six real KITTI scans, through the ``data stats`` command's code.

The reference is the real data (independent of the generator); tolerances are what a detector
trained on one and tested on the other would notice.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from robustbench3d.cli import main
from robustbench3d.dataset_stats import dataset_statistics


@pytest.fixture(scope="module")
def synth_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from robustbench3d.synth.writer import generate_dataset

    root = tmp_path_factory.mktemp("synth")
    generate_dataset(root, 4, seed=11, val_fraction=0.5, workers=1, progress=False)
    return root


def test_lidar_statistics_match_real_scans(kitti_samples: Path, synth_root: Path) -> None:
    real = dataset_statistics(str(kitti_samples), split=None)
    synth = dataset_statistics(str(synth_root), split=None)
    assert real["rings"] == synth["rings"] == {"min": 64, "max": 64}
    # Per-ring cone elevation: same beams (real rings span +1.94 .. -25.00 deg).
    np.testing.assert_allclose(synth["ring_elevation_deg"], real["ring_elevation_deg"], atol=0.05)
    np.testing.assert_allclose(synth["ring_origin_height_m"], real["ring_origin_height_m"], atol=0.005)
    assert synth["azimuth_step_deg"] == pytest.approx(real["azimuth_step_deg"], abs=0.005)
    # Real frames: 113k-127k points, ground 1.65-1.71 m below the sensor.
    for stats in (real, synth):
        assert 100_000 <= stats["points_per_frame"]["min"] <= stats["points_per_frame"]["max"] <= 130_000
    assert synth["ground_height_m"] == pytest.approx(real["ground_height_m"], abs=0.1)


def test_synthetic_cars_get_more_points_when_near(synth_root: Path) -> None:
    stats = dataset_statistics(str(synth_root), split=None)["car_points_by_distance"]
    medians = [stats[k]["median"] for k in ("10m", "20m", "40m") if stats[k]["cars"]]
    assert len(medians) >= 2 and all(m > 0 for m in medians)
    assert medians == sorted(medians, reverse=True)


def test_data_stats_command_prints_both_datasets(kitti_samples: Path, synth_root: Path, capsys) -> None:
    assert main(["data", "stats", str(kitti_samples), str(synth_root), "--frames", "2"]) == 0
    out = capsys.readouterr().out
    assert "max |d elevation| vs first, deg" in out and str(synth_root) in out
