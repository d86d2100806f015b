"""The per-scan beam-pattern cache: same renders as estimating each time, robust to bad files, keyed by content."""

from __future__ import annotations

import numpy as np
import torch

from robustbench3d.sensors.lidar_beams import BeamPattern, estimate_pattern, scan_ring_ids
from robustbench3d.sensors.lidar_render import render_lidar
from robustbench3d.sensors.mesh import icosphere
from robustbench3d.sensors.pattern_cache import FILE_MAGIC, PatternCache, scan_key

torch.set_num_threads(1)


def _scan(phase: float, seed: int) -> np.ndarray:
    """One return per ray of the generator's pattern turned by ``phase``, 5-40 m, azimuth jitter 0.03 deg."""
    rays = BeamPattern.generator(phase).rays
    rng = np.random.default_rng(seed)
    az = np.radians(rays.azimuth_deg + rng.uniform(-0.03, 0.03, len(rays)))
    phi = np.arcsin(rays.directions[:, 2])
    d = np.stack([np.cos(phi) * np.cos(az), np.cos(phi) * np.sin(az), np.sin(phi)], 1)
    xyz = rays.origins + rng.uniform(5.0, 40.0, len(rays))[:, None] * d
    return np.concatenate([xyz, np.full((len(xyz), 1), 0.3)], 1).astype(np.float32)


def _meshes() -> list:
    v, f = icosphere(2, 0.4)
    return [(v + np.array([12.0, 3.0, -0.1]), f, None), (v + np.array([20.0, -2.5, -0.3]), f, None)]


def _kept(cache: PatternCache, scan: np.ndarray) -> BeamPattern:
    """The pattern ``render_lidar`` uses for ``scan`` with ``cache`` (kept, or estimated and stored)."""
    key, kept = cache.lookup(scan)
    if kept is None:
        kept = estimate_pattern(scan, scan_ring_ids(scan))
        cache.store(key, kept)
    return kept


def _same(a: BeamPattern, b: BeamPattern) -> bool:
    return a.phases_deg.tobytes() == b.phases_deg.tobytes() and a.shift_deg == b.shift_deg


def test_cached_render_is_bit_identical_cold_and_warm_and_from_disk(tmp_path):
    scan = _scan(0.017, 0)
    plain = render_lidar(scan, _meshes())
    cache = PatternCache(tmp_path)
    cold = render_lidar(scan, _meshes(), patterns=cache)
    files = list(tmp_path.glob("*.pattern"))
    assert len(files) == 1 and files[0].stem == scan_key(scan, None)
    warm = render_lidar(scan, _meshes(), patterns=cache)  # from memory, azimuths of the culled lasers only
    warm_disk = render_lidar(scan, _meshes(), patterns=PatternCache(tmp_path))  # a new process: read from disk
    assert len(plain.added) > 20
    for r in (cold, warm, warm_disk):
        assert r.scan.tobytes() == plain.scan.tobytes()
        assert _same(r.pattern, plain.pattern)
        np.testing.assert_array_equal(r.removed_index, plain.removed_index)


def test_estimate_is_kept_bit_for_bit_and_different_scans_get_their_own(tmp_path):
    cache = PatternCache(tmp_path)
    for phase, seed in ((0.003, 1), (0.031, 2), (0.044, 3)):
        scan = _scan(phase, seed)
        truth = estimate_pattern(scan, scan_ring_ids(scan))
        assert cache.lookup(scan)[1] is None
        assert _same(_kept(cache, scan), truth)
        assert _same(PatternCache(tmp_path).lookup(scan)[1], truth)  # from its file
        assert truth.shift_deg == np.float64(truth.shift_deg)  # a float64 survives the file
    assert len(list(tmp_path.glob("*.pattern"))) == 3


def test_key_covers_the_bytes_and_the_given_laser_ids():
    scan = _scan(0.02, 4)
    other = scan.copy()
    other[100, 0] = np.nextafter(other[100, 0], np.float32(np.inf))
    ring = scan_ring_ids(scan)
    keys = {scan_key(scan, None), scan_key(other, None), scan_key(scan, ring), scan_key(scan[:-1], None)}
    assert len(keys) == 4


def _file_values(path) -> tuple[bytes, np.ndarray]:
    """(the magic, the float64 values) of a pattern file, read independently of the cache."""
    data = path.read_bytes()
    return data[:len(FILE_MAGIC)], np.frombuffer(data[len(FILE_MAGIC):], "<f8")


def test_pattern_file_is_the_magic_then_the_phases_and_turn_as_little_endian_float64(tmp_path):
    scan = _scan(0.029, 7)
    truth = estimate_pattern(scan, scan_ring_ids(scan))
    _kept(PatternCache(tmp_path), scan)
    magic, values = _file_values(tmp_path / f"{scan_key(scan, None)}.pattern")
    assert magic == FILE_MAGIC and values.shape == (65,)
    assert values[:64].tobytes() == truth.phases_deg.astype("<f8").tobytes() and values[64] == truth.shift_deg


def test_unreadable_or_foreign_files_are_recomputed_and_rewritten(tmp_path):
    scan = _scan(0.012, 5)
    truth = estimate_pattern(scan, scan_ring_ids(scan))
    path = tmp_path / f"{scan_key(scan, None)}.pattern"
    good = FILE_MAGIC + np.zeros(65, "<f8").tobytes()
    # empty, foreign, one byte short or long, the right length under another magic
    for bad in (b"", b"not a pattern", good[:-1], good + b"\0", b"X" + good[1:]):
        path.write_bytes(bad)
        assert _same(_kept(PatternCache(tmp_path), scan), truth)
        magic, values = _file_values(path)  # rewritten whole
        assert magic == FILE_MAGIC and values[:64].tobytes() == truth.phases_deg.tobytes()
    path.unlink()
    path.mkdir()  # a directory where the file should be: unreadable, recomputed (the write fails, rendering goes on)
    assert _same(_kept(PatternCache(tmp_path), scan), truth)


def test_memory_only_and_read_only_caches_still_render(tmp_path):
    scan = _scan(0.025, 6)
    truth = estimate_pattern(scan, scan_ring_ids(scan))
    assert _same(_kept(PatternCache(None), scan), truth)
    blocked = tmp_path / "file"
    blocked.write_text("x")  # a file where the directory should be: writes fail, rendering goes on
    cache = PatternCache(blocked / "sub")
    assert _same(_kept(cache, scan), truth)
    assert _same(_kept(cache, scan), truth)  # from memory
