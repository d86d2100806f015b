"""The no-grad search of :func:`robustbench3d.sensors.raycast.cast_rays` in torch (module docstring of
:mod:`robustbench3d.sensors.raycast`, step 1): rays against the bounding spheres of clusters of consecutive faces
(a ray-sphere GEMM), then against the faces of the clusters they pass through (:func:`_test_pairs`, the kernel
whose numpy twin is :func:`robustbench3d.sensors.pair_search.hit_pairs_np`), keeping the nearest face per ray.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

#: Rays x faces per chunk of the no-grad search (bounds its memory to about 150 MB even if every pair is tested).
SEARCH_CHUNK_PAIRS = 1 << 20
#: Consecutive faces sharing one bounding sphere in the search (icosphere level L: face k of level L - 1 becomes
#: faces 4k..4k+3; other meshes work whatever their face order, only faster when it is coherent).
CLUSTER_SIZE = 4


def _test_pairs(table: torch.Tensor, d_cols: torch.Tensor, h: torch.Tensor | None, ray: torch.Tensor,
                face: torch.Tensor, t_min: float, tol: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The Möller–Trumbore test of (ray, face) pairs, no grad, no division in the verdict: (positions (K,) int64 of the
    pairs that pass, their t (K,)). ``d_cols`` (3, R) are the directions by component, ``table`` from
    :func:`~robustbench3d.sensors.ray_faces._face_tables` (with offsets iff ``h`` is given). Per pair: a gather of the
    face's column and the ray's direction, three 3-term dot products (five with offsets), contiguous 1-D arithmetic.
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


def search_clusters(v0: torch.Tensor, e1: torch.Tensor, e2: torch.Tensor, table: torch.Tensor, d: torch.Tensor,
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


def search_cluster_groups(v0: torch.Tensor, e1: torch.Tensor, e2: torch.Tensor, table: torch.Tensor, d: torch.Tensor,
                          origin: torch.Tensor, h: torch.Tensor | None, axis: torch.Tensor, t_min: float, tol: float,
                          groups: Sequence[tuple[torch.Tensor, int, int]]) -> tuple[torch.Tensor, int]:
    """:func:`search_clusters` where each group (rays (K,) int64, first face, end face) tests its rays against its
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
