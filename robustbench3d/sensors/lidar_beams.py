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

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from robustbench3d.sensors.hdl64e import AZIMUTH_QUANTUM_DEG, HDL64E, BeamRays, ring_ids_from_azimuth_wrap

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
    def _ring_azimuth(self) -> tuple[np.ndarray, np.ndarray]:
        """(ring (R,) int64, azimuth_deg (R,)) of :attr:`rays`, without their geometry."""
        ring, az = self.sensor.ray_azimuths(np.asarray(self.phases_deg, dtype=np.float64) - self.shift_deg)
        return ring.astype(np.int64), az + self.shift_deg

    def ray_geometry(self, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(origins (K, 3), unit directions (K, 3)) of the rays ``index`` (K,): ``rays.origins[index]`` and
        ``rays.directions[index]``, bit for bit, without building every ray of the revolution."""
        index = np.asarray(index, dtype=np.int64)
        if "rays" in self.__dict__:
            return self.rays.origins[index], self.rays.directions[index]
        ring, az = self._ring_azimuth
        return self.sensor.origins(ring[index]), self.sensor.directions(ring[index], az[index])

    @cached_property
    def ring_start(self) -> np.ndarray:
        """(65,) index of each laser's first ray in :attr:`rays` (and the total at the end)."""
        return np.searchsorted(self._ring_azimuth[0], np.arange(self.sensor.num_lasers + 1))

    @cached_property
    def _keys(self) -> np.ndarray:
        ring, az = self._ring_azimuth
        return ring * _BAND + az

    def cull(self, center: np.ndarray, radius: float, margin_deg: float = AZIMUTH_STEP_DEG) -> np.ndarray:
        """Indices (int64, increasing) of the rays whose direction passes within ``radius`` (m) of ``center``
        (3,), widened by ``margin_deg`` of azimuth on each side.

        Per laser k with apex o_k = (0, 0, h0_k) and c = center - o_k: the ray at azimuth theta is within the
        sphere's tangent cone iff cos(phi_k) |c_xy| cos(theta - theta_c) + sin(phi_k) c_z >= sqrt(|c|^2 - r^2),
        which gives no azimuth (the laser's cone misses the sphere), all of them (apex inside), or an interval.
        """
        s = self.sensor
        c = np.asarray(center, dtype=np.float64)
        r = float(radius) * (1 + 1e-9) + 1e-9
        cz = c[2] - s.origin_z
        rho = float(np.hypot(c[0], c[1]))
        dist2 = rho * rho + cz * cz
        phi = np.radians(s.elevation_deg)
        inside = dist2 <= r * r
        with np.errstate(divide="ignore", invalid="ignore"):
            kappa = (np.sqrt(np.maximum(dist2 - r * r, 0.0)) - np.sin(phi) * cz) / (np.cos(phi) * rho)
        kappa = np.where(inside, -np.inf, np.nan_to_num(kappa, nan=np.inf, posinf=np.inf, neginf=-np.inf))
        active = np.flatnonzero(kappa <= 1.0)
        if len(active) == 0:
            return np.zeros(0, dtype=np.int64)
        half = np.degrees(np.arccos(np.clip(kappa[active], -1.0, 1.0))) + margin_deg
        theta = np.degrees(np.arctan2(c[1], c[0])) % 360.0
        full = half >= 180.0
        starts, stops = [], []
        for turn in (-360.0, 0.0, 360.0):
            lo = np.clip(theta - half + turn, -1.0, 500.0)
            hi = np.clip(theta + half + turn, -1.0, 500.0)
            lo[full], hi[full] = -1.0, 500.0
            starts.append(np.searchsorted(self._keys, active * _BAND + lo, "left"))
            stops.append(np.searchsorted(self._keys, active * _BAND + hi, "right"))
            if full.all():
                break
        return np.unique(_expand_ranges(np.concatenate(starts), np.concatenate(stops)))

    def near_rays(self, index: np.ndarray, ring: np.ndarray, azimuth_deg: np.ndarray,
                  max_deg: float = AZIMUTH_QUANTUM_DEG) -> np.ndarray:
        """(N,) bool, a superset of the points (laser ``ring``, ``azimuth_deg``) whose :meth:`nearest_ray` within
        ``max_deg`` can be one of the rays ``index``: those within about ``max_deg`` of such a ray's azimuth on
        the same laser (bins of ``max_deg`` per laser: the ray's bin and two on either side)."""
        nl = self.sensor.num_lasers
        ring = np.asarray(ring, dtype=np.int64)
        bins = int(np.ceil(360.0 / max_deg))
        rr, raz = self._ring_azimuth[0][index], self._ring_azimuth[1][index]
        grid = np.zeros((nl, bins), dtype=bool)
        b = np.floor(raz / max_deg).astype(np.int64)
        for step in range(-2, 3):
            grid[rr, (b + step) % bins] = True
        known = (ring >= 0) & (ring < nl)
        pb = np.floor((np.asarray(azimuth_deg, dtype=np.float64) % 360.0) / max_deg).astype(np.int64) % bins
        return known & grid[np.where(known, ring, 0), pb]

    def nearest_ray(self, ring: np.ndarray, azimuth_deg: np.ndarray, max_deg: float = AZIMUTH_QUANTUM_DEG
                    ) -> np.ndarray:
        """(N,) index of the ray of laser ``ring`` nearest in azimuth to ``azimuth_deg`` (circularly), or -1
        when none lies within ``max_deg`` or the ring is unknown (< 0 or >= 64)."""
        ring = np.asarray(ring, dtype=np.int64)
        az = np.asarray(azimuth_deg, dtype=np.float64) % 360.0
        out = np.full(len(ring), -1, dtype=np.int64)
        known = (ring >= 0) & (ring < self.sensor.num_lasers)
        if not known.any():
            return out
        rk, ak = ring[known], az[known]
        first, last = self.ring_start[rk], self.ring_start[rk + 1] - 1
        raz = self._ring_azimuth[1]
        best = np.full(len(rk), -1, dtype=np.int64)
        gap = np.full(len(rk), np.inf)
        for turn in (-360.0, 0.0, 360.0):
            pos = np.searchsorted(self._keys, rk * _BAND + ak + turn)
            for cand in (pos - 1, pos):
                ok = (cand >= first) & (cand <= last)
                cand = np.clip(cand, 0, len(raz) - 1)
                g = np.where(ok, np.abs(raz[cand] - (ak + turn)), np.inf)
                better = g < gap
                best[better], gap[better] = cand[better], g[better]
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
    pts = np.asarray(scan, dtype=np.float64)
    if len(pts) == 0:
        return np.zeros(0, dtype=np.int64)
    s = sensor or HDL64E()
    wrap = ring_ids_from_azimuth_wrap(pts)
    if wrap.max() == s.num_lasers - 1:
        return wrap
    rho = np.hypot(pts[:, 0], pts[:, 1])
    cone = rho[:, None] * np.tan(np.radians(s.elevation_deg))[None, :] + s.origin_z[None, :]
    return np.argmin(np.abs(pts[:, 2:3] - cone), axis=1).astype(np.int64)


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


def estimate_pattern(scan: np.ndarray, ring: np.ndarray, sensor: HDL64E | None = None) -> BeamPattern:
    """The beam pattern of a scan (N, >=3) with laser ids ``ring`` (N,) (see the module docstring).

    Lasers without points keep the generator's offsets (plus the common turn when one was found)."""
    s = sensor or HDL64E()
    q = s.azimuth_quantum_deg
    pts = np.asarray(scan, dtype=np.float64)
    az = np.degrees(np.arctan2(pts[:, 1], pts[:, 0])) % 360.0
    ring = np.asarray(ring, dtype=np.int64)
    offsets = GENERATOR_FIRING_OFFSETS_DEG[: s.num_lasers]
    phases = np.full(s.num_lasers, np.nan)
    if len(ring) and np.all(ring[1:] >= ring[:-1]):  # laser-ordered (KITTI order): each laser is one slice
        lasers = np.arange(s.num_lasers)
        lo, hi = np.searchsorted(ring, lasers, "left"), np.searchsorted(ring, lasers, "right")
        for k in np.flatnonzero(hi > lo):
            phases[k] = _circular_mean(az[lo[k]:hi[k]] % q, q)
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
