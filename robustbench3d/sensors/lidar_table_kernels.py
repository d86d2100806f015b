"""Compiled (numba) table builders of the LiDAR render: one pass each, no search over the pattern's keys
(conventions: :mod:`robustbench3d.sensors.array_kernels`).

* :func:`beam_table` forms a pattern's ray azimuths as
  :meth:`robustbench3d.sensors.hdl64e.HDL64E.ray_azimuths` does and ``BeamPattern`` turns them.
* :func:`near_bins` is the grid lookup of ``BeamPattern.near_rays`` (``compiled=False``: its numpy code).
* :func:`cull_runs` cuts the meshes' culled rays into runs of consecutive rays of one laser, for
  :func:`robustbench3d.sensors.lidar_kernels.sphere_pairs_nearest`.
* :func:`rows_but` copies the scan rows the objects leave (:mod:`robustbench3d.sensors.lidar_render`).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, inline="always")
def _first_at_least(p: float, steps: np.ndarray, n: int, v: float) -> int:  # pragma: no cover - compiled
    """The first j < n with p + steps[j] >= v (n if none): p + steps[j] does not decrease with j."""
    lo, hi = 0, n
    while lo < hi:
        mid = (lo + hi) >> 1
        if p + steps[mid] >= v:
            hi = mid
        else:
            lo = mid + 1
    return lo


@njit(cache=True, nogil=True)
def _beam_table(phases: np.ndarray, shift: float, steps: np.ndarray, sec_first: np.ndarray, sec_last: np.ndarray,
                sec_lo: np.ndarray, sec_hi: np.ndarray, sec_wrap: np.ndarray) -> tuple:  # pragma: no cover - compiled
    n_lasers, n = len(phases), len(steps)
    az = np.empty(n_lasers * n)
    start = np.zeros(n_lasers + 1, np.int64)
    cut_lo, cut_hi = np.empty(len(sec_first) + 1, np.int64), np.empty(len(sec_first) + 1, np.int64)
    q = 0
    for k in range(n_lasers):
        start[k] = q
        p = phases[k]
        # firings p + steps[j] do not decrease with j: those below 360 are a prefix (none if p is NaN), and each
        # sector of the laser drops a range of them ([from, to), and with to past 360 those below to - 360)
        n_valid = 0 if not p < 360.0 else _first_at_least(p, steps, n, 360.0)
        n_cut = 0
        for s in range(len(sec_first)):
            if sec_first[s] <= k <= sec_last[s]:
                cut_lo[n_cut] = _first_at_least(p, steps, n_valid, sec_lo[s])
                cut_hi[n_cut] = _first_at_least(p, steps, n_valid, sec_hi[s])
                n_cut += 1
                if sec_hi[s] > 360.0:
                    cut_lo[n_cut], cut_hi[n_cut] = 0, _first_at_least(p, steps, n_valid, sec_wrap[s])
                    n_cut += 1
        j = 0
        while j < n_valid:
            cut = -1
            for c in range(n_cut):
                if cut_lo[c] <= j < cut_hi[c]:
                    cut = c
            if cut >= 0:  # j is cut: go on from the cut's end
                j = cut_hi[cut]
                continue
            stop = n_valid  # the kept run from j: up to the first cut that starts after j
            for c in range(n_cut):
                if j < cut_lo[c] < stop and cut_hi[c] > cut_lo[c]:
                    stop = cut_lo[c]
            for i in range(j, stop):
                az[q + i - j] = (p + steps[i]) + shift
            q += stop - j
            j = stop
    start[n_lasers] = q
    lowest, highest = np.inf, -np.inf
    if np.isfinite(shift):  # each laser's azimuths (no NaN) do not decrease: its first and last are its extremes
        for k in range(n_lasers):
            if start[k + 1] > start[k]:
                lowest, highest = min(lowest, az[start[k]]), max(highest, az[start[k + 1] - 1])
    else:
        for i in range(q):
            if az[i] != az[i]:  # as numpy's min and max: NaN
                lowest, highest = np.nan, np.nan
                break
            lowest, highest = min(lowest, az[i]), max(highest, az[i])
    return az[:q], start, lowest, highest


def beam_table(phases: np.ndarray, shift: float, steps: np.ndarray,
               sectors: tuple[tuple[int, int, float, float], ...]) -> tuple[np.ndarray, np.ndarray, float, float]:
    """The rays of a revolution as :meth:`robustbench3d.sensors.hdl64e.HDL64E.ray_azimuths` forms them and
    ``BeamPattern`` turns them, in one pass: laser k's firings at ``phases[k] + steps`` (float64, below 360) but
    those in an occluded sector of that laser (``sectors``: (first laser, last laser, from, to) degrees, ``to``
    past 360 wrapping), turned by ``shift``. Returns (azimuth (R,) = firing + shift, laser by laser, start (L + 1,)
    index of each laser's first ray and the total, the lowest and highest azimuth (+-inf without rays)): the same
    values as the numpy code, element by element."""
    sec = np.array([[f, last, lo, hi, hi - 360.0] for f, last, lo, hi in sectors], np.float64).reshape(-1, 5)
    return _beam_table(np.ascontiguousarray(phases, np.float64), float(shift), np.ascontiguousarray(steps, np.float64),
                       sec[:, 0].astype(np.int64), sec[:, 1].astype(np.int64), sec[:, 2].copy(), sec[:, 3].copy(),
                       sec[:, 4].copy())


@njit(cache=True, nogil=True)
def _near_bins(ring: np.ndarray, az: np.ndarray, grid: np.ndarray, bins: int, max_deg: float,
               out: np.ndarray) -> int:  # pragma: no cover - compiled
    for i in range(len(az)):
        if not (az[i] > -360.0 and az[i] < 360.0):  # NaN too: numpy's modulo
            return -1
    width = bins + 1
    for i in range(len(az)):
        a = az[i]
        m = a + 360.0 if a < 0.0 else a + 0.0  # _mod360's fast path
        col = int(np.floor(m / max_deg))
        r = ring[i]
        if r < 0 or r * width >= len(grid) or col < 0 or col > bins:
            return i
        out[i] = grid[r * width + col]
    return -2


def near_bins(ring: np.ndarray, az: np.ndarray, grid: np.ndarray, bins: int, max_deg: float) -> np.ndarray | None:
    """``grid.reshape(-1)[ring * (bins + 1) + floor(_mod360(az) / max_deg)]`` of
    :meth:`robustbench3d.sensors.lidar_beams.BeamPattern.near_rays` for points (lasers ``ring`` (N,), azimuths
    ``az`` (N,) degrees) and a per-laser ``grid`` (L, bins + 1) bool of near bins of ``max_deg``: the same
    arithmetic point by point; None when an azimuth lies outside (-360, 360) or is NaN (the numpy code then
    takes it modulo 360)."""
    grid = np.ascontiguousarray(grid, np.bool_)
    if grid.ndim != 2 or grid.shape[1] != bins + 1 or len(ring) != len(az):
        raise ValueError(f"near_bins: grid {grid.shape} for {bins} bins, {len(ring)} lasers for {len(az)} azimuths")
    out = np.empty(len(az), np.bool_)
    status = _near_bins(np.ascontiguousarray(ring, np.int64), np.ascontiguousarray(az, np.float64),
                        grid.reshape(-1), int(bins), float(max_deg), out)
    if status == -1:
        return None
    if status >= 0:
        raise ValueError(f"near_bins: point {status} (laser {ring[status]}, azimuth {az[status]}) outside the grid")
    return out


@njit(cache=True, nogil=True)
def _cull_runs(rays: np.ndarray, counts: np.ndarray, ring_start: np.ndarray, idx: np.ndarray
               ) -> tuple:  # pragma: no cover - compiled
    n_lasers = len(ring_start) - 1
    n_runs = 0
    start, stop, pos = np.empty(len(rays), np.int64), np.empty(len(rays), np.int64), np.empty(len(rays), np.int64)
    ptr = np.zeros(len(counts) * n_lasers + 1, np.int64)
    q = 0
    for m in range(len(counts)):
        laser = -1
        for j in range(q, q + counts[m]):
            ray = rays[j]
            if j > q and ray == rays[j - 1] + 1 and ray < ring_start[laser + 1]:  # the run goes on
                stop[n_runs - 1] = ray + 1
                continue
            laser = np.searchsorted(ring_start, ray, side="right") - 1
            start[n_runs], stop[n_runs] = ray, ray + 1
            pos[n_runs] = np.searchsorted(idx, ray)
            ptr[m * n_lasers + laser + 1] += 1
            n_runs += 1
        q += counts[m]
    for k in range(len(ptr) - 1):
        ptr[k + 1] += ptr[k]
    return ptr, start[:n_runs], stop[:n_runs], pos[:n_runs]


def cull_runs(rays: np.ndarray, counts: np.ndarray, ring_start: np.ndarray, idx: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The culled rays of M meshes as runs of consecutive rays of one laser: ``rays`` the meshes' culls (each
    increasing) concatenated, ``counts`` (M,) their lengths, ``ring_start`` (L + 1,) the index of each laser's first
    ray (and the total), ``idx`` the sorted union of the culls. Returns (ptr (M * L + 1,): runs ptr[m L + k] to
    ptr[m L + k + 1] - 1 are mesh m's on laser k, in ray order; start, stop (end, exclusive) rays of each run; pos:
    position of its first ray in ``idx``, the others following it there)."""
    rays, counts = np.ascontiguousarray(rays, np.int64), np.ascontiguousarray(counts, np.int64)
    ring_start, idx = np.ascontiguousarray(ring_start, np.int64), np.ascontiguousarray(idx, np.int64)
    if counts.sum() != len(rays) or (len(rays) and (rays.min() < 0 or rays.max() >= ring_start[-1])):
        raise ValueError(f"cull_runs: {len(rays)} rays for counts summing to {counts.sum()}, or rays outside "
                         f"[0, {ring_start[-1]})")
    return _cull_runs(rays, counts, ring_start, idx)


@njit(cache=True, nogil=True)
def _rows_but(rows: np.ndarray, removed: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover - compiled
    q, prev = 0, 0
    for r in range(len(removed) + 1):
        stop = removed[r] if r < len(removed) else len(rows)
        n = stop - prev
        out[q:q + n] = rows[prev:stop]
        q += n
        prev = stop + 1


def rows_but(rows: np.ndarray, removed: np.ndarray, extra: int = 0) -> np.ndarray:
    """The rows of ``rows`` (N, C) but those of ``removed`` (increasing, distinct, in [0, N)), in order, copied as
    their raw bytes (uint32 words: any float bits, NaN payloads included, stay as they are), in an array of
    N - len(removed) + ``extra`` rows and ``rows``' dtype whose last ``extra`` rows are left for the caller."""
    rows = np.ascontiguousarray(rows)
    removed = np.ascontiguousarray(removed, np.int64)
    if rows.ndim != 2 or rows.itemsize != 4:
        raise ValueError(f"rows_but: field 'rows': expected (N, C) of 4-byte items, got {rows.shape} {rows.dtype}")
    if len(removed) and (removed[0] < 0 or removed[-1] >= len(rows) or np.any(removed[1:] <= removed[:-1])):
        raise ValueError(f"rows_but: field 'removed': indices must increase within [0, {len(rows)})")
    out = np.empty((len(rows) - len(removed) + extra, rows.shape[1]), rows.dtype)
    _rows_but(rows.view(np.uint32), removed, out.view(np.uint32))
    return out
