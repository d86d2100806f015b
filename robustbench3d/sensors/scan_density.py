"""Coarser horizontal resolution: keep every k-th azimuth column of each laser of a scan.

An HDL-64E whose lasers fire k times less often per revolution returns the points of every k-th firing of the
full-rate sensor. :func:`decimate_azimuth` makes that scan from a full-rate one: each point is matched to its
ray of the scan's beam pattern (:class:`~robustbench3d.sensors.lidar_beams.BeamPattern`: laser ids from
:func:`~robustbench3d.sensors.lidar_beams.scan_ring_ids` or given, the pattern given, kept in a
:class:`~robustbench3d.sensors.pattern_cache.PatternCache` or estimated; the nearest ray of the same laser
within half a firing step, 0.09 deg, as :mod:`robustbench3d.sensors.lidar_render` matches points to rays), and
a point is kept when its ray's **column** is a multiple of k. The column of a ray is its firing index j in its
laser's revolution (firing j at ``phase + 0.09 floor(j (360 / 2154) / 0.09)``, :mod:`~robustbench3d.sensors.
hdl64e`), counted over the ego-occluded firings too, so kept columns stay evenly spaced in azimuth across the
sectors the ego vehicle blocks. Which columns are kept depends on the pattern only, never on the other points.

Applied to an attacked scan (rendered object returns lie on the clean scan's rays, :mod:`robustbench3d.sensors.
lidar_render`), it decimates object returns and scene alike. Points that cannot be matched to a ray (laser
unknown, or no ray of their laser within 0.09 deg) are dropped for k > 1: no firing of the coarser sensor can
be shown to have produced them. Generated scans, clean or attacked, have none
(tests/sensors/test_sensors_scan_density.py);
:func:`point_columns` reports them as column -1.
"""

from __future__ import annotations

import numbers

import numpy as np

from robustbench3d.sensors.lidar_beams import BeamPattern, estimate_pattern, ring_ids_of
from robustbench3d.sensors.pattern_cache import PatternCache

__all__ = ["decimate_azimuth", "firing_columns", "point_columns"]


def firing_columns(pattern: BeamPattern) -> np.ndarray:
    """(R,) int64 firing index of each ray of ``pattern.rays`` in its laser's revolution (0 = the laser's first
    firing; the ego-occluded firings, which have no ray, keep their indices)."""
    s = pattern.sensor
    rays = pattern.rays
    # Every firing of the revolution, the same arithmetic as the pattern's rays without the ego sectors removed,
    # so a ray's azimuth equals its firing's bit for bit.
    ring_all, az_all = s.ray_azimuths(np.asarray(pattern.phases_deg, dtype=np.float64) - pattern.shift_deg,
                                      ego_occlusion=False)
    az_all = az_all + pattern.shift_deg
    ring_all = ring_all.astype(np.int64)
    ring = np.asarray(rays.ring, dtype=np.int64)
    first = np.searchsorted(ring_all, np.arange(s.num_lasers + 1))
    column = np.empty(len(ring), dtype=np.int64)
    for k in np.unique(ring).tolist():
        own = np.flatnonzero(ring == k)
        row = az_all[first[k]:first[k + 1]]
        pos = np.searchsorted(row, rays.azimuth_deg[own])
        if np.any(pos >= len(row)) or not np.array_equal(row[np.minimum(pos, len(row) - 1)], rays.azimuth_deg[own]):
            raise RuntimeError(f"firing_columns: the rays of laser {k} are not firings of its revolution")
        column[own] = pos
    return column


def _checked_scan(scan: np.ndarray, name: str) -> np.ndarray:
    pts = np.asarray(scan)
    if pts.ndim != 2 or pts.shape[1] != 4:
        raise ValueError(f"{name}: field 'scan': expected shape (N, 4), got {pts.shape}")
    return pts


def point_columns(scan: np.ndarray, *, ring_ids: np.ndarray | None = None, pattern: BeamPattern | None = None,
                  patterns: PatternCache | None = None) -> tuple[np.ndarray, np.ndarray, BeamPattern]:
    """(laser (N,) int64, column (N,) int64, pattern) of the points of ``scan`` (N, 4) velodyne: the firing
    index (:func:`firing_columns`) of each point's ray, -1 for a point without one (module doc).

    Args:
        ring_ids: (N,) laser of each point when known (else recovered from the scan).
        pattern: the scan's beam pattern when known (e.g. the clean scan's, for an attacked scan).
        patterns: where the estimated pattern is looked up and kept (without ``pattern``); default: estimated.
    """
    pts = _checked_scan(scan, "point_columns").astype(np.float32, copy=False)  # as the renderer reads it
    ring = ring_ids_of(pts, ring_ids, "point_columns")
    az = np.degrees(np.arctan2(pts[:, 1].astype(np.float64), pts[:, 0].astype(np.float64)))
    if pattern is None:
        key = None
        if patterns is not None:
            key, pattern = patterns.lookup(pts, ring_ids)
        if pattern is None:
            pattern = estimate_pattern(pts, ring, azimuth_deg=az)
            if key is not None:
                patterns.store(key, pattern)
    ray = pattern.nearest_ray(ring, az)
    column = np.where(ray >= 0, firing_columns(pattern)[np.maximum(ray, 0)], -1)
    return ring, column, pattern


def decimate_azimuth(scan: np.ndarray, k: int, *, ring_ids: np.ndarray | None = None,
                     pattern: BeamPattern | None = None, patterns: PatternCache | None = None) -> np.ndarray:
    """The rows of ``scan`` (N, 4) velodyne, in order, whose ray's firing column is a multiple of ``k`` (module
    doc): the scan of an HDL-64E with ``k`` times coarser horizontal resolution. ``k = 1`` returns ``scan``
    itself. ``ring_ids``, ``pattern``, ``patterns``: as :func:`point_columns`.

    Raises:
        ValueError: ``k`` not an integer >= 1, or a scan that is not (N, 4).
    """
    if isinstance(k, (bool, np.bool_)) or not isinstance(k, numbers.Integral) or k < 1:
        raise ValueError(f"decimate_azimuth: field 'k': expected an integer >= 1, got {k!r}")
    pts = _checked_scan(scan, "decimate_azimuth")
    if k == 1:
        return scan
    _, column, _ = point_columns(pts, ring_ids=ring_ids, pattern=pattern, patterns=patterns)
    return pts[(column >= 0) & (column % int(k) == 0)]
