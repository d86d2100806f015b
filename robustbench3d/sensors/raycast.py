"""Nearest ray/triangle hits in torch, differentiable in the vertices (Möller–Trumbore).

One core for both sensors: LiDAR beams (the HDL-64E lasers start at different heights on the z axis)
and camera pixel rays (one shared origin). Ray r starts at ``origin + origin_offset[r] * offset_axis``
and runs along the unit direction d_r; faces are two-sided.

Numerically safe form (performance-notes.md §2):

1. Search, no grad, chunked over rays. Rays are first tested against the bounding spheres of clusters of
   consecutive faces, then against the faces of the clusters they pass through. With T = o_r - V0 =
   T0 + h_r a (h_r the ray's offset along the axis a), Möller–Trumbore's det, u*det, v*det and t*det are
   each a per-face constant plus h_r times another per-face constant: five dot products of d_r with
   per-face vectors (a GEMM in dense form; here evaluated on the candidate pairs only: a gather of the face's
   column of constants and three 3-term dot products per pair). The test has no divisions; the sign that
   makes t > 0 is folded in per face for a shared origin (t*det is then per face), per pair with offsets;
   the nearest face per ray is kept. Optional back-face culling (:func:`back_faces`, ``skip_faces``).
2. Recompute, with grad, on the (ray, nearest face) pairs only; divisions by ``where(ok, det, 1)``. In numpy
   (:class:`FaceRows`: per-face rows of the faces hit, then per pair; compiled for one float dtype by
   :mod:`robustbench3d.sensors.kernels`, the same arithmetic) with a hand-written backward: a car's or a crop's
   few hundred to few thousand pairs would otherwise cost torch's per-op overhead.

Two entry points share the per-face table (:func:`_face_tables`) and the recompute (:func:`_recompute`):
:func:`cast_rays` builds the candidate pairs itself (bounding spheres, above) and tests them in torch
(:func:`_test_pairs`, :func:`_nearest`: large dense casts), and :func:`cast_ray_pairs` (and
:class:`PairCaster`) takes candidate (ray, face) pairs from the caller's own cull (the LiDAR's per-face
bounding spheres, the camera's per-face screen boxes) and tests them with a compiled twin of the same kernel
(:func:`search_pairs`: :func:`robustbench3d.sensors.kernels.nearest_of_pairs`; its numpy reference
:func:`search_pairs_np` is :func:`hit_pairs_np` and :func:`nearest_np`: a car's few thousand pairs cost torch's
per-op overhead; the same element-wise IEEE operations in the same order and dtype, so the same verdicts and t
bit for bit). Both test
a pair element-wise, so its verdict and t do not depend on the other pairs, and keep the nearest hit per ray
(equal t: the smallest face index). :func:`cast_ray_search` lets a caller whose cull finds the candidate pairs in
a compiled loop test them there with the same arithmetic (the LiDAR render's
:func:`robustbench3d.sensors.kernels.sphere_pairs_nearest`) and recomputes the winners as the others do.

Rejected: faces of (near) zero area, rays within ``arccos(cos_min)`` of grazing (relative cut
|cos(incidence)| > cos_min, which also bounds the gradients at about 1/cos_min), hits at t <= t_min.
Barycentric tolerance 1e-6 (float64) / 1e-5 (float32) so rays through edges and vertices never leak.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np
import torch

from robustbench3d.sensors.kernels import (
    face_rows,
    face_test_table,
    nearest_of_pairs,
    pair_tuv,
    scatter_pair_grads,
    scatter_rows,
    star_faces,
)
from robustbench3d.sensors.mesh import cross_rows

#: Rays x faces per chunk of the no-grad search (bounds its memory to about 150 MB even if every pair is tested).
SEARCH_CHUNK_PAIRS = 1 << 20
#: Consecutive faces sharing one bounding sphere in the search (icosphere level L: face k of level L - 1 becomes
#: faces 4k..4k+3; other meshes work whatever their face order, only faster when it is coherent).
CLUSTER_SIZE = 4
#: Faces whose |e1 x e2| is at or below this fraction of their longest squared edge are treated as degenerate.
_SLIVER = {torch.float64: 1e-10, torch.float32: 1e-5}
#: Barycentric tolerance: rays tangent to an edge or through a vertex still hit one of its faces.
_BARY_TOL = {torch.float64: 1e-6, torch.float32: 1e-5}

__all__ = ["CLUSTER_SIZE", "SEARCH_CHUNK_PAIRS", "FaceRows", "PairCaster", "PairSearch", "PairTUV", "PairTable",
           "RayHits", "back_faces", "cast_ray_pair_chunks", "cast_ray_pairs", "cast_ray_search", "cast_rays",
           "face_slots", "face_test_geometry", "hit_pairs_np", "nearest_np", "scatter_rows", "search_pairs",
           "search_pairs_np"]


@dataclass(frozen=True)
class RayHits:
    """Nearest hits of R rays.

    Attributes:
        hit: (R,) bool.
        face: (R,) int64 face index, -1 on a miss.
        t: (R,) distance along the unit direction, 0 on a miss; differentiable w.r.t. the vertices.
        u: (R,) barycentric weight of the face's vertex 1, 0 on a miss; differentiable.
        v: (R,) barycentric weight of vertex 2 (vertex 0 has 1 - u - v); differentiable.
        tests: number of ray-triangle pairs tested by the search (at most R x F).
    """

    hit: torch.Tensor
    face: torch.Tensor
    t: torch.Tensor
    u: torch.Tensor
    v: torch.Tensor
    tests: int = 0

    def points(self, origins: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
        """(R, 3) hit points origins + t * directions (origins (R, 3) or (3,)); zero rows on misses."""
        p = origins + self.t[:, None] * directions
        return torch.where(self.hit[:, None], p, torch.zeros_like(p))


def _as_tensor(x: object, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x.to(dtype=dtype, device=device)
    a = np.asarray(x)
    return torch.as_tensor(a if a.flags.writeable else a.copy(), dtype=dtype, device=device)


def _face_tables(v0: np.ndarray, e1: np.ndarray, e2: np.ndarray, valid: np.ndarray, origin: np.ndarray,
                 axis: np.ndarray, cos_min: float, offsets: bool) -> np.ndarray:
    """Per-face constants of the no-grad test (module docstring), component-major (k, F) so that gathers by
    face give contiguous rows: rows 3j..3j+2 the vector whose dot product with d is face f's det, u*det,
    v*det at h = 0 (j = 0, 1, 2), row 9 t*det at h = 0, row 10 the grazing floor of |det| (+inf: never hit),
    and with ``offsets`` (k = 18) the slopes in h of u*det, v*det (rows 11..16) and of t*det (row 17).
    In numpy in the vertices' dtype (a few hundred faces cost torch's per-op overhead).

    Shared origin (not ``offsets``): t*det is a per-face constant, so the sign that makes t > 0 is known
    per face; rows 0..9 are multiplied by sign(t*det) (exact), a hit then needs det > floor, and a face
    whose plane holds the origin (t*det = 0) gets an infinite floor."""
    t0 = origin - v0  # T at offset 0, (F, 3)
    n = cross_rows(e2, e1)  # det = d . (e2 x e1)
    s0 = dot3(e2, cross_rows(t0, e1))  # t*det = s0 + h s1
    # relative grazing cut |det| > cos_min * |n| * |d| (unit d), never on a degenerate face
    floor = np.where(valid, cos_min * np.sqrt(dot3(n, n)), np.inf)
    rows = [n, cross_rows(e2, t0), cross_rows(t0, e1), s0[:, None], floor[:, None]]
    if offsets:
        ax = np.broadcast_to(axis, e1.shape)
        rows += [cross_rows(e2, ax), cross_rows(ax, e1), dot3(e2, cross_rows(ax, e1))[:, None]]
    table = np.concatenate(rows, axis=1).T.copy()
    if not offsets:
        sign = np.sign(s0)
        table[:10] *= sign
        table[10] = np.where(sign != 0, table[10], np.inf)
    return table


def _test_pairs(table: torch.Tensor, d_cols: torch.Tensor, h: torch.Tensor | None, ray: torch.Tensor,
                face: torch.Tensor, t_min: float, tol: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The Möller–Trumbore test of (ray, face) pairs, no grad, no division in the verdict: (positions (K,)
    int64 of the pairs that pass, their t (K,)). ``d_cols`` (3, R) are the directions by component, ``table``
    from :func:`_face_tables` (with offsets iff ``h`` is given). Per pair: a gather of the face's column and
    the ray's direction, three 3-term dot products (five with offsets), contiguous 1-D arithmetic.
    Element-wise per pair, so a pair's verdict and t do not depend on which other pairs are tested with it."""
    g = table.index_select(1, face)
    d0, d1, d2 = d_cols.index_select(1, ray)
    det = g[0] * d0 + g[1] * d1 + g[2] * d2
    un = g[3] * d0 + g[4] * d1 + g[5] * d2
    vn = g[6] * d0 + g[7] * d1 + g[8] * d2
    tn = g[9]
    if h is not None:  # T = T0 + h a; fold the sign of t*det per pair (the table folds it per face otherwise)
        hr = h.index_select(0, ray)
        un = un + hr * (g[11] * d0 + g[12] * d1 + g[13] * d2)
        vn = vn + hr * (g[14] * d0 + g[15] * d1 + g[16] * d2)
        tn = tn + hr * g[17]
        sign = torch.sign(tn)  # t*det = 0 gives det = 0, which fails the floor test below
        det, un, vn, tn = det * sign, un * sign, vn * sign, tn.abs()
    slack = tol * det
    ok = (det > g[10]) & (un >= -slack) & (vn >= -slack) & (un + vn <= det + slack) & (tn > t_min * det)
    idx = torch.nonzero(ok).reshape(-1)
    return idx, tn.index_select(0, idx) / det.index_select(0, idx)


def hit_pairs_np(table: np.ndarray, d_cols: np.ndarray, h: np.ndarray | None, ray: np.ndarray, face: np.ndarray,
                  t_min: float, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_test_pairs` in numpy (the same element-wise operations in the same order and dtype: IEEE
    arithmetic, so the same verdicts and t bit for bit), for the few hundred to few thousand pairs of a car or a
    crop, whose cost in torch is its per-op overhead."""
    g = table.take(face, axis=1)
    d0, d1, d2 = d_cols.take(ray, axis=1)
    det = g[0] * d0 + g[1] * d1 + g[2] * d2
    un = g[3] * d0 + g[4] * d1 + g[5] * d2
    vn = g[6] * d0 + g[7] * d1 + g[8] * d2
    tn = g[9]
    if h is not None:
        hr = h.take(ray)
        un = un + hr * (g[11] * d0 + g[12] * d1 + g[13] * d2)
        vn = vn + hr * (g[14] * d0 + g[15] * d1 + g[16] * d2)
        tn = tn + hr * g[17]
        sign = np.sign(tn)
        det, un, vn, tn = det * sign, un * sign, vn * sign, np.abs(tn)
    slack = tol * det
    ok = (det > g[10]) & (un >= -slack) & (vn >= -slack) & (un + vn <= det + slack) & (tn > t_min * det)
    idx = ok.nonzero()[0]
    return idx, tn[idx] / det[idx]


#: "No face yet" in :func:`nearest_np`'s per-ray minimum.
_NO_FACE = np.iinfo(np.int64).max


def nearest_np(ray: np.ndarray, face: np.ndarray, t: np.ndarray, n_rays: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_nearest_t` in numpy: (nearest face per ray (n_rays,) or -1, its t or +inf); equal t resolve to the
    smallest face index."""
    best = np.full(n_rays, np.inf, t.dtype)
    np.minimum.at(best, ray, t)
    win = (t == best[ray]).nonzero()[0]
    first = np.full(n_rays, _NO_FACE)
    np.minimum.at(first, ray[win], face[win])
    return np.where(first != _NO_FACE, first, -1), best


def _nearest(ray: torch.Tensor, face: torch.Tensor, t: torch.Tensor, n_rays: int, n_faces: int) -> torch.Tensor:
    """(n_rays,) int64 nearest face per ray among the hitting pairs (ray, face, t), -1 where none; equal t
    resolve to the smallest face index (deterministic whatever the pair order)."""
    return _nearest_t(ray, face, t, n_rays, n_faces)[0]


def _nearest_t(ray: torch.Tensor, face: torch.Tensor, t: torch.Tensor, n_rays: int, n_faces: int
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`_nearest` and the nearest t per ray (+inf where none)."""
    best = torch.full((n_rays,), float("inf"), dtype=t.dtype, device=t.device).scatter_reduce(0, ray, t, "amin")
    win = t == best.index_select(0, ray)
    first = torch.full((n_rays,), n_faces, dtype=torch.int64, device=t.device)
    first = first.scatter_reduce(0, ray[win], face[win], "amin")
    return torch.where(first < n_faces, first, torch.full_like(first, -1)), best


def _one_float_dtype(*arrays: np.ndarray | None) -> bool:
    """Whether the arrays (None skipped) share one float32 or float64 dtype (the compiled kernels' case; numpy's
    promotion of mixed dtypes stays with the numpy code)."""
    dts = {a.dtype for a in arrays if a is not None}
    return len(dts) == 1 and dts.pop() in (np.dtype(np.float32), np.dtype(np.float64))


@dataclass(frozen=True, eq=False)
class FaceRows:
    """Möller–Trumbore's per-face rows of the faces ``faces`` (U, 3) of float ``vertices`` (numpy, their dtype):
    the edges e1 = a1 - a0, e2 = a2 - a0, T0 = origin - a0, q0 = T0 x e1, and ``rows`` (10 or 17, U),
    component-major: the det vector e2 x e1, the u*det vector e2 x T0, the v*det vector q0, t*det = e2 . q0, and
    with an offset ``axis`` (ray origins origin + h axis) the slopes in h: e2 x axis, q1 = axis x e1, e2 . q1."""

    faces: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    t0: np.ndarray
    q0: np.ndarray
    axis: np.ndarray | None
    q1: np.ndarray | None
    rows: np.ndarray

    @classmethod
    def of(cls, vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray, axis: np.ndarray | None = None
           ) -> FaceRows:
        if _one_float_dtype(vertices, origin, axis):  # compiled, the same arithmetic (the numpy code below)
            e1, e2, t0, q0, q1, rows = face_rows(vertices, faces, origin, axis)
            return cls(faces, e1, e2, t0, q0, axis, q1, rows)
        a0 = vertices[faces[:, 0]]
        e1, e2 = vertices[faces[:, 1]] - a0, vertices[faces[:, 2]] - a0
        t0 = origin - a0
        q0 = cross_rows(t0, e1)
        parts = [cross_rows(e2, e1), cross_rows(e2, t0), q0, dot3(e2, q0)[:, None]]
        q1 = None
        if axis is not None:
            ax = np.broadcast_to(axis, e1.shape)
            q1 = cross_rows(ax, e1)
            parts += [cross_rows(e2, ax), q1, dot3(e2, q1)[:, None]]
        return cls(faces, e1, e2, t0, q0, axis, q1, np.concatenate(parts, axis=1).T.copy())

    def tuv(self, slot: np.ndarray, d: np.ndarray, h: np.ndarray | None = None) -> PairTUV:
        """t, u, v of rays (unit directions ``d`` (K, 3), offsets ``h`` (K,) with an axis) against the faces
        ``slot`` (K,) (positions in :attr:`faces`): t*det / det etc., the division guarded by
        ``where(det != 0, det, 1)``."""
        if _one_float_dtype(self.rows, d, h):  # compiled, the same arithmetic (the numpy code below)
            return PairTUV(slot, d, h, *pair_tuv(self.rows, slot, d, h))
        g = self.rows.take(slot, axis=1)
        d0, d1, d2 = d.T
        det = g[0] * d0 + g[1] * d1 + g[2] * d2
        un = g[3] * d0 + g[4] * d1 + g[5] * d2
        vn = g[6] * d0 + g[7] * d1 + g[8] * d2
        tn = g[9]
        if h is not None:
            un = un + h * (g[10] * d0 + g[11] * d1 + g[12] * d2)
            vn = vn + h * (g[13] * d0 + g[14] * d1 + g[15] * d2)
            tn = tn + h * g[16]
        ok = det != 0
        inv = 1.0 / np.where(ok, det, det.dtype.type(1))
        return PairTUV(slot, d, h, ok, inv, tn * inv, un * inv, vn * inv)

    def edge_grads(self, pairs: PairTUV, gt: np.ndarray, gu: np.ndarray, gv: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Gradients (U, 3) float64 w.r.t. e1, e2 and T0 of the loss whose gradients w.r.t. the pairs' t, u, v
        are ``gt``, ``gu``, ``gv`` (K,) (the chain rule through :meth:`tuv` and the rows; for a x b the gradient
        is b x g w.r.t. a and g x a w.r.t. b)."""
        inv = pairs.inv
        gdet = np.where(pairs.ok, -(gt * pairs.t + gu * pairs.u + gv * pairs.v) * inv, 0.0)
        # per face the sums of the columns gdet d, gun d, gvn d, gtn (and, with offsets, those but gdet d times h)
        gm = scatter_pair_grads(pairs.slot, gdet, gu * inv, gv * inv, gt * inv, pairs.d, pairs.h, len(self.faces))
        e1, e2, t0 = self.e1, self.e2, self.t0
        g_det, g_ru = gm[:, 0:3], gm[:, 3:6]
        g_q0 = gm[:, 6:9] + gm[:, 9:10] * e2
        g_e1 = cross_rows(g_det, e2) + cross_rows(g_q0, t0)
        g_e2 = cross_rows(e1, g_det) + cross_rows(t0, g_ru) + gm[:, 9:10] * self.q0
        g_t0 = cross_rows(g_ru, e2) + cross_rows(e1, g_q0)
        if pairs.h is not None:
            ax = np.broadcast_to(self.axis, e1.shape)
            g_q1 = gm[:, 13:16] + gm[:, 16:17] * e2
            g_e1 = g_e1 + cross_rows(g_q1, ax)
            g_e2 = g_e2 + cross_rows(ax, gm[:, 10:13]) + gm[:, 16:17] * self.q1
        return g_e1, g_e2, g_t0

    def vertex_grads(self, g_e1: np.ndarray, g_e2: np.ndarray, g_t0: np.ndarray, n_vertices: int) -> np.ndarray:
        """(V, 3) float64: gradients w.r.t. e1 = a1 - a0, e2 = a2 - a0 and T0 = origin - a0 summed per vertex."""
        rows = np.concatenate([-(g_e1 + g_e2 + g_t0), g_e1, g_e2])
        return scatter_rows(np.concatenate([self.faces[:, 0], self.faces[:, 1], self.faces[:, 2]]), rows, n_vertices)


@dataclass(frozen=True, eq=False)
class PairTUV:
    """:meth:`FaceRows.tuv` of K pairs: their face positions ``slot``, directions ``d``, offsets ``h``, det != 0
    ``ok``, 1 / det (1 where det = 0) ``inv``, and t, u, v (K,)."""

    slot: np.ndarray
    d: np.ndarray
    h: np.ndarray | None
    ok: np.ndarray
    inv: np.ndarray
    t: np.ndarray
    u: np.ndarray
    v: np.ndarray


def face_slots(face: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(used, slot) of int64 indices ``face`` (K,) into range(n): the sorted distinct indices and each index's
    position among them (``np.unique(face, return_inverse=True)`` in O(K + n), without a sort)."""
    present = np.zeros(n, np.int64)
    present[face] = 1
    return present.nonzero()[0], (present.cumsum() - 1)[face]


class _RecomputeTUV(torch.autograd.Function):
    """Differentiable t, u, v (K,) of (ray, face) pairs (:class:`FaceRows`, in numpy in the vertices' dtype);
    backward by hand (:meth:`FaceRows.edge_grads`, checked against finite differences)."""

    @staticmethod
    def forward(ctx: object, vertices: torch.Tensor, faces: np.ndarray, face: np.ndarray, d: np.ndarray,
                origin: np.ndarray, h: np.ndarray | None, axis: np.ndarray | None
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        used, slot = face_slots(face, len(faces))
        fr = FaceRows.of(vertices.detach().numpy(), faces[used], origin, axis)
        pairs = fr.tuv(slot, d, h)
        ctx.fr, ctx.pairs, ctx.n_vertices, ctx.dtype = fr, pairs, len(vertices), vertices.dtype
        return torch.from_numpy(pairs.t), torch.from_numpy(pairs.u), torch.from_numpy(pairs.v)

    @staticmethod
    def backward(ctx: object, gt: torch.Tensor, gu: torch.Tensor, gv: torch.Tensor) -> tuple:
        fr, pairs = ctx.fr, ctx.pairs
        grads = fr.edge_grads(pairs, gt.numpy(), gu.numpy(), gv.numpy())
        gvert = torch.from_numpy(fr.vertex_grads(*grads, ctx.n_vertices)).to(ctx.dtype)
        return gvert, None, None, None, None, None, None


def _recompute(vertices: torch.Tensor, faces_t: torch.Tensor, d: torch.Tensor, origin: torch.Tensor,
               h: torch.Tensor | None, axis: torch.Tensor, ray: torch.Tensor, face: torch.Tensor
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Differentiable t, u, v (P,) of the (ray, face) pairs (which hit): Möller–Trumbore's per-face rows
    (:class:`FaceRows`, :func:`_face_tables`' vectors without the sign fold) of the faces of the pairs, then
    per pair (:class:`_RecomputeTUV`; numpy: a crop's or a car's few hundred pairs cost torch's per-op
    overhead)."""
    return _RecomputeTUV.apply(vertices, faces_t.numpy(), face.numpy(), d.index_select(0, ray).numpy(),
                               origin.numpy(), None if h is None else h.index_select(0, ray).numpy(),
                               None if h is None else axis.numpy())


def _cluster_spheres(v0: torch.Tensor, e1: torch.Tensor, e2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Bounding spheres (centres (C, 3), radii (C,)) of the clusters of :data:`CLUSTER_SIZE` consecutive faces,
    inflated (barycentric tolerance, rounding)."""
    n_faces = len(v0)
    n_cl = (n_faces + CLUSTER_SIZE - 1) // CLUSTER_SIZE
    pad = n_cl * CLUSTER_SIZE - n_faces
    corners = torch.stack([v0, v0 + e1, v0 + e2], 1)  # (F, 3, 3)
    if pad:
        corners = torch.cat([corners, corners[-1:].expand(pad, 3, 3)])
    corners = corners.reshape(n_cl, 3 * CLUSTER_SIZE, 3)
    centre = 0.5 * (corners.amin(1) + corners.amax(1))
    radius = torch.linalg.norm(corners - centre[:, None, :], dim=-1).amax(1)
    return centre, radius * (1 + 1e-3) + 1e-9


def _sphere_pairs(centre: torch.Tensor, radius: torch.Tensor, n_faces: int, dc: torch.Tensor, hc: torch.Tensor,
                  origin: torch.Tensor, axis: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(ray (K,) positions in ``dc``, face (K,)) pairs of the rays (unit ``dc`` (Rc, 3), offsets ``hc`` (Rc,))
    passing through the bounding sphere of the face's cluster (a ray-sphere GEMM)."""
    w0 = centre - origin[None, :]  # centre - ray origin = w0 - h a
    w0a = w0 @ axis
    w0sq = (w0 * w0).sum(-1)
    proj = dc @ w0.T - hc[:, None] * (dc @ axis)[:, None]  # (Rc, C) t of the closest approach
    dist2 = w0sq[None, :] - 2 * hc[:, None] * w0a[None, :] + (hc * hc)[:, None] - proj * proj
    near = (dist2 <= radius[None, :] ** 2) & (proj > -radius[None, :])
    ray_c, cl = torch.nonzero(near, as_tuple=True)
    ray = ray_c.repeat_interleave(CLUSTER_SIZE)
    fc = (cl[:, None] * CLUSTER_SIZE + torch.arange(CLUSTER_SIZE, device=dc.device)[None, :]).reshape(-1)
    if len(centre) * CLUSTER_SIZE > n_faces:
        inside = fc < n_faces
        ray, fc = ray[inside], fc[inside]
    return ray, fc


def _search(v0: torch.Tensor, e1: torch.Tensor, e2: torch.Tensor, table: torch.Tensor, d: torch.Tensor,
            origin: torch.Tensor, h: torch.Tensor | None, axis: torch.Tensor, t_min: float,
            tol: float) -> tuple[torch.Tensor, int]:
    """No-grad nearest face per ray: (face (R,) int64, -1 on a miss; number of ray-triangle tests).

    Faces are grouped in clusters of :data:`CLUSTER_SIZE` consecutive faces; a ray is tested (:func:`_test_pairs`)
    against the faces of the clusters whose bounding sphere it passes through (a ray-sphere GEMM)."""
    n_faces = len(v0)
    centre, radius = _cluster_spheres(v0, e1, e2)
    n_rays = len(d)
    hz = torch.zeros(n_rays, dtype=d.dtype, device=d.device) if h is None else h
    face = torch.full((n_rays,), -1, dtype=torch.int64, device=d.device)
    tests = 0
    step = max(1, SEARCH_CHUNK_PAIRS // max(n_faces, 1))
    for lo in range(0, n_rays, step):
        dc, hc = d[lo:lo + step], hz[lo:lo + step]
        ray, fc = _sphere_pairs(centre, radius, n_faces, dc, hc, origin, axis)
        tests += len(fc)
        if len(fc) == 0:
            continue
        ok, tc = _test_pairs(table, dc.T.contiguous(), None if h is None else hc, ray, fc, t_min, tol)
        if len(tc):
            face[lo:lo + step] = _nearest(ray.index_select(0, ok), fc.index_select(0, ok), tc, len(dc), n_faces)
    return face, tests


def _search_groups(v0: torch.Tensor, e1: torch.Tensor, e2: torch.Tensor, table: torch.Tensor, d: torch.Tensor,
                   origin: torch.Tensor, h: torch.Tensor | None, axis: torch.Tensor, t_min: float, tol: float,
                   groups: Sequence[tuple[torch.Tensor, int, int]]) -> tuple[torch.Tensor, int]:
    """:func:`_search` where each group (rays (K,) int64, first face, end face) tests its rays against its
    faces only (clusters formed within the group); the nearest face per ray is kept over all groups."""
    n_rays, n_faces = len(d), len(v0)
    hz = torch.zeros(n_rays, dtype=d.dtype, device=d.device) if h is None else h
    rays, faces = [], []
    for gr, f0, f1 in groups:
        if len(gr) == 0 or f1 <= f0:
            continue
        centre, radius = _cluster_spheres(v0[f0:f1], e1[f0:f1], e2[f0:f1])
        step = max(1, SEARCH_CHUNK_PAIRS // (f1 - f0))
        for lo in range(0, len(gr), step):
            rc = gr[lo:lo + step]
            ray, fc = _sphere_pairs(centre, radius, f1 - f0, d.index_select(0, rc), hz.index_select(0, rc),
                                    origin, axis)
            rays.append(rc.index_select(0, ray))
            faces.append(fc + f0)
    face = torch.full((n_rays,), -1, dtype=torch.int64, device=d.device)
    if not rays:
        return face, 0
    ray, fc = torch.cat(rays), torch.cat(faces)
    if len(fc):
        ok, tc = _test_pairs(table, d.T.contiguous(), h, ray, fc, t_min, tol)
        if len(tc):
            face = _nearest(ray.index_select(0, ok), fc.index_select(0, ok), tc, n_rays, n_faces)
    return face, len(fc)


def back_faces(vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray) -> np.ndarray | None:
    """(F,) bool mask of the faces that cannot be the nearest hit of any ray from ``origin``, or None when the
    mesh does not qualify for back-face culling (then every face must be tested).

    Rays from outside a closed surface enter it first: the nearest hit is on a face whose outward normal
    n points towards the origin o, (o - V0) . n > 0; faces with (o - V0) . n <= 0 can be culled. Qualifies:
    a mesh that is (1) closed and consistently oriented (every directed edge once, and its reverse once),
    (2) star-shaped about its vertex centroid c, outward-oriented: every face's (V0 - c) . (e1 x e2) > 0
    and the faces' solid angles seen from c sum to 4 pi (one sheet, no folds), so that it bounds a
    region, and (3) seen from outside: o lies outside the vertices' bounding sphere (centre of their box).
    A deformed icosphere stays so unless a vertex is pushed across the centre's line of sight of a neighbour.

    Culling changes no hit except at the rounding level or below the test's thresholds: a ray tangent to the
    surface (within the barycentric tolerance of a silhouette edge), or a front face rejected as grazing
    (|cos| <= cos_min) whose ray then met a back face within the object.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    if len(f) == 0 or not _closed_oriented(f.tobytes(), len(v)):
        return None
    c = v.sum(axis=0) / len(v)  # v.mean(axis=0), without its per-call overhead (the same sum and division)
    o = np.asarray(origin, np.float64).reshape(3)
    # per face a, b, cc relative to c: det[a, b, cc] = a . (e1 x e2) > 0, the solid angles 2 atan2(det, den)
    # (den = |a||b||cc| + (a.b)|cc| + (a.cc)|b| + (b.cc)|a|), and the cull (o - c - a) . (e1 x e2) <= 0 (compiled)
    positive, solid_angle, mask = star_faces(v, f, c, o)
    if not positive or abs(solid_angle - 4.0 * np.pi) > np.pi:  # the sum is 4 pi x the sheet count
        return None
    centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
    r = v - centre
    if np.linalg.norm(o - centre) <= np.sqrt(dot3(r, r).max()) * (1 + 1e-6):
        return None
    return mask


def dot3(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Dot products over a last axis of 3, summed as ((x0 y0 + x1 y1) + x2 y2): the order numpy's
    ``(x * y).sum(-1)`` adds them in (the same bits), without the cost of a reduction along a short axis."""
    return x[..., 0] * y[..., 0] + x[..., 1] * y[..., 1] + x[..., 2] * y[..., 2]


@lru_cache(maxsize=64)
def _closed_oriented(faces: bytes, n_vertices: int) -> bool:
    """Whether the (F, 3) int64 faces (raw bytes) hold every directed edge once and its reverse once."""
    f = np.frombuffer(faces, np.int64).reshape(-1, 3)
    head, tail = f.reshape(-1), np.roll(f, -1, axis=1).reshape(-1)  # directed edges head -> tail
    key = np.sort(head * n_vertices + tail)
    return bool(np.all(key[1:] != key[:-1]) and np.array_equal(key, np.sort(tail * n_vertices + head)))


@dataclass(frozen=True)
class _Prepared:
    """Validated inputs of a cast (see :func:`_prepare`)."""

    vertices: torch.Tensor
    faces: torch.Tensor
    d: torch.Tensor
    origin: torch.Tensor
    h: torch.Tensor | None
    axis: torch.Tensor
    tol: float


def _prepare(vertices: torch.Tensor, faces: torch.Tensor, directions: torch.Tensor, origin: torch.Tensor,
             origin_offset: torch.Tensor | None, offset_axis: Sequence[float], name: str, check: bool = True
             ) -> _Prepared:
    """The cast's inputs as tensors of the vertices' dtype, checked (ValueError naming the field); ``check=False``
    skips the finiteness of the vertices and the range of the face indices (the caller checked them)."""
    if not isinstance(vertices, torch.Tensor):
        vertices = torch.tensor(np.asarray(vertices, dtype=np.float64))
    dtype, dev = vertices.dtype, vertices.device
    if dtype not in _BARY_TOL:
        raise ValueError(f"{name}: field 'vertices': dtype must be float32 or float64, got {dtype}")
    faces_t = _as_tensor(faces, torch.int64, dev).reshape(-1, 3)
    d = _as_tensor(directions, dtype, dev).reshape(-1, 3)
    h = None if origin_offset is None else _as_tensor(origin_offset, dtype, dev).reshape(-1)
    if vertices.dim() != 2 or vertices.shape[1] != 3:
        raise ValueError(f"{name}: field 'vertices': expected shape (V, 3), got {tuple(vertices.shape)}")
    if check and not bool(torch.isfinite(vertices.detach()).all()):
        raise ValueError(f"{name}: field 'vertices': contains NaN or inf")
    if h is not None and len(h) != len(d):
        raise ValueError(f"{name}: field 'origin_offset': {len(h)} offsets for {len(d)} rays")
    if check and len(faces_t) and (int(faces_t.min()) < 0 or int(faces_t.max()) >= len(vertices)):
        raise ValueError(f"{name}: field 'faces': indices must lie in [0, {len(vertices)})")
    return _Prepared(vertices, faces_t, d, _as_tensor(origin, dtype, dev).reshape(3),
                     h, _as_tensor(offset_axis, dtype, dev).reshape(3), _BARY_TOL[dtype])


def _face_geometry(p: _Prepared, cos_min: float, skip: torch.Tensor | None = None, checked: bool = False
                   ) -> tuple[torch.Tensor, ...]:
    """No grad: v0, e1, e2 (F, 3) and the test's per-face table (:func:`_face_tables`) as tensors; faces of the
    mask ``skip`` (F,) never hit. Formed in numpy in the vertices' dtype (:func:`face_test_geometry`; ``checked``:
    the faces are known to index the vertices)."""
    return tuple(torch.from_numpy(x) for x in face_test_geometry(
        p.vertices.detach().numpy(), p.faces.numpy(), p.origin.numpy(), cos_min,
        None if p.h is None else p.axis.numpy(), None if skip is None else skip.numpy(), checked=checked))


def face_test_geometry(vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray, cos_min: float = 1e-3,
                       axis: np.ndarray | None = None, skip: np.ndarray | None = None, *, checked: bool = False
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """v0, e1, e2 (F, 3) and the per-face table of the no-grad test (:func:`_face_tables`; offsets along ``axis``
    if given, else shared origin) of faces (F, 3) int64 into float32 or float64 ``vertices`` (V, 3) (validated
    by the caller), in their dtype; a face that is a sliver (:data:`_SLIVER`) or in the mask ``skip`` (F,) is
    never hit. ``cos_min`` as in :func:`cast_rays`."""
    vd = vertices
    if _one_float_dtype(vd, origin, axis):  # compiled, the same arithmetic (the numpy code below)
        return face_test_table(vd, faces, origin, cos_min, axis, skip,
                               _SLIVER[torch.float32 if vd.dtype == np.float32 else torch.float64], checked=checked)
    v0, v1, v2 = vd[faces[:, 0]], vd[faces[:, 1]], vd[faces[:, 2]]
    e1, e2 = v1 - v0, v2 - v0
    c = cross_rows(e1, e2)
    area2 = np.sqrt(dot3(c, c))
    e3 = v2 - v1
    longest = np.maximum(np.maximum(dot3(e1, e1), dot3(e2, e2)), dot3(e3, e3))
    valid = (area2 > _SLIVER[torch.float32 if vd.dtype == np.float32 else torch.float64] * longest) \
        & np.isfinite(area2)
    if skip is not None:
        valid &= ~skip
    ax = np.zeros(3, vd.dtype) if axis is None else axis
    return v0, e1, e2, _face_tables(v0, e1, e2, valid, origin, ax, cos_min, axis is not None)


def _hits(p: _Prepared, face: torch.Tensor, tests: int) -> RayHits:
    """:class:`RayHits` of the nearest faces ``face`` (R,) (-1 on a miss), recomputed with grad."""
    n_rays = len(face)
    hit = face >= 0
    idx = torch.nonzero(hit).reshape(-1)
    zeros = p.vertices.new_zeros(n_rays) + 0.0 * p.vertices.sum()  # keeps the graph connected on all-miss
    if len(idx) == 0:
        return RayHits(hit, face, zeros, zeros, zeros, tests)
    t, u, v = _recompute(p.vertices, p.faces, p.d, p.origin, p.h, p.axis, idx, face.index_select(0, idx))
    return RayHits(hit, face, zeros.index_put((idx,), t), zeros.index_put((idx,), u), zeros.index_put((idx,), v),
                   tests)


def cast_rays(vertices: torch.Tensor, faces: torch.Tensor, directions: torch.Tensor, origin: torch.Tensor,
              origin_offset: torch.Tensor | None = None, offset_axis: Sequence[float] = (0.0, 0.0, 1.0), *,
              t_min: float = 1e-6, cos_min: float = 1e-3, skip_faces: torch.Tensor | None = None,
              groups: Sequence[tuple[np.ndarray, int, int]] | None = None) -> RayHits:
    """Nearest hit of each ray origin_r + t * d_r, origin_r = origin + origin_offset[r] * offset_axis.

    Args:
        vertices: (V, 3) float tensor (float64 recommended; the computation runs in its dtype), may require grad.
        faces: (F, 3) int vertex indices (tensor or array).
        directions: (R, 3) unit ray directions.
        origin: (3,) common ray origin.
        origin_offset: (R,) offsets along ``offset_axis`` (the HDL-64E lasers' heights h0_k on z), or None.
        offset_axis: (3,) unit axis of the offsets.
        t_min: hits at t <= t_min are ignored.
        cos_min: hits with |cos(incidence)| <= cos_min are ignored (grazing rays).
        skip_faces: (F,) bool, faces never hit (e.g. :func:`back_faces`), or None.
        groups: None (every ray against every face), or (rays (K,) int indices, first face, end face) per
            group (e.g. per mesh: the rays of its cull and its faces): a ray is tested only against the faces
            of its groups (the same hits as casting each group alone and keeping the nearest, equal t: the
            smaller face index; much cheaper than one cast of all rays at all faces).
    Returns:
        :class:`RayHits`; t, u, v carry gradients w.r.t. ``vertices`` (finite everywhere).
    """
    p = _prepare(vertices, faces, directions, origin, origin_offset, offset_axis, "cast_rays")
    n_rays = len(p.d)
    skip = None if skip_faces is None else _as_tensor(skip_faces, torch.bool, p.d.device).reshape(-1)
    if skip is not None and len(skip) != len(p.faces):
        raise ValueError(f"cast_rays: field 'skip_faces': {len(skip)} flags for {len(p.faces)} faces")
    checked = None if groups is None else _check_groups(groups, n_rays, len(p.faces), p.d.device)
    with torch.no_grad():
        if n_rays and len(p.faces):
            v0, e1, e2, table = _face_geometry(p, cos_min, skip)
            if checked is None:
                face, tests = _search(v0, e1, e2, table, p.d, p.origin, p.h, p.axis, t_min, p.tol)
            else:
                face, tests = _search_groups(v0, e1, e2, table, p.d, p.origin, p.h, p.axis, t_min, p.tol, checked)
        else:
            face, tests = torch.full((n_rays,), -1, dtype=torch.int64, device=p.d.device), 0
    return _hits(p, face, tests)


def _check_groups(groups: Sequence[tuple[np.ndarray, int, int]], n_rays: int, n_faces: int,
                  device: torch.device) -> list[tuple[torch.Tensor, int, int]]:
    out = []
    for i, (rays, f0, f1) in enumerate(groups):
        r = _as_tensor(rays, torch.int64, device).reshape(-1)
        if not 0 <= int(f0) <= int(f1) <= n_faces or (len(r) and (int(r.min()) < 0 or int(r.max()) >= n_rays)):
            raise ValueError(f"cast_rays: field 'groups[{i}]': rays must index {n_rays} rays and "
                             f"faces [{f0}, {f1}) lie in [0, {n_faces}]")
        out.append((r, int(f0), int(f1)))
    return out


def cast_ray_pairs(vertices: torch.Tensor, faces: torch.Tensor, directions: torch.Tensor, origin: torch.Tensor,
                   ray_index: torch.Tensor, face_index: torch.Tensor, origin_offset: torch.Tensor | None = None,
                   offset_axis: Sequence[float] = (0.0, 0.0, 1.0), *, t_min: float = 1e-6,
                   cos_min: float = 1e-3) -> RayHits:
    """Like :func:`cast_rays`, but each ray is tested only against the faces the caller pairs it with.

    The caller's cull (e.g. the camera's per-face screen boxes) builds the candidate pairs
    (ray_index[k], face_index[k]); they are tested with the same kernel as :func:`cast_rays` under no_grad,
    the nearest hit per ray is kept (equal t: the smallest face index), and t, u, v are recomputed with
    gradients on the winning pairs only. The result equals :func:`cast_rays`' wherever the pairs include
    every face a ray can hit. Arguments as :func:`cast_rays`, plus ray_index, face_index (P,) int64;
    ``RayHits.tests`` = P. :func:`cast_ray_pair_chunks` takes the pairs in chunks (bounded memory).
    """
    return cast_ray_pair_chunks(vertices, faces, directions, origin, [(ray_index, face_index)], origin_offset,
                                offset_axis, t_min=t_min, cos_min=cos_min, name="cast_ray_pairs")


def cast_ray_pair_chunks(vertices: torch.Tensor, faces: torch.Tensor, directions: torch.Tensor, origin: torch.Tensor,
                         chunks: Iterable[tuple[torch.Tensor, torch.Tensor]],
                         origin_offset: torch.Tensor | None = None, offset_axis: Sequence[float] = (0.0, 0.0, 1.0),
                         *, t_min: float = 1e-6, cos_min: float = 1e-3, name: str = "cast_ray_pair_chunks") -> RayHits:
    """:func:`cast_ray_pairs` of the concatenated (ray_index, face_index) ``chunks`` (e.g. a generator), tested
    one chunk at a time: the same hits as one call with all pairs (the test is element-wise and the nearest
    hit is taken over all chunks), with temporaries bounded by the largest chunk."""
    p = _prepare(vertices, faces, directions, origin, origin_offset, offset_axis, name)
    with torch.no_grad():
        table = _face_geometry(p, cos_min)[3] if len(p.faces) else None
    face, _, tests = _pair_search(p, table, chunks, t_min, name)
    return _hits(p, face, tests)


#: A caller's no-grad search of :func:`cast_ray_search`: (per-face ``table`` of :func:`_face_tables` or None
#: without faces, directions by component ``d_cols`` (3, R), offsets ``h`` (R,) or None, ``t_min``, ``tol``) ->
#: (nearest face per ray (R,) int64 or -1, its t (R,) or +inf, pairs tested).
PairSearch = Callable[[np.ndarray | None, np.ndarray, np.ndarray | None, float, float],
                      tuple[np.ndarray, np.ndarray, int]]


def cast_ray_search(vertices: torch.Tensor, faces: torch.Tensor, directions: torch.Tensor, origin: torch.Tensor,
                    search: PairSearch, origin_offset: torch.Tensor | None = None,
                    offset_axis: Sequence[float] = (0.0, 0.0, 1.0), *, t_min: float = 1e-6, cos_min: float = 1e-3,
                    name: str = "cast_ray_search", checked: bool = False) -> RayHits:
    """:func:`cast_ray_pairs` whose no-grad search is the caller's ``search`` (:data:`PairSearch`), run on the
    validated cast's per-face table and rays: for a cull that tests its candidate pairs as it finds them (e.g.
    :func:`robustbench3d.sensors.kernels.sphere_pairs_nearest`) with :func:`search_pairs`' arithmetic and choice
    (the nearest t, equal t the smallest face index). t, u, v are recomputed with gradients on the winners.
    ``checked=True``: the caller has checked that the vertices are finite and the faces index them (e.g. a
    renderer that checked its meshes on entry): those checks are not made again."""
    p = _prepare(vertices, faces, directions, origin, origin_offset, offset_axis, name, check=not checked)
    with torch.no_grad():
        table = _face_geometry(p, cos_min, checked=checked)[3].numpy() if len(p.faces) else None
    face, _, tests = search(table, p.d.numpy().T.copy(), None if p.h is None else p.h.numpy(), t_min, p.tol)
    if face.shape != (len(p.d),):
        raise ValueError(f"{name}: field 'search': {face.shape} faces for {len(p.d)} rays")
    return _hits(p, torch.from_numpy(face), int(tests))


@dataclass(frozen=True, eq=False)
class PairTable:
    """What :meth:`PairCaster.search`'s kernel runs on, in numpy: the per-face ``table`` of the no-grad test from
    a shared origin (:func:`_face_tables`, (11, F) in the vertices' dtype; None without faces), ``t_min`` and the
    barycentric tolerance ``tol`` of that dtype. For a renderer that validated its mesh and searches with the
    numpy or compiled kernels (no tensors, no gradients)."""

    table: np.ndarray | None
    t_min: float
    tol: float

    @classmethod
    def of(cls, vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray, *, t_min: float = 1e-6,
           cos_min: float = 1e-3, name: str = "PairTable") -> PairTable:
        """The table of faces (F, 3) int64 into float32 or float64 ``vertices`` (V, 3), rays from ``origin`` (3,)
        (taken in the vertices' dtype, as :class:`PairCaster` takes it); ``t_min``, ``cos_min`` as there."""
        dtype = {np.dtype(np.float32): torch.float32, np.dtype(np.float64): torch.float64}.get(vertices.dtype)
        if dtype is None:
            raise ValueError(f"{name}: field 'vertices': dtype must be float32 or float64, got {vertices.dtype}")
        o = np.asarray(origin).astype(vertices.dtype).reshape(3)
        table = face_test_geometry(vertices, faces, o, cos_min)[3] if len(faces) else None
        return cls(table, t_min, _BARY_TOL[dtype])


class PairCaster:
    """Casts of candidate (ray, face) pairs from one shared origin against one triangle mesh, with the
    per-face test table (:func:`_face_tables`) built once for every cast: :meth:`search` (no grad, the
    kernel of :func:`cast_ray_pairs`) finds the nearest face of each ray, :meth:`recompute` gives t, u, v with
    gradients w.r.t. the vertices for (direction, face) pairs, e.g. the winners of several searches at once.

    Args: as :func:`cast_rays` (``vertices`` may require grad); ``name`` prefixes error messages.
    """

    def __init__(self, vertices: torch.Tensor, faces: torch.Tensor, origin: torch.Tensor, *, t_min: float = 1e-6,
                 cos_min: float = 1e-3, name: str = "PairCaster") -> None:
        self.name, self.t_min = name, t_min
        self._p = _prepare(vertices, faces, np.zeros((0, 3)), origin, None, (0.0, 0.0, 1.0), name)
        with torch.no_grad():
            self._table = _face_geometry(self._p, cos_min)[3] if len(self._p.faces) else None

    @property
    def dtype(self) -> torch.dtype:
        return self._p.vertices.dtype

    @property
    def table(self) -> torch.Tensor | None:
        """The per-face test table of :meth:`search` (:func:`_face_tables`, shared origin: (11, F), no grad;
        None without faces); not to be modified."""
        return self._table

    @property
    def tol(self) -> float:
        """The barycentric tolerance of the test in this dtype (:data:`_BARY_TOL`)."""
        return self._p.tol

    def search(self, directions: torch.Tensor, chunks: Iterable[tuple[torch.Tensor, torch.Tensor]], *,
               check: bool = True) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, int]:
        """No grad: (rays (K,) ascending, their nearest faces (K,), the test's t (K,), pairs tested) of the rays
        (unit directions (R, 3)) that hit a face of their candidate pairs (``chunks`` of (ray_index, face_index)
        as :func:`cast_ray_pair_chunks`; equal t: the smallest face index). ``check=False`` skips the range
        check of the pairs (for a caller whose cull builds them in range)."""
        d = _as_tensor(directions, self.dtype, self._p.vertices.device).reshape(-1, 3)
        face, best, tests = _pair_search(replace(self._p, d=d), self._table, chunks, self.t_min, self.name, check)
        ray = torch.nonzero(face >= 0).reshape(-1)
        return ray, face.index_select(0, ray), best.index_select(0, ray), tests

    def recompute(self, directions: torch.Tensor, face: torch.Tensor
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """t, u, v (K,) of rays (unit directions (K, 3)) against the faces ``face`` (K,) they hit (a
        :meth:`search`'s winners), differentiable w.r.t. the vertices (0 with a connected graph if K = 0)."""
        p = self._p
        if len(face) == 0:
            zero = p.vertices.new_zeros(0) + 0.0 * p.vertices.sum()
            return zero, zero, zero
        d = _as_tensor(directions, self.dtype, p.vertices.device).reshape(-1, 3)
        return _recompute(p.vertices, p.faces, d, p.origin, None, p.axis, torch.arange(len(face)), face)


#: Chunks of :func:`_pair_search` after which the hits so far are reduced to each ray's nearest.
_COMPACT_EVERY = 512


def _compact(rays: list[np.ndarray], faces: list[np.ndarray], ts: list[np.ndarray], n_rays: int
             ) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """The hits of several chunks reduced to each hit ray's nearest (face, t) (:func:`nearest_np`: the nearest t,
    equal t the smallest face), so that the final reduction over all chunks gives the same winners."""
    ray, face, t = np.concatenate(rays), np.concatenate(faces), np.concatenate(ts)
    if len(t) == 0:
        return [ray], [face], [t]
    nearest, best = nearest_np(ray, face, t, n_rays)
    keep = (nearest >= 0).nonzero()[0]
    return [keep], [nearest[keep]], [best[keep]]


def _as_index(x: torch.Tensor | np.ndarray) -> np.ndarray:
    return np.asarray(x.numpy() if isinstance(x, torch.Tensor) else x, np.int64).reshape(-1)


def _checked_pairs(chunks: Iterable[tuple[torch.Tensor | np.ndarray, torch.Tensor | np.ndarray]], n_rays: int,
                   n_faces: int, name: str, check: bool) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """The (ray, face) int64 index arrays of each chunk, refused (ValueError naming the field) when their lengths
    differ or, with ``check``, when a pair does not index ``n_rays`` rays and ``n_faces`` faces."""
    for ray_index, face_index in chunks:
        ray, fc = _as_index(ray_index), _as_index(face_index)
        if len(ray) != len(fc):
            raise ValueError(f"{name}: field 'face_index': {len(fc)} faces for {len(ray)} rays")
        if check and len(ray) and (int(ray.min()) < 0 or int(ray.max()) >= n_rays or int(fc.min()) < 0
                                   or int(fc.max()) >= n_faces):
            raise ValueError(f"{name}: field 'ray_index': pairs must index {n_rays} rays and {n_faces} faces")
        yield ray, fc


def search_pairs_np(table: np.ndarray | None, d_cols: np.ndarray, h: np.ndarray | None,
                    chunks: Iterable[tuple[torch.Tensor | np.ndarray, torch.Tensor | np.ndarray]], t_min: float,
                    tol: float, name: str = "search_pairs_np", check: bool = True
                    ) -> tuple[np.ndarray, np.ndarray, int]:
    """The no-grad search of candidate (ray, face) pairs in numpy: (nearest face per ray (R,) or -1, its t (R,) or
    +inf, pairs tested) of rays with directions by component ``d_cols`` (3, R) (offsets ``h`` (R,) or None) against
    the per-face ``table`` (:func:`_face_tables`; None without faces), each pair tested by :func:`hit_pairs_np`,
    equal t resolved to the smallest face. ``check=False`` skips the range check of the pairs."""
    n_rays, n_faces = d_cols.shape[1], 0 if table is None else table.shape[1]
    rays, faces_hit, ts = [], [], []
    tests = 0
    for ray, fc in _checked_pairs(chunks, n_rays, n_faces, name, check):
        tests += len(ray)
        if len(ray) == 0:
            continue
        ok, t = hit_pairs_np(table, d_cols, h, ray, fc, t_min, tol)
        rays.append(ray[ok])
        faces_hit.append(fc[ok])
        ts.append(t)
        if len(ts) >= _COMPACT_EVERY:  # many chunks (e.g. a full-scene cast): keep each ray's nearest so far
            rays, faces_hit, ts = _compact(rays, faces_hit, ts, n_rays)
    face = np.full(n_rays, -1, np.int64)
    best = np.full(n_rays, np.inf, d_cols.dtype)
    if ts and sum(len(t) for t in ts):
        face, best = nearest_np(np.concatenate(rays), np.concatenate(faces_hit), np.concatenate(ts), n_rays)
    return face, best, tests


def search_pairs(table: np.ndarray | None, d_cols: np.ndarray, h: np.ndarray | None,
                 chunks: Iterable[tuple[torch.Tensor | np.ndarray, torch.Tensor | np.ndarray]], t_min: float,
                 tol: float, name: str = "search_pairs", check: bool = True) -> tuple[np.ndarray, np.ndarray, int]:
    """:func:`search_pairs_np` (same arguments and result, the same bits) with each chunk tested and reduced to
    each ray's nearest hit by the compiled kernel :func:`robustbench3d.sensors.kernels.nearest_of_pairs`."""
    n_rays, n_faces = d_cols.shape[1], 0 if table is None else table.shape[1]
    face = np.full(n_rays, -1, np.int64)
    best = np.full(n_rays, np.inf, d_cols.dtype)
    tests = 0
    for ray, fc in _checked_pairs(chunks, n_rays, n_faces, name, check or table is None):
        tests += len(ray)
        if len(ray):
            nearest_of_pairs(table, d_cols, h, ray, fc, t_min, tol, face, best)
    return face, best, tests


def _pair_search(p: _Prepared, table: torch.Tensor | None, chunks: Iterable[tuple[torch.Tensor, torch.Tensor]],
                 t_min: float, name: str, check: bool = True) -> tuple[torch.Tensor, torch.Tensor, int]:
    """:func:`search_pairs` of the prepared cast's rays, as tensors."""
    face, best, tests = search_pairs(None if table is None else table.numpy(), p.d.numpy().T.copy(),
                                     None if p.h is None else p.h.numpy(), chunks, t_min, p.tol, name, check)
    return torch.from_numpy(face), torch.from_numpy(best), tests
