"""HDL-64E scan of a scene: Embree ray casting plus return, noise and reflectance models.

Frame: velodyne (x forward, y left, z up; m). Output rows are (x, y, z, reflectance) float32 in
KITTI scan order (laser by laser from the top, azimuth increasing from 0 deg; rays without a
return are dropped, the order of the others is kept).

Models (fitted by eye to the six real KITTI scans; ranges in m):

* Rays: :class:`~robustbench3d.sensors.hdl64e.HDL64E` with 2,154 firings per laser, fixed per-laser
  firing offsets and a random rotation phase per frame.
* Return or not: a pulse returns with probability ``return_prob(material) * sigmoid(ln(S / S0) /
  0.5)`` with received signal S = rho * max(cos(incidence), 0.02) / r^2 and S0 = 3.9e-6, so grazing
  asphalt fades out around 50-60 m while walls and cars return up to the 120 m maximum range.
  Glass returns three pulses in four (the rest pass through or scatter away), tyres most.
* Range noise: Gaussian along the ray, sigma 1 cm clipped at 3 cm (the point stays on its laser's
  cone, as in real scans).
* Reflectance: rho * (0.55 + 0.45 cos(incidence)) * (1 - 0.012 max(0, r - 20)) with 12 % log-normal
  noise, reported as 0 with probability 0.04 + 0.9 sigmoid((r - 45) / 5) (real scans: about 5 % zeros
  below 25 m, half at 45 m, 90 % beyond 60 m), quantised to 0.01 and kept in [0, 0.99].
  rho comes from the material (asphalt 0.30, lane paint 0.75, grass 0.40, car paint 0.23-0.58 by
  brightness, glass 0.08, signs 0.97, ...).
"""

from __future__ import annotations

from functools import lru_cache
from typing import NamedTuple

import numpy as np

from robustbench3d.sensors.hdl64e import AZIMUTH_QUANTUM_DEG, HDL64E, MAX_RANGE_M
from robustbench3d.synth.materials import REFLECTIVITY, RETURN_PROB, Mat
from robustbench3d.synth.raytrace import SceneGeometry
from robustbench3d.synth.scene import Scene

SIGNAL_THRESHOLD = 3.9e-6
RANGE_NOISE_SD = 0.01
#: Returns closer than this are discarded, m (the real scans start at about 1.4 m).
MIN_RANGE_M = 1.0


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * x))


def ground_reflectivity(scene: Scene, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """LiDAR reflectivity of terrain points (velodyne x, y): asphalt, lane paint or grass."""
    s, d = scene.road.to_road(x, y)
    rho = np.full(len(x), 0.40, dtype=np.float32)
    rho[scene.road.road_surface(s, d)] = 0.30
    rho[scene.road.lane_paint(s, d)] = 0.75
    return rho


#: Materials whose reflectivity scales with the albedo's brightness (indexed by material id).
_TINTED = np.isin(np.arange(len(Mat)), [Mat.PAINT, Mat.FACADE, Mat.WALL, Mat.CLOTH])


def surface_reflectivity(scene: Scene, material: np.ndarray, color: np.ndarray, x: np.ndarray,
                         y: np.ndarray) -> np.ndarray:
    """Reflectivity rho in [0, 1) per hit (velodyne x, y) from material, albedo brightness and road markings."""
    rho = REFLECTIVITY[material]
    lum = color @ np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)
    tinted = _TINTED[material]
    rho[tinted] *= 0.55 + 0.9 * np.sqrt(lum[tinted])
    g = material == Mat.GROUND
    if g.any():
        rho[g] = ground_reflectivity(scene, x[g], y[g])
    return np.clip(rho, 0.0, 0.98)


class _Beams(NamedTuple):
    """The rays of :func:`_base_rays` as the scan simulation uses them (vectors stored by component, (3, N),
    so that elementwise operations run over whole rows)."""

    origins: np.ndarray  # (N, 3) float32, Embree's input
    origin_rows: np.ndarray  # (3, N) float64
    direction_rows: np.ndarray  # (3, N) float64, before the frame's rotation phase


@lru_cache(maxsize=1)
def _base_rays() -> _Beams:
    """One revolution of the default sensor with fixed per-laser firing offsets (like the real unit's
    per-laser rotational corrections), in [0, half the azimuth quantum)."""
    sensor = HDL64E()
    offsets = np.random.default_rng(64).uniform(0.0, AZIMUTH_QUANTUM_DEG / 2, sensor.num_lasers)
    rays = sensor.rays(offsets)
    return _Beams(rays.origins.astype(np.float32), np.ascontiguousarray(rays.origins.T),
                  np.ascontiguousarray(rays.directions.T))


def simulate_scan(scene: Scene, geometry: SceneGeometry, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """One revolution of the HDL-64E (2,154 firings per laser, a random rotation phase per frame).

    Returns:
        scan: (N, 4) float32 x, y, z (velodyne, m), reflectance in [0, 0.99].
        point_object: (N,) int32 index into ``scene.objects`` of the surface each point lies on.
    """
    beams = _base_rays()
    phase = np.radians(rng.uniform(0.0, AZIMUTH_QUANTUM_DEG / 2))
    c, s = np.cos(phase), np.sin(phase)
    bx, by, bz = beams.direction_rows
    directions = np.stack([c * bx - s * by, s * bx + c * by, bz])
    hits = geometry.intersect(beams.origins, directions.T, MAX_RANGE_M)
    idx = np.flatnonzero(hits.hit & (hits.t > MIN_RANGE_M))
    prim = hits.prim[idx]
    t = hits.t[idx].astype(np.float64)
    d = directions.take(idx, axis=1)
    o = beams.origin_rows.take(idx, axis=1)
    nrm = geometry.face_normals.take(prim, axis=0)
    cos_inc = np.abs(nrm[:, 0] * d[0] + nrm[:, 1] * d[1] + nrm[:, 2] * d[2])  # = sum(nrm * d.T, axis=1)
    material = geometry.tri_material[prim]
    rho = surface_reflectivity(scene, material, geometry.tri_color.take(prim, axis=0), o[0] + t * d[0],
                               o[1] + t * d[1])

    signal = rho * np.maximum(cos_inc, 0.02) / (t * t)
    p_return = RETURN_PROB[material] * _sigmoid(np.log(np.maximum(signal, 1e-30) / SIGNAL_THRESHOLD) / 0.5)
    keep = np.flatnonzero(rng.random(len(idx)) < p_return)
    prim, t, cos_inc, rho = prim[keep], t[keep], cos_inc[keep], rho[keep]
    d, o = d.take(keep, axis=1), o.take(keep, axis=1)

    n = len(keep)
    r = t + np.clip(rng.normal(0.0, RANGE_NOISE_SD, n), -3 * RANGE_NOISE_SD, 3 * RANGE_NOISE_SD)
    level = np.clip(1.0 - 0.012 * np.maximum(r - 20.0, 0.0), 0.3, 1.0)
    refl = rho * (0.55 + 0.45 * cos_inc) * level * np.exp(rng.normal(0.0, 0.12, n))
    zero = rng.random(n) < 0.04 + 0.9 * _sigmoid((r - 45.0) / 5.0)
    scan = np.empty((n, 4), dtype=np.float32)
    scan[:, :3] = (o + r * d).T
    scan[:, 3] = np.where(zero, 0.0, np.clip(np.floor(refl * 100.0) / 100.0, 0.0, 0.99))
    return scan, geometry.tri_object[prim]
