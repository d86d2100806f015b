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
   the nearest face per ray is kept. Optional back-face culling
   (:func:`~robustbench3d.sensors.ray_faces.back_faces`, ``skip_faces``).
2. Recompute, with grad, on the (ray, nearest face) pairs only; divisions by ``where(ok, det, 1)``. In numpy
   (:class:`~robustbench3d.sensors.ray_rows.FaceRows`: per-face rows of the faces hit, then per pair; compiled
   for one float dtype by :mod:`robustbench3d.sensors.ray_kernels`, the same arithmetic) with a hand-written
   backward: a car's or a crop's few hundred to few thousand pairs would otherwise cost torch's per-op overhead.

The modules: :mod:`~robustbench3d.sensors.ray_faces` (the per-face table of the test, back faces),
:mod:`~robustbench3d.sensors.cluster_search` (step 1 in torch, for :func:`cast_rays`),
:mod:`~robustbench3d.sensors.pair_search` (step 1 on a caller's candidate pairs, compiled, with its numpy
reference), :mod:`~robustbench3d.sensors.ray_rows` (step 2) and this one, the entry points.

Three entry points share the per-face table (:func:`~robustbench3d.sensors.ray_faces.face_test_geometry`) and the
recompute (:func:`~robustbench3d.sensors.ray_rows.recompute_tuv`): :func:`cast_rays` builds the candidate pairs
itself (bounding spheres, above) and tests them in torch (large dense casts), and :func:`cast_ray_pairs` (and
:class:`PairCaster`) takes candidate (ray, face) pairs from the caller's own cull (the LiDAR's per-face
bounding spheres, the camera's per-face screen boxes) and tests them with a compiled twin of the same kernel
(:func:`~robustbench3d.sensors.pair_search.search_pairs`: a car's few thousand pairs cost torch's per-op
overhead; the same element-wise IEEE operations in the same order and dtype, so the same verdicts and t bit for
bit). Both test a pair element-wise, so its verdict and t do not depend on the other pairs, and keep the nearest
hit per ray (equal t: the smallest face index). :func:`cast_ray_search` lets a caller whose cull finds the
candidate pairs in a compiled loop test them there with the same arithmetic (the LiDAR render's
:func:`robustbench3d.sensors.lidar_kernels.sphere_pairs_nearest`) and recomputes the winners as the others do.

Rejected: faces of (near) zero area, rays within ``arccos(cos_min)`` of grazing (relative cut
|cos(incidence)| > cos_min, which also bounds the gradients at about 1/cos_min), hits at t <= t_min.
Barycentric tolerance 1e-6 (float64) / 1e-5 (float32) so rays through edges and vertices never leak.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, replace

import numpy as np
import torch

from robustbench3d.sensors.cluster_search import search_cluster_groups, search_clusters
from robustbench3d.sensors.pair_search import search_pairs
from robustbench3d.sensors.ray_faces import BARY_TOL, face_test_geometry
from robustbench3d.sensors.ray_rows import recompute_tuv

__all__ = ["PairCaster", "PairSearch", "RayHits", "cast_ray_pair_chunks", "cast_ray_pairs", "cast_ray_search",
           "cast_rays"]


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
    if dtype not in BARY_TOL:
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
                     h, _as_tensor(offset_axis, dtype, dev).reshape(3), BARY_TOL[dtype])


def _face_geometry(p: _Prepared, cos_min: float, skip: torch.Tensor | None = None, checked: bool = False
                   ) -> tuple[torch.Tensor, ...]:
    """No grad: v0, e1, e2 (F, 3) and the test's per-face table (:func:`~robustbench3d.sensors.ray_faces._face_tables`)
    as tensors; faces of the mask ``skip`` (F,) never hit. Formed in numpy in the vertices' dtype
    (:func:`face_test_geometry`; ``checked``: the faces are known to index the vertices)."""
    return tuple(torch.from_numpy(x) for x in face_test_geometry(
        p.vertices.detach().numpy(), p.faces.numpy(), p.origin.numpy(), cos_min,
        None if p.h is None else p.axis.numpy(), None if skip is None else skip.numpy(), checked=checked))


def _hits(p: _Prepared, face: torch.Tensor, tests: int) -> RayHits:
    """:class:`RayHits` of the nearest faces ``face`` (R,) (-1 on a miss), recomputed with grad."""
    n_rays = len(face)
    hit = face >= 0
    idx = torch.nonzero(hit).reshape(-1)
    zeros = p.vertices.new_zeros(n_rays) + 0.0 * p.vertices.sum()  # keeps the graph connected on all-miss
    if len(idx) == 0:
        return RayHits(hit, face, zeros, zeros, zeros, tests)
    t, u, v = recompute_tuv(p.vertices, p.faces, p.d, p.origin, p.h, p.axis, idx, face.index_select(0, idx))
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
        skip_faces: (F,) bool, faces never hit (e.g. :func:`~robustbench3d.sensors.ray_faces.back_faces`), or None.
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
                face, tests = search_clusters(v0, e1, e2, table, p.d, p.origin, p.h, p.axis, t_min, p.tol)
            else:
                face, tests = search_cluster_groups(v0, e1, e2, table, p.d, p.origin, p.h, p.axis, t_min, p.tol,
                                                    checked)
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


#: A caller's no-grad search of :func:`cast_ray_search`: (per-face ``table`` of
#: :func:`~robustbench3d.sensors.ray_faces._face_tables` or None without faces, directions by component ``d_cols`` (3,
#: R), offsets ``h`` (R,) or None, ``t_min``, ``tol``) -> (nearest face per ray (R,) int64 or -1, its t (R,) or +inf,
#: pairs tested).
PairSearch = Callable[[np.ndarray | None, np.ndarray, np.ndarray | None, float, float],
                      tuple[np.ndarray, np.ndarray, int]]


def cast_ray_search(vertices: torch.Tensor, faces: torch.Tensor, directions: torch.Tensor, origin: torch.Tensor,
                    search: PairSearch, origin_offset: torch.Tensor | None = None,
                    offset_axis: Sequence[float] = (0.0, 0.0, 1.0), *, t_min: float = 1e-6, cos_min: float = 1e-3,
                    name: str = "cast_ray_search", checked: bool = False) -> RayHits:
    """:func:`cast_ray_pairs` whose no-grad search is the caller's ``search`` (:data:`PairSearch`), run on the
    validated cast's per-face table and rays: for a cull that tests its candidate pairs as it finds them (e.g.
    :func:`robustbench3d.sensors.lidar_kernels.sphere_pairs_nearest`) with :func:`search_pairs`' arithmetic and choice
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


class PairCaster:
    """Casts of candidate (ray, face) pairs from one shared origin against one triangle mesh, with the per-face test
    table (:func:`~robustbench3d.sensors.ray_faces._face_tables`) built once for every cast: :meth:`search` (no grad,
    the kernel of :func:`cast_ray_pairs`) finds the nearest face of each ray, :meth:`recompute` gives t, u, v with
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
        """The per-face test table of :meth:`search` (:func:`~robustbench3d.sensors.ray_faces._face_tables`, shared
        origin: (11, F), no grad; None without faces); not to be modified."""
        return self._table

    @property
    def tol(self) -> float:
        """The barycentric tolerance of the test in this dtype (:data:`BARY_TOL`)."""
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
        return recompute_tuv(p.vertices, p.faces, d, p.origin, None, p.axis, torch.arange(len(face)), face)


def _pair_search(p: _Prepared, table: torch.Tensor | None, chunks: Iterable[tuple[torch.Tensor, torch.Tensor]],
                 t_min: float, name: str, check: bool = True) -> tuple[torch.Tensor, torch.Tensor, int]:
    """:func:`search_pairs` of the prepared cast's rays, as tensors."""
    face, best, tests = search_pairs(None if table is None else table.numpy(), p.d.numpy().T.copy(),
                                     None if p.h is None else p.h.numpy(), chunks, t_min, p.tol, name, check)
    return torch.from_numpy(face), torch.from_numpy(best), tests
