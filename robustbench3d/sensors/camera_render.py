"""Render meshes with per-vertex colours into a camera-2 image, only where they project (differentiable).

Frames: meshes in rect (x right, y down, z forward; m), image-2 pixels (integer = pixel centre, as P2).

Per mesh, the vertices are projected with P2 and the pixels of their bounding box (clipped to the
image) are rendered; a mesh entirely behind the camera or whose box misses the image is not
rendered (:attr:`CameraRenderResult.status`). A mesh straddling the camera plane gets the whole
image as its box. The boxes of all meshes are rendered together, so meshes overlapping in a pixel
resolve by depth.

Sampling (adaptive anti-aliasing): each rendered pixel first gets one sample at its centre. A pixel whose
centre shows another mesh (or none) than one of its 8 neighbours' centres lies on a silhouette or an
occlusion edge and is refined to s x s samples (``supersample`` = s) at the centres of an s x s grid of
sub-pixels; every other pixel keeps its centre sample (the generator renders its scene with one ray per
pixel, so object interiors look like the scene's surfaces, and soft edges are where they differ). Each
sample is a ray from the camera-2 centre (-K^-1 P2[:, 3] in rect). Rays meet the meshes in the same
Möller–Trumbore core as the LiDAR (one per-face table, :class:`robustbench3d.sensors.raycast.PairTable`, as
:class:`~robustbench3d.sensors.raycast.PairCaster` builds it; a no-grad search of candidate (sample, face) pairs
keeping the nearest hit per sample, ties to the smallest face id, the caster's kernel operation for operation,
compiled: :func:`robustbench3d.sensors.kernels.nearest_in_region` walks each face's box and spans without
materialising the pairs; a crop's few thousand pairs cost numpy's and torch's per-op overhead; then one
recompute with gradients on the winners of both passes, :class:`~robustbench3d.sensors.raycast.FaceRows`),
culled as a scanline rasteriser does: each face's projected vertices give a screen box (widened by
:data:`BOX_MARGIN_PX` plus 1e-5 of its size, which covers the core's barycentric tolerance and rounding), and in
each sample row of the box only the columns whose 2D barycentrics are all >= -delta (:meth:`_FaceCull.spans`,
the numpy reference of the compiled walk; a margin covering the core's tolerance, its rounding in the geometry
dtype and perspective) become candidates. Back faces of a closed star-shaped mesh seen from outside its bounding
sphere get no pairs (:func:`~robustbench3d.sensors.raycast.back_faces`, which states the condition; the
full-image reference skips the same faces). A face whose vertices are all at camera depth <= 0 cannot be hit
by a ray through the image (every hit has depth t * (K[2] . d) > 0) and gets no pairs; a face with a vertex at
depth <= 1e-6 (crossing the camera plane: its projection is unbounded) gets the whole rendered region as its box
(not split: this only happens for an object within its own size of the camera). The cull is conservative, so a
crop renders exactly like the full image; ``full_image=True`` is an independent reference that pairs every
sample of the image near a mesh's bounding sphere with every face (same sampling rule, no boxes, no spans).
Measured against 8 x 8 samples on every pixel (a random-shape object at 10 m): mean |difference| 1.7 8-bit
levels, against 0.6 for 3 x 3 samples everywhere and 3.2 for one sample per pixel, at a third of the rays of
3 x 3 everywhere.

A sample hitting face f at barycentrics (u, v) and distance t is coloured with the vertex colours
c = (1 - u - v) c0 + u c1 + v c2 (linear-RGB albedo in [0, 1], like the generator's paint), shaded with
the generator's camera model (:mod:`robustbench3d.sensors.camera_model`, same formulas, in torch):

* flat Lambertian shading of the face, normal turned towards the camera: albedo *
  (ambient * (0.6 + 0.4 n.up) * sky + max(n.l, 0) * sun) (:func:`~camera_model.diffuse_faces`; the object
  is taken to be sunlit: no cast shadows, no specular term);
* haze over the distance t (:func:`~camera_model.aerial_perspective`);
* the tone curve at the scene's exposure (:func:`~camera_model.tone_curve`, the continuous curve behind
  the generator's 8-bit LUT; no sensor noise or blur).

The lighting is the embedded scene's when the depth source knows it
(:class:`robustbench3d.synth.scene_depth.SceneRayDepth`), else :data:`DEFAULT_LIGHTING` (or the
``lighting`` argument). A sample is hidden where the scene depth (:mod:`robustbench3d.sensors.camera_depth`:
camera-2 depth, i.e. rect z relative to the camera centre) is smaller than the sample's depth t * (K[2] . d).
With w = 1 for a centre sample and 1 / s^2 for a refined pixel's samples, alpha = sum_visible w and the
pixel is

    out = photo + sum_visible w_k (colour_k - photo) = alpha * mean_visible(colour) + (1 - alpha) * photo,

in display values (the photo's [0, 1] values); the recompute of t, u, v, the shading and the compositing run
fused with a hand-written backward (:class:`_ShadeHits`: numpy and the compiled kernels of
:mod:`robustbench3d.sensors.kernels`, with numpy's arithmetic; a crop's few thousand samples cost torch's
per-op overhead). Gradients: to the colours through the barycentric
interpolation, to the vertices through u, v (interpolation), the face normal (shading) and t (haze).
The silhouette has **no** gradient: hit/miss, visibility and the nearest-face choice are piecewise
constant; coverage changes only by whole samples.
"""

from __future__ import annotations

import weakref
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np
import torch

from robustbench3d.kitti.calib import Calibration
from robustbench3d.sensors.camera_depth import DepthSource, camera_centre_rect, pixel_ray_components
from robustbench3d.sensors.camera_model import Lighting
from robustbench3d.sensors.kernels import (
    face_cull,
    nearest_in_region,
    scatter_add,
    shade_exposure,
    shade_grads,
    shade_tone,
    touching_faces,
)
from robustbench3d.sensors.mesh import cross_rows
from robustbench3d.sensors.raycast import (
    FaceRows,
    PairTable,
    back_faces,
    dot3,
    face_slots,
    scatter_rows,
    search_pairs_np,
)

#: Absolute widening (pixels) of each face's projected box in the candidate cull (see the module docstring).
BOX_MARGIN_PX = 1e-3
#: Candidate (sample, face) pairs tested per chunk (bounds the ray test's temporaries to about 30 MB).
PAIR_CHUNK = 1 << 17
#: 2D barycentric margin of the scanline cull (:meth:`_FaceCull.spans`), before the dtype's rounding term.
SPAN_MARGIN = 1e-3
#: Faces whose vertex depths differ by more than this factor skip the scanline cull (keep their box).
SPAN_DEPTH_RATIO = 20.0
#: Vertices nearer than this camera-2 depth (m) count as behind the camera for the boxes.
_NEAR = 1e-6

#: Lighting for frames without a known scene (real KITTI): a clear day, sun 40 degrees high behind-left
#: (velodyne frame), colours in the middle of the generator's clear-weather ranges.
DEFAULT_LIGHTING = Lighting(
    sun_direction=np.array([np.cos(np.radians(40)) * np.cos(np.radians(135)),
                            np.cos(np.radians(40)) * np.sin(np.radians(135)), np.sin(np.radians(40))]),
    sun_color=2.7 * np.array([1.0, 0.96, 0.885]), sky_zenith=np.array([0.18, 0.32, 0.75]),
    sky_horizon=np.array([0.62, 0.72, 0.86]) * 0.985, ambient=0.425, haze_distance=1050.0, exposure=1.0)

MeshInput = tuple[Any, Any, Any]  # (vertices_rect (V, 3), faces (F, 3), colors (V, 3)), numpy or torch
Box = tuple[int, int, int, int]  # (u0, v0, u1, v1): pixels image[v0:v1, u0:u1]


@dataclass(frozen=True, eq=False)
class CameraRenderResult:
    """Output of :func:`render_camera`.

    Attributes:
        image: (H, W, 3) uint8 composited image (pixels outside ``boxes`` are the input's, bit for bit).
        boxes: per mesh the rendered pixel box (u0, v0, u1, v1) (half-open), None if not rendered.
        status: per mesh 'rendered', 'behind' (every vertex behind the camera) or 'outside' (box misses the image).
        alpha: (H, W) float32 coverage: fraction of a pixel's samples showing an object (0 outside the boxes).
    """

    image: np.ndarray
    boxes: list[Box | None]
    status: list[str]
    alpha: np.ndarray


def mesh_box(calib: Calibration, vertices: np.ndarray, image_size: tuple[int, int]) -> tuple[Box | None, str]:
    """Pixel box of a mesh (rect vertices (V, 3)) in an image of (width, height): (box, status).

    A pixel p can hold a hit only if its footprint [p - 0.5, p + 0.5] overlaps the projected vertices'
    range, so the box is ceil(min - 0.5) .. floor(max + 0.5), clipped to the image.
    """
    w, h = image_size
    uv, depth = calib.rect_to_image(np.asarray(vertices, np.float64))
    if not np.all(np.isfinite(depth)) or len(depth) == 0:
        raise ValueError("render_camera: field 'vertices': empty, NaN or inf")
    if np.all(depth <= _NEAR):
        return None, "behind"
    if np.any(depth <= _NEAR):  # straddles the camera plane: the projection is unbounded
        return (0, 0, w, h), "rendered"
    u0, v0 = np.ceil(uv.min(axis=0) - 0.5)
    u1, v1 = np.floor(uv.max(axis=0) + 0.5) + 1
    u0, u1 = int(min(max(u0, 0), w)), int(min(max(u1, 0), w))
    v0, v1 = int(min(max(v0, 0), h)), int(min(max(v1, 0), h))
    if u0 >= u1 or v0 >= v1:
        return None, "outside"
    return (u0, v0, u1, v1), "rendered"


@dataclass(frozen=True, eq=False)
class _CameraConstants:
    """What a render derives from a calibration alone (its matrices are read-only, see :class:`Calibration`):
    the camera-2 centre (rect, m; :func:`camera_centre_rect`), K^-1 of K = P2[:, :3] (as
    :func:`~robustbench3d.sensors.camera_depth.pixel_rays_rect` forms it) and the rect lightings of
    :func:`_rect_lighting` by (lighting, dtype)."""

    centre: np.ndarray
    kinv: np.ndarray
    lights: dict


#: Per calibration (weakly held) its :class:`_CameraConstants`.
_CONSTANTS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
#: Lightings kept per calibration (the oldest is dropped beyond this).
_MAX_LIGHTS = 8


def _constants(calib: Calibration) -> _CameraConstants:
    """The :class:`_CameraConstants` of ``calib`` (computed on its first render)."""
    c = _CONSTANTS.get(calib)
    if c is None:
        c = _CONSTANTS[calib] = _CameraConstants(camera_centre_rect(calib), np.linalg.inv(calib.P2[:, :3]), {})
    return c


def _cached_lighting(lighting: Lighting, calib: Calibration, dtype: torch.dtype) -> dict[str, torch.Tensor | float]:
    """:func:`_rect_lighting`, kept per calibration for the lighting object (held, so its id stays its own) and
    dtype: a render of the same lighting and calibration reuses the (constant, never modified) tensors."""
    lights = _constants(calib).lights
    key = (id(lighting), dtype)
    hit = lights.get(key)
    if hit is None or hit[0] is not lighting:
        if len(lights) >= _MAX_LIGHTS:
            del lights[next(iter(lights))]
        with torch.inference_mode(False):  # normal tensors, usable in and out of inference mode
            hit = lights[key] = (lighting, _rect_lighting(lighting, calib, dtype))
    return hit[1]


def _rect_lighting(lighting: Lighting, calib: Calibration, dtype: torch.dtype) -> dict[str, torch.Tensor | float]:
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
    (rect), distance from the camera (N,) m; ``light`` from :func:`_rect_lighting` (see the module docstring)."""
    return shade_lit(albedo, irradiance(normals, light), distance, light)


@dataclass(frozen=True, eq=False)
class _HitSet:
    """The hits a render shades (no grad): the distinct faces hit ``faces`` (U, 3), per hit its face's
    position among them ``slot`` (K,), its unit ray direction ``dirs`` (K, 3) and its pixel ``owner`` (K,)
    with weight ``weight`` (K,) (geometry dtype); the camera centre ``origin`` (3,) (geometry dtype)."""

    faces: np.ndarray
    slot: np.ndarray
    dirs: np.ndarray
    owner: np.ndarray
    weight: np.ndarray
    origin: np.ndarray


class _ShadeHits(torch.autograd.Function):
    """The differentiable part of a render, fused, in numpy with a hand-written backward (the per-hit loops
    compiled: :func:`~robustbench3d.sensors.kernels.shade_exposure`, ``shade_tone``, ``shade_grads``, the same
    arithmetic; exp and the tone curve's power stay numpy's): per face hit,
    Möller–Trumbore's rows (:class:`~robustbench3d.sensors.raycast.FaceRows`, the core's recompute) and
    the flat shading (unit normal of e1 x e2 turned towards the camera, :func:`irradiance`, lit colours
    L_j = exposure * c_j * irradiance); per hit t, u, v (division guarded by ``where(det != 0, det, 1)``) and
    ``tone(E h (1 - f) + f ((1 - u - v) L0 + u L1 + v L2))``, f = exp(-t / haze) (E the exposure, h the horizon
    colour, tone the curve of :func:`srgb_tone_curve`); pixel p of ``base`` (P, 3) becomes
    ``base_p + sum w_k (colour_k - base_p)`` over its hits. The same formulas as :func:`shade` (checked
    against it and against finite differences); the backward is their chain rule, scattered to the vertices
    and colours. Per-hit arrays are component-major (3, K)."""

    @staticmethod
    def forward(ctx: Any, verts: torch.Tensor, colors: torch.Tensor, base: torch.Tensor, hits: _HitSet,
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
            out_c = torch.from_numpy(scatter_rows(hits.faces.reshape(-1), gc, c_shape[0])).to(c_dtype)
        if ctx.needs_input_grad[0]:
            g_irr = (g_litf * cf).sum(1) * lt["exposure"]  # (U, 3)
            # irradiance = ambient (0.6 + 0.4 n.up) sky + max(n.sun, 0) sun_color (clamp passes its gradient at 0)
            g_nrm = ((lt["ambient"] * 0.4) * (g_irr @ lt["sky"]))[:, None] * lt["up"] + \
                (np.where(sun_cos >= 0, g_irr @ lt["sun_color"], 0.0))[:, None] * lt["sun"]
            g_unit = g_nrm * flip[:, None]
            g_n = (g_unit - unit * dot3(unit, g_unit)[:, None]) / m[:, None]  # through n / |n|
            # Möller–Trumbore's t, u, v (FaceRows), plus the shading normal e1 x e2 (for a x b: b x g, g x a)
            g_e1, g_e2, g_t0 = fr.edge_grads(pairs, g_t, g_u, g_v)
            out_v = torch.from_numpy(fr.vertex_grads(g_e1 + cross_rows(fr.e2, g_n), g_e2 + cross_rows(g_n, fr.e1),
                                                     g_t0, v_shape[0])).to(v_dtype)
        if ctx.needs_input_grad[2]:
            covered = scatter_add(hits.owner, hits.weight[None], gn.shape[1])[0]  # then 1 - it in the grad's dtype
            out_b = (grad * (1.0 - torch.from_numpy(covered).to(grad.dtype))[:, None]).to(b_dtype)
        return out_v, out_c, out_b, None, None


def _sample_offsets(s: int) -> np.ndarray:
    return (np.arange(s) + 0.5) / s - 0.5


@lru_cache(maxsize=16)
def _sub_sample_offsets(s: int) -> tuple[np.ndarray, np.ndarray]:
    """(s^2,) column and row offsets (pixels) of a pixel's s x s samples, sample k = (row i, col j) = divmod(k, s)
    (read-only)."""
    off = _sample_offsets(s)
    col, row = np.tile(off, s), np.repeat(off, s)
    col.flags.writeable = row.flags.writeable = False
    return col, row


@dataclass(frozen=True, eq=False)
class _Region:
    """The pixels to render: the bounding rectangle ``rect`` (u0, v0, u1, v1) of the rendered pixels, the
    ``mask`` (v1 - v0, u1 - u0) of those inside it, and their flat image indices ``pixels`` (P,), row-major."""

    rect: Box
    mask: np.ndarray
    pixels: np.ndarray


def _culled_faces(meshes: list[tuple[torch.Tensor, np.ndarray, torch.Tensor]], origin: np.ndarray,
                  vnp: np.ndarray | None = None) -> np.ndarray:
    """(F,) bool over the meshes' concatenated faces: the back faces of the meshes that qualify for
    culling (:func:`~robustbench3d.sensors.raycast.back_faces`: closed, star-shaped, camera outside).
    ``vnp``: the meshes' concatenated vertices in float64, if each mesh's own values (saves converting them)."""
    masks = []
    start = 0
    for v, f, _ in meshes:
        vm = v.detach().cpu().numpy() if vnp is None else vnp[start:start + len(v)]
        start += len(v)
        m = back_faces(vm, f, origin)
        masks.append(np.zeros(len(f), bool) if m is None else m)
    return np.concatenate(masks) if len(masks) > 1 else masks[0]


@dataclass(frozen=True, eq=False)
class _FaceCull:
    """What the sample cull needs of each face (F faces), computed once per render from the float64 vertices.

    Attributes:
        lo, hi: (F, 2) the projected vertices' box (pixels), widened by the box margin (module docstring).
        crossing: (F,) faces with a vertex at camera depth <= 1e-6: their box is the whole region.
        unreachable: (F,) faces that cannot be hit (every vertex behind the camera, or culled back faces).
        edge: (F, 3, 3) per edge k (opposite vertex k) a, b, c with a x + b y + c >= 0 where the face's 2D
            barycentric of vertex k is >= -delta_f (the scanline cull of :meth:`spans`).
        tight: (F,) faces the scanline cull applies to (else whole box rows).
    """

    lo: np.ndarray
    hi: np.ndarray
    crossing: np.ndarray
    unreachable: np.ndarray
    edge: np.ndarray
    tight: np.ndarray

    @classmethod
    def of(cls, calib: Calibration, vertices: np.ndarray, faces: np.ndarray, skip: np.ndarray | None,
           dtype: torch.dtype, centre: np.ndarray | None = None) -> _FaceCull:
        """Faces (F, 3) of float64 rect ``vertices``; ``skip`` (F,) bool faces never hit; ``dtype`` the ray
        test's (its rounding widens the scanline margin); ``centre`` the camera centre (rect; computed if None)."""
        uv, depth = calib.rect_to_image(vertices)
        skip = np.zeros(len(faces), bool) if skip is None else skip
        return cls(*face_cull(uv[faces], depth[faces], vertices[faces], skip,
                              camera_centre_rect(calib) if centre is None else centre, near=_NEAR,
                              box_margin=BOX_MARGIN_PX, span_margin=SPAN_MARGIN,
                              eps64=64 * float(torch.finfo(dtype).eps), depth_ratio=SPAN_DEPTH_RATIO))

    def boxes(self, s: int, rect: Box) -> np.ndarray:
        """(F, 4) int64 per face the half-open box (c0, r0, c1, r1) of the sample grid (sample column c at
        u = (c + 0.5) / s - 0.5, row r likewise) that can hold its hits, clipped to ``rect``'s samples; empty
        for the unreachable faces."""
        lim = np.array(rect, np.float64) * s  # the region's samples
        with np.errstate(invalid="ignore"):
            c_lo = np.ceil((self.lo + 0.5) * s - 0.5)
            c_hi = np.floor((self.hi + 0.5) * s - 0.5) + 1
        lo_lim, hi_lim = lim[:2], lim[2:]  # np.clip(x, lo, hi) is minimum(maximum(x, lo), hi), without its overhead
        box = np.concatenate([np.minimum(np.maximum(c_lo, lo_lim), hi_lim),
                              np.minimum(np.maximum(c_hi, lo_lim), hi_lim)], axis=1)
        box[self.crossing] = lim
        box[self.unreachable] = 0
        return box.astype(np.int64)

    def touching(self, region: _Region, compiled: bool = True) -> np.ndarray:
        """(F,) bool: the faces whose box overlaps the footprint [c - 0.5, c + 0.5]^2 of a pixel of ``region``'s
        mask (so they may hit one of its samples, at any supersampling). Compiled
        (:func:`~robustbench3d.sensors.kernels.touching_faces`); ``compiled=False`` is its numpy reference."""
        if compiled:
            return touching_faces(self.lo, self.hi, self.crossing, self.unreachable, region.mask, region.rect[:2])
        u0, v0 = region.rect[0], region.rect[1]
        mh, mw = region.mask.shape
        with np.errstate(invalid="ignore"):
            box = np.concatenate([np.ceil(self.lo - 0.5), np.floor(self.hi + 0.5) + 1], axis=1)
        box[self.crossing] = [u0, v0, u0 + mw, v0 + mh]
        box[self.unreachable] = [u0, v0, u0, v0]
        box = np.minimum(np.maximum(box - np.array([u0, v0, u0, v0]), 0), np.array([mw, mh, mw, mh])).astype(np.int64)
        area = np.zeros((mh + 1, mw + 1), np.int64)  # summed-area table of the mask
        area[1:, 1:] = region.mask.cumsum(0).cumsum(1)
        inside = area[box[:, 3], box[:, 2]] - area[box[:, 1], box[:, 2]] - area[box[:, 3], box[:, 0]] + area[box[:, 1],
                                                                                                           box[:, 0]]
        return (inside > 0) & (box[:, 2] > box[:, 0]) & (box[:, 3] > box[:, 1])

    def spans(self, s: int, rect: Box, faces: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per face and sample row of its box (:meth:`boxes`), the half-open span [c0, c1) of sample columns
        that can hold its hits: (face, row, c0, c1) int64 arrays of the non-empty spans, face-major, rows
        ascending (absolute sample grid).

        The scanline cull of the projected triangle: a sample is kept if each of its 2D barycentrics (of the
        projected vertices) is >= -delta_f, delta_f = :data:`SPAN_MARGIN` plus 64 machine epsilons of the ray
        test's dtype times the face's conditioning |centre - camera| / (shortest edge * |cos|). The ray test
        accepts a 3D barycentric >= -1e-5 (plus its rounding), which is a 2D barycentric of the same sign
        scaled by at most the face's depth ratio; faces whose vertex depths differ by more than
        :data:`SPAN_DEPTH_RATIO`, that cross the camera plane, or whose projection is a sliver keep their whole
        box rows. The cull is therefore conservative: it drops only pairs the ray test rejects. ``faces``
        (F,) bool restricts the spans to those faces (e.g. :meth:`touching` a sparse region)."""
        boxes = self.boxes(s, rect)
        if faces is not None:
            boxes[~faces] = 0
        height = np.maximum(boxes[:, 3] - boxes[:, 1], 0)
        nz = np.flatnonzero(height * np.maximum(boxes[:, 2] - boxes[:, 0], 0))
        h = height[nz]
        face = nz.repeat(h)
        row = (boxes[nz, 1] - (h.cumsum() - h)).repeat(h) + np.arange(h.sum())
        c0, c1 = boxes[face, 0], boxes[face, 2]
        t = self.tight[face]
        every = bool(t.all())  # usually: then no subsets to gather and scatter (the same values)
        ft, y = (face, (row + 0.5) / s - 0.5) if every else (face[t], (row[t] + 0.5) / s - 0.5)
        e = self.edge[ft]  # (T, 3 edges, a b c)
        rhs = -(e[:, :, 1] * y[:, None] + e[:, :, 2])  # a x >= rhs
        af = e[:, :, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            x = rhs / af
            lows = np.where(af > 0, x, -np.inf)
            highs = np.where(af < 0, x, np.inf)
            lo = np.maximum(np.maximum(lows[:, 0], lows[:, 1]), lows[:, 2])
            hi = np.minimum(np.minimum(highs[:, 0], highs[:, 1]), highs[:, 2])
            dead = (af == 0) & (rhs > 0)
            lo[dead[:, 0] | dead[:, 1] | dead[:, 2]] = np.inf
            c_lo = np.ceil((lo + 0.5) * s - 0.5)
            c_hi = np.floor((hi + 0.5) * s - 0.5) + 1
        if every:
            c0, c1 = (np.minimum(np.maximum(c_lo, c0), c1).astype(np.int64),
                      np.minimum(np.maximum(c_hi, c0), c1).astype(np.int64))
        else:
            b0, b1 = c0[t], c1[t]
            c0[t] = np.minimum(np.maximum(c_lo, b0), b1).astype(np.int64)
            c1[t] = np.minimum(np.maximum(c_hi, b0), b1).astype(np.int64)
        keep = c1 > c0
        return face[keep], row[keep], c0[keep], c1[keep]


def _candidate_pairs(spans: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], region: _Region, s: int,
                     chunk: int | None = None) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Candidate (sample, face) pairs: every sample of each span (:meth:`_FaceCull.spans`) whose pixel is rendered,
    in span order (the numpy reference of the pairs :func:`~robustbench3d.sensors.kernels.nearest_in_region`
    tests; the renders use the compiled walk). Samples are numbered pixel-major in ``region.pixels`` order (s^2
    per pixel, sub-pixel row-major). Yields (samples, faces) in chunks of whole spans of at most ``chunk`` pairs
    each (one span's if larger), all in one chunk for None."""
    face, row, c0, c1 = spans
    count = c1 - c0
    if len(count) == 0:
        return
    mask = region.mask.reshape(-1)
    mh, mw = region.mask.shape
    (pv, i), (pu, j) = np.divmod(np.arange(mh * s), s), np.divmod(np.arange(mw * s), s)  # per sample row / column
    whole = bool(mask.all())  # one box: every candidate's pixel is rendered, numbered row-major
    if whole:
        row_part, col_part = pv * (mw * s * s) + i * s, pu * (s * s) + j  # sample = row_part + col_part
    else:
        pos = np.where(mask, mask.cumsum() - 1, -1)  # position of a pixel of the mask in region.pixels
        row_local, row_sub = pv * mw, i * s
    ends = count.cumsum()
    start = 0
    while start < len(count):
        done = ends[start - 1] if start else 0
        if chunk is None or ends[-1] <= done + chunk:  # the rest fits (what the search below would find)
            stop = len(count)
        else:
            stop = max(start + 1, int(np.searchsorted(ends, done + chunk, "right")))
        k = count[start:stop]
        lr = (row[start:stop] - region.rect[1] * s).repeat(k)  # region-local sample row and column per pair
        col = (c0[start:stop] - region.rect[0] * s - (k.cumsum() - k)).repeat(k) + np.arange(int(k.sum()))
        fc = face[start:stop].repeat(k)
        start = stop
        if whole:
            yield row_part[lr] + col_part[col], fc
            continue
        at = pos[row_local[lr] + pu[col]]
        keep = at >= 0
        yield (at * (s * s) + row_sub[lr] + j[col])[keep], fc[keep]


def _as_tensor(x: Any, dtype: torch.dtype | None = None) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x if dtype is None else x.to(dtype)
    return torch.tensor(np.asarray(x, np.float64), dtype=dtype or torch.float64)  # a copy: x may be read-only


def _check_meshes(meshes: Sequence[MeshInput]) -> list[tuple[torch.Tensor, np.ndarray, torch.Tensor]]:
    out = []
    for i, mesh in enumerate(meshes):
        if len(mesh) != 3:
            raise ValueError(f"render_camera: field 'meshes[{i}]': expected (vertices, faces, colors)")
        v = _as_tensor(mesh[0])
        f = np.asarray(mesh[1].detach().cpu() if isinstance(mesh[1], torch.Tensor) else mesh[1], np.int64)
        c = _as_tensor(mesh[2], v.dtype)
        if v.dim() != 2 or v.shape[1] != 3 or c.shape != v.shape:
            raise ValueError(f"render_camera: field 'meshes[{i}]': vertices {tuple(v.shape)} and colors "
                             f"{tuple(c.shape)} must both be (V, 3)")
        if f.ndim != 2 or f.shape[1] != 3 or (f.size and (f.min() < 0 or f.max() >= len(v))):
            raise ValueError(f"render_camera: field 'meshes[{i}]': faces must be (F, 3) indices into {len(v)} vertices")
        if not (np.isfinite(v.detach().cpu().numpy()).all() and np.isfinite(c.detach().cpu().numpy()).all()):
            raise ValueError(f"render_camera: field 'meshes[{i}]': NaN or inf in vertices or colors")
        out.append((v, f, c))
    return out


@dataclass(frozen=True, eq=False)
class _Geometry:
    """The meshes of a render, concatenated: vertices (V, 3) and colours (V, 3) in the geometry dtype, faces
    (F, 3), float64 vertices, the culled back faces (F,) bool, each face's mesh (F,), the camera centre (rect,
    float64) and the faces' cull (:class:`_FaceCull`)."""

    verts: torch.Tensor
    colors: torch.Tensor
    faces: np.ndarray
    vnp: np.ndarray
    culled: np.ndarray
    mesh_of_face: np.ndarray
    centre: np.ndarray
    cull: _FaceCull

    @property
    def np_dtype(self) -> np.dtype:
        """The geometry dtype in numpy."""
        return np.dtype(np.float32 if self.verts.dtype == torch.float32 else np.float64)

    @classmethod
    def of(cls, meshes: list[tuple[torch.Tensor, np.ndarray, torch.Tensor]], calib: Calibration) -> _Geometry:
        dtype = meshes[0][0].dtype
        if len(meshes) == 1:
            faces = meshes[0][1].copy()
        else:
            offsets = np.cumsum([0] + [len(m[0]) for m in meshes[:-1]])
            faces = np.concatenate([m[1] + off for m, off in zip(meshes, offsets, strict=True)])
        # one mesh: its tensors as they are (a concatenation of one is a copy, and a node in the backward)
        verts = meshes[0][0] if len(meshes) == 1 else torch.cat([m[0].to(dtype) for m in meshes])
        colors = meshes[0][2].to(dtype) if len(meshes) == 1 else torch.cat([m[2].to(dtype) for m in meshes])
        centre = _constants(calib).centre
        vnp = verts.detach().cpu().numpy().astype(np.float64)
        own = all(m[0].dtype == dtype for m in meshes)  # vnp holds each mesh's own values (not converted)
        culled = _culled_faces(meshes, centre, vnp if own else None)
        mesh_of_face = (np.zeros(len(faces), np.int64) if len(meshes) == 1
                        else np.repeat(np.arange(len(meshes)), [len(m[1]) for m in meshes]))
        return cls(verts, colors, faces, vnp, culled, mesh_of_face, centre,
                   _FaceCull.of(calib, vnp, faces, culled, dtype, centre))


@dataclass(frozen=True, eq=False)
class _Hits:
    """Visible hits of a set of samples (no grad yet): the sample indices (K,) ascending, their faces (K,) and
    ray directions (K, 3) in the geometry dtype; the samples cast and the (sample, face) pairs tested."""

    sample: np.ndarray
    face: np.ndarray
    dirs: np.ndarray
    cast: int
    tests: int

    def select(self, keep: np.ndarray) -> _Hits:
        return _Hits(self.sample[keep], self.face[keep], self.dirs.take(keep, axis=0), self.cast, self.tests)


def _dense_pairs(rays: np.ndarray, faces: np.ndarray) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Every (ray, face) pair of ``rays`` x ``faces``, in chunks of about :data:`PAIR_CHUNK` pairs."""
    step = max(1, PAIR_CHUNK // max(len(faces), 1))
    for i in range(0, len(rays), step):
        r = rays[i:i + step]
        yield np.repeat(r, len(faces)), np.tile(faces, len(r))


def _search_pairs(test: PairTable, d_cols: np.ndarray, pairs: Iterator[tuple[np.ndarray, np.ndarray]]
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """:meth:`PairCaster.search` on numpy pairs without building tensors: (rays (K,) ascending, their nearest faces
    (K,), t (K,), pairs tested) of the rays (unit directions by component ``d_cols`` (3, R), in the table's
    dtype) hitting a face of their candidate ``pairs`` (in range): the caster's kernel
    (:func:`~robustbench3d.sensors.raycast.search_pairs_np`, shared origin) and its choice, the nearest t per ray,
    equal t to the smallest face index. The full-image reference's search (and the crop's numpy reference)."""
    face, best, tests = search_pairs_np(test.table, d_cols, None, pairs, test.t_min, test.tol, check=False)
    hit = (face >= 0).nonzero()[0]
    return hit, face[hit], best[hit], tests


def _visible_hits(calib: Calibration, g: _Geometry, test: PairTable, region: _Region, w: int, s: int,
                  scene_depth: DepthSource | None, full_image: bool) -> _Hits:
    """Search the s x s samples of each pixel of ``region`` (numbered pixel-major, s^2 per pixel, sub-pixel
    row-major) and keep the nearest hits the scene depth does not hide (module docstring)."""
    pix_v, pix_u = np.divmod(region.pixels, w)
    if s == 1:  # the centres (the offset 0 added below changes nothing)
        su, sv = pix_u.astype(np.float64), pix_v.astype(np.float64)
    else:
        col_off, row_off = _sub_sample_offsets(s)
        su = (pix_u[:, None] + col_off[None, :]).reshape(-1)  # sample k = (row i, col j), k = i * s + j
        sv = (pix_v[:, None] + row_off[None, :]).reshape(-1)
    d64 = pixel_ray_components(_constants(calib).kinv, su, sv)  # (3, N)
    d_cols = d64.astype(g.np_dtype)  # by component, in the geometry dtype
    if full_image:  # the reference: every sample near a mesh's bounding sphere x every face not culled
        mesh_verts = [g.vnp[np.unique(g.faces[g.mesh_of_face == i])] for i in range(g.mesh_of_face.max() + 1)]
        pairs = _dense_pairs(_sphere_cull(np.ascontiguousarray(d64.T), g.centre, mesh_verts),
                             np.flatnonzero(~g.culled))
        sample, face, t, tests = _search_pairs(test, d_cols, pairs)
    else:
        # a whole box (one mesh's first pass): every face whose sample box meets it touches it, no filter needed
        touching = None if region.mask.all() else g.cull.touching(region)
        nearest, best, tests = nearest_in_region(g.cull, touching, test.table, d_cols, region.mask, region.rect, s,
                                                 test.t_min, test.tol)
        sample = (nearest >= 0).nonzero()[0]
        face, t = nearest[sample], best[sample]
    hits = _Hits(sample, face, d_cols.take(sample, axis=1).T, len(su), tests)
    if scene_depth is None or len(hits.sample) == 0:
        return hits
    kz = np.ascontiguousarray(d64.T[sample]) @ calib.P2[2, :3]  # camera-2 depth per unit of ray length
    scene = np.asarray(scene_depth.depth(su[sample], sv[sample]), np.float64)
    return hits.select(np.flatnonzero(~(scene < t.astype(np.float64) * kz)))


def _edge_pixels(region: _Region, shows: np.ndarray) -> np.ndarray:
    """(P,) bool over ``region.pixels``: the pixels whose centre shows another mesh (or none, -1) than one of
    their 8 neighbours' centres (``shows`` (P,) per pixel; pixels outside the region show none)."""
    mh, mw = region.mask.shape
    grid = np.full((mh + 2, mw + 2), -1, np.int64)
    grid[1:-1, 1:-1][region.mask] = shows
    # a centre differs from one of its 8 neighbours iff its 3 x 3 neighbourhood's minimum and maximum differ
    # (separable: over the columns, then the rows)
    lo = np.minimum(np.minimum(grid[:, :-2], grid[:, 1:-1]), grid[:, 2:])
    hi = np.maximum(np.maximum(grid[:, :-2], grid[:, 1:-1]), grid[:, 2:])
    lo = np.minimum(np.minimum(lo[:-2], lo[1:-1]), lo[2:])
    hi = np.maximum(np.maximum(hi[:-2], hi[1:-1]), hi[2:])
    return (lo != hi)[region.mask]


def _render_pixels(base: torch.Tensor, w: int, calib: Calibration,
                   meshes: list[tuple[torch.Tensor, np.ndarray, torch.Tensor]],
                   region: _Region, supersample: int, scene_depth: DepthSource | None, lighting: Lighting,
                   full_image: bool) -> tuple[torch.Tensor, np.ndarray, tuple[int, int]]:
    """Render the pixels of ``region`` of an image ``w`` pixels wide whose photo values there are ``base`` (P, 3):
    (values (P, 3), alpha (P,), (samples cast, pairs tested)). Sampling: the module docstring."""
    s, s2 = supersample, supersample * supersample
    g = _Geometry.of(meshes, calib)
    test = PairTable.of(g.verts.detach().numpy(), g.faces, g.centre, name="render_camera")
    centre = _visible_hits(calib, g, test, region, w, 1, scene_depth, full_image)
    parts, owner, weight = [centre], centre.sample, np.ones(len(centre.sample))
    cast, tests = centre.cast, centre.tests
    if s > 1:
        shows = np.full(len(region.pixels), -1, np.int64)
        shows[centre.sample] = g.mesh_of_face[centre.face]
        edge = _edge_pixels(region, shows)
        refined = np.flatnonzero(edge)
        if len(refined):
            mask = np.zeros_like(region.mask)
            mask[region.mask] = edge
            fine = _visible_hits(calib, g, test, _Region(region.rect, mask, region.pixels[refined]), w, s,
                                 scene_depth, full_image)
            keep = np.flatnonzero(~edge[centre.sample])
            parts = [centre.select(keep), fine]
            owner = np.concatenate([centre.sample[keep], refined[fine.sample // s2]])
            weight = np.concatenate([np.ones(len(keep)), np.full(len(fine.sample), 1.0 / s2)])
            cast, tests = cast + fine.cast, tests + fine.tests
    face = np.concatenate([p.face for p in parts])
    used, slot = face_slots(face, len(g.faces))  # the distinct faces hit, and each hit's position among them
    hits = _HitSet(g.faces[used], slot,
                   np.concatenate([p.dirs for p in parts]), owner, weight.astype(g.np_dtype),
                   g.centre.astype(g.np_dtype))
    out = _ShadeHits.apply(g.verts, g.colors, base, hits, _cached_lighting(lighting, calib, g.verts.dtype))
    alpha = np.bincount(owner, weights=weight, minlength=len(region.pixels))
    return out, alpha, (cast, tests)


def camera_ray_tests(calib: Calibration, meshes: Sequence[MeshInput], image_size: tuple[int, int],
                     supersample: int = 3) -> tuple[int, int]:
    """(samples cast, candidate (sample, face) pairs tested) of a crop render (for benchmarks)."""
    _check_supersample(supersample)
    checked = _check_meshes(meshes)
    region = _pixel_set(calib, checked, image_size, False)[0] if checked else None
    if region is None:
        return 0, 0
    with torch.inference_mode():
        base = torch.zeros(len(region.pixels), 3, dtype=torch.float64)
        return _render_pixels(base, image_size[0], calib, checked, region, supersample, None, DEFAULT_LIGHTING,
                              False)[2]


def _sphere_cull(dirs: np.ndarray, origin: np.ndarray, meshes: list[np.ndarray]) -> np.ndarray:
    """Sorted indices of the rays (unit ``dirs`` (N, 3) from ``origin``) that pass within each mesh's bounding
    sphere (centre of its vertex box, radius inflated by 1e-3 relative and 1e-9 m) ahead of the origin."""
    near = np.zeros(len(dirs), bool)
    for v in meshes:
        centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
        radius = np.linalg.norm(v - centre, axis=1).max() * (1 + 1e-3) + 1e-9
        w = centre - origin
        proj = dirs @ w
        near |= (w @ w - proj * proj <= radius * radius) & (proj > -radius)
    return np.flatnonzero(near)


def _pixel_set(calib: Calibration, meshes: list, image_size: tuple[int, int], full_image: bool
               ) -> tuple[_Region | None, list[Box | None], list[str]]:
    """The pixels to render (None if none): the union of the meshes' boxes, or the whole image."""
    w, h = image_size
    boxes, status = [], []
    for v, _, _ in meshes:
        box, st = mesh_box(calib, v.detach().cpu().numpy(), image_size)
        boxes.append(box)
        status.append(st)
    shown = [b for b in boxes if b is not None]
    if full_image:
        rect: Box = (0, 0, w, h)
    elif shown:
        rect = (min(b[0] for b in shown), min(b[1] for b in shown), max(b[2] for b in shown),
                max(b[3] for b in shown))
    else:
        return None, boxes, status
    mask = np.full((rect[3] - rect[1], rect[2] - rect[0]), full_image)
    for b in shown:
        mask[b[1] - rect[1]:b[3] - rect[1], b[0] - rect[0]:b[2] - rect[0]] = True
    if len(shown) == 1 and not full_image:  # one box: its pixels row-major, without dividing indices
        pixels = ((np.arange(rect[1], rect[3]) * w)[:, None] + np.arange(rect[0], rect[2])[None, :]).reshape(-1)
        return _Region(rect, mask, pixels), boxes, status
    lv, lu = np.divmod(np.flatnonzero(mask), mask.shape[1])
    return _Region(rect, mask, (lv + rect[1]) * w + lu + rect[0]), boxes, status


def _resolve_lighting(lighting: Lighting | None, scene_depth: DepthSource | None) -> Lighting:
    if lighting is not None:
        return lighting
    return getattr(scene_depth, "lighting", None) or DEFAULT_LIGHTING


def _check_supersample(supersample: int) -> None:
    if isinstance(supersample, bool) or not isinstance(supersample, (int, np.integer)) or supersample < 1:
        raise ValueError(f"render_camera: field 'supersample': must be an integer >= 1, got {supersample!r}")


@dataclass(frozen=True, eq=False)
class CameraCrop:
    """The rendered pixels of :func:`render_camera_crop_torch`.

    Attributes:
        pixels: (P,) int64 flat indices v * W + u of the rendered pixels (row-major; empty if none).
        values: (P, 3) their composited display values in [0, 1], differentiable like the image.
        rect: (u0, v0, u1, v1) bounding box of the pixels (half-open), None if nothing is rendered.
    """

    pixels: torch.Tensor
    values: torch.Tensor
    rect: Box | None

    def composite(self, image: torch.Tensor) -> torch.Tensor:
        """The (H, W, 3) image with the crop's pixels replaced (a copy; gradients to both)."""
        h, w, _ = image.shape
        return image.reshape(-1, 3).index_put((self.pixels,), self.values).reshape(h, w, 3)


def render_camera_crop_torch(image: torch.Tensor, calib: Calibration, meshes: Sequence[MeshInput], *,
                             scene_depth: DepthSource | None = None, supersample: int = 3,
                             lighting: Lighting | None = None, full_image: bool = False) -> CameraCrop:
    """Differentiable camera render of only the pixels the meshes can cover (:class:`CameraCrop`); arguments
    as :func:`render_camera_torch`, which is ``render_camera_crop_torch(...).composite(image)``. Nothing of
    the size of the image is computed: a loss on the crop costs only the object's pixels."""
    _check_supersample(supersample)
    if image.dim() != 3 or image.shape[2] != 3:
        raise ValueError(f"render_camera: field 'image': expected (H, W, 3), got {tuple(image.shape)}")
    checked = _check_meshes(meshes)
    h, w, _ = image.shape
    region = _pixel_set(calib, checked, (w, h), full_image)[0] if checked else None
    if region is None:
        return CameraCrop(torch.zeros(0, dtype=torch.int64), image.new_zeros(0, 3), None)
    index = torch.from_numpy(region.pixels)
    values = _render_pixels(image.reshape(-1, 3).index_select(0, index), w, calib, checked, region, supersample,
                            scene_depth, _resolve_lighting(lighting, scene_depth), full_image)[0]
    return CameraCrop(index, values, region.rect)


def render_camera_torch(image: torch.Tensor, calib: Calibration, meshes: Sequence[MeshInput], *,
                        scene_depth: DepthSource | None = None, supersample: int = 3,
                        lighting: Lighting | None = None, full_image: bool = False) -> torch.Tensor:
    """Differentiable camera render: the (H, W, 3) composited image, with gradients to ``image``, the
    meshes' vertices and colours (tensors that require grad). See the module docstring.

    Args:
        image: (H, W, 3) float tensor of display values in [0, 1] (the photo).
        calib: the frame's calibration (P2 and, for the lighting, velodyne -> rect).
        meshes: (vertices_rect (V, 3), faces (F, 3), colors (V, 3) linear RGB in [0, 1]) per mesh; the
            geometry runs in the first mesh's vertex dtype (float64 for numpy input).
        scene_depth: occluding scene depth (:mod:`robustbench3d.sensors.camera_depth`), or None.
        supersample: s; s x s samples per pixel.
        lighting: sun and sky (velodyne directions); default: the depth source's, else DEFAULT_LIGHTING.
        full_image: render every pixel of the image, not only the meshes' boxes (a reference; slow).
    """
    crop = render_camera_crop_torch(image, calib, meshes, scene_depth=scene_depth, supersample=supersample,
                                    lighting=lighting, full_image=full_image)
    return image if crop.rect is None else crop.composite(image)


def render_camera(image: np.ndarray, calib: Calibration, meshes: Sequence[MeshInput], *,
                  scene_depth: DepthSource | None = None, supersample: int = 3, lighting: Lighting | None = None,
                  full_image: bool = False) -> CameraRenderResult:
    """Render meshes into a uint8 (H, W, 3) image (numpy in, numpy out; float64 geometry, no gradients).

    The same computation as :func:`render_camera_torch` (arguments alike), run under ``inference_mode`` on
    image / 255; rendered pixels are rounded back to uint8, all others are copied unchanged.
    """
    _check_supersample(supersample)
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"render_camera: field 'image': expected (H, W, 3) uint8, got {image.shape} {image.dtype}")
    h, w, _ = image.shape
    checked = _check_meshes(meshes)
    out = image.copy()
    alpha = np.zeros((h, w), np.float32)
    if not checked:
        return CameraRenderResult(out, [], [], alpha)
    region, boxes, status = _pixel_set(calib, checked, (w, h), full_image)
    if region is not None:
        with torch.inference_mode():
            base = torch.from_numpy(image.reshape(-1, 3)[region.pixels].astype(np.float64)) / 255.0
            values, cover, _ = _render_pixels(base, w, calib, checked, region, supersample, scene_depth,
                                           _resolve_lighting(lighting, scene_depth), full_image)
        rendered = np.clip(np.round(values.numpy() * 255.0), 0, 255).astype(np.uint8)
        out.reshape(-1, 3)[region.pixels] = rendered
        alpha.reshape(-1)[region.pixels] = cover
    return CameraRenderResult(out, boxes, status, alpha)
