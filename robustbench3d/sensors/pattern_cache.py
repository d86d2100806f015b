"""The beam pattern of each clean scan, estimated once and kept (memory and disk).

:func:`~robustbench3d.sensors.lidar_beams.estimate_pattern` reads every point of a scan (about 9 ms for a
120k-point scan, a third of rendering an object into it). The pattern is a property of the clean scan, not
of the object, and the same frame is attacked once per victim x proposals x attack cell, by every training
step that revisits it and by ``attack apply``: so it is estimated once per scan and kept in

    <cache>/scan_patterns/<sha256 of the scan>.pattern

(the key hashes the float32 (N, 4) scan bytes, their shape and, when given, the laser ids; about 1 ms).
A file holds :data:`FILE_MAGIC` and then the pattern's 64 per-laser phases and its turn as little-endian float64,
bit for bit those of the estimate (528 bytes, read in about 0.01 ms: an ``.npz`` took 0.35 ms, a twentieth of
a render); files are written atomically, and one that cannot be read (missing, truncated, another layout) is
recomputed and rewritten: the cache changes speed, never values. The last :data:`MEMORY_ITEMS` patterns are
also kept in memory (phases and turn only: each call returns a fresh
:class:`~robustbench3d.sensors.lidar_beams.BeamPattern`, whose cached ray tables, 2 MB and more, go with it).
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from pathlib import Path

import numpy as np

from robustbench3d.fileio import atomic_write_bytes
from robustbench3d.sensors.lidar_beams import BeamPattern

#: Bump when the estimate or the file layout changes: older files are then never read (2: the raw ``.pattern``
#: layout; version 1 wrote ``.npz`` files).
CACHE_VERSION = 2
#: First bytes of a pattern file; then :data:`_N_LASERS` phases and the turn, little-endian float64.
FILE_MAGIC = b"robustbench3d beam pattern v2\n"
_N_LASERS = 64
_FILE_BYTES = len(FILE_MAGIC) + 8 * (_N_LASERS + 1)
#: Patterns kept in memory per cache (least recently used dropped first).
MEMORY_ITEMS = 4096

__all__ = ["CACHE_VERSION", "FILE_MAGIC", "PatternCache", "default_pattern_cache", "scan_key"]


def scan_key(pts: np.ndarray, ring_ids: np.ndarray | None) -> str:
    """Hex sha256 of a float32 (N, 4) scan, its shape and the given laser ids (None: derived from the scan)."""
    h = hashlib.sha256(f"v{CACHE_VERSION} {pts.shape} {pts.dtype.str}".encode())
    h.update(np.ascontiguousarray(pts))
    if ring_ids is None:
        h.update(b"ring:derived")
    else:
        h.update(b"ring:")
        h.update(np.ascontiguousarray(ring_ids, dtype=np.int64))
    return h.hexdigest()


class PatternCache:
    """Estimated beam patterns by scan content, in memory and (if ``directory`` is given) on disk."""

    def __init__(self, directory: str | Path | None):
        self.directory = None if directory is None else Path(directory)
        self._memory: OrderedDict[str, tuple[np.ndarray, float]] = OrderedDict()

    def lookup(self, pts: np.ndarray, ring_ids: np.ndarray | None = None) -> tuple[str, BeamPattern | None]:
        """(key, the kept pattern of float32 points (N, 4) or None); ``ring_ids``: the laser ids as the renderer
        was given them (None when derived from the scan), part of the key."""
        key = scan_key(pts, ring_ids)
        found = self._memory.get(key)
        if found is not None:
            self._memory.move_to_end(key)
        else:
            found = self._read(key)
            if found is None:
                return key, None
            self._remember(key, found)
        return key, BeamPattern(found[0].copy(), found[1])

    def store(self, key: str, pattern: BeamPattern) -> None:
        """Keep the estimated ``pattern`` of the scan with ``key`` in memory and on disk."""
        found = (np.array(pattern.phases_deg, dtype=np.float64), float(pattern.shift_deg))
        self._write(key, *found)
        self._remember(key, found)

    def _remember(self, key: str, found: tuple[np.ndarray, float]) -> None:
        self._memory[key] = found
        if len(self._memory) > MEMORY_ITEMS:
            self._memory.popitem(last=False)

    def _path(self, key: str) -> Path | None:
        return None if self.directory is None else self.directory / f"{key}.pattern"

    def _read(self, key: str) -> tuple[np.ndarray, float] | None:
        path = self._path(key)
        if path is None:
            return None
        try:
            data = path.read_bytes()
        except OSError:  # missing or unreadable: recomputed and rewritten
            return None
        if len(data) != _FILE_BYTES or not data.startswith(FILE_MAGIC):
            return None
        values = np.frombuffer(data, "<f8", offset=len(FILE_MAGIC)).astype(np.float64)
        return values[:_N_LASERS], float(values[_N_LASERS])

    def _write(self, key: str, phases: np.ndarray, shift: float) -> None:
        path = self._path(key)
        if path is None or phases.shape != (_N_LASERS,):  # another sensor's pattern: kept in memory only
            return
        data = FILE_MAGIC + np.concatenate([phases, [shift]]).astype("<f8").tobytes()
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            atomic_write_bytes(path, data)
        except OSError:  # a read-only cache still renders, only slower
            pass


_DEFAULT: dict[Path, PatternCache] = {}


def default_pattern_cache() -> PatternCache:
    """The process's cache under ``<cache>/scan_patterns`` (:func:`robustbench3d.paths.cache_dir`, read now)."""
    from robustbench3d.paths import cache_dir

    directory = cache_dir() / "scan_patterns"
    if directory not in _DEFAULT:
        _DEFAULT[directory] = PatternCache(directory)
    return _DEFAULT[directory]
