"""The no-grad search of candidate (ray, face) pairs that a caller's cull builds (the LiDAR's per-face bounding
spheres, the camera's per-face screen boxes): the nearest hit per ray, equal t to the smallest face index.

:func:`search_pairs` tests each chunk of pairs with the compiled
:func:`robustbench3d.sensors.ray_kernels.nearest_of_pairs`; its numpy reference :func:`search_pairs_np`
(:func:`hit_pairs_np`, then :func:`nearest_np`; also the camera's full-image reference render) is beside it: the
same element-wise IEEE operations in the same order and dtype, so the same verdicts and t bit for bit.
:class:`PairTable` is the per-face table both run on (:func:`robustbench3d.sensors.ray_faces.face_test_geometry`).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np
import torch

from robustbench3d.sensors.ray_faces import BARY_TOL, face_test_geometry
from robustbench3d.sensors.ray_kernels import nearest_of_pairs


@dataclass(frozen=True, eq=False)
class PairTable:
    """What :meth:`robustbench3d.sensors.raycast.PairCaster.search`'s kernel runs on, in numpy: the per-face ``table``
    of the no-grad test from a shared origin (:func:`~robustbench3d.sensors.ray_faces._face_tables`, (11, F) in the
    vertices' dtype; None without faces), ``t_min`` and the barycentric tolerance ``tol`` of that dtype. For a renderer
    that validated its mesh and searches with the numpy or compiled kernels (no tensors, no gradients)."""

    table: np.ndarray | None
    t_min: float
    tol: float

    @classmethod
    def of(cls, vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray, *, t_min: float = 1e-6,
           cos_min: float = 1e-3, name: str = "PairTable") -> PairTable:
        """The table of faces (F, 3) int64 into float32 or float64 ``vertices`` (V, 3), rays from ``origin`` (3,) (taken
        in the vertices' dtype, as :class:`~robustbench3d.sensors.raycast.PairCaster` takes it); ``t_min``, ``cos_min``
        as there."""
        dtype = {np.dtype(np.float32): torch.float32, np.dtype(np.float64): torch.float64}.get(vertices.dtype)
        if dtype is None:
            raise ValueError(f"{name}: field 'vertices': dtype must be float32 or float64, got {vertices.dtype}")
        o = np.asarray(origin).astype(vertices.dtype).reshape(3)
        table = face_test_geometry(vertices, faces, o, cos_min)[3] if len(faces) else None
        return cls(table, t_min, BARY_TOL[dtype])


def hit_pairs_np(table: np.ndarray, d_cols: np.ndarray, h: np.ndarray | None, ray: np.ndarray, face: np.ndarray,
                  t_min: float, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`robustbench3d.sensors.cluster_search._test_pairs` in numpy (the same element-wise operations in the same
    order and dtype: IEEE arithmetic, so the same verdicts and t bit for bit), for the few hundred to few thousand pairs
    of a car or a crop, whose cost in torch is its per-op overhead."""
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
    """:func:`robustbench3d.sensors.cluster_search._nearest_t` in numpy: (nearest face per ray (n_rays,) or -1, its t or
    +inf); equal t resolve to the smallest face index."""
    best = np.full(n_rays, np.inf, t.dtype)
    np.minimum.at(best, ray, t)
    win = (t == best[ray]).nonzero()[0]
    first = np.full(n_rays, _NO_FACE)
    np.minimum.at(first, ray[win], face[win])
    return np.where(first != _NO_FACE, first, -1), best


#: Chunks of :func:`search_pairs_np` after which the hits so far are reduced to each ray's nearest.
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
    +inf, pairs tested) of rays with directions by component ``d_cols`` (3, R) (offsets ``h`` (R,) or None) against the
    per-face ``table`` (:func:`~robustbench3d.sensors.ray_faces._face_tables`; None without faces), each pair tested by
    :func:`hit_pairs_np`, equal t resolved to the smallest face. ``check=False`` skips the range check of the pairs."""
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
    each ray's nearest hit by the compiled kernel :func:`robustbench3d.sensors.ray_kernels.nearest_of_pairs`."""
    n_rays, n_faces = d_cols.shape[1], 0 if table is None else table.shape[1]
    face = np.full(n_rays, -1, np.int64)
    best = np.full(n_rays, np.inf, d_cols.dtype)
    tests = 0
    for ray, fc in _checked_pairs(chunks, n_rays, n_faces, name, check or table is None):
        tests += len(ray)
        if len(ray):
            nearest_of_pairs(table, d_cols, h, ray, fc, t_min, tol, face, best)
    return face, best, tests
