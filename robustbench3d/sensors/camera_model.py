"""Camera-2 shading model: the radiance of a surface point, aerial perspective, tone mapping and sensor noise.

Used by the generator (:func:`robustbench3d.synth.camera.render_image`) and meant for anything else that
renders into the image. Colours are linear RGB (albedo in [0, 1], radiance in units of a white
Lambertian surface lit head-on by a unit sun); directions are unit vectors in one frame (the
generator's is velodyne: x forward, y left, z up); distances in m. Per-face quantities are (F, 3)
arrays; per-point quantities are stored by component, (3, N), as the generator keeps them (numpy's
elementwise operations then run over whole rows). Every function is pure and vectorised; the
random parts take their random numbers as arrays.

The steps, in the generator's order:

1. Diffuse (flat per face; :func:`diffuse_faces`): with n the face normal turned towards the camera
   (:func:`face_toward`) and l the unit direction towards the sun,
   ``shadowed = albedo * ambient * (0.6 + 0.4 n_z) * sky`` with ``sky`` the mean of zenith and horizon
   colours, and ``lit = shadowed + albedo * max(n.l, 0) * sun_color``.
2. Shadows: a point shows ``lit`` where the sun reaches it (an input mask: n.l > 0 and a shadow ray from
   :func:`shadow_ray_origins` towards the sun is free for SHADOW_RAY_LENGTH m), else ``shadowed``
   (:func:`gather_faces`).
3. (Procedural textures of the generator's scenery multiply in here; not part of this model.)
4. Specular (:func:`specular_shading`, materials with specular strength s > 0): mirror reflection of the
   sky gradient with Schlick's Fresnel term (at least 0.08, 0.28 for glass), plus a Phong highlight
   (exponent 64) of the sun where the point is sunlit.
5. Haze (:func:`aerial_perspective`): radiance fades towards the horizon colour as exp(-t / haze_distance).
6. Tone map (:func:`tone_curve`, :func:`display_lut`, :func:`lut_index`): radiance * exposure, a soft
   shoulder x / (1 + x / 4), then the sRGB transfer curve, in 1/1024 steps, to 8-bit values.
7. Sensor noise (:func:`apply_sensor_noise`): the sum of two uniform 3-bit draws, centred (triangular on
   -7..7, sd 3.2 grey levels), then a [1, 2, 1] x [1, 2, 1] / 16 blur (:func:`optics_blur`).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import NamedTuple

import numpy as np


@dataclass(frozen=True)
class Lighting:
    """Sun and sky of a frame (directions in the velodyne frame, colours linear RGB)."""

    sun_direction: np.ndarray  # unit vector towards the sun
    sun_color: np.ndarray
    sky_zenith: np.ndarray
    sky_horizon: np.ndarray
    ambient: float  # sky-light strength relative to the sun
    haze_distance: float  # m, e-folding distance of aerial perspective
    exposure: float


#: Shadow rays start this far off the surface, along the (camera-facing) normal, m.
SHADOW_RAY_OFFSET_M = 0.03
#: Shadow rays stop after this distance, m (all occluders of interest are closer).
SHADOW_RAY_LENGTH = 80.0
#: Phong exponent of the sun highlight.
HIGHLIGHT_EXPONENT = 64
#: Display-LUT steps per unit of exposed radiance, and the LUT's size (exposed radiance in [0, 4)).
LUT_STEPS_PER_UNIT = 1024
LUT_SIZE = 4096


def dot3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot products of (N, 3) arrays, summed in the order of ``np.sum(a * b, axis=1)``."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def face_toward(normals: np.ndarray, anchors: np.ndarray, eye: np.ndarray) -> np.ndarray:
    """Unit face normals (F, 3) float32 turned towards the viewpoint ``eye`` (3,): a normal is negated where
    it points away from the eye, judged at a point ``anchors`` (F, 3) of each face (all float32, m)."""
    return normals * np.where(dot3(normals, anchors - eye) > 0, -1.0, 1.0).astype(np.float32)[:, None]


def sky_light(sky_zenith: np.ndarray, sky_horizon: np.ndarray) -> np.ndarray:
    """(3,) float32 colour of the ambient sky light: the mean of the zenith and horizon colours (linear RGB)."""
    return (0.5 * sky_zenith + 0.5 * sky_horizon).astype(np.float32)


def ambient_irradiance(normals: np.ndarray, ambient: float, sky_rgb: np.ndarray) -> np.ndarray:
    """(F, 3) sky light reaching faces with unit normals (F, 3) (z up): ``ambient`` (sky strength relative to
    the sun) * (0.6 + 0.4 n_z) * ``sky_rgb`` (3,), so 1.0 for a face looking up, 0.2 for one looking down."""
    return (np.float32(ambient) * (0.6 + 0.4 * normals[:, 2:3])) * sky_rgb


def sun_irradiance(cos_sun: np.ndarray, sun_color: np.ndarray) -> np.ndarray:
    """(F, 3) sunlight reaching faces whose normals make cos = ``cos_sun`` (F,) with the sun direction:
    max(cos, 0) * ``sun_color`` (3,) (Lambert's law)."""
    return np.maximum(cos_sun, 0.0)[:, None] * sun_color.astype(np.float32)


class FaceShading(NamedTuple):
    """Diffuse radiance of faces, float32.

    Attributes:
        cos_sun: (F,) n.l, cosine between each face normal and the direction towards the sun.
        shadowed: (F, 3) radiance with the sun blocked (sky light only).
        lit: (F, 3) radiance in sunlight (sky light plus the Lambertian sun term).
    """

    cos_sun: np.ndarray
    shadowed: np.ndarray
    lit: np.ndarray


def diffuse_faces(albedo: np.ndarray, normals: np.ndarray, sun_direction: np.ndarray, sun_color: np.ndarray,
                  ambient: float, sky_zenith: np.ndarray, sky_horizon: np.ndarray) -> FaceShading:
    """Flat Lambertian shading of faces.

    Args:
        albedo: (F, 3) float32 linear RGB in [0, 1].
        normals: (F, 3) float32 unit normals, turned towards the camera (:func:`face_toward`).
        sun_direction: (3,) float32 unit vector towards the sun.
        sun_color, sky_zenith, sky_horizon: (3,) linear RGB of the sun and the sky.
        ambient: sky-light strength relative to the sun.
    """
    cos_sun = normals @ sun_direction
    shadowed = albedo * ambient_irradiance(normals, ambient, sky_light(sky_zenith, sky_horizon))
    lit = shadowed + albedo * sun_irradiance(cos_sun, sun_color)
    return FaceShading(cos_sun, shadowed, lit)


def gather_faces(shadowed: np.ndarray, lit: np.ndarray, face: np.ndarray, sunlit: np.ndarray) -> np.ndarray:
    """(3, N) radiance of N points lying on faces ``face`` (N,) indices into the (F, 3) ``shadowed`` / ``lit``
    radiances: ``lit`` where the mask ``sunlit`` (N,) bool is set, ``shadowed`` elsewhere."""
    return np.ascontiguousarray(np.concatenate([shadowed, lit]).T).take(face + len(shadowed) * sunlit, axis=1)


def shadow_ray_origins(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(3, N) starts of the shadow rays of surface points (3, N), SHADOW_RAY_OFFSET_M along their
    camera-facing unit normals (3, N); the rays run towards the sun for SHADOW_RAY_LENGTH m."""
    return points + SHADOW_RAY_OFFSET_M * normals


def sky_gradient(up: np.ndarray, sky_horizon: np.ndarray, sky_zenith: np.ndarray) -> np.ndarray:
    """(3, N) sky radiance along directions with z components ``up`` (N,): horizon colour at and below the
    horizon, blending to the zenith colour as sqrt(z)."""
    return sky_horizon[:, None] + (sky_zenith - sky_horizon)[:, None] * np.sqrt(np.clip(up, 0.0, 1.0))


def mirror_reflection(normals: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reflection of view rays at surfaces: (reflected (3, N), cos_view (N,)) for unit camera-facing normals
    (3, N) and unit view directions (3, N) from the camera to the points; cos_view = clip(-n.d, 0, 1)."""
    cos_v = np.clip(-(normals[0] * directions[0] + normals[1] * directions[1] + normals[2] * directions[2]),
                    0.0, 1.0)
    return directions + 2.0 * cos_v * normals, cos_v


def schlick_fresnel(cos_view: np.ndarray) -> np.ndarray:
    """Schlick's Fresnel reflectance 0.04 + 0.96 (1 - cos)^5 (0.04 head-on, 1 at grazing incidence)."""
    c1 = 1.0 - cos_view
    c2 = c1 * c1
    return 0.04 + 0.96 * c2 * c2 * c1


def sky_reflection(reflected: np.ndarray, base: np.ndarray, sky_horizon: np.ndarray,
                   sky_zenith: np.ndarray) -> np.ndarray:
    """(3, N) float32 radiance mirrored into view: :func:`sky_gradient` along reflected directions (3, N)
    that point up, else a dim copy 0.25 * base + 0.02 of the point's own radiance ``base`` (3, N) float32
    (the ground and the scenery)."""
    up = reflected[2] > 0
    env = 0.25 * base + 0.02
    env[:, up] = sky_gradient(reflected[2, up], sky_horizon, sky_zenith)
    return env


def phong_highlight(reflected: np.ndarray, sun_direction: np.ndarray) -> np.ndarray:
    """(N,) max(r.l, 0)^64 of reflected directions (3, N) and the unit direction towards the sun (3,)."""
    r1 = np.clip(np.ascontiguousarray(reflected.T) @ sun_direction, 0.0, 1.0)  # the (N, 3) matmul
    r4 = (r1 * r1) ** 2
    r16 = (r4 * r4) ** 2
    return (r16 * r16) ** 2  # HIGHLIGHT_EXPONENT


def specular_shading(base: np.ndarray, normals: np.ndarray, directions: np.ndarray, strength: np.ndarray,
                     glass: np.ndarray, sunlit: np.ndarray, sun_direction: np.ndarray, sun_color: np.ndarray,
                     sky_horizon: np.ndarray, sky_zenith: np.ndarray) -> np.ndarray:
    """(3, N) radiance of shiny points: ``base * (1 - k) + k * sky_reflection + highlight``.

    k = strength * max(Fresnel, 0.08 (0.28 for glass)); highlight = phong * sunlit * sun_color * strength.

    Args:
        base: (3, N) float32 diffuse (and textured) radiance.
        normals: (3, N) float32 unit normals turned towards the camera.
        directions: (3, N) float32 unit view directions, camera to point.
        strength: (N,) float32 specular strength of the material (:data:`~robustbench3d.sensors.materials.SPECULAR`).
        glass: (N,) bool, the point is glass.
        sunlit: (N,) bool shadow mask (as in :func:`gather_faces`).
        sun_direction: (3,) float32 unit vector towards the sun.
        sun_color, sky_horizon, sky_zenith: (3,) linear RGB.
    """
    refl, cos_v = mirror_reflection(normals, directions)
    fresnel = schlick_fresnel(cos_v)
    env = sky_reflection(refl, base, sky_horizon, sky_zenith)
    k = strength * np.maximum(fresnel, 0.08 + 0.2 * glass)
    highlight = (phong_highlight(refl, sun_direction) * sunlit) * sun_color[:, None] * strength
    return base * (1.0 - k) + k * env + highlight.astype(np.float32)


def aerial_perspective(radiance: np.ndarray, distance: np.ndarray, sky_horizon: np.ndarray,
                       haze_distance: float) -> np.ndarray:
    """(3, N) radiance (3, N) of points at ``distance`` (N,) m from the camera, faded towards the horizon
    colour (3,) with the e-folding distance ``haze_distance`` m."""
    horizon = sky_horizon.astype(np.float32)[:, None]
    return horizon + (radiance - horizon) * np.exp(-distance / np.float32(haze_distance))


def tone_curve(exposed: np.ndarray) -> np.ndarray:
    """Display value in [0, 1] of exposed linear radiance x >= 0: the sRGB transfer curve of the soft
    shoulder x / (1 + x / 4) (keeps highlights from clipping), clipped to [0, 1]."""
    x = exposed / (1.0 + 0.25 * exposed)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(np.maximum(x, 0.0031308), 1 / 2.4) - 0.055)
    return np.clip(srgb, 0.0, 1.0)


@lru_cache(maxsize=1)
def display_lut() -> np.ndarray:
    """(LUT_SIZE,) int16 8-bit display values of :func:`tone_curve` at exposed radiance i / LUT_STEPS_PER_UNIT
    (read-only)."""
    lut = np.round(tone_curve(np.arange(LUT_SIZE, dtype=np.float64) / float(LUT_STEPS_PER_UNIT)) * 255.0)
    lut = lut.astype(np.int16)
    lut.flags.writeable = False
    return lut


def exposure_scale(exposure: float) -> np.float32:
    """Display-LUT steps per unit of linear radiance at camera ``exposure``."""
    return np.float32(exposure * float(LUT_STEPS_PER_UNIT))


def lut_index(radiance: np.ndarray, scale: np.float32) -> np.ndarray:
    """int16 :func:`display_lut` index of linear radiance times ``scale`` (:func:`exposure_scale`): rounded
    down, clipped to the table."""
    return np.clip(radiance * scale, 0, LUT_SIZE - 1).astype(np.int16)


def tone_map(radiance: np.ndarray, exposure: float) -> np.ndarray:
    """int16 8-bit display values of linear radiance (any shape) at camera ``exposure``, before noise."""
    return display_lut().take(lut_index(radiance, exposure_scale(exposure)))


def apply_sensor_noise(display: np.ndarray, random_bytes: np.ndarray) -> np.ndarray:
    """uint8 image of int16 display values (H, W, 3) plus the sensor noise made from uniform random bytes
    of the same shape: (b & 7) + (b >> 5) - 7, triangular on -7..7 grey levels, clipped to [0, 255]."""
    img = display + (random_bytes & 7)
    img += random_bytes >> 5
    return np.clip(img - 7, 0, 255).astype(np.uint8)


def optics_blur(img: np.ndarray) -> np.ndarray:
    """3x3 binomial blur ([1, 2, 1] x [1, 2, 1] / 16, PIL's rounding) of an (H, W, 3) uint8 image (the soft
    KITTI optics)."""
    from PIL import Image, ImageFilter

    kernel = ImageFilter.Kernel((3, 3), [1, 2, 1, 2, 4, 2, 1, 2, 1], scale=16)
    return np.asarray(Image.fromarray(img, "RGB").filter(kernel))
