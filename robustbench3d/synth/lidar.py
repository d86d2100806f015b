"""HDL-64E scan of a scene: Embree ray casting plus return, noise and reflectance models.

Frame: velodyne (x forward, y left, z up; m). Output rows are (x, y, z, reflectance) float32 in
KITTI scan order (laser by laser from the top, azimuth increasing from 0 deg; rays without a
return are dropped, the order of the others is kept).

Rays: :class:`~robustbench3d.sensors.hdl64e.HDL64E` with 2,154 firings per laser, fixed per-laser
firing offsets and a random rotation phase per frame. Return, range-noise and reflectance model:
:mod:`robustbench3d.sensors.lidar_model` (fitted by eye to the six real KITTI scans); this module adds
the terrain's per-point reflectivity (asphalt 0.30, lane paint 0.75, grass 0.40).
"""

from __future__ import annotations

from functools import lru_cache
from typing import NamedTuple

import numpy as np

from robustbench3d.sensors import lidar_model as lm
from robustbench3d.sensors.hdl64e import AZIMUTH_QUANTUM_DEG, HDL64E, MAX_RANGE_M
from robustbench3d.sensors.lidar_beams import GENERATOR_FIRING_OFFSETS_DEG
from robustbench3d.synth.materials import RETURN_PROB, Mat
from robustbench3d.synth.raytrace import SceneGeometry
from robustbench3d.synth.scene import Scene


def ground_reflectivity(scene: Scene, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """LiDAR reflectivity of terrain points (velodyne x, y): asphalt, lane paint or grass."""
    s, d = scene.road.to_road(x, y)
    rho = np.full(len(x), 0.40, dtype=np.float32)
    rho[scene.road.road_surface(s, d)] = 0.30
    rho[scene.road.lane_paint(s, d)] = 0.75
    return rho


def surface_reflectivity(scene: Scene, material: np.ndarray, color: np.ndarray, x: np.ndarray,
                         y: np.ndarray) -> np.ndarray:
    """Reflectivity rho in [0, 0.98] per hit (velodyne x, y): :func:`~robustbench3d.sensors.lidar_model.
    material_reflectivity` of material and albedo, the terrain's from the road markings."""
    rho = lm.material_reflectivity(material, color)
    g = material == Mat.GROUND
    if g.any():
        rho[g] = ground_reflectivity(scene, x[g], y[g])
    return rho


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
    rays = HDL64E().rays(GENERATOR_FIRING_OFFSETS_DEG)
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
    idx = np.flatnonzero(hits.hit & lm.in_range(hits.t))
    prim = hits.prim[idx]
    t = hits.t[idx].astype(np.float64)
    d = directions.take(idx, axis=1)
    o = beams.origin_rows.take(idx, axis=1)
    cos_inc = lm.cos_incidence(geometry.face_normals.take(prim, axis=0), d.T)
    material = geometry.tri_material[prim]
    rho = surface_reflectivity(scene, material, geometry.tri_color.take(prim, axis=0), o[0] + t * d[0],
                               o[1] + t * d[1])

    p_return = lm.return_probability(RETURN_PROB[material], rho, cos_inc, t)
    keep = np.flatnonzero(rng.random(len(idx)) < p_return)
    prim, t, cos_inc, rho = prim[keep], t[keep], cos_inc[keep], rho[keep]
    d, o = d.take(keep, axis=1), o.take(keep, axis=1)

    n = len(keep)
    r = t + lm.range_noise(rng, n)
    refl = lm.reflectance_mean(rho, cos_inc, r) * lm.reflectance_noise(rng, n)
    zero = rng.random(n) < lm.zero_reflectance_probability(r)
    scan = np.empty((n, 4), dtype=np.float32)
    scan[:, :3] = (o + r * d).T
    scan[:, 3] = lm.quantize_reflectance(refl, zero)
    return scan, geometry.tri_object[prim]
