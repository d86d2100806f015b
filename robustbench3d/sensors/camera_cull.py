"""Which (sample, face) pairs the camera render tests: the per-face cull of a scanline rasteriser, computed once
per render (:class:`FaceCull`), and the search of the nearest face per sample within it (:func:`nearest_in_region`).

Frames: rect (m) for the vertices, image-2 pixels (integer = pixel centre) for the boxes; samples on an s x s grid
per pixel (sample column c at u = (c + 0.5) / s - 0.5, row r likewise).

Each face's projected vertices give a screen box (widened by :data:`BOX_MARGIN_PX` plus 1e-5 of its size, which
covers the ray test's barycentric tolerance and rounding), and in each sample row of the box only the columns whose
2D barycentrics are all >= -delta (:meth:`FaceCull.spans`; a margin covering the test's tolerance, its rounding in
the geometry dtype and perspective) become candidates. Back faces of a closed star-shaped mesh seen from outside
its bounding sphere get no pairs (:func:`culled_faces`, :func:`robustbench3d.sensors.ray_faces.back_faces`, which
states the condition). A face whose vertices are all at camera depth <= 0 cannot be hit by a ray through the image
(every hit has depth t * (K[2] . d) > 0) and gets no pairs; a face with a vertex at depth <= :data:`NEAR_DEPTH_M`
(crossing the camera plane: its projection is unbounded) gets the whole rendered region as its box (not split:
this only happens for an object within its own size of the camera). The cull is conservative (it drops only pairs
the ray test rejects), so a crop renders exactly like the full image.

Compiled: :meth:`FaceCull.of` (:func:`robustbench3d.sensors.camera_kernels.face_cull`), :meth:`FaceCull.touching`
(:func:`~robustbench3d.sensors.camera_kernels.touching_faces`; ``compiled=False`` its numpy code) and
:func:`nearest_in_region` (:func:`robustbench3d.sensors.ray_kernels.walk_faces`, which walks each face's box and
spans without materialising the pairs). Their numpy references are here: :meth:`FaceCull.boxes`,
:meth:`FaceCull.spans` and :func:`candidate_pairs` give the pairs the walk tests.

The full-image reference render (``full_image=True``) pairs instead every sample near a mesh's bounding sphere
(:func:`sphere_cull`) with every face not culled (:func:`dense_pairs`): no boxes, no spans.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import torch

from robustbench3d.kitti.calib import Calibration
from robustbench3d.sensors.camera_depth import camera_centre_rect
from robustbench3d.sensors.camera_kernels import face_cull, touching_faces
from robustbench3d.sensors.ray_faces import back_faces
from robustbench3d.sensors.ray_kernels import walk_faces

#: Absolute widening (pixels) of each face's projected box in the candidate cull (see the module docstring).
BOX_MARGIN_PX = 1e-3
#: 2D barycentric margin of the scanline cull (:meth:`FaceCull.spans`), before the dtype's rounding term.
SPAN_MARGIN = 1e-3
#: Faces whose vertex depths differ by more than this factor skip the scanline cull (keep their box).
SPAN_DEPTH_RATIO = 20.0
#: Vertices nearer than this camera-2 depth (m) count as behind the camera for the boxes.
NEAR_DEPTH_M = 1e-6
Box = tuple[int, int, int, int]  # (u0, v0, u1, v1): pixels image[v0:v1, u0:u1]


@dataclass(frozen=True, eq=False)
class Region:
    """The pixels to render: the bounding rectangle ``rect`` (u0, v0, u1, v1) of the rendered pixels, the
    ``mask`` (v1 - v0, u1 - u0) of those inside it, and their flat image indices ``pixels`` (P,), row-major."""

    rect: Box
    mask: np.ndarray
    pixels: np.ndarray


def culled_faces(meshes: list[tuple[torch.Tensor, np.ndarray, torch.Tensor]], origin: np.ndarray,
                 vnp: np.ndarray | None = None) -> np.ndarray:
    """(F,) bool over the meshes' concatenated faces: the back faces of the meshes that qualify for
    culling (:func:`~robustbench3d.sensors.ray_faces.back_faces`: closed, star-shaped, camera outside).
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
class FaceCull:
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
           dtype: torch.dtype, centre: np.ndarray | None = None) -> FaceCull:
        """Faces (F, 3) of float64 rect ``vertices``; ``skip`` (F,) bool faces never hit; ``dtype`` the ray
        test's (its rounding widens the scanline margin); ``centre`` the camera centre (rect; computed if None)."""
        uv, depth = calib.rect_to_image(vertices)
        skip = np.zeros(len(faces), bool) if skip is None else skip
        return cls(*face_cull(uv, depth, vertices, faces, skip,
                              camera_centre_rect(calib) if centre is None else centre, near=NEAR_DEPTH_M,
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

    def touching(self, region: Region, compiled: bool = True) -> np.ndarray:
        """(F,) bool: the faces whose box overlaps the footprint [c - 0.5, c + 0.5]^2 of a pixel of ``region``'s
        mask (so they may hit one of its samples, at any supersampling). Compiled
        (:func:`~robustbench3d.sensors.camera_kernels.touching_faces`); ``compiled=False`` is its numpy reference."""
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


def candidate_pairs(spans: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], region: Region, s: int,
                    chunk: int | None = None) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Candidate (sample, face) pairs: every sample of each span (:meth:`FaceCull.spans`) whose pixel is rendered,
    in span order (the numpy reference of the pairs :func:`~robustbench3d.sensors.camera_cull.nearest_in_region`
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


def nearest_in_region(cull: FaceCull, faces: np.ndarray | None, table: np.ndarray | None, d_cols: np.ndarray,
                      mask: np.ndarray, rect: tuple[int, int, int, int], s: int, t_min: float, tol: float
                      ) -> tuple[np.ndarray, np.ndarray, int]:
    """The nearest face of each sample of a region among the faces whose scanline span holds it: (face (N,) int64
    or -1, t (N,) or +inf, pairs tested).

    Args:
        cull: the per-face cull (``lo``, ``hi``, ``crossing``, ``unreachable``, ``edge``, ``tight`` of
            :class:`FaceCull`).
        faces: (F,) bool: only these faces (None: all).
        table: (11, F) per-face test table, shared origin (:func:`robustbench3d.sensors.ray_faces._face_tables`),
            in the geometry dtype; None without faces.
        d_cols: (3, N) unit sample directions by component, the same dtype, numbered pixel-major over the True
            pixels of ``mask`` (row-major), s^2 per pixel, sub-pixel row-major.
        mask: (H', W') bool rendered pixels of the region ``rect`` (u0, v0, u1, v1), pixels.
        s: samples per pixel side; ``t_min``, ``tol``: the test's minimum distance and barycentric tolerance.
    """
    n = d_cols.shape[1]
    best_face = np.full(n, -1, np.int64)
    best_t = np.full(n, np.inf, d_cols.dtype)
    if table is None or n == 0:
        return best_face, best_t, 0
    if table.dtype != d_cols.dtype:
        raise ValueError(f"nearest_in_region: table {table.dtype} and directions {d_cols.dtype} differ")
    # the walk reads the faces' rows and the samples' directions by index: their counts must be the cull's and mask's
    if table.shape[1] != len(cull.lo) or n != int(mask.sum()) * s * s:
        raise ValueError(f"nearest_in_region: {table.shape[1]} faces in the table for {len(cull.lo)} culled, "
                         f"{n} directions for {int(mask.sum())} pixels of {s} x {s} samples")
    skip = cull.unreachable if faces is None else cull.unreachable | ~faces
    flat = mask.reshape(-1)
    pos = np.where(flat, flat.cumsum() - 1, -1)  # a pixel's position among the rendered ones
    scalar = d_cols.dtype.type  # the test's constants in the geometry dtype, as numpy takes Python floats
    tests = walk_faces(cull.lo, cull.hi, cull.crossing, skip, cull.tight, cull.edge,
                       np.array(rect, np.float64) * s, s, pos, mask.shape[1], table, d_cols, scalar(t_min),
                       scalar(tol), best_face, best_t)
    return best_face, best_t, int(tests)


#: Candidate (sample, face) pairs tested per chunk (bounds the ray test's temporaries to about 30 MB).
PAIR_CHUNK = 1 << 17


def sphere_cull(dirs: np.ndarray, origin: np.ndarray, meshes: list[np.ndarray]) -> np.ndarray:
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


def dense_pairs(rays: np.ndarray, faces: np.ndarray) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Every (ray, face) pair of ``rays`` x ``faces``, in chunks of about :data:`PAIR_CHUNK` pairs."""
    step = max(1, PAIR_CHUNK // max(len(faces), 1))
    for i in range(0, len(rays), step):
        r = rays[i:i + step]
        yield np.repeat(r, len(faces)), np.tile(faces, len(r))
