"""Camera-2 image of a scene: one Embree ray per pixel, Lambertian shading with sun, sky and shadows.

Geometry: pixel (u, v) (integer coordinates are pixel centres, as in KITTI's P2) looks along
K^-1 [u, v, 1] from the camera-2 centre -K^-1 P2[:, 3] in rect, both mapped to the velodyne frame
with the frame's calibration, so the image is exactly the P2 projection of the same scene the
LiDAR sees.

Shading (linear RGB, then exposure, a soft tone curve and the sRGB transfer curve):
  colour = albedo * (sun * max(0, n.l) * lit + ambient * sky(n)) [+ sky reflection on paint/glass]
where ``lit`` comes from a shadow ray towards the sun. Textures: asphalt and terrain noise, lane
markings, sidewalk tiles, foliage and facade noise. Distant surfaces fade towards the horizon
colour (aerial perspective). The image is then slightly blurred (a [1, 2, 1] kernel, like the soft
KITTI optics) after the sensor noise is added. The shading, haze, tone-mapping and noise models are
:mod:`robustbench3d.sensors.camera_model`'s; this module casts the rays and adds the scenery's textures
and sky.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import NamedTuple

import numpy as np

from robustbench3d.sensors import camera_model as cm
from robustbench3d.sensors.camera_model import SHADOW_RAY_LENGTH
from robustbench3d.synth.calibs import CameraDay
from robustbench3d.synth.materials import SPECULAR, Mat
from robustbench3d.synth.raytrace import SceneGeometry
from robustbench3d.synth.scene import Scene


@dataclass(frozen=True, eq=False)
class CameraRays:
    """Per-pixel rays of a recording day's camera 2 (velodyne frame).

    Attributes:
        origin: (3,) camera-2 centre, m.
        origins: (H*W, 3) float32, the centre repeated for every ray (Embree's input).
        directions: (H*W, 3) float32 unit directions, row-major over (v, u).
        channels: (3, H*W) float32, the same directions stored by component (for the shading).
        odd_column: (H*W,) bool, the pixel lies in an odd image column.
        image_size: (width, height).
    """

    origin: np.ndarray
    origins: np.ndarray
    directions: np.ndarray
    channels: np.ndarray
    odd_column: np.ndarray
    image_size: tuple[int, int]


@lru_cache(maxsize=4)
def _camera_pose(day: CameraDay) -> tuple[np.ndarray, np.ndarray]:
    """Camera-2 centre (3,) in the velodyne frame and the rect -> velodyne transform (4, 4) of ``day``
    (cached, read-only)."""
    calib = day.calib
    k_inv_p4 = np.linalg.solve(calib.P2[:, :3], calib.P2[:, 3])
    origin = calib.rect_to_velo_points(-k_inv_p4[None])[0]
    rect_to_velo = calib.rect_to_velo
    origin.flags.writeable = rect_to_velo.flags.writeable = False
    return origin, rect_to_velo


def pixel_directions(day: CameraDay, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera-2 origin (3,) and unit directions (N, 3) through pixels (u, v), velodyne frame."""
    fu, fv, cu, cv = day.calib.intrinsics
    origin, rect_to_velo = _camera_pose(day)
    d_rect = np.column_stack([(np.asarray(u, np.float64) - cu) / fu, (np.asarray(v, np.float64) - cv) / fv,
                              np.ones(np.size(u))])
    d = d_rect @ rect_to_velo[:3, :3].T
    return origin, d / np.linalg.norm(d, axis=1, keepdims=True)


@lru_cache(maxsize=4)
def camera_rays(day: CameraDay) -> CameraRays:
    """All pixel rays of ``day``'s image (cached per day)."""
    w, h = day.image_size
    vv, uu = np.mgrid[0:h, 0:w]
    origin, d = pixel_directions(day, uu.ravel(), vv.ravel())
    d = d.astype(np.float32)
    origins = np.ascontiguousarray(np.broadcast_to(origin, d.shape), dtype=np.float32)
    return CameraRays(origin, origins, d, np.ascontiguousarray(d.T), uu.ravel() % 2 == 1, (w, h))


_TEX = 512


@lru_cache(maxsize=1)
def _fbm_texture() -> np.ndarray:
    """Tileable 512x512 fractal noise in [0, 1] (float32), the same in every process, as a (512 * 512, 4)
    table: row ``ix * 512 + iy`` holds the texels (ix, iy), (ix + 1, iy), (ix, iy + 1), (ix + 1, iy + 1)
    (indices wrapping around), the four corners of a bilinear lookup, fetched by :class:`Noise` at once."""
    rng = np.random.default_rng(20240531)  # fixed: a constant texture, frames differ by their offsets
    out = np.zeros((_TEX, _TEX), dtype=np.float64)
    amp, norm = 1.0, 0.0
    for cells in (8, 16, 32, 64, 128):
        lattice = rng.random((cells, cells))
        pos = np.arange(_TEX) * cells / _TEX
        i0 = np.floor(pos).astype(int)
        t = pos - i0
        t = t * t * (3 - 2 * t)
        i1 = (i0 + 1) % cells
        rows = lattice[i0] * (1 - t)[:, None] + lattice[i1] * t[:, None]
        out += amp * (rows[:, i0] * (1 - t) + rows[:, i1] * t)
        norm += amp
        amp *= 0.55
    out /= norm
    out = (out - out.min()) / (out.max() - out.min())
    tex = out.astype(np.float32)
    up = np.roll(tex, -1, axis=0)  # texel (ix + 1, iy) at (ix, iy)
    return np.stack([tex, up, np.roll(tex, -1, axis=1), np.roll(up, -1, axis=1)], axis=-1).reshape(-1, 4)


class Noise:
    """Smooth noise in [0, 1] at world coordinates: bilinear lookups into the fixed fractal texture,
    shifted by per-frame random offsets (one texel = 1 unit of the scaled coordinates)."""

    def __init__(self, rng: np.random.Generator):
        self.table = _fbm_texture()
        self.offset = rng.uniform(0, _TEX, size=(8, 2))

    def __call__(self, x: np.ndarray, y: np.ndarray, channel: int = 0) -> np.ndarray:
        ox, oy = self.offset[channel]
        x = np.asarray(x, np.float32) + np.float32(ox)
        y = np.asarray(y, np.float32) + np.float32(oy)
        fx, fy = np.floor(x), np.floor(y)
        tx, ty = x - fx, y - fy
        m = _TEX - 1
        t00, t10, t01, t11 = self.table.take((fx.astype(np.int32) & m) * _TEX + (fy.astype(np.int32) & m), axis=0).T
        a = t00 + tx * (t10 - t00)
        b = t01 + tx * (t11 - t01)
        return a + ty * (b - a)


def _put_columns(dst: np.ndarray, idx: np.ndarray, values: np.ndarray) -> None:
    """``dst[:, idx] = values`` for a (C, N) array, one 1-D assignment per row (much faster than numpy's
    fancy assignment along the second axis)."""
    for row, vals in zip(dst, values, strict=True):
        row[idx] = vals


def _sky(scene: Scene, d: np.ndarray, noise: Noise) -> np.ndarray:
    """(3, N) sky radiance along unit directions d (N, 3)."""
    lt = scene.lighting
    el = np.clip(d[:, 2], 0.0, 1.0)
    col = cm.sky_gradient(d[:, 2], lt.sky_horizon, lt.sky_zenith)
    glow = np.clip(d @ lt.sun_direction, 0.0, 1.0) ** 32
    col = col + 0.6 * glow * lt.sun_color[:, None] / 3.0
    az = np.arctan2(d[:, 1], d[:, 0])
    cloud = noise(az * 40.0, el * 150.0, 1)
    cover = 0.4 + 0.5 * (lt.ambient > 0.8)
    c = np.clip((cloud - (1.0 - cover)) * 2.5, 0.0, 1.0)
    return (col * (1.0 - 0.6 * c) + 0.6 * c * lt.sky_horizon[:, None] * 1.1).astype(np.float32)


def _ground_albedo(scene: Scene, p: np.ndarray, noise: Noise) -> np.ndarray:
    """(3, N) albedo of terrain hits (asphalt with markings, grass/dirt) at points p (3, N), velodyne."""
    road = scene.road
    s, d = road.to_road(p[0], p[1])
    s = s.astype(np.float32)
    d = d.astype(np.float32)
    grain = noise(s * 8.0, d * 8.0, 2)  # the texture holds octaves from 0.5 m to 8 m at this scale
    on_road = road.road_surface(s, d)
    tone = 0.05 + 0.05 * float(noise.offset[7, 0]) / _TEX
    asphalt = (tone * (0.6 + 0.8 * grain)) * np.array([[1.0], [1.0], [1.04]], np.float32)
    col = np.where(on_road & road.lane_paint(s, d), 0.45 + 0.2 * grain, asphalt)
    g = np.flatnonzero(~on_road)
    mix = np.clip((noise(s[g] * 1.5, d[g] * 1.5, 4) - 0.35) * 2.5, 0, 1)
    grass = np.array([[0.06], [0.10], [0.035]], np.float32)
    dirt = np.array([[0.16], [0.13], [0.09]], np.float32)
    _put_columns(col, g, (grass + (dirt - grass) * mix) * (0.5 + grain[g]))
    return col


#: Procedural texture per material: (scale in texels per m, strength) of a multiplicative noise.
_TEXTURES = {Mat.FOLIAGE: (20.0, 0.8), Mat.FACADE: (4.0, 0.25), Mat.WALL: (8.0, 0.3), Mat.BARK: (20.0, 0.4),
             Mat.SIDEWALK: (6.0, 0.3), Mat.ROOF: (4.0, 0.3), Mat.CLOTH: (30.0, 0.15)}
_TEX_SCALE = np.zeros(len(Mat), np.float32)
_TEX_STRENGTH = np.zeros(len(Mat), np.float32)
for _m, (_scale, _strength) in _TEXTURES.items():
    _TEX_SCALE[_m], _TEX_STRENGTH[_m] = _scale, _strength


def _apply_textures(scene: Scene, material: np.ndarray, p: np.ndarray, shade: np.ndarray, noise: Noise) -> None:
    """Multiply procedural textures into the per-pixel shade (3, N) (in place) at the points p (3, N);
    ground albedo is set here (ground faces carry a white colour)."""
    g = np.flatnonzero(material == Mat.GROUND)
    if len(g):
        _put_columns(shade, g, shade.take(g, axis=1) * _ground_albedo(scene, p.take(g, axis=1), noise))
    strength = _TEX_STRENGTH[material]
    tex = np.flatnonzero(strength > 0)
    if len(tex):
        q = p.take(tex, axis=1)
        scale = _TEX_SCALE[material[tex]]
        n = noise((q[0] + 0.7 * q[2]) * scale, (q[1] - 0.7 * q[2]) * scale, 5)
        k = strength[tex]
        _put_columns(shade, tex, shade.take(tex, axis=1) * (1.0 - 0.5 * k + k * n))
    sw = np.flatnonzero(material == Mat.SIDEWALK)
    if len(sw):  # paving slabs with dark joints every 0.5 m
        s, d = scene.road.to_road(p[0, sw], p[1, sw])
        joint = sw[(np.mod(s, 0.5) < 0.03) | (np.mod(d, 0.5) < 0.03)]
        _put_columns(shade, joint, shade.take(joint, axis=1) * np.float32(0.7))


def _in_shadow(geometry: SceneGeometry, cand: np.ndarray, pix: np.ndarray, pix_object: np.ndarray, p: np.ndarray,
               normal: np.ndarray, sun: np.ndarray, odd_column: np.ndarray) -> np.ndarray:
    """(len(cand),) bool: the sun is blocked at the hits ``cand`` (ascending indices into the hit arrays:
    pixels ``pix``, their objects ``pix_object``, surface points ``p`` (3, N) and normals ``normal`` (3, N)).

    Shadow rays start 3 cm off the surface (:func:`~robustbench3d.sensors.camera_model.shadow_ray_origins`).
    A pixel in an odd column (``odd_column``, per pixel) reuses the answer of its left neighbour when both
    show the same object, which halves the rays at a one-pixel blur of shadow edges.
    """
    px, obj = pix[cand], pix_object[cand]
    # px is ascending, so a pixel's left neighbour, if it is a candidate at all, is the entry just before it
    reuse = np.zeros(len(cand), dtype=bool)
    reuse[1:] = (px[1:] - px[:-1] == 1) & (obj[1:] == obj[:-1])
    reuse &= odd_column[px]
    cast = np.flatnonzero(~reuse)
    q = cand[cast]
    blocked = np.zeros(len(cand), dtype=bool)
    origins = cm.shadow_ray_origins(p.take(q, axis=1), normal.take(q, axis=1))
    blocked[cast] = geometry.occluded(origins.T, sun, SHADOW_RAY_LENGTH)
    copy = np.flatnonzero(reuse)
    blocked[copy] = blocked[copy - 1]
    return blocked


class PixelHits(NamedTuple):
    """Step 1 of :func:`render_image`: what each pixel's ray hits.

    Attributes:
        hit: (N,) ascending indices of the pixels (row-major over (v, u)) whose ray hits a triangle.
        miss: indices of the pixels that see the sky.
        prim: (N,) int32 triangle hit by each of those pixels.
        t: (N,) float32 distance to the hit, m.
        hit_object: (N,) int32 scene object of each hit.
        object_id: (H*W,) int32 scene object seen at each pixel, -1 for sky.
    """

    hit: np.ndarray
    miss: np.ndarray
    prim: np.ndarray
    t: np.ndarray
    hit_object: np.ndarray
    object_id: np.ndarray


def intersect_pixels(rays: CameraRays, geometry: SceneGeometry) -> PixelHits:
    """Cast every pixel's ray into the scene (first hits within 2 km)."""
    w, h = rays.image_size
    hits = geometry.intersect(rays.origins, rays.directions, 2000.0)
    hit = np.flatnonzero(hits.hit)
    miss = np.flatnonzero(~hits.hit)
    object_id = np.full(w * h, -1, dtype=np.int32)
    prim = hits.prim[hit]
    hit_object = geometry.tri_object.take(prim)
    object_id[hit] = hit_object
    return PixelHits(hit, miss, prim, hits.t[hit], hit_object, object_id)


class Surface(NamedTuple):
    """Step 2 of :func:`render_image`: the surface seen at each hit pixel (per point (3, N) float32, velodyne).

    Attributes:
        points: (3, N) hit points, m.
        view: (3, N) unit view directions, camera to point.
        face_normals: (F, 3) unit normals of all triangles, turned towards the camera.
        normals: (3, N) those normals at the hits.
        material: (N,) uint8 material ids.
    """

    points: np.ndarray
    view: np.ndarray
    face_normals: np.ndarray
    normals: np.ndarray
    material: np.ndarray


def surface_attributes(rays: CameraRays, geometry: SceneGeometry, px: PixelHits) -> Surface:
    """Hit points, view directions, camera-facing normals and materials of the hit pixels."""
    dh = rays.channels.take(px.hit, axis=1)
    origin = rays.origin.astype(np.float32)
    p = origin[:, None] + px.t * dh
    nf = cm.face_toward(geometry.face_normals, geometry.face_anchor, origin)
    n_hit = np.ascontiguousarray(nf.T).take(px.prim, axis=1)
    return Surface(p, dh, nf, n_hit, geometry.tri_material.take(px.prim))


def shade_diffuse(scene: Scene, geometry: SceneGeometry, rays: CameraRays, px: PixelHits,
                  surf: Surface) -> tuple[np.ndarray, np.ndarray]:
    """Step 3: flat Lambertian shading with cast shadows (every term but shadows is per triangle).

    Returns:
        shaded: (3, N) float32 radiance of the hit pixels.
        sunlit: (N,) bool, the sun reaches the point.
    """
    lt = scene.lighting
    sun = lt.sun_direction.astype(np.float32)
    faces = cm.diffuse_faces(geometry.tri_color, surf.face_normals, sun, lt.sun_color, lt.ambient, lt.sky_zenith,
                             lt.sky_horizon)
    lit = faces.cos_sun.take(px.prim) > 0
    cand = np.flatnonzero(lit)
    blocked = _in_shadow(geometry, cand, px.hit, px.hit_object, surf.points, surf.normals, sun, rays.odd_column)
    lit[cand[blocked]] = False
    return cm.gather_faces(faces.shadowed, faces.lit, px.prim, lit), lit


def apply_specular(scene: Scene, surf: Surface, shaded: np.ndarray, sunlit: np.ndarray) -> None:
    """Step 5: sky reflection and sun highlight of shiny materials, into ``shaded`` (3, N) in place."""
    spec = SPECULAR[surf.material]
    shiny = np.flatnonzero(spec > 0)
    if len(shiny):
        lt = scene.lighting
        out = cm.specular_shading(shaded.take(shiny, axis=1), surf.normals.take(shiny, axis=1),
                                  surf.view.take(shiny, axis=1), spec[shiny], surf.material[shiny] == Mat.GLASS,
                                  sunlit[shiny], lt.sun_direction.astype(np.float32), lt.sun_color, lt.sky_horizon,
                                  lt.sky_zenith)
        _put_columns(shaded, shiny, out)


def render_image(scene: Scene, geometry: SceneGeometry, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Render camera 2: intersection -> surface attributes -> diffuse shading and shadows -> textures ->
    specular -> haze -> tone map -> sensor noise and blur (the shading steps are
    :mod:`robustbench3d.sensors.camera_model`'s).

    Per-pixel quantities are stored by component, (3, N), so that numpy's elementwise operations run
    over whole rows (the (N, 3) layout broadcasts over rows of three, several times slower).

    Returns:
        image: (H, W, 3) uint8 RGB.
        object_id: (H, W) int32 index into ``scene.objects`` of the surface seen at each pixel, -1 for sky.
    """
    rays = camera_rays(scene.day)
    w, h = rays.image_size
    lt = scene.lighting
    noise = Noise(rng)
    px = intersect_pixels(rays, geometry)

    exposure = cm.exposure_scale(lt.exposure)
    lut_index = np.empty((3, w * h), dtype=np.int16)  # display-LUT index of the exposed radiance
    _put_columns(lut_index, px.miss, cm.lut_index(_sky(scene, rays.directions.take(px.miss, axis=0), noise), exposure))

    surf = surface_attributes(rays, geometry, px)
    shaded, sunlit = shade_diffuse(scene, geometry, rays, px, surf)
    _apply_textures(scene, surf.material, surf.points, shaded, noise)
    apply_specular(scene, surf, shaded, sunlit)
    radiance = cm.aerial_perspective(shaded, px.t, lt.sky_horizon, lt.haze_distance)
    _put_columns(lut_index, px.hit, cm.lut_index(radiance, exposure))

    img = cm.display_lut().take(lut_index.T).reshape(h, w, 3)
    b = np.frombuffer(rng.bytes(img.size), dtype=np.uint8).reshape(img.shape)
    return cm.optics_blur(cm.apply_sensor_noise(img, b)), px.object_id.reshape(h, w)
