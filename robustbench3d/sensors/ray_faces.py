"""Per-face geometry of the ray/triangle test (Möller–Trumbore) in numpy: the no-grad test's per-face table and
back-face culling (module docstring of :mod:`robustbench3d.sensors.raycast`).

:func:`face_test_geometry` forms the table with the compiled
:func:`robustbench3d.sensors.ray_kernels.face_test_table` for one float dtype; its numpy form (:func:`_face_tables`,
also the path of mixed dtypes) is beside it, the reference the tests compare it with. :func:`back_faces` tests a
mesh for culling with :func:`~robustbench3d.sensors.ray_kernels.star_faces`. :data:`BARY_TOL` is the test's
barycentric tolerance per dtype.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import torch

from robustbench3d.sensors.array_kernels import column_stats
from robustbench3d.sensors.mesh import cross_rows, dot3
from robustbench3d.sensors.ray_kernels import face_test_table, star_faces

#: Faces whose |e1 x e2| is at or below this fraction of their longest squared edge are treated as degenerate.
_SLIVER = {torch.float64: 1e-10, torch.float32: 1e-5}
#: Barycentric tolerance: rays tangent to an edge or through a vertex still hit one of its faces.
BARY_TOL = {torch.float64: 1e-6, torch.float32: 1e-5}


def one_float_dtype(*arrays: np.ndarray | None) -> bool:
    """Whether the arrays (None skipped) share one float32 or float64 dtype (the compiled kernels' case; numpy's
    promotion of mixed dtypes stays with the numpy code)."""
    dts = {a.dtype for a in arrays if a is not None}
    return len(dts) == 1 and dts.pop() in (np.dtype(np.float32), np.dtype(np.float64))


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


def face_test_geometry(vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray, cos_min: float = 1e-3,
                       axis: np.ndarray | None = None, skip: np.ndarray | None = None, *, checked: bool = False
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """v0, e1, e2 (F, 3) and the per-face table of the no-grad test (:func:`_face_tables`; offsets along ``axis``
    if given, else shared origin) of faces (F, 3) int64 into float32 or float64 ``vertices`` (V, 3) (validated
    by the caller), in their dtype; a face that is a sliver (:data:`_SLIVER`) or in the mask ``skip`` (F,) is
    never hit. ``cos_min`` as in :func:`~robustbench3d.sensors.raycast.cast_rays`."""
    vd = vertices
    if one_float_dtype(vd, origin, axis):  # compiled, the same arithmetic (the numpy code below)
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


def back_faces(vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray) -> np.ndarray | None:
    """(F,) bool mask of the faces (F, 3) of finite ``vertices`` (V, 3) that cannot be the nearest hit of any ray from
    ``origin``, or None when the mesh does not qualify for back-face culling (then every face must be tested).

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
    lo, hi, total = column_stats(v)  # numpy's v.min / max / sum(axis=0), in one compiled pass
    c = total / len(v)  # v.mean(axis=0), without its per-call overhead (the same sum and division)
    o = np.asarray(origin, np.float64).reshape(3)
    # per face a, b, cc relative to c: det[a, b, cc] = a . (e1 x e2) > 0, the solid angles 2 atan2(det, den)
    # (den = |a||b||cc| + (a.b)|cc| + (a.cc)|b| + (b.cc)|a|), and the cull (o - c - a) . (e1 x e2) <= 0 (compiled)
    positive, solid_angle, mask = star_faces(v, f, c, o)
    if not positive or abs(solid_angle - 4.0 * np.pi) > np.pi:  # the sum is 4 pi x the sheet count
        return None
    centre = 0.5 * (lo + hi)
    r = v - centre
    if np.linalg.norm(o - centre) <= np.sqrt(dot3(r, r).max()) * (1 + 1e-6):
        return None
    return mask


@lru_cache(maxsize=64)
def _closed_oriented(faces: bytes, n_vertices: int) -> bool:
    """Whether the (F, 3) int64 faces (raw bytes) hold every directed edge once and its reverse once."""
    f = np.frombuffer(faces, np.int64).reshape(-1, 3)
    head, tail = f.reshape(-1), np.roll(f, -1, axis=1).reshape(-1)  # directed edges head -> tail
    key = np.sort(head * n_vertices + tail)
    return bool(np.all(key[1:] != key[:-1]) and np.array_equal(key, np.sort(tail * n_vertices + head)))
