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
KITTI optics) after the sensor noise is added.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from robustbench3d.synth.calibs import CameraDay
from robustbench3d.synth.materials import SPECULAR, Mat
from robustbench3d.synth.raytrace import SceneGeometry
from robustbench3d.synth.scene import Scene

#: Shadow rays stop after this distance, m (all occluders of interest are closer).
SHADOW_RAY_LENGTH = 80.0


@dataclass(frozen=True, eq=False)
class CameraRays:
    """Per-pixel rays of a recording day's camera 2 (velodyne frame).

    Attributes:
        origin: (3,) camera-2 centre, m.
        directions: (H*W, 3) float32 unit directions, row-major over (v, u).
        image_size: (width, height).
    """

    origin: np.ndarray
    directions: np.ndarray
    image_size: tuple[int, int]


def pixel_directions(day: CameraDay, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera-2 origin (3,) and unit directions (N, 3) through pixels (u, v), velodyne frame."""
    calib = day.calib
    fu, fv, cu, cv = calib.intrinsics
    k_inv_p4 = np.linalg.solve(calib.P2[:, :3], calib.P2[:, 3])
    origin = calib.rect_to_velo_points(-k_inv_p4[None])[0]
    d_rect = np.column_stack([(np.asarray(u, np.float64) - cu) / fu, (np.asarray(v, np.float64) - cv) / fv,
                              np.ones(np.size(u))])
    d = d_rect @ calib.rect_to_velo[:3, :3].T
    return origin, d / np.linalg.norm(d, axis=1, keepdims=True)


@lru_cache(maxsize=4)
def camera_rays(day: CameraDay) -> CameraRays:
    """All pixel rays of ``day``'s image (cached per day)."""
    w, h = day.image_size
    vv, uu = np.mgrid[0:h, 0:w]
    origin, d = pixel_directions(day, uu.ravel(), vv.ravel())
    return CameraRays(origin, d.astype(np.float32), (w, h))


_TEX = 512


@lru_cache(maxsize=1)
def _fbm_texture() -> np.ndarray:
    """Tileable 512x512 fractal noise in [0, 1] (float32), the same in every process."""
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
    return out.astype(np.float32).ravel()


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
        ix, iy = fx.astype(np.int32) & m, fy.astype(np.int32) & m
        i00 = ix * _TEX + iy
        i10 = ((ix + 1) & m) * _TEX + iy
        i01 = ix * _TEX + ((iy + 1) & m)
        i11 = ((ix + 1) & m) * _TEX + ((iy + 1) & m)
        t = self.table
        a = t[i00] + tx * (t[i10] - t[i00])
        b = t[i01] + tx * (t[i11] - t[i01])
        return a + ty * (b - a)


def _sky(scene: Scene, d: np.ndarray, noise: Noise) -> np.ndarray:
    """Sky radiance along unit directions d (N, 3)."""
    lt = scene.lighting
    el = np.clip(d[:, 2], 0.0, 1.0)[:, None]
    col = lt.sky_horizon + (lt.sky_zenith - lt.sky_horizon) * np.sqrt(el)
    glow = np.clip(d @ lt.sun_direction, 0.0, 1.0) ** 32
    col = col + 0.6 * glow[:, None] * lt.sun_color / 3.0
    az = np.arctan2(d[:, 1], d[:, 0])
    cloud = noise(az * 40.0, el[:, 0] * 150.0, 1)
    cover = 0.4 + 0.5 * (lt.ambient > 0.8)
    c = np.clip((cloud - (1.0 - cover)) * 2.5, 0.0, 1.0)[:, None]
    return (col * (1.0 - 0.6 * c) + 0.6 * c * lt.sky_horizon * 1.1).astype(np.float32)


def _ground_albedo(scene: Scene, p: np.ndarray, noise: Noise) -> np.ndarray:
    """Albedo of terrain hits (asphalt with markings, grass/dirt), points p (N, 3) velodyne."""
    road = scene.road
    s, d = road.to_road(p[:, 0], p[:, 1])
    s = s.astype(np.float32)
    d = d.astype(np.float32)
    grain = noise(s * 8.0, d * 8.0, 2)  # the texture holds octaves from 0.5 m to 8 m at this scale
    on_road = road.road_surface(s, d)
    col = np.empty((len(s), 3), dtype=np.float32)
    r = np.flatnonzero(on_road)
    tone = 0.05 + 0.05 * float(noise.offset[7, 0]) / _TEX
    col[r] = (tone * (0.6 + 0.8 * grain[r]))[:, None] * np.array([1.0, 1.0, 1.04], np.float32)
    paint = r[road.lane_paint(s[r], d[r])]
    col[paint] = (0.45 + 0.2 * grain[paint])[:, None]
    g = np.flatnonzero(~on_road)
    mix = np.clip((noise(s[g] * 1.5, d[g] * 1.5, 4) - 0.35) * 2.5, 0, 1)[:, None]
    grass = np.array([0.06, 0.10, 0.035], np.float32)
    dirt = np.array([0.16, 0.13, 0.09], np.float32)
    col[g] = (grass + (dirt - grass) * mix) * (0.5 + grain[g, None])
    return col


#: Procedural texture per material: (scale in texels per m, strength) of a multiplicative noise.
_TEXTURES = {Mat.FOLIAGE: (20.0, 0.8), Mat.FACADE: (4.0, 0.25), Mat.WALL: (8.0, 0.3), Mat.BARK: (20.0, 0.4),
             Mat.SIDEWALK: (6.0, 0.3), Mat.ROOF: (4.0, 0.3), Mat.CLOTH: (30.0, 0.15)}
_TEX_SCALE = np.zeros(len(Mat), np.float32)
_TEX_STRENGTH = np.zeros(len(Mat), np.float32)
for _m, (_scale, _strength) in _TEXTURES.items():
    _TEX_SCALE[_m], _TEX_STRENGTH[_m] = _scale, _strength


def _apply_textures(scene: Scene, material: np.ndarray, p: np.ndarray, shade: np.ndarray, noise: Noise) -> None:
    """Multiply procedural textures into the per-pixel shade (in place); ground albedo is set here
    (ground faces carry a white colour)."""
    g = np.flatnonzero(material == Mat.GROUND)
    if len(g):
        shade[g] *= _ground_albedo(scene, p[g], noise)
    strength = _TEX_STRENGTH[material]
    tex = np.flatnonzero(strength > 0)
    if len(tex):
        q = p[tex]
        scale = _TEX_SCALE[material[tex]]
        n = noise((q[:, 0] + 0.7 * q[:, 2]) * scale, (q[:, 1] - 0.7 * q[:, 2]) * scale, 5)
        k = strength[tex]
        shade[tex] *= (1.0 - 0.5 * k + k * n)[:, None]
    sw = np.flatnonzero(material == Mat.SIDEWALK)
    if len(sw):  # paving slabs with dark joints every 0.5 m
        s, d = scene.road.to_road(p[sw, 0], p[sw, 1])
        joint = (np.mod(s, 0.5) < 0.03) | (np.mod(d, 0.5) < 0.03)
        shade[sw[joint]] *= 0.7


def _in_shadow(geometry: SceneGeometry, cand: np.ndarray, hit: np.ndarray, object_id: np.ndarray, p: np.ndarray,
               face_normal: np.ndarray, prim: np.ndarray, sun: np.ndarray, width: int) -> np.ndarray:
    """(len(cand),) bool: the sun is blocked for hit points ``cand`` (indices into the hit arrays).

    Shadow rays start 3 cm off the surface. A pixel in an odd column reuses the answer of its left
    neighbour when both show the same object, which halves the rays at a one-pixel blur of shadow edges.
    """
    pix = hit[cand]
    pos = np.full(len(object_id), -1, dtype=np.int64)
    pos[pix] = np.arange(len(cand))
    left = pix - 1
    reuse = ((pix % width) % 2 == 1) & (pos[left] >= 0) & (object_id[left] == object_id[pix])
    cast = np.flatnonzero(~reuse)
    blocked = np.zeros(len(cand), dtype=bool)
    q = cand[cast]
    origins = p[q] + 0.03 * face_normal[prim[q]]
    blocked[cast] = geometry.occluded(origins, np.broadcast_to(sun, (len(q), 3)), SHADOW_RAY_LENGTH)
    blocked[reuse] = blocked[pos[left[reuse]]]
    return blocked


@lru_cache(maxsize=1)
def _display_lut() -> np.ndarray:
    """4096-entry int16 table: linear radiance (after exposure) in [0, 4) -> 8-bit display value.

    A soft shoulder x / (1 + x / 4) keeps highlights from clipping, then the sRGB transfer curve.
    """
    x = np.arange(4096, dtype=np.float64) / 1024.0
    x = x / (1.0 + 0.25 * x)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(np.maximum(x, 0.0031308), 1 / 2.4) - 0.055)
    return np.round(np.clip(srgb, 0.0, 1.0) * 255.0).astype(np.int16)


def render_image(scene: Scene, geometry: SceneGeometry, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Render camera 2.

    Returns:
        image: (H, W, 3) uint8 RGB.
        object_id: (H, W) int32 index into ``scene.objects`` of the surface seen at each pixel, -1 for sky.
    """
    rays = camera_rays(scene.day)
    w, h = rays.image_size
    lt = scene.lighting
    noise = Noise(rng)
    d = rays.directions
    hits = geometry.intersect(rays.origin, d, 2000.0)
    hit = np.flatnonzero(hits.hit)
    miss = np.flatnonzero(~hits.hit)
    object_id = np.full(w * h, -1, dtype=np.int32)
    prim = hits.prim[hit]
    object_id[hit] = geometry.tri_object[prim]

    color = np.empty((w * h, 3), dtype=np.float32)
    color[miss] = _sky(scene, d[miss], noise)
    dh = d[hit]
    t = hits.t[hit]
    p = rays.origin.astype(np.float32) + t[:, None] * dh

    # flat shading: every term but textures and shadows is per triangle
    sun = lt.sun_direction.astype(np.float32)
    nf = geometry.face_normals
    nf = nf * np.where(np.sum(nf * (geometry.face_anchor - rays.origin.astype(np.float32)), axis=1) > 0, -1.0,
                       1.0).astype(np.float32)[:, None]  # towards the camera
    ndl = nf @ sun
    sky_rgb = (0.5 * lt.sky_zenith + 0.5 * lt.sky_horizon).astype(np.float32)
    amb = (np.float32(lt.ambient) * (0.6 + 0.4 * nf[:, 2:3])) * sky_rgb
    face_shadow = geometry.tri_color * amb
    face_lit = face_shadow + geometry.tri_color * (np.maximum(ndl, 0.0)[:, None] * lt.sun_color.astype(np.float32))

    lit = ndl[prim] > 0
    cand = np.flatnonzero(lit)
    lit[cand[_in_shadow(geometry, cand, hit, object_id, p, nf, prim, sun, w)]] = False
    shaded = np.concatenate([face_shadow, face_lit])[prim + len(nf) * lit]
    material = geometry.tri_material[prim]
    _apply_textures(scene, material, p, shaded, noise)

    spec = SPECULAR[material]
    shiny = np.flatnonzero(spec > 0)
    if len(shiny):
        ns, ds = nf[prim[shiny]], dh[shiny]
        cos_v = np.clip(-np.sum(ns * ds, axis=1), 0.0, 1.0)
        refl = ds + 2.0 * cos_v[:, None] * ns
        c1 = 1.0 - cos_v
        c2 = c1 * c1
        fresnel = 0.04 + 0.96 * c2 * c2 * c1
        up = refl[:, 2] > 0
        env = 0.25 * shaded[shiny] + 0.02
        el = np.sqrt(np.clip(refl[up, 2:3], 0.0, 1.0))
        env[up] = lt.sky_horizon + (lt.sky_zenith - lt.sky_horizon) * el
        k = (spec[shiny] * np.maximum(fresnel, 0.08 + 0.2 * (material[shiny] == Mat.GLASS)))[:, None]
        r1 = np.clip(refl @ sun, 0.0, 1.0)
        r4 = (r1 * r1) ** 2
        r16 = (r4 * r4) ** 2
        r64 = (r16 * r16) ** 2  # Phong exponent 64
        highlight = (r64 * lit[shiny])[:, None] * lt.sun_color * spec[shiny, None]
        shaded[shiny] = shaded[shiny] * (1.0 - k) + k * env + highlight.astype(np.float32)

    horizon = lt.sky_horizon.astype(np.float32)
    color[hit] = horizon + (shaded - horizon) * np.exp(-t / np.float32(lt.haze_distance))[:, None]

    idx = np.clip(color * np.float32(lt.exposure * 1024.0), 0, 4095).astype(np.int16)
    img = _display_lut()[idx].reshape(h, w, 3)
    # sensor noise: sum of two uniform 3-bit draws, centred (triangular on -7..7, sd 3.2 grey levels)
    b = np.frombuffer(rng.bytes(img.size), dtype=np.uint8).reshape(img.shape)
    img += (b & 7).astype(np.int16)
    img += (b >> 5).astype(np.int16)
    img8 = np.clip(img - 7, 0, 255).astype(np.uint8)
    return _blur121(img8), object_id.reshape(h, w)


def _blur121(img: np.ndarray) -> np.ndarray:
    """3x3 binomial blur ([1, 2, 1] x [1, 2, 1] / 16) of an (H, W, 3) uint8 image."""
    from PIL import Image, ImageFilter

    kernel = ImageFilter.Kernel((3, 3), [1, 2, 1, 2, 4, 2, 1, 2, 1], scale=16)
    return np.asarray(Image.fromarray(img, "RGB").filter(kernel))
