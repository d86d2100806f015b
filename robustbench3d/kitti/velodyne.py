"""Velodyne scans (``velodyne/*.bin``): float32 rows of x, y, z (m, velodyne frame), reflectance [0, 1]."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from robustbench3d.errors import DataFormatError
from robustbench3d.fileio import atomic_write_bytes, read_data_bytes


def read_scan(path: str | Path) -> np.ndarray:
    """Read a scan as an (N, 4) float32 array, in file (ring) order."""
    path = Path(path)
    data = read_data_bytes(path)
    if len(data) % 16:
        raise DataFormatError(path, f"size {len(data)} bytes is not a multiple of 16 (4 float32 per point)")
    scan = np.frombuffer(data, dtype="<f4").reshape(-1, 4).copy()
    if not np.all(np.isfinite(scan)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(scan), axis=1))[0])
        raise DataFormatError(path, f"point {bad} has a non-finite value")
    return scan


def write_scan(path: str | Path, scan: np.ndarray) -> None:
    """Write an (N, 4) scan as little-endian float32, atomically."""
    scan = np.asarray(scan)
    if scan.ndim != 2 or scan.shape[1] != 4:
        raise ValueError(f"scan must be (N, 4), got {scan.shape}")
    atomic_write_bytes(path, np.ascontiguousarray(scan, dtype="<f4").tobytes())


def scan_rows(scan: np.ndarray) -> np.ndarray:
    """(N,) one opaque 16-byte value per point of an (N, 4) scan (its float32 bytes), so whole points
    compare with ``np.isin`` (e.g. which points an attack added or removed)."""
    return np.ascontiguousarray(scan, dtype="<f4").view(np.dtype((np.void, 16))).reshape(-1)



def row_indices(value: np.ndarray, what: str) -> np.ndarray:
    """``value`` as a read-only (M,) int64 copy of rows of a scan: 1-D integers, >= 0, strictly increasing
    (sorted, unique); ValueError starting with ``what`` otherwise. An empty array of any dtype is allowed."""
    arr = np.asarray(value)
    if arr.ndim != 1 or (arr.size and arr.dtype.kind not in "iu"):
        raise ValueError(f"{what}: expected a 1-D array of integer scan rows, got shape {arr.shape} {arr.dtype}")
    arr = np.array(arr, dtype=np.int64)
    if arr.size and (arr[0] < 0 or np.any(np.diff(arr) <= 0)):
        raise ValueError(f"{what}: scan rows must be >= 0, sorted and unique")
    arr.flags.writeable = False
    return arr
