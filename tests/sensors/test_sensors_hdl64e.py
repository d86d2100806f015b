"""The HDL-64E beam model against the real KITTI sample scans (independent reference)."""

from __future__ import annotations

import numpy as np
import pytest

from robustbench3d.kitti import read_scan
from robustbench3d.sensors import HDL64E, ring_ids_from_azimuth_wrap

FRAMES = [f"{i:06d}" for i in range(6)]


def _rings_by_wrap(points: np.ndarray) -> np.ndarray:
    """Reference ring ids, written out here: a new laser where azimuth in [0, 360) drops > 180 deg."""
    az = np.degrees(np.arctan2(points[:, 1], points[:, 0])) % 360.0
    return np.concatenate([[0], np.cumsum(np.diff(az) < -180.0)])


def _fit_cones(points: np.ndarray, ring: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per ring least squares z = rho tan(phi) + h0 over 2.5 m < rho < 70 m: (phi deg, h0 m, rms m)."""
    rho = np.hypot(points[:, 0], points[:, 1])
    phi, h0, rms = [], [], []
    for k in range(int(ring.max()) + 1):
        m = (ring == k) & (rho > 2.5) & (rho < 70.0)
        a = np.column_stack([rho[m], np.ones(m.sum())])
        coef, *_ = np.linalg.lstsq(a, points[m, 2], rcond=None)
        phi.append(np.degrees(np.arctan(coef[0])))
        h0.append(coef[1])
        rms.append(np.sqrt(np.mean((a @ coef - points[m, 2]) ** 2)))
    return np.array(phi), np.array(h0), np.array(rms)


@pytest.fixture(scope="module")
def real_scans(kitti_samples) -> list[np.ndarray]:
    return [read_scan(kitti_samples / "training" / "velodyne" / f"{f}.bin").astype(np.float64) for f in FRAMES]


def _model_points(sensor: HDL64E, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Points at random ranges along the model's rays (as if every ray hit something)."""
    rays = sensor.rays(rng.uniform(0, sensor.azimuth_quantum_deg, 64))
    t = rng.uniform(3.0, 60.0, len(rays))
    return rays.origins + t[:, None] * rays.directions, rays.ring


def test_model_rays_reproduce_the_per_ring_cones_of_real_scans(real_scans):
    fits = [_fit_cones(s, _rings_by_wrap(s)) for s in real_scans]
    for phi, _, rms in fits:
        assert len(phi) == 64
        assert np.median(rms) < 0.001 and rms.max() < 0.01  # real KITTI points lie on exact cones
    real_phi = np.mean([f[0] for f in fits], axis=0)
    real_h0 = np.mean([f[1] for f in fits], axis=0)
    pts, ring = _model_points(HDL64E(), np.random.default_rng(0))
    model_phi, model_h0, model_rms = _fit_cones(pts, ring)
    assert model_rms.max() < 1e-6
    np.testing.assert_allclose(model_phi, real_phi, atol=0.02)
    np.testing.assert_allclose(model_h0, real_h0, atol=0.003)
    assert np.all(np.diff(model_phi) < 0)  # ring 0 is the top laser


def test_scan_order_is_kittis(real_scans):
    sensor = HDL64E()
    rays = sensor.rays(np.random.default_rng(1).uniform(0, 0.09, 64))
    # laser by laser from the top, azimuth increasing from just above 0 within a laser
    assert np.all(np.diff(rays.ring) >= 0)
    for k in range(64):
        az = rays.azimuth_deg[rays.ring == k]
        assert np.all(np.diff(az) > 0) and az[0] >= 0 and az[-1] < 360
        assert k > 56 or az[0] < 0.2  # the lowest lasers' forward sector is hidden by the ego car
    assert np.array_equal(ring_ids_from_azimuth_wrap(rays.origins + 10 * rays.directions), rays.ring)
    for scan in real_scans:  # the same structure in the real files
        ring = ring_ids_from_azimuth_wrap(scan)
        assert ring.max() == 63
        az = np.degrees(np.arctan2(scan[:, 1], scan[:, 0])) % 360
        first = np.flatnonzero(np.diff(np.concatenate([[-1], ring])))
        assert np.median(az[first]) < 1.0  # each laser starts just above 0 deg (straight ahead)


def test_azimuth_spacing_matches_real_scans(real_scans):
    def spacing(az: np.ndarray) -> tuple[float, float]:
        d = np.diff(az)
        d = d[(d > 0.05) & (d < 0.25)]
        return float(np.median(d)), float(np.mean(d < 0.12))

    real = [spacing((np.degrees(np.arctan2(s[:, 1], s[:, 0])) % 360)[ring_ids_from_azimuth_wrap(s) == 20])
            for s in real_scans]
    rays = HDL64E().rays()
    model = spacing(rays.azimuth_deg[rays.ring == 20])
    assert model[0] == pytest.approx(np.median([r[0] for r in real]), abs=0.002)  # 0.18 deg
    assert model[1] == pytest.approx(np.median([r[1] for r in real]), abs=0.02)  # ~14 % half steps


def test_ego_occlusion_matches_real_per_ring_counts(real_scans):
    """The lowest lasers see only the ground around the car: their real point counts are set by the
    ego-vehicle shadow, which the model's ray count per ring must reproduce."""
    real_max = np.max([np.bincount(ring_ids_from_azimuth_wrap(s), minlength=64) for s in real_scans], axis=0)
    model = np.bincount(HDL64E().rays().ring, minlength=64)
    ratio = model[44:] / real_max[44:]
    assert np.all((ratio > 0.93) & (ratio < 1.08)), ratio
    assert 125_000 < model.sum() < 132_000
