"""Azimuth decimation (robustbench3d.sensors.scan_density) against a scan built by hand from the generator's
firing formula, on a generated frame, and on an attacked one (object returns decimated like the scene)."""

from __future__ import annotations

import numpy as np
import pytest

from robustbench3d.sensors.hdl64e import EGO_OCCLUSION_SECTORS, LASER_ELEVATION_DEG, LASER_ORIGIN_Z_M
from robustbench3d.sensors.lidar_beams import GENERATOR_FIRING_OFFSETS_DEG, BeamPattern
from robustbench3d.sensors.scan_density import decimate_azimuth, firing_columns, point_columns

TURN_DEG = 0.0271  # the frame phase of the hand-built scan


def _firings(turn: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(laser, firing index j, azimuth) of every ray of the generator's revolution turned by ``turn``, written
    from the documented formula: firing j of laser k at offset_k + 0.09 floor(j (360 / 2154) / 0.09), the
    ego sectors dropped, then the whole revolution turned (KITTI order: laser by laser, azimuth increasing)."""
    lasers, js, azs = [], [], []
    for k in range(64):
        j = np.arange(2154)
        az = GENERATOR_FIRING_OFFSETS_DEG[k] + 0.09 * np.floor(j * (360.0 / 2154) / 0.09 + 1e-9)
        keep = az < 360.0
        for first, last, lo, hi in EGO_OCCLUSION_SECTORS:
            if first <= k <= last:
                keep &= ~(((az >= lo) & (az < hi)) | ((az < hi - 360.0) if hi > 360.0 else False))
        lasers.append(np.full(keep.sum(), k))
        js.append(j[keep])
        azs.append(az[keep] + turn)
    return np.concatenate(lasers), np.concatenate(js), np.concatenate(azs)


@pytest.fixture(scope="module")
def hand_scan() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(scan (N, 4) float32: one return per ray at 8-30 m, laser ids, firing indices)."""
    laser, j, az = _firings(TURN_DEG)
    rng = np.random.default_rng(5)
    dist = rng.uniform(8.0, 30.0, len(laser))
    phi, th = np.radians(LASER_ELEVATION_DEG[laser]), np.radians(az)
    scan = np.empty((len(laser), 4), dtype=np.float32)
    scan[:, 0] = dist * np.cos(phi) * np.cos(th)
    scan[:, 1] = dist * np.cos(phi) * np.sin(th)
    scan[:, 2] = LASER_ORIGIN_Z_M[laser] + dist * np.sin(phi)
    scan[:, 3] = rng.uniform(0.0, 1.0, len(laser))
    return scan, laser, j


def _row_indices(rows: np.ndarray, scan: np.ndarray) -> np.ndarray:
    """Index in ``scan`` of each row of ``rows`` (every row must be a row of ``scan``; rows of ``scan`` unique)."""
    void = np.dtype((np.void, scan.dtype.itemsize * scan.shape[1]))
    keys = np.ascontiguousarray(scan).view(void).reshape(-1)
    order = np.argsort(keys)
    found = np.ascontiguousarray(rows).view(void).reshape(-1)
    pos = np.searchsorted(keys[order], found)
    assert np.all(pos < len(keys)) and np.array_equal(keys[order][pos], found), "a row that is not in the input"
    return order[pos]


@pytest.mark.parametrize("k", [2, 3, 4, 7])
def test_hand_built_scan_keeps_the_firings_j_mod_k_zero(hand_scan, k):
    scan, laser, j = hand_scan
    expected = scan[j % k == 0]
    # the pattern given (the generator's), estimated from the scan, and with the laser ids given
    for kwargs in ({"pattern": BeamPattern.generator(TURN_DEG)}, {}, {"ring_ids": laser}):
        out = decimate_azimuth(scan, k, **kwargs)
        assert out.dtype == scan.dtype and out.tobytes() == expected.tobytes(), kwargs
    # per laser about 1/k of the firings (exactly ceil(n / k) for the lasers without ego sectors)
    for k_laser in range(64):
        n = int((laser == k_laser).sum())
        got = int((laser[j % k == 0] == k_laser).sum())
        if k_laser < 42:
            assert got == -(-n // k)
        assert abs(got / n - 1 / k) < 0.01


def test_columns_of_the_hand_built_scan_are_its_firing_indices(hand_scan):
    scan, laser, j = hand_scan
    ring, column, pattern = point_columns(scan)
    assert np.array_equal(ring, laser) and np.array_equal(column, j)
    assert pattern.shift_deg == pytest.approx(TURN_DEG, abs=1e-9)
    assert np.array_equal(firing_columns(BeamPattern.generator(TURN_DEG)), j)  # one point per ray, in ray order


def test_kept_columns_depend_on_the_pattern_only(hand_scan):
    """A part of the scan (the points ahead, a shuffled copy) decimates to the same points as the whole."""
    scan, laser, j = hand_scan
    pattern = BeamPattern.generator(TURN_DEG)
    part = np.flatnonzero(scan[:, 0] > 0)
    whole = decimate_azimuth(scan, 3, pattern=pattern)
    alone = decimate_azimuth(scan[part], 3, pattern=pattern, ring_ids=laser[part])
    assert alone.tobytes() == scan[part][j[part] % 3 == 0].tobytes()
    assert set(_row_indices(alone, scan)) <= set(_row_indices(whole, scan))
    perm = np.random.default_rng(0).permutation(len(scan))
    shuffled = decimate_azimuth(scan[perm], 3, pattern=pattern, ring_ids=laser[perm])
    assert shuffled.tobytes() == scan[perm][j[perm] % 3 == 0].tobytes()


def test_points_off_every_ray_are_dropped(hand_scan):
    """A return of laser 55 straight behind (inside its ego sector 156-206 deg: no ray within 0.09 deg) and one
    of an unknown laser get column -1 and are dropped; a return on a ray of column 0 is kept."""
    scan, laser, j = hand_scan
    pattern = BeamPattern.generator(TURN_DEG)
    on = np.flatnonzero((laser == 55) & (j == 0))[0]
    points = np.array([[-10.0, 0.0, -3.0, 0.5], scan[on], scan[on]], dtype=np.float32)
    ring = np.array([55, 64, 55])
    _, column, _ = point_columns(points, ring_ids=ring, pattern=pattern)
    assert column.tolist() == [-1, -1, 0]
    assert decimate_azimuth(points, 2, ring_ids=ring, pattern=pattern).tobytes() == points[2:].tobytes()


@pytest.fixture(scope="module")
def frame():
    from robustbench3d.synth.frame import generate_frame

    return generate_frame(0, 1)


def test_generated_frame(frame):
    scan = frame.scan
    assert decimate_azimuth(scan, 1) is scan  # k = 1: the scan itself, same bytes
    ring, column, _ = point_columns(scan)
    assert np.all(column >= 0)  # every generated point lies on a ray
    halves = decimate_azimuth(scan, 2)
    for k in (2, 3, 4):
        out = decimate_azimuth(scan, k)
        idx = _row_indices(out, scan)
        assert np.all(np.diff(idx) > 0)  # exact rows of the input, in input order
        assert np.all(column[idx] % k == 0)
        for laser in range(64):
            n = int((ring == laser).sum())
            if n >= 500:
                assert abs(int((ring[idx] == laser).sum()) / n - 1 / k) < 0.03, (k, laser)
        if k == 4:
            assert set(idx) <= set(_row_indices(halves, scan))  # multiples of 4 are multiples of 2


def test_attacked_scan_decimates_object_returns_like_the_scene(frame):
    from robustbench3d.attacks.base import target_cars
    from robustbench3d.attacks.object import random_shape
    from robustbench3d.attacks.roof import RoofObjectAttack
    from robustbench3d.sensors.lidar_render import render_lidar

    attack = RoofObjectAttack(random_shape(2))
    placed = attack.place(target_cars(frame.labels).select(slice(0, 4)), np.random.default_rng(0))
    meshes = [(frame.calib.rect_to_velo_points(v), attack.obj.faces, attack.obj.colors) for v, _ in placed]
    result = render_lidar(frame.scan, meshes, rng=np.random.default_rng(1), range_noise_m=0.02, dropout=0.05)
    assert len(result.added) > 200
    _, clean_column, pattern = point_columns(frame.scan)
    # the reference: each clean point's column, each added point's ray's firing index from the formula
    laser, j, _ = _firings(pattern.shift_deg)
    assert np.array_equal(laser, pattern.ray_rings(np.arange(len(laser))))
    kept = np.ones(len(frame.scan), dtype=bool)
    kept[result.removed_index] = False
    column = np.concatenate([clean_column[kept], j[result.ray_index]])
    ring, got, attacked_pattern = point_columns(result.scan)  # laser ids recovered from an unordered scan
    assert np.array_equal(got, column)
    for k in (2, 4):
        out = decimate_azimuth(result.scan, k) if k == 2 else \
            decimate_azimuth(result.scan, k, ring_ids=ring, pattern=attacked_pattern)
        assert out.tobytes() == result.scan[column % k == 0].tobytes()
        added_kept = (j[result.ray_index] % k == 0).sum()
        assert 0 < added_kept < len(result.added)


@pytest.mark.parametrize("k", [0, -2, 1.5, 2.0, True, "2", None])
def test_bad_k_names_the_field(hand_scan, k):
    with pytest.raises(ValueError, match=r"decimate_azimuth: field 'k': expected an integer >= 1"):
        decimate_azimuth(hand_scan[0], k)


def test_bad_scan_names_the_field():
    with pytest.raises(ValueError, match=r"decimate_azimuth: field 'scan': expected shape \(N, 4\)"):
        decimate_azimuth(np.zeros((5, 3), dtype=np.float32), 2)
