"""Render meshes with per-vertex colours into a camera-2 image, only where they project (differentiable).

Frames: meshes in rect (x right, y down, z forward; m), image-2 pixels (integer = pixel centre, as P2).

Per mesh, the vertices are projected with P2 and the pixels of their bounding box (clipped to the
image) are rendered; a mesh entirely behind the camera or whose box misses the image is not
rendered (:attr:`CameraRenderResult.status`). A mesh straddling the camera plane gets the whole
image as its box. The boxes of all meshes are rendered together, so meshes overlapping in a pixel
resolve by depth.

Each rendered pixel gets s x s samples (``supersample`` = s) at the centres of an s x s grid of
sub-pixels; each sample is a ray from the camera-2 centre (-K^-1 P2[:, 3] in rect). Rays meet the
meshes in the same Möller–Trumbore core as the LiDAR (:mod:`robustbench3d.sensors.raycast`), culled as
a sparse rasteriser does: each face's projected vertices give a screen box (widened by
:data:`BOX_MARGIN_PX` plus 1e-5 of its size, which covers the core's barycentric tolerance and rounding),
the samples inside it (and inside the rendered pixels) become candidate (sample, face) pairs
(``repeat_interleave`` over the boxes), which :func:`~robustbench3d.sensors.raycast.cast_ray_pairs` tests
under no_grad, keeps the nearest hit per sample (ties: smallest face id) and recomputes with gradients
on the winners only. Back faces of a closed star-shaped mesh seen from outside its bounding sphere get no
pairs (:func:`~robustbench3d.sensors.raycast.back_faces`, which states the condition; the full-image
reference skips the same faces). A face whose vertices are all at camera depth <= 0 cannot be hit by a ray through
the image (every hit has depth t * (K[2] . d) > 0) and gets no pairs; a face with a vertex at depth <= 1e-6
(crossing the camera plane: its projection is unbounded) gets the whole rendered region as its box (not
split: this only happens for an object within its own size of the camera). The box cull is
conservative, so a crop renders exactly like the full image; ``full_image=True`` is an independent
reference that casts every sample of the image with :func:`~robustbench3d.sensors.raycast.cast_rays`
(its own 3D bounding-sphere cull).

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
With alpha = (visible samples) / s^2 the pixel is

    out = photo + sum_visible (colour_k - photo) / s^2 = alpha * mean_visible(colour) + (1 - alpha) * photo,

in display values (the photo's [0, 1] values). Gradients: to the colours through the barycentric
interpolation, to the vertices through u, v (interpolation), the face normal (shading) and t (haze).
The silhouette has **no** gradient: hit/miss, visibility and the nearest-face choice are piecewise
constant; coverage changes only by whole samples.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from robustbench3d.kitti.calib import Calibration
from robustbench3d.sensors.camera_depth import DepthSource, camera_centre_rect, pixel_rays_rect
from robustbench3d.sensors.camera_model import Lighting
from robustbench3d.sensors.raycast import back_faces, cast_ray_pair_chunks, cast_rays

#: Absolute widening (pixels) of each face's projected box in the candidate cull (see the module docstring).
BOX_MARGIN_PX = 1e-3
#: Candidate (sample, face) pairs tested per chunk (bounds the ray test's temporaries to about 30 MB).
PAIR_CHUNK = 1 << 17
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
    u0, u1 = int(np.clip(u0, 0, w)), int(np.clip(u1, 0, w))
    v0, v1 = int(np.clip(v0, 0, h)), int(np.clip(v1, 0, h))
    if u0 >= u1 or v0 >= v1:
        return None, "outside"
    return (u0, v0, u1, v1), "rendered"


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


def _sample_offsets(s: int) -> np.ndarray:
    return (np.arange(s) + 0.5) / s - 0.5


@dataclass(frozen=True, eq=False)
class _Region:
    """The pixels to render: the bounding rectangle ``rect`` (u0, v0, u1, v1) of the rendered pixels, the
    ``mask`` (v1 - v0, u1 - u0) of those inside it, and their flat image indices ``pixels`` (P,), row-major."""

    rect: Box
    mask: np.ndarray
    pixels: np.ndarray


def _culled_faces(meshes: list[tuple[torch.Tensor, np.ndarray, torch.Tensor]], origin: np.ndarray) -> np.ndarray:
    """(F,) bool over the meshes' concatenated faces: the back faces of the meshes that qualify for
    culling (:func:`~robustbench3d.sensors.raycast.back_faces`: closed, star-shaped, camera outside)."""
    masks = []
    for v, f, _ in meshes:
        m = back_faces(v.detach().cpu().numpy(), f, origin)
        masks.append(np.zeros(len(f), bool) if m is None else m)
    return np.concatenate(masks)


def _face_sample_boxes(calib: Calibration, vertices: np.ndarray, faces: np.ndarray, s: int, rect: Box,
                       skip: np.ndarray | None = None) -> np.ndarray:
    """(F, 4) int64 per face the half-open box (c0, r0, c1, r1) of the sample grid (sample column c at
    u = (c + 0.5) / s - 0.5, row r likewise) that can hold its hits, clipped to ``rect``'s samples; empty
    for faces that cannot be hit (see the module docstring) and those of ``skip`` (F,) bool."""
    uv, depth = calib.rect_to_image(vertices)
    fd = depth[faces]  # (F, 3)
    unreachable = (fd <= 0).all(axis=1)
    if skip is not None:
        unreachable |= skip
    crossing = (fd <= _NEAR).any(axis=1) & ~unreachable
    lim = np.array([rect[0], rect[1], rect[2], rect[3]], np.float64) * s  # the region's samples
    with np.errstate(divide="ignore", invalid="ignore"):
        fuv = np.where(crossing[:, None, None] | unreachable[:, None, None], 0.0, uv[faces])  # (F, 3, 2)
        lo, hi = fuv.min(axis=1), fuv.max(axis=1)
        margin = BOX_MARGIN_PX + 1e-5 * (hi - lo).max(axis=1, keepdims=True)
        c_lo = np.ceil((lo - margin + 0.5) * s - 0.5)
        c_hi = np.floor((hi + margin + 0.5) * s - 0.5) + 1
    box = np.concatenate([np.clip(c_lo, lim[:2], lim[2:]), np.clip(c_hi, lim[:2], lim[2:])], axis=1)
    box[crossing] = lim
    box[unreachable] = 0
    return box.astype(np.int64)


def _candidate_pairs(boxes: np.ndarray, region: _Region, s: int,
                     chunk: int | None = None) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Candidate (sample, face) pairs: every sample of each face's box (:func:`_face_sample_boxes`) whose
    pixel is rendered, face-major and row-major within a box. Samples are numbered pixel-major in
    ``region.pixels`` order (s^2 per pixel, sub-pixel row-major). Yields (samples, faces) in chunks of whole
    faces of at most ``chunk`` pairs each (one face's if larger), all in one chunk for None."""
    width = np.maximum(boxes[:, 2] - boxes[:, 0], 0)
    height = np.maximum(boxes[:, 3] - boxes[:, 1], 0)
    nonempty = np.flatnonzero(width * height)
    if len(nonempty) == 0:
        return
    mask = region.mask.reshape(-1)
    mh, mw = region.mask.shape
    (pv, i), (pu, j) = np.divmod(np.arange(mh * s), s), np.divmod(np.arange(mw * s), s)  # per sample row / column
    whole = bool(mask.all())  # one box: every candidate's pixel is rendered, numbered row-major
    if whole:
        row_part, col_part = pv * (mw * s * s) + i * s, pu * (s * s) + j  # sample = row_part + col_part
    else:
        pos = np.where(mask, np.cumsum(mask) - 1, -1)  # position of a pixel of the mask in region.pixels
        row_local, row_sub = pv * mw, i * s
    ends = np.cumsum(width[nonempty] * height[nonempty])
    start = 0
    while start < len(nonempty):
        done = ends[start - 1] if start else 0
        stop = len(nonempty) if chunk is None else max(start + 1, int(np.searchsorted(ends, done + chunk, "right")))
        f = nonempty[start:stop]
        start = stop
        h, w = height[f], width[f]
        # one entry per box row (region sample row ``row``), then one per sample of the row (column ``col``)
        row = np.repeat(boxes[f, 1] - region.rect[1] * s - (np.cumsum(h) - h), h) + np.arange(h.sum())
        rw = np.repeat(w, h)
        col = np.repeat(np.repeat(boxes[f, 0] - region.rect[0] * s, h) - (np.cumsum(rw) - rw), rw)
        col += np.arange(len(col))
        face = np.repeat(np.repeat(f, h), rw)
        if whole:
            yield np.repeat(row_part[row], rw) + col_part[col], face
            continue
        at = pos[np.repeat(row_local[row], rw) + pu[col]]
        keep = at >= 0
        yield (at * (s * s) + np.repeat(row_sub[row], rw) + j[col])[keep], face[keep]


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
        if not bool(torch.isfinite(v.detach()).all()) or not bool(torch.isfinite(c.detach()).all()):
            raise ValueError(f"render_camera: field 'meshes[{i}]': NaN or inf in vertices or colors")
        out.append((v, f, c))
    return out


def _render_pixels(base: torch.Tensor, w: int, calib: Calibration,
                   meshes: list[tuple[torch.Tensor, np.ndarray, torch.Tensor]],
                   region: _Region, supersample: int, scene_depth: DepthSource | None, lighting: Lighting,
                   full_image: bool) -> tuple[torch.Tensor, np.ndarray]:
    """Render the pixels of ``region`` of an image ``w`` pixels wide whose photo values there are ``base`` (P, 3):
    (values (P, 3), alpha (P,))."""
    pixels = region.pixels
    s, s2 = supersample, supersample * supersample
    dtype = meshes[0][0].dtype
    verts = torch.cat([m[0].to(dtype) for m in meshes])
    colors = torch.cat([m[2].to(dtype) for m in meshes])
    offsets = np.cumsum([0] + [len(m[0]) for m in meshes[:-1]])
    faces = np.concatenate([m[1] + off for m, off in zip(meshes, offsets, strict=True)])
    faces_t = torch.from_numpy(faces)

    pix_v, pix_u = np.divmod(pixels, w)
    off = _sample_offsets(s)
    su = (pix_u[:, None] + np.tile(off, s)[None, :]).reshape(-1)  # sample k = (row i, col j), k = i * s + j
    sv = (pix_v[:, None] + np.repeat(off, s)[None, :]).reshape(-1)
    dirs_np = pixel_rays_rect(calib, su, sv)
    dirs = torch.from_numpy(dirs_np).to(dtype)
    centre = camera_centre_rect(calib)
    origin = torch.from_numpy(centre).to(dtype)
    culled = _culled_faces(meshes, centre)
    if full_image:  # the reference: every sample near a mesh's bounding sphere, with cast_rays' own cull
        cast = _sphere_cull(dirs_np, centre, [m[0].detach().cpu().numpy() for m in meshes])
        hits = cast_rays(verts, faces_t, dirs.index_select(0, torch.from_numpy(cast)), origin,
                         skip_faces=torch.from_numpy(culled))
    else:
        boxes = _face_sample_boxes(calib, verts.detach().cpu().numpy().astype(np.float64), faces, s, region.rect,
                                   culled)
        pairs = ((torch.from_numpy(a), torch.from_numpy(b)) for a, b in _candidate_pairs(boxes, region, s, PAIR_CHUNK))
        hits = cast_ray_pair_chunks(verts, faces_t, dirs, origin, pairs, name="render_camera")
        cast = None
    hit_t = torch.nonzero(hits.hit).reshape(-1)
    samples = hit_t.numpy() if cast is None else cast[hit_t.numpy()]
    face_t = hits.face.index_select(0, hit_t)
    t, u, v = hits.t.index_select(0, hit_t), hits.u.index_select(0, hit_t), hits.v.index_select(0, hit_t)

    if scene_depth is not None and len(samples):
        kz = dirs_np[samples] @ calib.P2[2, :3]  # camera-2 depth per unit of ray length
        scene = np.asarray(scene_depth.depth(su[samples], sv[samples]), np.float64)
        keep = torch.from_numpy(np.flatnonzero(~(scene < t.detach().cpu().numpy().astype(np.float64) * kz)))
        samples, face_t, t, u, v = samples[keep.numpy()], face_t[keep], t[keep], u[keep], v[keep]

    # per face of the hits: camera-facing unit normal and the irradiance factor (shade); per sample: albedo
    used, slot = torch.unique(face_t, return_inverse=True)
    fu = faces_t.index_select(0, used)
    a0 = verts.index_select(0, fu[:, 0])
    n = torch.linalg.cross(verts.index_select(0, fu[:, 1]) - a0, verts.index_select(0, fu[:, 2]) - a0, dim=-1)
    n = n / torch.clamp(torch.linalg.norm(n, dim=-1, keepdim=True), min=1e-30)
    # two-sided: turned towards the camera (the sign of n . d is the same for every ray hitting the face)
    n = torch.where(((a0 - origin) * n).sum(-1, keepdim=True).detach() > 0, -n, n)
    light = _rect_lighting(lighting, calib, dtype)
    fv = fu.index_select(0, slot)
    w0 = (1.0 - u - v)[:, None]
    albedo = (w0 * colors.index_select(0, fv[:, 0]) + u[:, None] * colors.index_select(0, fv[:, 1])
              + v[:, None] * colors.index_select(0, fv[:, 2]))
    colour = shade_lit(albedo, irradiance(n, light).index_select(0, slot), t, light).to(base.dtype)
    samples_t = torch.from_numpy(samples)

    owner = samples_t // s2
    acc = torch.zeros_like(base).index_add(0, owner, colour - base[owner])
    alpha = np.bincount(samples // s2, minlength=len(pixels)) / s2
    return base + acc / s2, alpha


def camera_ray_tests(calib: Calibration, meshes: Sequence[MeshInput], image_size: tuple[int, int],
                     supersample: int = 3) -> tuple[int, int]:
    """(samples rendered, candidate (sample, face) pairs tested) of a crop render (for benchmarks)."""
    _check_supersample(supersample)
    checked = _check_meshes(meshes)
    region = _pixel_set(calib, checked, image_size, False)[0] if checked else None
    if region is None:
        return 0, 0
    verts = np.concatenate([m[0].detach().cpu().numpy().astype(np.float64) for m in checked])
    offsets = np.cumsum([0] + [len(m[0]) for m in checked[:-1]])
    faces = np.concatenate([m[1] + off for m, off in zip(checked, offsets, strict=True)])
    boxes = _face_sample_boxes(calib, verts, faces, supersample, region.rect,
                               _culled_faces(checked, camera_centre_rect(calib)))
    return len(region.pixels) * supersample ** 2, sum(len(a) for a, _ in _candidate_pairs(boxes, region, supersample))


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
    lv, lu = np.divmod(np.flatnonzero(mask), mask.shape[1])
    return _Region(rect, mask, (lv + rect[1]) * w + lu + rect[0]), boxes, status


def _resolve_lighting(lighting: Lighting | None, scene_depth: DepthSource | None) -> Lighting:
    if lighting is not None:
        return lighting
    return getattr(scene_depth, "lighting", None) or DEFAULT_LIGHTING


def _check_supersample(supersample: int) -> None:
    if isinstance(supersample, bool) or not isinstance(supersample, (int, np.integer)) or supersample < 1:
        raise ValueError(f"render_camera: field 'supersample': must be an integer >= 1, got {supersample!r}")


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
    _check_supersample(supersample)
    if image.dim() != 3 or image.shape[2] != 3:
        raise ValueError(f"render_camera: field 'image': expected (H, W, 3), got {tuple(image.shape)}")
    checked = _check_meshes(meshes)
    h, w, _ = image.shape
    if not checked:
        return image
    region, _, _ = _pixel_set(calib, checked, (w, h), full_image)
    if region is None:
        return image
    index = torch.from_numpy(region.pixels)
    values, _ = _render_pixels(image.reshape(-1, 3).index_select(0, index), w, calib, checked, region, supersample,
                               scene_depth, _resolve_lighting(lighting, scene_depth), full_image)
    return image.reshape(-1, 3).index_put((index,), values).reshape(h, w, 3)


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
            values, cover = _render_pixels(base, w, calib, checked, region, supersample, scene_depth,
                                           _resolve_lighting(lighting, scene_depth), full_image)
        rendered = np.clip(np.round(values.numpy() * 255.0), 0, 255).astype(np.uint8)
        out.reshape(-1, 3)[region.pixels] = rendered
        alpha.reshape(-1)[region.pixels] = cover
    return CameraRenderResult(out, boxes, status, alpha)
