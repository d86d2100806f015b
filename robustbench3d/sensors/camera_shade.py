"""The camera render's shading and compositing (differentiable), and what a render derives from its calibration
and lighting.

A sample hitting face f at barycentrics (u, v) and distance t is coloured with the vertex colours
c = (1 - u - v) c0 + u c1 + v c2 (linear-RGB albedo in [0, 1], like the generator's paint), shaded with
the generator's camera model (:mod:`robustbench3d.sensors.camera_model`, same formulas, in torch):

* flat Lambertian shading of the face, normal turned towards the camera: albedo *
  (ambient * (0.6 + 0.4 n.up) * sky + max(n.l, 0) * sun) (:func:`~camera_model.diffuse_faces`; the object
  is taken to be sunlit: no cast shadows, no specular term);
* haze over the distance t (:func:`~camera_model.aerial_perspective`);
* the tone curve at the scene's exposure (:func:`~camera_model.tone_curve`, the continuous curve behind
  the generator's 8-bit LUT; no sensor noise or blur).

:func:`shade` is that in torch (the reference); :class:`ShadeHits` runs the recompute of t, u, v, the shading and
the compositing of :mod:`robustbench3d.sensors.camera_render` fused, as a torch autograd function with a
hand-written backward (numpy and the compiled kernels of :mod:`robustbench3d.sensors.camera_kernels`, with numpy's
arithmetic; a crop's few thousand samples cost torch's per-op overhead). Without a scene that knows its lighting,
renders use :data:`DEFAULT_LIGHTING`.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from robustbench3d.kitti.calib import Calibration
from robustbench3d.sensors.array_kernels import scatter_add, scatter_rows
from robustbench3d.sensors.camera_depth import camera_centre_rect
from robustbench3d.sensors.camera_kernels import shade_exposure, shade_grads, shade_tone
from robustbench3d.sensors.camera_model import Lighting
from robustbench3d.sensors.mesh import cross_rows, dot3
from robustbench3d.sensors.ray_rows import FaceRows

#: Lighting for frames without a known scene (real KITTI): a clear day, sun 40 degrees high behind-left
#: (velodyne frame), colours in the middle of the generator's clear-weather ranges.
DEFAULT_LIGHTING = Lighting(
    sun_direction=np.array([np.cos(np.radians(40)) * np.cos(np.radians(135)),
                            np.cos(np.radians(40)) * np.sin(np.radians(135)), np.sin(np.radians(40))]),
    sun_color=2.7 * np.array([1.0, 0.96, 0.885]), sky_zenith=np.array([0.18, 0.32, 0.75]),
    sky_horizon=np.array([0.62, 0.72, 0.86]) * 0.985, ambient=0.425, haze_distance=1050.0, exposure=1.0)


@dataclass(frozen=True, eq=False)
class CameraConstants:
    """What a render derives from a calibration alone (its matrices are read-only, see :class:`Calibration`):
    the camera-2 centre (rect, m; :func:`camera_centre_rect`), K^-1 of K = P2[:, :3] (as
    :func:`~robustbench3d.sensors.camera_depth.pixel_rays_rect` forms it) and the rect lightings of
    :func:`rect_lighting` by (lighting, dtype)."""

    centre: np.ndarray
    kinv: np.ndarray
    lights: dict


#: Per calibration (weakly held) its :class:`CameraConstants`.
_CONSTANTS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
#: Lightings kept per calibration (the oldest is dropped beyond this).
MAX_LIGHTS = 8


def camera_constants(calib: Calibration) -> CameraConstants:
    """The :class:`CameraConstants` of ``calib`` (computed on its first render)."""
    c = _CONSTANTS.get(calib)
    if c is None:
        c = _CONSTANTS[calib] = CameraConstants(camera_centre_rect(calib), np.linalg.inv(calib.P2[:, :3]), {})
    return c


def cached_lighting(lighting: Lighting, calib: Calibration, dtype: torch.dtype) -> dict[str, torch.Tensor | float]:
    """:func:`rect_lighting`, kept per calibration for the lighting object (held, so its id stays its own) and
    dtype: a render of the same lighting and calibration reuses the (constant, never modified) tensors."""
    lights = camera_constants(calib).lights
    key = (id(lighting), dtype)
    hit = lights.get(key)
    if hit is None or hit[0] is not lighting:
        if len(lights) >= MAX_LIGHTS:
            del lights[next(iter(lights))]
        with torch.inference_mode(False):  # normal tensors, usable in and out of inference mode
            hit = lights[key] = (lighting, rect_lighting(lighting, calib, dtype))
    return hit[1]


def rect_lighting(lighting: Lighting, calib: Calibration, dtype: torch.dtype) -> dict[str, torch.Tensor | float]:
    """The lighting's directions turned into rect, colours as tensors."""
    rot = calib.velo_to_rect[:3, :3]

    def tens(x: np.ndarray) -> torch.Tensor:
        return torch.tensor(np.asarray(x, np.float64), dtype=dtype)  # a copy: the arrays may be read-only

    sun = rot @ np.asarray(lighting.sun_direction, np.float64)
    up = rot @ np.array([0.0, 0.0, 1.0])
    sky = 0.5 * np.asarray(lighting.sky_zenith, np.float64) + 0.5 * np.asarray(lighting.sky_horizon, np.float64)
    return {"sun": tens(sun / np.linalg.norm(sun)), "up": tens(up / np.linalg.norm(up)),
            "sun_color": tens(lighting.sun_color), "sky": tens(sky), "horizon": tens(lighting.sky_horizon),
            "ambient": float(lighting.ambient), "haze": float(lighting.haze_distance),
            "exposure": float(lighting.exposure)}


def srgb_tone_curve(exposed: torch.Tensor) -> torch.Tensor:
    """Torch twin of :func:`camera_model.tone_curve`: x / (1 + x / 4), sRGB transfer curve, clipped to [0, 1]."""
    x = exposed / (1.0 + 0.25 * exposed)
    lin = 12.92 * x
    gam = 1.055 * torch.pow(torch.clamp(x, min=0.0031308), 1 / 2.4) - 0.055
    return torch.clamp(torch.where(x <= 0.0031308, lin, gam), 0.0, 1.0)


def irradiance(normals: torch.Tensor, light: dict) -> torch.Tensor:
    """(N, 3) ambient * (0.6 + 0.4 n.up) * sky + max(n.l, 0) * sun of unit camera-facing normals (N, 3) (rect)."""
    amb = (light["ambient"] * (0.6 + 0.4 * (normals @ light["up"])))[:, None] * light["sky"]
    return amb + torch.clamp(normals @ light["sun"], min=0.0)[:, None] * light["sun_color"]


def shade_lit(albedo: torch.Tensor, irr: torch.Tensor, distance: torch.Tensor, light: dict) -> torch.Tensor:
    """(N, 3) display values in [0, 1]: albedo (N, 3) * :func:`irradiance` (N, 3), hazed over the distance
    (N,) m and tone-mapped (see the module docstring)."""
    horizon = light["horizon"]
    hazed = horizon + (albedo * irr - horizon) * torch.exp(-distance / light["haze"])[:, None]
    return srgb_tone_curve(hazed * light["exposure"])


def shade(albedo: torch.Tensor, normals: torch.Tensor, distance: torch.Tensor, light: dict) -> torch.Tensor:
    """(N, 3) display values in [0, 1] of surface points: albedo (N, 3), unit camera-facing normals (N, 3)
    (rect), distance from the camera (N,) m; ``light`` from :func:`rect_lighting` (see the module docstring)."""
    return shade_lit(albedo, irradiance(normals, light), distance, light)


@dataclass(frozen=True, eq=False)
class HitSet:
    """The hits a render shades (no grad): the distinct faces hit ``faces`` (U, 3), per hit its face's
    position among them ``slot`` (K,), its unit ray direction ``dirs`` (K, 3) and its pixel ``owner`` (K,)
    with weight ``weight`` (K,) (geometry dtype); the camera centre ``origin`` (3,) (geometry dtype)."""

    faces: np.ndarray
    slot: np.ndarray
    dirs: np.ndarray
    owner: np.ndarray
    weight: np.ndarray
    origin: np.ndarray


def _as_torch(x: np.ndarray, dtype: torch.dtype) -> torch.Tensor:
    """``torch.from_numpy(x).to(dtype)`` for a float32 / float64 ``dtype``, converted by numpy (the same rounding to
    nearest, the same bits; torch converts a large array on its thread pool, whose wake-up costs more CPU time than
    the copy itself on a busy machine)."""
    want = np.float32 if dtype == torch.float32 else np.float64 if dtype == torch.float64 else None
    if want is None:
        return torch.from_numpy(x).to(dtype)
    return torch.from_numpy(x if x.dtype == want else x.astype(want))


class ShadeHits(torch.autograd.Function):
    """The differentiable part of a render, fused, in numpy with a hand-written backward (the per-hit loops
    compiled: :func:`~robustbench3d.sensors.camera_kernels.shade_exposure`, ``shade_tone``, ``shade_grads``, the same
    arithmetic; exp and the tone curve's power stay numpy's): per face hit,
    Möller–Trumbore's rows (:class:`~robustbench3d.sensors.ray_rows.FaceRows`, the core's recompute) and
    the flat shading (unit normal of e1 x e2 turned towards the camera, :func:`irradiance`, lit colours
    L_j = exposure * c_j * irradiance); per hit t, u, v (division guarded by ``where(det != 0, det, 1)``) and
    ``tone(E h (1 - f) + f ((1 - u - v) L0 + u L1 + v L2))``, f = exp(-t / haze) (E the exposure, h the horizon
    colour, tone the curve of :func:`srgb_tone_curve`); pixel p of ``base`` (P, 3) becomes
    ``base_p + sum w_k (colour_k - base_p)`` over its hits. The same formulas as :func:`shade` (checked
    against it and against finite differences); the backward is their chain rule, scattered to the vertices
    and colours. Per-hit arrays are component-major (3, K)."""

    @staticmethod
    def forward(ctx: Any, verts: torch.Tensor, colors: torch.Tensor, base: torch.Tensor, hits: HitSet,
                light: dict) -> torch.Tensor:
        vn, cn = verts.detach().numpy(), colors.detach().numpy()
        dt = vn.dtype
        f = hits.faces
        fr = FaceRows.of(vn, f, hits.origin)
        pairs = fr.tuv(hits.slot, hits.dirs)
        t, u, v, e1, e2 = pairs.t, pairs.u, pairs.v, fr.e1, fr.e2
        a0 = vn[f[:, 0]]
        # shading normal e1 x e2, unit, turned towards the camera (the sign of n . d is the same for every hit)
        n = cross_rows(e1, e2)
        norm = np.sqrt(dot3(n, n))
        m = np.maximum(norm, dt.type(1e-30))
        unit = n / m[:, None]
        flip = np.where(dot3(a0 - hits.origin, unit) > 0, dt.type(-1), dt.type(1))
        nrm = unit * flip[:, None]
        lt = {k: (x.numpy() if isinstance(x, torch.Tensor) else x) for k, x in light.items()}
        amb = lt["ambient"] * (0.6 + 0.4 * (nrm @ lt["up"]))
        sun_cos = nrm @ lt["sun"]
        irr = amb[:, None] * lt["sky"] + np.maximum(sun_cos, 0.0)[:, None] * lt["sun_color"]  # (U, 3)
        cf = cn[f]  # (U, 3 vertices, 3 channels)
        lit = (cf * irr[:, None, :] * lt["exposure"]).reshape(-1, 9)
        # per hit (compiled, numpy's arithmetic): exposed = E h (1 - f) + f ((1 - u - v) L0 + u L1 + v L2), f the
        # haze's fade; den = 1 + exposed / 4, x = exposed / den; the tone curve's power from numpy
        fade = np.exp(t * (-1.0 / lt["haze"]))
        haze = lt["horizon"] * lt["exposure"]
        dl1, dl2, exposed_minus_haze, den, x, knee_x = shade_exposure(lit, hits.slot, u, v, fade, haze)
        power = np.power(knee_x, 1 / 2.4)
        bn = base.detach().numpy()
        base_t = bn.T.astype(dt)  # (3, P)
        # y = tone(x), its slope d y / d exposed times the hit's weight, and base + sum w (clip(y) - base) per pixel
        acc, slope_w = shade_tone(x, den, power, base_t, hits.owner, hits.weight)
        ctx.saved = (hits, lt, fr, pairs, fade, dl1, dl2, exposed_minus_haze, slope_w, m, unit, flip, sun_cos, irr, cf)
        ctx.shapes = (vn.shape, cn.shape, verts.dtype, colors.dtype, base.dtype)
        return torch.from_numpy((base_t + acc).T.astype(bn.dtype))

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple:
        hits, lt, fr, pairs, fade, dl1, dl2, exposed_minus_haze, slope, m, unit, flip, sun_cos, irr, cf = ctx.saved
        v_shape, c_shape, v_dtype, c_dtype, b_dtype = ctx.shapes
        dt = pairs.inv.dtype
        u, v = pairs.u, pairs.v
        gn = grad.detach().numpy().T.astype(dt)  # (3, P)
        # per hit g_t, g_u, g_v and per face the gradients w.r.t. its lit colours (compiled, numpy's arithmetic)
        g_t, g_u, g_v, g_litf = shade_grads(gn, hits.owner, slope, fade, exposed_minus_haze, dl1, dl2, u, v,
                                            hits.slot, len(hits.faces), lt["haze"])
        g_litf = g_litf.reshape(-1, 3, 3)  # (U, 3 vertices, 3 channels)
        out_v = out_c = out_b = None
        if ctx.needs_input_grad[1]:
            gc = (g_litf * (irr[:, None, :] * lt["exposure"])).reshape(-1, 3)
            out_c = _as_torch(scatter_rows(hits.faces.reshape(-1), gc, c_shape[0]), c_dtype)
        if ctx.needs_input_grad[0]:
            g_irr = (g_litf * cf).sum(1) * lt["exposure"]  # (U, 3)
            # irradiance = ambient (0.6 + 0.4 n.up) sky + max(n.sun, 0) sun_color (clamp passes its gradient at 0)
            g_nrm = ((lt["ambient"] * 0.4) * (g_irr @ lt["sky"]))[:, None] * lt["up"] + \
                (np.where(sun_cos >= 0, g_irr @ lt["sun_color"], 0.0))[:, None] * lt["sun"]
            g_unit = g_nrm * flip[:, None]
            g_n = (g_unit - unit * dot3(unit, g_unit)[:, None]) / m[:, None]  # through n / |n|
            # Möller–Trumbore's t, u, v (FaceRows), plus the shading normal e1 x e2 (for a x b: b x g, g x a)
            g_e1, g_e2, g_t0 = fr.edge_grads(pairs, g_t, g_u, g_v)
            out_v = _as_torch(fr.vertex_grads(g_e1 + cross_rows(fr.e2, g_n), g_e2 + cross_rows(g_n, fr.e1), g_t0,
                                              v_shape[0]), v_dtype)
        if ctx.needs_input_grad[2]:
            covered = scatter_add(hits.owner, hits.weight[None], gn.shape[1])[0]  # then 1 - it in the grad's dtype
            out_b = (grad * (1.0 - torch.from_numpy(covered).to(grad.dtype))[:, None]).to(b_dtype)
        return out_v, out_c, out_b, None, None
