"""Velodyne HDL-64E S2 beam model as mounted on the KITTI car.

Frame: velodyne (x forward, y left, z up; metres), origin at the sensor's reference point,
ground at about z = -1.73 m. Angles in degrees unless a name says ``_rad``.

Each laser k traces an exact cone: its rays start at (0, 0, h0_k) and leave with elevation phi_k,
so a return at horizontal range rho lies on z = rho * tan(phi_k) + h0_k. phi and h0 are the
per-laser fits of reference.md §4.2 (measured on real KITTI scans; ring 0 = top laser).

Scan order (as in KITTI ``velodyne/*.bin``, checked on the real sample scans): laser by laser,
top laser first; within a laser, azimuth atan2(y, x) increases from just above 0 deg (straight
ahead) through 180 deg to just below 360 deg. A new laser therefore starts where the azimuth,
measured from -x, jumps by more than 180 deg (:func:`ring_ids_from_azimuth_wrap`).

Azimuth sampling (measured on the real scans): consecutive returns of one laser are 0.18 deg
apart, except that about every seventh step is a half step of 0.09 deg; a revolution at 10 Hz
holds about 2,154 firings per laser (2,148-2,162 across the samples). The model puts firing j
of a laser at ``phase + 0.09 * floor(j * (360 / N) / 0.09)``, which reproduces both the 0.18 deg
median spacing and the 14 % share of half steps.

The lowest lasers are partly blocked by the ego vehicle and the sensor mount;
:data:`EGO_OCCLUSION_SECTORS` lists the azimuth sectors that return nothing in the real scans.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

#: Cone elevation phi_k of the 64 lasers, ring 0 (top) to 63, degrees (reference.md §4.2).
LASER_ELEVATION_DEG = np.array([
    1.94, 1.57, 1.30, 0.87, 0.58, 0.18, -0.09, -0.45, -0.80, -1.20, -1.49, -1.83, -2.21, -2.55, -2.87, -3.24,
    -3.54, -3.94, -4.22, -4.59, -4.91, -5.25, -5.61, -5.96, -6.33, -6.68, -7.00, -7.29, -7.68, -8.06, -8.31,
    -8.71, -9.03, -9.57, -10.06, -10.47, -10.96, -11.60, -12.11, -12.56, -13.04, -13.48, -14.05, -14.60,
    -15.19, -15.66, -16.18, -16.55, -17.19, -17.73, -18.32, -18.80, -19.32, -19.74, -20.22, -20.79, -21.32,
    -21.94, -22.44, -22.86, -23.32, -23.97, -24.50, -25.00,
])

#: Cone apex height h0_k of the 64 lasers above the velodyne origin, metres (reference.md §4.2).
LASER_ORIGIN_Z_M = np.array([
    0.209, 0.209, 0.208, 0.208, 0.207, 0.207, 0.206, 0.206, 0.206, 0.205, 0.205, 0.204, 0.204, 0.204, 0.203,
    0.203, 0.203, 0.202, 0.202, 0.201, 0.201, 0.201, 0.200, 0.200, 0.200, 0.199, 0.199, 0.199, 0.199, 0.198,
    0.198, 0.198, 0.126, 0.125, 0.125, 0.125, 0.124, 0.124, 0.124, 0.123, 0.123, 0.123, 0.122, 0.122, 0.122,
    0.121, 0.121, 0.121, 0.120, 0.120, 0.120, 0.119, 0.119, 0.119, 0.119, 0.118, 0.118, 0.118, 0.118, 0.117,
    0.117, 0.117, 0.116, 0.116,
])

NUM_LASERS = 64
#: Height of the velodyne origin above the road under the KITTI car, metres.
MOUNT_HEIGHT_M = 1.73
#: Smallest azimuth increment between two firings of a laser, degrees (half of the 0.18 deg step).
AZIMUTH_QUANTUM_DEG = 0.09
#: Mean firings per laser and revolution at 10 Hz (measured 2,148-2,162).
FIRINGS_PER_REVOLUTION = 2154
#: Maximum range of the sensor, metres (HDL-64E data sheet).
MAX_RANGE_M = 120.0

#: Azimuth sectors without returns (ego vehicle, mount), measured on the six real scans in 2 deg
#: bins (fewer than 30 % of the expected returns): (first ring, last ring, from deg, to deg);
#: azimuth in [0, 360), a sector may run past 360.
EGO_OCCLUSION_SECTORS: tuple[tuple[int, int, float, float], ...] = (
    (42, 52, 156.0, 165.0), (42, 52, 197.0, 204.0), (52, 52, 170.0, 194.0), (53, 63, 156.0, 206.0),
    (47, 63, 280.0, 300.0), (55, 63, 127.0, 135.0), (55, 63, 228.0, 235.0),
    (57, 59, 346.0, 374.0), (60, 63, 342.0, 379.0), (60, 63, 322.0, 333.0), (61, 63, 26.0, 39.0),
    (62, 63, 135.0, 146.0),
)


@dataclass(frozen=True)
class BeamRays:
    """Rays of one revolution in KITTI scan order.

    Attributes:
        origins: (N, 3) float64 ray origins, velodyne frame, m.
        directions: (N, 3) float64 unit directions, velodyne frame.
        ring: (N,) int16 laser index, 0 = top laser.
        azimuth_deg: (N,) float64 azimuth atan2(y, x) in [0, 360), increasing within a ring.
    """

    origins: np.ndarray
    directions: np.ndarray
    ring: np.ndarray
    azimuth_deg: np.ndarray

    def __len__(self) -> int:
        return len(self.ring)


@dataclass(frozen=True)
class HDL64E:
    """Beam geometry of the KITTI HDL-64E (see the module docstring for the measured facts)."""

    elevation_deg: np.ndarray = field(default_factory=lambda: LASER_ELEVATION_DEG.copy())
    origin_z: np.ndarray = field(default_factory=lambda: LASER_ORIGIN_Z_M.copy())
    firings_per_revolution: int = FIRINGS_PER_REVOLUTION
    azimuth_quantum_deg: float = AZIMUTH_QUANTUM_DEG
    max_range: float = MAX_RANGE_M

    @property
    def num_lasers(self) -> int:
        return len(self.elevation_deg)

    def ring_azimuths(self, phase_deg: float = 0.0, firings: int | None = None) -> np.ndarray:
        """Firing azimuths of one laser over a revolution, degrees in [0, 360), increasing.

        Args:
            phase_deg: azimuth of the first firing, in [0, azimuth_quantum_deg).
            firings: firings per revolution (default :attr:`firings_per_revolution`).
        """
        n = self.firings_per_revolution if firings is None else int(firings)
        az = phase_deg + _firing_steps(n, self.azimuth_quantum_deg)
        return az[az < 360.0]

    def directions(self, ring: np.ndarray, azimuth_deg: np.ndarray) -> np.ndarray:
        """(N, 3) unit ray directions of lasers ``ring`` at ``azimuth_deg`` (velodyne frame)."""
        phi = np.radians(self.elevation_deg[np.asarray(ring)])
        th = np.radians(np.asarray(azimuth_deg, dtype=np.float64))
        cp = np.cos(phi)
        return np.stack([cp * np.cos(th), cp * np.sin(th), np.sin(phi)], axis=1)

    def rays(self, phases_deg: np.ndarray | None = None, firings: int | None = None,
             ego_occlusion: bool = True) -> BeamRays:
        """All rays of one revolution in KITTI scan order.

        Args:
            phases_deg: (64,) first-firing azimuth per laser in [0, azimuth_quantum_deg); zeros if None.
            firings: firings per laser and revolution (default :attr:`firings_per_revolution`).
            ego_occlusion: drop the rays of :data:`EGO_OCCLUSION_SECTORS` (they never return).
        """
        ring, azimuth = self.ray_azimuths(phases_deg, firings, ego_occlusion)
        return BeamRays(self.origins(ring), self.directions(ring, azimuth), ring, azimuth)

    def ray_azimuths(self, phases_deg: np.ndarray | None = None, firings: int | None = None,
                     ego_occlusion: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """(ring (N,) int16, azimuth_deg (N,)) of :meth:`rays` without the geometry (arguments alike)."""
        nl = self.num_lasers
        phases = np.zeros(nl) if phases_deg is None else np.asarray(phases_deg, dtype=np.float64)
        n = self.firings_per_revolution if firings is None else int(firings)
        az = phases[:nl, None] + _firing_steps(n, self.azimuth_quantum_deg)[None, :]  # row k: ring_azimuths(k)
        keep = az < 360.0
        if ego_occlusion:
            for first, last, lo, hi in EGO_OCCLUSION_SECTORS:  # drop the sectors' azimuths of their lasers
                if first < nl:
                    rows = az[first:last + 1]
                    out = (rows >= lo) & (rows < hi)
                    if hi > 360.0:
                        out |= rows < hi - 360.0
                    keep[first:last + 1] &= ~out
        return np.repeat(np.arange(nl, dtype=np.int16), keep.sum(axis=1)), az[keep]

    def origins(self, ring: np.ndarray) -> np.ndarray:
        """(N, 3) ray origins (0, 0, h0_k) of lasers ``ring`` (velodyne frame, m)."""
        ring = np.asarray(ring)
        origins = np.zeros((len(ring), 3))
        origins[:, 2] = self.origin_z[ring]
        return origins


@lru_cache(maxsize=8)
def _firing_steps(firings: int, quantum_deg: float) -> np.ndarray:
    """(firings,) read-only offsets q floor(j (360 / n) / q) of the firings from the phase (module doc)."""
    j = np.arange(firings, dtype=np.float64)
    steps = quantum_deg * np.floor(j * (360.0 / firings) / quantum_deg + 1e-9)
    steps.flags.writeable = False
    return steps


def ring_ids_from_azimuth_wrap(points: np.ndarray) -> np.ndarray:
    """Laser index of each point of a KITTI-ordered scan (velodyne frame, (N, >=2)).

    Each laser sweeps counter-clockwise from just above the +x axis, so a new laser starts where
    consecutive points cross the +x axis: there the azimuth measured from -x, atan2(y, -x),
    jumps by more than 180 deg. (Testing the crossing, not a drop of atan2(y, x) in [0, 360),
    keeps points whose azimuth jitters around 0 deg at a sweep's ends on the right laser.)
    Returns (N,) int64 starting at 0; a full real scan yields 0..63.

    Only consecutive points whose y differ in sign bit can jump (atan2(y, -x) lies in [0, pi] for a y with
    the sign bit clear, in [-pi, -0] otherwise), so atan2 is evaluated on those pairs only.
    """
    pts = np.asarray(points)
    if pts.dtype not in (np.float32, np.float64):
        pts = pts.astype(np.float64)
    ring = np.zeros(len(pts), dtype=np.int64)
    if len(pts) > 1:
        sign = np.signbit(pts[:, 1])  # float32 -> float64 keeps the sign
        pair = np.flatnonzero(sign[1:] != sign[:-1])
        p0, p1 = pts[pair, :2].astype(np.float64), pts[pair + 1, :2].astype(np.float64)
        yaw0 = np.arctan2(p0[:, 1], -p0[:, 0])
        yaw1 = np.arctan2(p1[:, 1], -p1[:, 0])
        first = pair[np.abs(yaw1 - yaw0) > np.pi] + 1  # the first point of each next laser
        ring = np.repeat(np.arange(len(first) + 1, dtype=np.int64), np.diff(first, prepend=0, append=len(pts)))
    return ring
