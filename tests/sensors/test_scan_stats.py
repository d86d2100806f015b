"""Ring recovery and cone fits: exact on constructed scans, and the reference table on real scans."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from robustbench3d.kitti import read_scan
from robustbench3d.scan_stats import azimuth_step_deg, fit_ring_cones, ground_height
from robustbench3d.sensors.hdl64e import ring_ids_from_azimuth_wrap


def _constructed_scan(phis_deg: np.ndarray, h0: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Laser-by-laser sweep like KITTI: each ring starts just left of +x and runs counter-clockwise."""
    rows = []
    for phi, h in zip(np.radians(phis_deg), h0, strict=True):
        az = np.radians(np.arange(0.5, 359.5, 0.18))
        keep = rng.random(az.size) > 0.2  # dropouts
        az = az[keep]
        rho = rng.uniform(3, 60, size=az.size)
        rows.append(np.stack([rho * np.cos(az), rho * np.sin(az), rho * np.tan(phi) + h, np.zeros_like(az)], 1))
    return np.concatenate(rows).astype(np.float32)


def test_rings_and_cones_recovered_exactly_on_constructed_scan() -> None:
    rng = np.random.default_rng(0)
    phis = np.linspace(2.0, -24.0, 64)
    h0 = np.where(np.arange(64) < 32, 0.2, 0.12)
    scan = _constructed_scan(phis, h0, rng)
    rings = ring_ids_from_azimuth_wrap(scan)
    assert rings.max() == 63 and np.all(np.diff(rings) >= 0)
    fit = fit_ring_cones(scan, rings)
    np.testing.assert_allclose(fit.elevation_deg, phis, atol=1e-3)
    np.testing.assert_allclose(fit.origin_height, h0, atol=2e-3)
    assert azimuth_step_deg(scan, rings) == pytest.approx(0.18, abs=1e-3)


def test_real_scans_match_reference_table(kitti_samples: Path) -> None:
    # reference.md §4.2 (measured on real KITTI scans): ring: (phi deg, h0 m).
    table = {0: (1.94, 0.209), 17: (-3.94, 0.202), 31: (-8.71, 0.198), 32: (-9.03, 0.126), 63: (-25.00, 0.116)}
    for f in range(6):
        scan = read_scan(kitti_samples / "training/velodyne" / f"{f:06d}.bin")
        fit = fit_ring_cones(scan)
        assert len(fit.elevation_deg) == 64
        assert np.nanmax(fit.rms) < 1e-3
        for ring, (phi, h0) in table.items():
            assert fit.elevation_deg[ring] == pytest.approx(phi, abs=0.02)
            assert fit.origin_height[ring] == pytest.approx(h0, abs=0.003)
        assert -1.8 < ground_height(scan) < -1.6


def test_ground_height_of_flat_plane() -> None:
    rng = np.random.default_rng(1)
    xy = rng.uniform([4, -10], [20, 10], size=(5000, 2))
    clutter = rng.uniform([4, -10, -1.0], [20, 10, 0.0], size=(500, 3))
    plane = np.column_stack([xy, np.full(5000, -1.73)])
    scan = np.column_stack([np.concatenate([plane, clutter]), np.zeros(5500)])
    assert ground_height(scan) == pytest.approx(-1.73, abs=0.02)
