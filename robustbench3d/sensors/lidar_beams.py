"""The HDL-64E rays of one scan, and which rays can reach an object (culling).

Frame: velodyne (x forward, y left, z up; m), angles in degrees. The generator
(:mod:`robustbench3d.synth.lidar`) fires laser k at azimuths ``offset_k + 0.09 floor(j (360 / 2154) / 0.09)``
(:meth:`~robustbench3d.sensors.hdl64e.HDL64E.ring_azimuths`, fixed per-laser offsets
:data:`GENERATOR_FIRING_OFFSETS_DEG`), drops the ego-occluded sectors, then turns the whole revolution by a
random frame phase in [0, 0.045). A :class:`BeamPattern` holds exactly that: per laser the phase of its first
firing after the turn, plus the turn itself (the ego sectors are fixed to the sensor, before the turn).

:func:`estimate_pattern` recovers the pattern from a scan: a point's azimuth atan2(y, x) is its ray's azimuth
(the lasers sit on the z axis), so each laser's phase is the circular mean of its points' azimuths modulo
0.09 deg. On generator scans the per-laser phases minus the generator's offsets agree to rounding, and the
exact generator pattern is returned; on real KITTI scans each laser keeps its measured phase.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from robustbench3d.sensors.hdl64e import (
    AZIMUTH_QUANTUM_DEG,
    EGO_OCCLUSION_SECTORS,
    HDL64E,
    BeamRays,
    _firing_steps,
    ring_ids_from_azimuth_wrap,
)
from robustbench3d.sensors.lidar_kernels import cone_cull, nearest_rays, sphere_pairs_nearest, sphere_ray_ranges
from robustbench3d.sensors.lidar_table_kernels import beam_table, cull_runs, near_bins

#: Per-laser firing offsets of the generator's sensor (used by ``synth.lidar``), degrees in [0, 0.045).
GENERATOR_FIRING_OFFSETS_DEG = np.random.default_rng(64).uniform(0.0, AZIMUTH_QUANTUM_DEG / 2, 64)
#: Nominal azimuth step between firings of one laser, degrees.
AZIMUTH_STEP_DEG = 2 * AZIMUTH_QUANTUM_DEG
#: Largest spread (deg) of the per-laser phase minus generator offset for a scan to count as the generator's.
_GENERATOR_PHASE_TOL_DEG = 2e-3
_BAND = 1000.0  # key = ring * _BAND + azimuth sorts rays by laser, then azimuth

__all__ = ["AZIMUTH_STEP_DEG", "GENERATOR_FIRING_OFFSETS_DEG", "BeamPattern", "estimate_pattern", "scan_ring_ids"]


@dataclass(frozen=True)
class BeamPattern:
    """Ray pattern of one revolution.

    Attributes:
        phases_deg: (64,) azimuth of each laser's first firing, after the turn, degrees (about [-0.045, 0.09)).
        shift_deg: the revolution's turn (the generator's frame phase); 0 for real scans.
        sensor: beam geometry (elevations, laser heights, firings per revolution).
    """

    phases_deg: np.ndarray
    shift_deg: float = 0.0
    sensor: HDL64E = field(default_factory=HDL64E)

    @classmethod
    def generator(cls, frame_phase_deg: float) -> BeamPattern:
        """The generator's pattern for a frame turned by ``frame_phase_deg`` (its first lidar rng draw)."""
        return cls(GENERATOR_FIRING_OFFSETS_DEG + frame_phase_deg, float(frame_phase_deg))

    @cached_property
    def rays(self) -> BeamRays:
        """All rays of the revolution in scan order (laser by laser, azimuth increasing)."""
        ring, az = self._ring_azimuth
        return BeamRays(self.sensor.origins(ring), self.sensor.directions(ring, az), ring, az)

    @cached_property
    def _table(self) -> tuple[np.ndarray, np.ndarray, float, float]:
        """(azimuth_deg (R,) of :attr:`rays`, :attr:`ring_start`, lowest and highest azimuth (+-inf without rays)),
        without the rays' geometry or lasers: the firings of ``sensor.ray_azimuths(phases_deg - shift_deg)`` turned by
        ``shift_deg``, in one compiled pass (:func:`robustbench3d.sensors.lidar_table_kernels.beam_table`, the same
        values)."""
        s = self.sensor
        phases = (np.asarray(self.phases_deg, dtype=np.float64) - self.shift_deg)[:s.num_lasers]
        return beam_table(phases, self.shift_deg, _firing_steps(s.firings_per_revolution, s.azimuth_quantum_deg),
                          EGO_OCCLUSION_SECTORS)

    @cached_property
    def _ring_azimuth(self) -> tuple[np.ndarray, np.ndarray]:
        """(ring (R,) int64, azimuth_deg (R,)) of :attr:`rays`, without their geometry."""
        start = self.ring_start
        return np.repeat(np.arange(len(start) - 1, dtype=np.int64), np.diff(start)), self._table[0]

    @property
    def _banded(self) -> bool:
        """Whether the rays' azimuths lie in [-1, 361) degrees, so that a key ring x _BAND + azimuth of laser k in
        k x _BAND + [-360, 720) sorts between the lower and the higher lasers' rays: the compiled searches then
        look for keys laser by laser (see :func:`robustbench3d.sensors.lidar_kernels.cone_cull`)."""
        lowest, highest = self._azimuth_range
        return bool(lowest >= -1.0 and highest < 361.0)

    def ray_geometry(self, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(origins (K, 3), unit directions (K, 3)) of the rays ``index`` (K,): ``rays.origins[index]`` and
        ``rays.directions[index]``, bit for bit, without building every ray of the revolution."""
        index = np.asarray(index, dtype=np.int64)
        if "rays" in self.__dict__:
            return self.rays.origins[index], self.rays.directions[index]
        ring = self.ray_rings(index)
        return self.sensor.origins(ring), self.sensor.directions(ring, self._table[0][index])

    @property
    def ring_start(self) -> np.ndarray:
        """(65,) index of each laser's first ray in :attr:`rays` (and the total at the end)."""
        return self._table[1]

    @property
    def _azimuth_range(self) -> tuple[float, float]:
        """(lowest, highest) azimuth of the rays, degrees (+-inf without rays)."""
        return self._table[2], self._table[3]

    @cached_property
    def _keys(self) -> np.ndarray:
        """(R,) ring x _BAND + azimuth of the rays, sorted (the numpy code's search keys; the compiled searches
        form them as they go)."""
        ring, az = self._ring_azimuth
        return ring * _BAND + az

    def cull(self, center: np.ndarray, radius: float, margin_deg: float = AZIMUTH_STEP_DEG) -> np.ndarray:
        """Indices (int64, increasing) of the rays whose direction passes within ``radius`` (m) of ``center``
        (3,), widened by ``margin_deg`` of azimuth on each side.

        Per laser k with apex o_k = (0, 0, h0_k) and c = center - o_k: the ray at azimuth theta is within the
        sphere's tangent cone iff cos(phi_k) |c_xy| cos(theta - theta_c) + sin(phi_k) c_z >= sqrt(|c|^2 - r^2),
        which gives no azimuth (the laser's cone misses the sphere), all of them (apex inside), or an interval.
        """
        return self.cull_many(np.reshape(np.asarray(center, dtype=np.float64), (1, 3)), [radius], margin_deg)[0]

    def cull_many(self, centers: np.ndarray, radii: np.ndarray, margin_deg: float = AZIMUTH_STEP_DEG,
                  compiled: bool = True) -> list[np.ndarray]:
        """:meth:`cull` of each sphere (``centers`` (M, 3), ``radii`` (M,)), all lasers of all spheres at once.
        ``compiled=False``: the numpy code (the reference of the compiled
        :func:`robustbench3d.sensors.lidar_kernels.cone_cull`, which gives the same rays)."""
        s = self.sensor
        c = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
        if compiled and self._banded:  # the same arithmetic, sphere by sphere and laser by laser (the numpy code)
            return cone_cull(c, np.asarray(radii, dtype=np.float64).reshape(-1), np.radians(s.elevation_deg),
                             s.origin_z, margin_deg, self._table[0], self.ring_start, _BAND)
        r = np.asarray(radii, dtype=np.float64).reshape(-1) * (1 + 1e-9) + 1e-9
        cz = c[:, 2:3] - s.origin_z[None, :]
        rho = np.hypot(c[:, 0], c[:, 1])[:, None]
        dist2 = rho * rho + cz * cz
        r2 = (r * r)[:, None]
        phi = np.radians(s.elevation_deg)
        inside = dist2 <= r2
        with np.errstate(divide="ignore", invalid="ignore"):
            kappa = (np.sqrt(np.maximum(dist2 - r2, 0.0)) - np.sin(phi) * cz) / (np.cos(phi) * rho)
        # lowered by 1e-9 as in sphere_rays: kappa's rounding (~1e-15) would otherwise decide a sphere seen under
        # less than ~1e-7 rad, whose cos is 1 - 5e-15 or closer
        kappa = np.where(inside, -np.inf, np.nan_to_num(kappa, nan=np.inf, posinf=np.inf, neginf=-np.inf)) - 1e-9
        sphere, active = np.nonzero(kappa <= 1.0)  # (sphere, laser) pairs whose cone reaches the sphere
        half = np.degrees(np.arccos(np.clip(kappa[sphere, active], -1.0, 1.0))) + margin_deg
        theta = (np.degrees(np.arctan2(c[:, 1], c[:, 0])) % 360.0)[sphere]
        full = half >= 180.0
        starts, stops = [], []
        for turn in (-360.0, 0.0, 360.0):  # a full laser gets its whole range three times (dropped by unique)
            lo = np.clip(theta - half + turn, -1.0, 500.0)
            hi = np.clip(theta + half + turn, -1.0, 500.0)
            lo[full], hi[full] = -1.0, 500.0
            starts.append(np.searchsorted(self._keys, active * _BAND + lo, "left"))
            stops.append(np.searchsorted(self._keys, active * _BAND + hi, "right"))
        start, stop = np.concatenate(starts), np.concatenate(stops)
        owner = np.repeat(np.tile(sphere, 3), np.maximum(stop - start, 0))
        n_rays = len(self._keys)
        key = np.unique(owner * n_rays + _expand_ranges(start, stop))  # by sphere, then ray
        bounds = np.searchsorted(key, np.arange(len(c) + 1) * n_rays)
        rays = key - np.repeat(np.arange(len(c)) * n_rays, np.diff(bounds))
        return [rays[bounds[i]:bounds[i + 1]] for i in range(len(c))]

    def sphere_rays(self, centers: np.ndarray, radii: np.ndarray, first_laser: np.ndarray, last_laser: np.ndarray,
                    compiled: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """(sphere (K,), ray (K,)) int64 pairs: for each sphere (``centers`` (M, 3), ``radii``
        (M,)) the rays of lasers ``first_laser[m]``..``last_laser[m]`` that can pass through it.

        The lasers are first narrowed to those whose elevation is within the sphere's angular radius of the
        centre's elevation seen from some laser origin; then per laser the azimuths within its cone's reach of the
        sphere (:meth:`cull`'s test, without its margin). The tests keep margins (1e-9, 1e-7 deg) far above their
        rounding: a superset of those rays; cheaper than :meth:`cull` for many small spheres on few lasers.
        ``compiled=False``: the numpy code (the reference of the compiled
        :func:`robustbench3d.sensors.lidar_kernels.sphere_ray_ranges`, which gives the same pairs in the same order)."""
        s = self.sensor
        c = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
        r = np.asarray(radii, dtype=np.float64).reshape(-1)
        first = np.asarray(first_laser, dtype=np.int64).reshape(-1)
        last = np.asarray(last_laser, dtype=np.int64).reshape(-1)
        if compiled:  # the same arithmetic, sphere by sphere and laser by laser (the numpy code below)
            return sphere_ray_ranges(c, r, first, last, np.radians(s.elevation_deg), s.origin_z, self._keys, _BAND)
        rho = np.hypot(c[:, 0], c[:, 1])
        phi = np.radians(s.elevation_deg)
        if np.all(np.diff(phi) < 0):  # lasers top down: keep those within the sphere's reach from any apex height
            h_lo, h_hi = float(s.origin_z.min()), float(s.origin_z.max())
            d_min = np.hypot(rho, c[:, 2] - np.clip(c[:, 2], h_lo, h_hi))  # from the nearest apex
            with np.errstate(divide="ignore", invalid="ignore"):
                reach = np.arcsin(np.minimum(r / d_min, 1.0)) + 1e-9
            top = np.where(r >= d_min, np.inf, np.arctan2(c[:, 2] - h_lo, rho) + reach)
            bottom = np.where(r >= d_min, -np.inf, np.arctan2(c[:, 2] - h_hi, rho) - reach)
            first = np.maximum(first, np.searchsorted(-phi, -top, "left"))
            last = np.minimum(last, np.searchsorted(-phi, -bottom, "right") - 1)
        width = np.maximum(last - first + 1, 0)
        sphere = np.repeat(np.arange(len(c)), width)
        laser = first[sphere] + np.arange(len(sphere)) - np.repeat(np.cumsum(width) - width, width)
        # The cone of laser k (apex o_k, elevation phi_k) and the sphere: the ray at azimuth theta passes within r
        # of c iff cos(phi_k) rho cos(theta - theta_c) + sin(phi_k) (c_z - h_k) >= sqrt(|c - o_k|^2 - r^2), i.e.
        # cos(theta - theta_c) >= kappa (as in cull); kappa is lowered by 1e-9 (far above its rounding, ~1e-15)
        # before the arccos, whose slope is unbounded at 1.
        rs, rho_s, dz = r[sphere], rho[sphere], c[sphere, 2] - s.origin_z[laser]
        dist2 = rho_s * rho_s + dz * dz
        with np.errstate(divide="ignore", invalid="ignore"):
            kappa = (np.sqrt(np.maximum(dist2 - rs * rs, 0.0)) - np.sin(phi[laser]) * dz) / (np.cos(phi[laser]) * rho_s)
        kappa = kappa - 1e-9
        full = (rs >= rho_s) | (dist2 <= rs * rs) | (kappa <= -1.0)  # every azimuth (or the axis in reach)
        hit = np.flatnonzero(full | (kappa <= 1.0))
        sphere, laser, full = sphere[hit], laser[hit], full[hit]
        theta = (np.degrees(np.arctan2(c[:, 1], c[:, 0])) % 360.0)[sphere]
        with np.errstate(invalid="ignore"):
            half = np.degrees(np.arccos(np.clip(kappa[hit], -1.0, 1.0))) + 1e-7
        lo, hi = theta - half, theta + half
        lo[full], hi[full] = -1.0, 500.0
        wrap = np.flatnonzero(~full & ((lo < 1.0) | (hi > 359.0)))  # may also reach rays a turn away
        lo = np.concatenate([lo, lo[wrap] + 360.0, lo[wrap] - 360.0]).clip(-1.0, 500.0)
        hi = np.concatenate([hi, hi[wrap] + 360.0, hi[wrap] - 360.0]).clip(-1.0, 500.0)
        sphere = np.concatenate([sphere, sphere[wrap], sphere[wrap]])
        laser = np.concatenate([laser, laser[wrap], laser[wrap]])
        start = np.searchsorted(self._keys, laser * _BAND + lo, "left")
        stop = np.searchsorted(self._keys, laser * _BAND + hi, "right")
        return np.repeat(sphere, np.maximum(stop - start, 0)), _expand_ranges(start, stop)

    def cull_runs(self, culls: Sequence[np.ndarray], idx: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The rays of M culls (each increasing, e.g. :meth:`cull_many`'s) as runs of consecutive rays of one laser, for
        :meth:`sphere_nearest` (:func:`robustbench3d.sensors.lidar_table_kernels.cull_runs`); ``idx``: the sorted union
        of the culls, which numbers the rays of the search."""
        rays = np.concatenate(culls) if len(culls) else np.zeros(0, np.int64)
        return cull_runs(rays, np.array([len(c) for c in culls], np.int64), self.ring_start, idx)

    def sphere_nearest(self, centers: np.ndarray, radii: np.ndarray, mesh: np.ndarray,
                       runs: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], table: np.ndarray,
                       d_cols: np.ndarray, h: np.ndarray, t_min: float, tol: float
                       ) -> tuple[np.ndarray, np.ndarray, int]:
        """The nearest of the faces (bounding spheres ``centers`` (F, 3), ``radii`` (F,), their culls ``mesh``
        (F,) among those of ``runs``, :meth:`cull_runs`) hit by each culled ray: (face (R,) or -1, t (R,) or +inf,
        pairs tested) of the Möller–Trumbore test (per-face ``table`` (18, F) with offsets, directions ``d_cols``
        (3, R) and apex heights ``h`` (R,) of the R rays of ``idx``) on the pairs of :meth:`sphere_rays` (lasers of
        each face's cull) whose ray is in the face's cull, tested as they are found
        (:func:`robustbench3d.sensors.lidar_kernels.sphere_pairs_nearest`)."""
        s = self.sensor
        return sphere_pairs_nearest(centers, radii, mesh, runs, np.radians(s.elevation_deg), s.origin_z,
                                    self._table[0], _BAND, table, d_cols, h, t_min, tol)

    def ray_rings(self, index: np.ndarray) -> np.ndarray:
        """(K,) int64 laser of the rays ``index`` (K,), without building the rays (from :attr:`ring_start`; an
        index outside [0, R) is read as numpy reads the lasers of all rays at it)."""
        index = np.asarray(index, dtype=np.int64)
        start = self.ring_start
        if index.size and not (index.min() >= 0 and index.max() < start[-1]):
            return self._ring_azimuth[0][index]
        return np.searchsorted(start, index, "right") - 1

    def near_rays(self, index: np.ndarray, ring: np.ndarray, azimuth_deg: np.ndarray,
                  max_deg: float = AZIMUTH_QUANTUM_DEG, compiled: bool = True) -> np.ndarray:
        """(N,) bool, a superset of the points (laser ``ring``, ``azimuth_deg``) whose :meth:`nearest_ray` within
        ``max_deg`` can be one of the rays ``index``: those within about ``max_deg`` of such a ray's azimuth on
        the same laser (bins of ``max_deg`` per laser: the ray's bin and two on either side). The points' bins are
        looked up by :func:`robustbench3d.sensors.lidar_table_kernels.near_bins` (``compiled=False``: the numpy code,
        which it follows point by point)."""
        nl = self.sensor.num_lasers
        ring = np.asarray(ring, dtype=np.int64)
        bins = int(np.ceil(360.0 / max_deg))
        rr, raz = self.ray_rings(index), self._table[0][np.asarray(index, dtype=np.int64)]
        # One extra column repeats column 0: a point's bin floor(az / max_deg), az in [0, 360], is at most bins,
        # where bin % bins = 0.
        grid = np.zeros((nl, bins + 1), dtype=bool)
        b = np.floor(raz / max_deg).astype(np.int64)
        for step in range(-2, 3):
            grid[rr, (b + step) % bins] = True
        grid[:, bins] = grid[:, 0]
        out = np.zeros(len(ring), dtype=bool)
        if len(rr) == 0:
            return out
        # Only the points of the rays' lasers can be near: when the points are laser-ordered, those from the first
        # to the last of these lasers (a slice; the other lasers in between have no near bin).
        if len(ring) and np.all(ring[1:] >= ring[:-1]):
            pick: slice | np.ndarray = slice(int(np.searchsorted(ring, rr.min(), "left")),
                                             int(np.searchsorted(ring, rr.max(), "right")))
        else:
            pick = np.flatnonzero(np.isin(ring, np.unique(rr)))
        az = np.asarray(azimuth_deg, dtype=np.float64)[pick]
        found = near_bins(ring[pick], az, grid, bins, max_deg) if compiled else None
        if found is not None:
            out[pick] = found
            return out
        b = np.floor(_mod360(az) / max_deg).astype(np.int64)
        if len(b) and b.min() < 0:  # NaN azimuths (their int64 is negative): wrap as bin % bins does
            b %= bins
        out[pick] = grid.reshape(-1)[ring[pick] * (bins + 1) + b]
        return out

    def nearest_ray(self, ring: np.ndarray, azimuth_deg: np.ndarray, max_deg: float = AZIMUTH_QUANTUM_DEG,
                    compiled: bool = True) -> np.ndarray:
        """(N,) index of the ray of laser ``ring`` nearest in azimuth to ``azimuth_deg`` (circularly), or -1
        when none lies within ``max_deg`` or the ring is unknown (< 0 or >= 64). ``compiled=False``: the numpy
        code (the reference of :func:`robustbench3d.sensors.lidar_kernels.nearest_rays`, which gives the same rays)."""
        ring = np.asarray(ring, dtype=np.int64)
        az = _mod360(azimuth_deg)
        if compiled and self._banded and len(ring) == len(az):
            return nearest_rays(ring, az, self.ring_start, self._table[0], self._azimuth_range, max_deg, _BAND)
        out = np.full(len(ring), -1, dtype=np.int64)
        known = (ring >= 0) & (ring < self.sensor.num_lasers)
        if not known.any():
            return out
        rk, ak = ring[known], az[known]
        first, last = self.ring_start[rk], self.ring_start[rk + 1] - 1
        raz = self._table[0]
        best = np.full(len(rk), -1, dtype=np.int64)
        gap = np.full(len(rk), np.inf)
        # A turn of -360 (+360) can only bring a ray within max_deg of the points within max_deg of the lowest
        # ray azimuth + 360 (the highest - 360), with 1e-6 deg to spare over the rounding (~1e-13); the other
        # points' candidates of that turn lie farther than max_deg, so they decide nothing: whichever candidate
        # is kept for such a point, its gap is then above max_deg and it ends at -1 in either case.
        lowest, highest = self._azimuth_range
        reach = {-360.0: ak >= lowest + 360.0 - max_deg - 1e-6, 360.0: ak <= highest - 360.0 + max_deg + 1e-6}
        for turn in (-360.0, 0.0, 360.0):
            sel = None if turn == 0.0 else np.flatnonzero(reach[turn])
            if sel is None:
                r_s, a_s, f_s, l_s = rk, ak, first, last
            elif len(sel):
                r_s, a_s, f_s, l_s = rk[sel], ak[sel], first[sel], last[sel]
            else:
                continue
            pos = np.searchsorted(self._keys, r_s * _BAND + a_s + turn)
            for cand in (pos - 1, pos):
                ok = (cand >= f_s) & (cand <= l_s)
                cand = np.clip(cand, 0, len(raz) - 1)
                g = np.where(ok, np.abs(raz[cand] - (a_s + turn)), np.inf)
                if sel is None:
                    better = g < gap
                    best[better], gap[better] = cand[better], g[better]
                else:
                    better = g < gap[sel]
                    best[sel[better]], gap[sel[better]] = cand[better], g[better]
        out[known] = np.where(gap <= max_deg, best, -1)
        return out


def _expand_ranges(starts: np.ndarray, stops: np.ndarray) -> np.ndarray:
    """Concatenation of arange(s, e) over the pairs (empty ranges allowed)."""
    n = np.maximum(stops - starts, 0)
    if n.sum() == 0:
        return np.zeros(0, dtype=np.int64)
    keep = n > 0
    starts, n = starts[keep], n[keep]
    offs = np.repeat(starts - np.concatenate([[0], np.cumsum(n)[:-1]]), n)
    return offs + np.arange(n.sum())


def scan_ring_ids(scan: np.ndarray, sensor: HDL64E | None = None) -> np.ndarray:
    """(N,) laser index of each point of a scan (velodyne (N, >=3)).

    KITTI-ordered scans with all 64 lasers present (real and generated ones): the azimuth-wrap heuristic
    (:func:`~robustbench3d.sensors.hdl64e.ring_ids_from_azimuth_wrap`). Otherwise (unordered or with empty
    lasers) the laser whose cone z = rho tan(phi_k) + h0_k passes closest to the point.
    """
    if len(scan) == 0:
        return np.zeros(0, dtype=np.int64)
    s = sensor or HDL64E()
    wrap = ring_ids_from_azimuth_wrap(scan)
    if wrap.max() == s.num_lasers - 1:
        return wrap
    pts = np.asarray(scan, dtype=np.float64)
    rho = np.hypot(pts[:, 0], pts[:, 1])
    cone = rho[:, None] * np.tan(np.radians(s.elevation_deg))[None, :] + s.origin_z[None, :]
    return np.argmin(np.abs(pts[:, 2:3] - cone), axis=1).astype(np.int64)


def ring_ids_of(pts: np.ndarray, ring_ids: np.ndarray | None, where: str) -> np.ndarray:
    """(N,) int64 laser of each point of ``pts``: ``ring_ids`` checked for length (error naming ``where``), else
    recovered from the points (:func:`scan_ring_ids`)."""
    if ring_ids is None:
        return scan_ring_ids(pts)
    ring = np.asarray(ring_ids, dtype=np.int64).reshape(-1)
    if len(ring) != len(pts):
        raise ValueError(f"{where}: field 'ring_ids': {len(ring)} ids for {len(pts)} points")
    return ring


def _circular_mean(x: np.ndarray, period: float) -> float:
    """Circular mean of ``x`` modulo ``period``, in [-period / 2, period / 2), then again over the values within
    a quarter period of it (robust to a few stray points). A phase just below a multiple of the azimuth quantum
    comes out slightly negative, so the firings keep their index (``ring_azimuths`` counts from the phase)."""
    a = 2 * np.pi * np.asarray(x) / period
    m = np.arctan2(np.sin(a).mean(), np.cos(a).mean())
    near = np.cos(a - m) > 0.0
    if near.any():
        m = np.arctan2(np.sin(a[near]).mean(), np.cos(a[near]).mean())
    return (float(m * period / (2 * np.pi)) + period / 2) % period - period / 2


def _mod360(az: np.ndarray) -> np.ndarray:
    """``az % 360.0``, bit for bit; for azimuths within (-360, 360) (those of atan2) without the division."""
    az = np.asarray(az, dtype=np.float64)
    if len(az) and not (az.min() > -360.0 and az.max() < 360.0):  # NaN too
        return az % 360.0
    out = az + 0.0  # + 0.0: -0.0 % 360 is +0.0
    np.add(az, 360.0, out=out, where=az < 0.0)
    return out


def _mod_positive(x: np.ndarray, q: float) -> np.ndarray:
    """``x % q`` (q > 0), bit for bit; for 0 <= x < 2^20 q without fmod: with q = qh + ql split in 26-bit
    halves (Veltkamp) and n = floor(x / q), ``(x - n qh) - n ql`` is exact (both products are, the first
    difference is smaller than 2x, and the result x - n q, fmod's, is representable) once n is the exact
    quotient's floor; a rounded division that crossed an integer shows as a result outside [0, q)."""
    x = np.asarray(x, dtype=np.float64)
    if len(x) == 0 or not (x.min() >= 0.0 and x.max() < q * 2.0 ** 20):
        return x % q
    c = 134217729.0 * q  # 2^27 + 1
    qh = c - (c - q)
    ql = q - qh
    n = x / q
    np.floor(n, out=n)
    r = n * qh
    np.subtract(x, r, out=r)
    r -= n * ql  # (x - n qh) - n ql, the same operations without temporaries
    if r.min() < 0.0 or r.max() >= q:
        off = np.flatnonzero((r < 0.0) | (r >= q))
        n[off] += np.where(r[off] < 0.0, -1.0, 1.0)
        r[off] = (x[off] - n[off] * qh) - n[off] * ql
    return r


def _circular_means(x: np.ndarray, lo: np.ndarray, hi: np.ndarray, period: float) -> np.ndarray:
    """:func:`_circular_mean` of each slice ``x[lo[k]:hi[k]]`` (non-empty, increasing, disjoint), bit for bit:
    the same element-wise values and sums (``v.mean()`` is ``np.add.reduce(v) / len(v)``; a slice's sin and cos
    are summed by one ``np.add.reduce(.., axis=1)`` of their (2, n) rows, the same pairwise sums), with sin and
    cos of ``x`` evaluated once. The second pass of a slice changes nothing when all its values pass the test
    cos(a - m) > 0, which holds when the slice's box of (cos a, sin a) (per-slice minima and maxima) keeps
    cos a cos m + sin a sin m above 1e-9 (far above its rounding, ~1e-16); the other slices decide the test
    value by value as :func:`_circular_mean` does."""
    total = np.add.reduce
    lo, hi = np.asarray(lo, dtype=np.int64), np.asarray(hi, dtype=np.int64)
    a = np.multiply(2 * np.pi, x)
    a /= period  # 2 pi x / period
    sc = np.empty((2, len(a)))
    np.sin(a, out=sc[0])
    np.cos(a, out=sc[1])
    n = hi - lo
    sums = np.array([total(sc[:, i:j], axis=1) for i, j in zip(lo.tolist(), hi.tolist(), strict=True)])
    sums = sums.reshape(-1, 2)
    m = np.arctan2(sums[:, 0] / n, sums[:, 1] / n)
    # Per slice (cos a, sin a) lies in [c_lo, c_hi] x [s_lo, s_hi]: a lower bound of cos a cos m + sin a sin m.
    ends = np.stack([lo, hi], axis=1).reshape(-1)
    ends = ends[ends < len(a)]
    low = np.minimum.reduceat(sc, ends, axis=1)[:, ::2]
    high = np.maximum.reduceat(sc, ends, axis=1)[:, ::2]
    sin_m, cos_m = np.sin(m), np.cos(m)
    bound = (np.minimum(low[1] * cos_m, high[1] * cos_m) + np.minimum(low[0] * sin_m, high[0] * sin_m))
    for k in np.flatnonzero(~(bound > 1e-9)).tolist():  # slices whose values may fail cos(a - m) > 0
        i, j = int(lo[k]), int(hi[k])
        sin, cos = sc[0, i:j], sc[1, i:j]
        c = cos * cos_m[k] + sin * sin_m[k]  # cos(a - m), within 1e-14 of np.cos(a - m)
        near = c > 1e-12
        edge = np.flatnonzero(np.abs(c) <= 1e-12)
        near[edge] = np.cos(a[i:j][edge] - m[k]) > 0.0
        if near.any() and not near.all():
            m[k] = np.arctan2(total(sin[near]) / near.sum(), total(cos[near]) / near.sum())
    return (m * period / (2 * np.pi) + period / 2) % period - period / 2


def estimate_pattern(scan: np.ndarray, ring: np.ndarray, sensor: HDL64E | None = None, *,
                     azimuth_deg: np.ndarray | None = None) -> BeamPattern:
    """The beam pattern of a scan (N, >=3) with laser ids ``ring`` (N,) (see the module docstring).

    Lasers without points keep the generator's offsets (plus the common turn when one was found).
    ``azimuth_deg``: the points' degrees(arctan2(y, x)) in float64 when already computed."""
    s = sensor or HDL64E()
    q = s.azimuth_quantum_deg
    if azimuth_deg is None:
        pts = np.asarray(scan, dtype=np.float64)
        azimuth_deg = np.degrees(np.arctan2(pts[:, 1], pts[:, 0]))
    az = _mod360(azimuth_deg)
    ring = np.asarray(ring, dtype=np.int64)
    offsets = GENERATOR_FIRING_OFFSETS_DEG[: s.num_lasers]
    phases = np.full(s.num_lasers, np.nan)
    if len(ring) and np.all(ring[1:] >= ring[:-1]):  # laser-ordered (KITTI order): each laser is one slice
        lasers = np.arange(s.num_lasers)
        lo, hi = np.searchsorted(ring, lasers, "left"), np.searchsorted(ring, lasers, "right")
        seen = np.flatnonzero(hi > lo)
        if len(seen):
            first, last = lo[seen[0]], hi[seen[-1]]  # the lasers' points, one run
            phases[seen] = _circular_means(_mod_positive(az[first:last], q), lo[seen] - first, hi[seen] - first, q)
    else:
        for k in np.unique(ring[(ring >= 0) & (ring < s.num_lasers)]):
            phases[k] = _circular_mean(az[ring == k] % q, q)
    seen = np.isfinite(phases)
    if not seen.any():
        return BeamPattern(offsets.copy(), 0.0, s)
    turn = _circular_mean((phases[seen] - offsets[seen]) % q, q)
    spread = np.abs((phases[seen] - offsets[seen] - turn + q / 2) % q - q / 2).max()
    if spread <= _GENERATOR_PHASE_TOL_DEG and -_GENERATOR_PHASE_TOL_DEG < turn < q / 2 + _GENERATOR_PHASE_TOL_DEG:
        return BeamPattern(offsets + turn, turn, s)
    return BeamPattern(np.where(seen, phases, offsets + turn), 0.0, s)
