"""Compiled (numba) kernels of the renderers' hot loops, each with the arithmetic of the numpy code it replaced.

A render of one car tests a few thousand (ray, face) pairs and shades a few thousand hits; in numpy each step
costs tens of operations on small arrays, which was most of a render's time. Each kernel here does exactly the
arithmetic of the numpy code it replaces, in the same order and dtype (numba compiles without fast-math: no
operation is reassociated or contracted; constants are cast to the arrays' dtype as numpy casts Python floats;
exp, power and matrix products stay numpy's), so the results are the same bits; ``tests/test_sensors_kernels.py``
and the camera tests compare each with its numpy reference. Compiled code does not check bounds: the Python
wrappers check the indices they pass (pairs, owners, slots, faces). Kernels compile on first use and are cached
(``cache=True``: the package's ``__pycache__``, or numba's user cache directory).

Camera (:mod:`robustbench3d.sensors.camera_render`):

* :func:`nearest_in_region` walks each face's sample box and scanline spans (``_FaceCull.boxes`` / ``spans``
  and ``_candidate_pairs``, the numpy reference) and tests every sample there with the Möller–Trumbore test of
  :func:`robustbench3d.sensors.raycast.hit_pairs_np` (shared origin), keeping the choice of
  :func:`~robustbench3d.sensors.raycast.nearest_np` (the nearest t, equal t to the smallest face index), without
  materialising the pairs.
* :func:`face_cull` is the per-face part of ``_FaceCull.of`` (the numpy reference is ``_face_cull_reference`` of
  ``tests/test_sensors_camera_render.py``); :func:`touching_faces` is ``_FaceCull.touching``.
* :func:`shade_exposure`, :func:`shade_tone` and :func:`shade_grads` are the per-hit arithmetic of the fused
  shading ``_ShadeHits`` (forward and backward).

LiDAR (:mod:`robustbench3d.sensors.lidar_beams`, :mod:`robustbench3d.sensors.lidar_render`): :func:`cone_cull` is
``BeamPattern.cull_many``, :func:`sphere_ray_ranges` the per-(sphere, laser) part of ``BeamPattern.sphere_rays`` and
:func:`nearest_rays` ``BeamPattern.nearest_ray`` (``compiled=False`` runs their numpy code); :func:`beam_table`
forms a pattern's ray azimuths as ``HDL64E.ray_azimuths`` does. :func:`sphere_pairs_nearest` is the render's cast:
the pairs of ``sphere_ray_ranges`` within each mesh's cull (:func:`cull_runs`), tested by
:func:`nearest_of_pairs`' arithmetic as they are found (the pairs formed in numpy, ``lidar_render._face_pairs``, are
its reference); :func:`rows_but` copies the scan rows the objects leave.

Shared (:mod:`robustbench3d.sensors.raycast`, :mod:`robustbench3d.sensors.mesh`):

* :func:`nearest_of_pairs` tests explicit (ray, face) pairs (shared origin or per-ray offsets along an axis) and
  keeps each ray's nearest hit: :func:`~robustbench3d.sensors.raycast.search_pairs_np`'s arithmetic.
* :func:`face_test_table` is ``face_test_geometry`` (edges, sliver test and the per-face table of the no-grad
  test); :func:`face_rows` and :func:`pair_tuv` are ``FaceRows``' rows and t, u, v; :func:`scatter_pair_grads`
  is ``FaceRows.edge_grads``' per-pair products summed by face; :func:`star_faces` is the per-face part of
  ``back_faces``.
* :func:`scatter_rows` sums rows by an index in float64, in order (``np.bincount``'s arithmetic);
  :func:`scatter_add` in the values' dtype, in order (``np.add.at``'s); :func:`cross_rows_float` is
  ``mesh.cross_rows`` of float32 / float64 rows.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numba import njit

if TYPE_CHECKING:
    from robustbench3d.sensors.camera_render import _FaceCull as FaceCullArrays


@njit(cache=True, nogil=True, inline="always")
def _keep_if_nearer(det: float, un: float, vn: float, tn: float, floor: float, t_min: float, tol: float, r: int,
                    f: int, best_face: np.ndarray, best_t: np.ndarray) -> None:  # pragma: no cover - compiled
    """The verdict of :func:`robustbench3d.sensors.raycast.hit_pairs_np` on one pair (det, u*det, v*det, t*det with
    t*det's sign folded in, the face's grazing floor), and the choice of
    :func:`~robustbench3d.sensors.raycast.nearest_np`: ray r keeps face f if it is hit nearer, or as near by a
    smaller face index."""
    slack = tol * det
    if det > floor and un >= -slack and vn >= -slack and un + vn <= det + slack and tn > t_min * det:
        t = tn / det
        if t < best_t[r] or (t == best_t[r] and f < best_face[r]):
            best_t[r] = t
            best_face[r] = f


@njit(cache=True, nogil=True)
def _walk_faces(lo: np.ndarray, hi: np.ndarray, crossing: np.ndarray, skip: np.ndarray, tight: np.ndarray,
                edge: np.ndarray, lim: np.ndarray, s: int, pos: np.ndarray, mw: int, table: np.ndarray,
                d_cols: np.ndarray, t_min: float, tol: float, best_face: np.ndarray, best_t: np.ndarray
                ) -> int:  # pragma: no cover - compiled (run by the tests through nearest_in_region)
    row0, col0 = int(lim[1]), int(lim[0])
    s2 = s * s
    tests = 0
    for f in range(len(skip)):
        if skip[f]:
            continue
        # the face's sample box (_FaceCull.boxes)
        if crossing[f]:
            b0, b1, b2, b3 = lim[0], lim[1], lim[2], lim[3]
        else:
            b0 = min(max(np.ceil((lo[f, 0] + 0.5) * s - 0.5), lim[0]), lim[2])
            b1 = min(max(np.ceil((lo[f, 1] + 0.5) * s - 0.5), lim[1]), lim[3])
            b2 = min(max(np.floor((hi[f, 0] + 0.5) * s - 0.5) + 1, lim[0]), lim[2])
            b3 = min(max(np.floor((hi[f, 1] + 0.5) * s - 0.5) + 1, lim[1]), lim[3])
        c0, r0, c1, r1 = int(b0), int(b1), int(b2), int(b3)
        if c1 <= c0 or r1 <= r0:
            continue
        g0, g1, g2 = table[0, f], table[1, f], table[2, f]
        g3, g4, g5 = table[3, f], table[4, f], table[5, f]
        g6, g7, g8 = table[6, f], table[7, f], table[8, f]
        tn, floor = table[9, f], table[10, f]
        for row in range(r0, r1):
            a, b = c0, c1
            if tight[f]:  # the scanline span of this row (_FaceCull.spans)
                y = (row + 0.5) / s - 0.5
                x_lo, x_hi = -np.inf, np.inf
                for k in range(3):
                    af = edge[f, k, 0]
                    rhs = -(edge[f, k, 1] * y + edge[f, k, 2])
                    if af > 0:
                        x_lo = max(x_lo, rhs / af)
                    elif af < 0:
                        x_hi = min(x_hi, rhs / af)
                    elif rhs > 0:
                        x_lo = np.inf
                        break
                a = int(min(max(np.ceil((x_lo + 0.5) * s - 0.5), c0), c1))
                b = int(min(max(np.floor((x_hi + 0.5) * s - 0.5) + 1, c0), c1))
            lr = row - row0
            pv = lr // s
            sub_row = (lr - pv * s) * s
            row_base = pv * mw
            for c in range(a, b):
                col = c - col0
                pu = col // s
                at = pos[row_base + pu]
                if at < 0:
                    continue
                r = at * s2 + sub_row + (col - pu * s)
                tests += 1
                d0, d1, d2 = d_cols[0, r], d_cols[1, r], d_cols[2, r]
                det = g0 * d0 + g1 * d1 + g2 * d2
                un = g3 * d0 + g4 * d1 + g5 * d2
                vn = g6 * d0 + g7 * d1 + g8 * d2
                _keep_if_nearer(det, un, vn, tn, floor, t_min, tol, r, f, best_face, best_t)
    return tests


def nearest_in_region(cull: FaceCullArrays, faces: np.ndarray | None, table: np.ndarray | None, d_cols: np.ndarray,
                      mask: np.ndarray, rect: tuple[int, int, int, int], s: int, t_min: float, tol: float
                      ) -> tuple[np.ndarray, np.ndarray, int]:
    """The nearest face of each sample of a region among the faces whose scanline span holds it: (face (N,) int64
    or -1, t (N,) or +inf, pairs tested).

    Args:
        cull: the per-face cull (``lo``, ``hi``, ``crossing``, ``unreachable``, ``edge``, ``tight`` of
            :class:`robustbench3d.sensors.camera_render._FaceCull`).
        faces: (F,) bool: only these faces (None: all).
        table: (11, F) per-face test table, shared origin (:func:`robustbench3d.sensors.raycast._face_tables`),
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
    tests = _walk_faces(cull.lo, cull.hi, cull.crossing, skip, cull.tight, cull.edge,
                        np.array(rect, np.float64) * s, s, pos, mask.shape[1], table, d_cols, scalar(t_min),
                        scalar(tol), best_face, best_t)
    return best_face, best_t, int(tests)


@njit(cache=True, nogil=True)
def _scatter_rows(index: np.ndarray, rows: np.ndarray, n: int) -> np.ndarray:  # pragma: no cover - compiled
    out = np.zeros((n, rows.shape[1]))
    for k in range(len(index)):
        i = index[k]
        for c in range(rows.shape[1]):
            out[i, c] += rows[k, c]
    return out


@njit(cache=True, nogil=True)
def _scatter_add(index: np.ndarray, values: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover - compiled
    for k in range(len(index)):
        i = index[k]
        for c in range(values.shape[0]):
            out[c, i] += values[c, k]


def _checked_faces(faces: np.ndarray, n_vertices: int, name: str) -> np.ndarray:
    """(F, 3) int64 contiguous ``faces``, every index in [0, n_vertices) (the kernels read vertices by them)."""
    faces = np.ascontiguousarray(faces, np.int64)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"{name}: field 'faces': expected (F, 3), got {faces.shape}")
    if faces.size and (int(faces.min()) < 0 or int(faces.max()) >= n_vertices):
        raise ValueError(f"{name}: field 'faces': indices must lie in [0, {n_vertices})")
    return faces


def _checked_index(index: np.ndarray, k: int, n: int, name: str) -> np.ndarray:
    index = np.ascontiguousarray(index, np.int64)
    if index.ndim != 1 or len(index) != k:
        raise ValueError(f"{name}: field 'index': expected ({k},), got {index.shape}")
    if k and (int(index.min()) < 0 or int(index.max()) >= n):
        raise ValueError(f"{name}: field 'index': entries must lie in [0, {n})")
    return index


def scatter_rows(index: np.ndarray, rows: np.ndarray, n: int) -> np.ndarray:
    """(n, C) float64 sums of the rows (K, C) by ``index`` (K,) in [0, n): each entry converted to float64 and
    added in order, as ``np.bincount(index, weights=rows[:, c], minlength=n)`` for each column c."""
    rows = np.ascontiguousarray(rows)
    return _scatter_rows(_checked_index(index, len(rows), n, "scatter_rows"), rows, n)


def scatter_add(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """(C, n) sums of the columns of ``values`` (C, K) by ``index`` (K,) in [0, n), in the values' dtype, added
    in order: ``np.add.at(out.T, index, values.T)`` on zeros."""
    values = np.ascontiguousarray(values)
    out = np.zeros((values.shape[0], n), values.dtype)
    _scatter_add(_checked_index(index, values.shape[1], n, "scatter_add"), values, out)
    return out


@njit(cache=True, nogil=True)
def _cross_rows(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover - compiled
    for i in range(a.shape[0]):
        out[i, 0] = a[i, 1] * b[i, 2] - a[i, 2] * b[i, 1]
        out[i, 1] = a[i, 2] * b[i, 0] - a[i, 0] * b[i, 2]
        out[i, 2] = a[i, 0] * b[i, 1] - a[i, 1] * b[i, 0]


def cross_rows_float(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise a x b of two (N, 3) float32 or float64 arrays (any strides: copied contiguous), in numpy's result
    dtype (a float32 operand of a float64 product is widened first, as numpy does): the components of np.cross,
    the same bits (the caller checks the shapes and dtypes)."""
    out = np.empty(a.shape, np.result_type(a.dtype, b.dtype))
    _cross_rows(np.ascontiguousarray(a), np.ascontiguousarray(b), out)  # one compiled layout per dtype pair
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def _face_cull(p: np.ndarray, fd: np.ndarray, v3: np.ndarray, skip: np.ndarray, centre: np.ndarray, near: float,
               box_margin: float, span_margin: float, eps64: float, depth_ratio: float
               ) -> tuple:  # pragma: no cover - compiled
    n = p.shape[0]
    lo, hi = np.empty((n, 2)), np.empty((n, 2))
    crossing, unreachable, tight = np.zeros(n, np.bool_), np.zeros(n, np.bool_), np.zeros(n, np.bool_)
    edge_fn = np.zeros((n, 3, 3))
    edge = np.empty((3, 2))
    e3 = np.empty((3, 3))
    for f in range(n):
        d0, d1, d2 = fd[f, 0], fd[f, 1], fd[f, 2]
        unreachable[f] = ((d0 <= 0) and (d1 <= 0) and (d2 <= 0)) or skip[f]
        crossing[f] = ((d0 <= near) or (d1 <= near) or (d2 <= near)) and not unreachable[f]
        ahead = not (crossing[f] or unreachable[f])
        for a in range(2):
            if ahead:
                x0, x1, x2 = p[f, 0, a], p[f, 1, a], p[f, 2, a]
                lo[f, a] = np.minimum(np.minimum(x0, x1), x2)
                hi[f, a] = np.maximum(np.maximum(x0, x1), x2)
            else:
                lo[f, a] = hi[f, a] = 0.0
        margin = box_margin + 1e-5 * np.maximum(hi[f, 0] - lo[f, 0], hi[f, 1] - lo[f, 1])
        for a in range(2):
            lo[f, a] -= margin
            hi[f, a] += margin
        if not ahead:
            continue
        for k in range(3):  # edge k runs from vertex (k + 1) % 3 to (k + 2) % 3
            i, j = (k + 1) % 3, (k + 2) % 3
            edge[k, 0], edge[k, 1] = p[f, j, 0] - p[f, i, 0], p[f, j, 1] - p[f, i, 1]
            for c in range(3):
                e3[k, c] = v3[f, j, c] - v3[f, i, c]
        area2 = edge[1, 0] * edge[2, 1] - edge[1, 1] * edge[2, 0]
        # n3 = e3[2] x (-e3[1])
        b0, b1, b2 = -e3[1, 0], -e3[1, 1], -e3[1, 2]
        n0 = e3[2, 1] * b2 - e3[2, 2] * b1
        n1 = e3[2, 2] * b0 - e3[2, 0] * b2
        n2 = e3[2, 0] * b1 - e3[2, 1] * b0
        r0 = (v3[f, 0, 0] + v3[f, 1, 0] + v3[f, 2, 0]) / 3 - centre[0]
        r1 = (v3[f, 0, 1] + v3[f, 1, 1] + v3[f, 2, 1]) / 3 - centre[1]
        r2 = (v3[f, 0, 2] + v3[f, 1, 2] + v3[f, 2, 2]) / 3 - centre[2]
        ray2 = r0 * r0 + r1 * r1 + r2 * r2
        cos = np.abs(n0 * r0 + n1 * r1 + n2 * r2) / np.sqrt((n0 * n0 + n1 * n1 + n2 * n2) * ray2)
        sq0 = e3[0, 0] * e3[0, 0] + e3[0, 1] * e3[0, 1] + e3[0, 2] * e3[0, 2]
        sq1 = e3[1, 0] * e3[1, 0] + e3[1, 1] * e3[1, 1] + e3[1, 2] * e3[1, 2]
        sq2 = e3[2, 0] * e3[2, 0] + e3[2, 1] * e3[2, 1] + e3[2, 2] * e3[2, 2]
        cond = np.sqrt(ray2 / np.minimum(np.minimum(sq0, sq1), sq2)) / cos
        delta = span_margin + eps64 * cond
        l0 = edge[0, 0] * edge[0, 0] + edge[0, 1] * edge[0, 1]
        l1 = edge[1, 0] * edge[1, 0] + edge[1, 1] * edge[1, 1]
        l2 = edge[2, 0] * edge[2, 0] + edge[2, 1] * edge[2, 1]
        ok = ((np.maximum(np.maximum(d0, d1), d2) <= depth_ratio * np.minimum(np.minimum(d0, d1), d2))
              and (np.abs(area2) > 1e-6 * np.maximum(np.maximum(l0, l1), l2)) and np.isfinite(delta))
        sign = np.sign(area2)
        widen = (delta if ok else 0.0) * np.abs(area2)
        for k in range(3):
            i = (k + 1) % 3
            edge_fn[f, k, 0] = -edge[k, 1] * sign
            edge_fn[f, k, 1] = edge[k, 0] * sign
            edge_fn[f, k, 2] = (edge[k, 1] * p[f, i, 0] - edge[k, 0] * p[f, i, 1]) * sign + widen
        tight[f] = ok
    return lo, hi, crossing, unreachable, edge_fn, tight


def face_cull(p: np.ndarray, fd: np.ndarray, v3: np.ndarray, skip: np.ndarray, centre: np.ndarray, *, near: float,
              box_margin: float, span_margin: float, eps64: float, depth_ratio: float) -> tuple[np.ndarray, ...]:
    """Per face: (lo, hi, crossing, unreachable, edge, tight) of
    :class:`robustbench3d.sensors.camera_render._FaceCull` (its docstring) from the faces' projected vertices
    ``p`` (F, 3, 2) (pixels), camera depths ``fd`` (F, 3) and rect vertices ``v3`` (F, 3, 3) (all float64), the
    mask ``skip`` (F,) of faces never hit and the camera centre (3,); the constants as named there
    (``eps64``: 64 machine epsilons of the ray test's dtype)."""
    return _face_cull(np.ascontiguousarray(p), np.ascontiguousarray(fd), np.ascontiguousarray(v3),
                      np.ascontiguousarray(skip, np.bool_), np.ascontiguousarray(centre, np.float64), near, box_margin,
                      span_margin, eps64, depth_ratio)


@njit(cache=True, nogil=True, error_model="numpy")
def _star_faces(v: np.ndarray, f: np.ndarray, c: np.ndarray, o: np.ndarray
                ) -> tuple:  # pragma: no cover - compiled
    n = f.shape[0]
    mask = np.empty(n, np.bool_)
    positive = True
    angle = 0.0
    for i in range(n):
        p0, p1, p2 = f[i, 0], f[i, 1], f[i, 2]
        a0, a1, a2 = v[p0, 0] - c[0], v[p0, 1] - c[1], v[p0, 2] - c[2]
        b0, b1, b2 = v[p1, 0] - c[0], v[p1, 1] - c[1], v[p1, 2] - c[2]
        c0, c1, c2 = v[p2, 0] - c[0], v[p2, 1] - c[1], v[p2, 2] - c[2]
        x0, x1, x2 = b0 - a0, b1 - a1, b2 - a2  # e1
        y0, y1, y2 = c0 - a0, c1 - a1, c2 - a2  # e2
        n0, n1, n2 = x1 * y2 - x2 * y1, x2 * y0 - x0 * y2, x0 * y1 - x1 * y0
        triple = a0 * n0 + a1 * n1 + a2 * n2
        if not triple > 0:
            positive = False
        la = np.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
        lb = np.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
        lc = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
        den = (la * lb * lc + (a0 * b0 + a1 * b1 + a2 * b2) * lc + (a0 * c0 + a1 * c1 + a2 * c2) * lb
               + (b0 * c0 + b1 * c1 + b2 * c2) * la)
        angle += np.arctan2(triple, den)
        q0, q1, q2 = o[0] - c[0] - a0, o[1] - c[1] - a1, o[2] - c[2] - a2
        mask[i] = q0 * n0 + q1 * n1 + q2 * n2 <= 0
    return positive, 2.0 * angle, mask


def star_faces(vertices: np.ndarray, faces: np.ndarray, centroid: np.ndarray, origin: np.ndarray
               ) -> tuple[bool, float, np.ndarray]:
    """Per face (a, b, c) of float64 ``vertices`` (V, 3) relative to ``centroid`` (3,): (every triple product
    a . (b - a) x (c - a) > 0, the faces' solid angles seen from the centroid summed, the mask of faces with
    (origin - centroid - a) . ((b - a) x (c - a)) <= 0) (the arithmetic of
    :func:`robustbench3d.sensors.raycast.back_faces`: the mask bit for bit, the sum up to its order)."""
    positive, angle, mask = _star_faces(np.ascontiguousarray(vertices, np.float64),
                                        _checked_faces(faces, len(vertices), "star_faces"),
                                        np.ascontiguousarray(centroid, np.float64),
                                        np.ascontiguousarray(origin, np.float64))
    return bool(positive), float(angle), mask


@njit(cache=True, nogil=True)
def _scatter_pair_grads(slot: np.ndarray, gdet: np.ndarray, gun: np.ndarray, gvn: np.ndarray, gtn: np.ndarray,
                        d: np.ndarray, h: np.ndarray, offsets: bool, n: int) -> np.ndarray:  # pragma: no cover
    out = np.zeros((n, 17 if offsets else 10))
    for k in range(len(slot)):
        i = slot[k]
        d0, d1, d2 = d[k, 0], d[k, 1], d[k, 2]
        cols = (gdet[k] * d0, gdet[k] * d1, gdet[k] * d2, gun[k] * d0, gun[k] * d1, gun[k] * d2,
                gvn[k] * d0, gvn[k] * d1, gvn[k] * d2, gtn[k])
        for c in range(10):
            out[i, c] += cols[c]
        if offsets:
            for c in range(7):
                out[i, 10 + c] += cols[3 + c] * h[k]
    return out


def scatter_pair_grads(slot: np.ndarray, gdet: np.ndarray, gun: np.ndarray, gvn: np.ndarray, gtn: np.ndarray,
                       d: np.ndarray, h: np.ndarray | None, n: int) -> np.ndarray:
    """(n, 10) float64, or (n, 17) with offsets ``h`` (K,): per face the sums over its pairs (``slot`` (K,) in
    [0, n)) of gdet d, gun d, gvn d (d (K, 3)), gtn and, with offsets, of those but gdet d times h; each product
    in the arrays' dtype, summed in float64 in pair order (what ``scatter_rows`` of the stacked columns gives)."""
    slot = _checked_index(slot, len(gdet), n, "scatter_pair_grads")
    hh = np.zeros(0, gdet.dtype) if h is None else np.ascontiguousarray(h)
    return _scatter_pair_grads(slot, np.ascontiguousarray(gdet), np.ascontiguousarray(gun), np.ascontiguousarray(gvn),
                               np.ascontiguousarray(gtn), np.ascontiguousarray(d), hh, h is not None, n)


@njit(cache=True, nogil=True)
def _nearest_of_pairs(table: np.ndarray, d_cols: np.ndarray, h: np.ndarray, offsets: bool, ray: np.ndarray,
                      face: np.ndarray, t_min: float, tol: float, best_face: np.ndarray,
                      best_t: np.ndarray) -> int:  # pragma: no cover - compiled
    n_rays, n_faces = d_cols.shape[1], table.shape[1]
    for k in range(len(ray)):
        r, f = ray[k], face[k]
        if r < 0 or r >= n_rays or f < 0 or f >= n_faces:  # never read outside the arrays
            return k
        d0, d1, d2 = d_cols[0, r], d_cols[1, r], d_cols[2, r]
        det = table[0, f] * d0 + table[1, f] * d1 + table[2, f] * d2
        un = table[3, f] * d0 + table[4, f] * d1 + table[5, f] * d2
        vn = table[6, f] * d0 + table[7, f] * d1 + table[8, f] * d2
        tn = table[9, f]
        if offsets:
            hr = h[r]
            un = un + hr * (table[11, f] * d0 + table[12, f] * d1 + table[13, f] * d2)
            vn = vn + hr * (table[14, f] * d0 + table[15, f] * d1 + table[16, f] * d2)
            tn = tn + hr * table[17, f]
            sign = np.sign(tn)
            det, un, vn, tn = det * sign, un * sign, vn * sign, np.abs(tn)
        _keep_if_nearer(det, un, vn, tn, table[10, f], t_min, tol, r, f, best_face, best_t)
    return -1


def nearest_of_pairs(table: np.ndarray, d_cols: np.ndarray, h: np.ndarray | None, ray: np.ndarray,
                     face: np.ndarray, t_min: float, tol: float, best_face: np.ndarray, best_t: np.ndarray) -> None:
    """Test the pairs (``ray`` (K,), ``face`` (K,) int64) of rays with directions by
    component ``d_cols`` (3, R) (offsets ``h`` (R,) with an offset table, or None) against the per-face ``table``
    (:func:`robustbench3d.sensors.raycast._face_tables`, the same dtype) and update each ray's nearest hit in
    ``best_face`` (R,) int64 (-1: none) and ``best_t`` (R,) (+inf: none) in place: the smaller t wins, equal t
    the smaller face index (so the result does not depend on how the pairs are split or ordered). A pair out of
    range raises IndexError (the pairs before it are applied)."""
    scalar = d_cols.dtype.type  # the test's constants in the geometry dtype, as numpy takes Python floats
    hh = np.zeros(0, d_cols.dtype) if h is None else np.ascontiguousarray(h)
    if h is not None and len(hh) != d_cols.shape[1]:
        raise ValueError(f"nearest_of_pairs: field 'h': {len(hh)} offsets for {d_cols.shape[1]} rays")
    ray, face = np.ascontiguousarray(ray, np.int64), np.ascontiguousarray(face, np.int64)
    bad = _nearest_of_pairs(np.ascontiguousarray(table), np.ascontiguousarray(d_cols), hh, h is not None, ray, face,
                            scalar(t_min), scalar(tol), best_face, best_t)
    if bad >= 0:
        raise IndexError(f"nearest_of_pairs: pair {bad} (ray {ray[bad]}, face {face[bad]}) outside "
                         f"{d_cols.shape[1]} rays and {table.shape[1]} faces")


@njit(cache=True, nogil=True)
def _face_rows(v: np.ndarray, f: np.ndarray, origin: np.ndarray, axis: np.ndarray, offsets: bool
               ) -> tuple:  # pragma: no cover - compiled
    n = f.shape[0]
    e1, e2, t0, q0 = np.empty((n, 3), v.dtype), np.empty((n, 3), v.dtype), np.empty((n, 3), v.dtype), \
        np.empty((n, 3), v.dtype)
    q1 = np.empty((n if offsets else 0, 3), v.dtype)
    rows = np.empty((17 if offsets else 10, n), v.dtype)
    for i in range(n):
        for c in range(3):
            a = v[f[i, 0], c]
            e1[i, c] = v[f[i, 1], c] - a
            e2[i, c] = v[f[i, 2], c] - a
            t0[i, c] = origin[c] - a
        x0, x1, x2 = e1[i, 0], e1[i, 1], e1[i, 2]
        y0, y1, y2 = e2[i, 0], e2[i, 1], e2[i, 2]
        z0, z1, z2 = t0[i, 0], t0[i, 1], t0[i, 2]
        q0[i, 0], q0[i, 1], q0[i, 2] = z1 * x2 - z2 * x1, z2 * x0 - z0 * x2, z0 * x1 - z1 * x0  # T0 x e1
        rows[0, i], rows[1, i], rows[2, i] = y1 * x2 - y2 * x1, y2 * x0 - y0 * x2, y0 * x1 - y1 * x0  # e2 x e1
        rows[3, i], rows[4, i], rows[5, i] = y1 * z2 - y2 * z1, y2 * z0 - y0 * z2, y0 * z1 - y1 * z0  # e2 x T0
        rows[6, i], rows[7, i], rows[8, i] = q0[i, 0], q0[i, 1], q0[i, 2]
        rows[9, i] = y0 * q0[i, 0] + y1 * q0[i, 1] + y2 * q0[i, 2]
        if offsets:
            w0, w1, w2 = axis[0], axis[1], axis[2]
            q1[i, 0], q1[i, 1], q1[i, 2] = w1 * x2 - w2 * x1, w2 * x0 - w0 * x2, w0 * x1 - w1 * x0  # axis x e1
            rows[10, i], rows[11, i], rows[12, i] = y1 * w2 - y2 * w1, y2 * w0 - y0 * w2, y0 * w1 - y1 * w0
            rows[13, i], rows[14, i], rows[15, i] = q1[i, 0], q1[i, 1], q1[i, 2]
            rows[16, i] = y0 * q1[i, 0] + y1 * q1[i, 1] + y2 * q1[i, 2]
    return e1, e2, t0, q0, q1, rows


def face_rows(vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray, axis: np.ndarray | None
              ) -> tuple[np.ndarray, ...]:
    """(e1, e2, T0, q0, q1 or None, rows) of :meth:`robustbench3d.sensors.raycast.FaceRows.of` for float32 or
    float64 ``vertices`` (V, 3), ``origin`` (3,) and ``axis`` (3,) or None all of one dtype, faces (U, 3) int64 in
    range (the caller checks)."""
    offsets = axis is not None
    ax = np.zeros(3, vertices.dtype) if axis is None else np.ascontiguousarray(axis)
    e1, e2, t0, q0, q1, rows = _face_rows(vertices, _checked_faces(faces, len(vertices), "face_rows"),
                                          np.ascontiguousarray(origin), ax, offsets)
    return e1, e2, t0, q0, q1 if offsets else None, rows


@njit(cache=True, nogil=True)
def _pair_tuv(rows: np.ndarray, slot: np.ndarray, d: np.ndarray, h: np.ndarray, offsets: bool, one: float
              ) -> tuple:  # pragma: no cover - compiled
    k = len(slot)
    ok = np.empty(k, np.bool_)
    inv, t, u, v = np.empty(k, d.dtype), np.empty(k, d.dtype), np.empty(k, d.dtype), np.empty(k, d.dtype)
    for i in range(k):
        s = slot[i]
        d0, d1, d2 = d[i, 0], d[i, 1], d[i, 2]
        det = rows[0, s] * d0 + rows[1, s] * d1 + rows[2, s] * d2
        un = rows[3, s] * d0 + rows[4, s] * d1 + rows[5, s] * d2
        vn = rows[6, s] * d0 + rows[7, s] * d1 + rows[8, s] * d2
        tn = rows[9, s]
        if offsets:
            un = un + h[i] * (rows[10, s] * d0 + rows[11, s] * d1 + rows[12, s] * d2)
            vn = vn + h[i] * (rows[13, s] * d0 + rows[14, s] * d1 + rows[15, s] * d2)
            tn = tn + h[i] * rows[16, s]
        ok[i] = det != 0
        r = one / (det if ok[i] else one)
        inv[i], t[i], u[i], v[i] = r, tn * r, un * r, vn * r
    return ok, inv, t, u, v


def pair_tuv(rows: np.ndarray, slot: np.ndarray, d: np.ndarray, h: np.ndarray | None
             ) -> tuple[np.ndarray, ...]:
    """(ok, inv, t, u, v) (K,) of :meth:`robustbench3d.sensors.raycast.FaceRows.tuv` for ``rows`` (10 or 17, U),
    directions ``d`` (K, 3) and offsets ``h`` (K,) or None all of one float dtype; ``slot`` (K,) int64 in [0, U)
    (checked)."""
    slot = _checked_index(slot, len(d), rows.shape[1], "pair_tuv")
    offsets = h is not None
    hh = np.zeros(0, d.dtype) if h is None else np.ascontiguousarray(h)
    return _pair_tuv(np.ascontiguousarray(rows), slot, np.ascontiguousarray(d), hh, offsets, d.dtype.type(1))


@njit(cache=True, nogil=True)
def _face_test_table(vd: np.ndarray, f: np.ndarray, origin: np.ndarray, axis: np.ndarray, offsets: bool,
                     skip: np.ndarray, sliver: float, cos_min: float) -> tuple:  # pragma: no cover - compiled
    n = f.shape[0]
    dt = vd.dtype
    v0, e1, e2 = np.empty((n, 3), dt), np.empty((n, 3), dt), np.empty((n, 3), dt)
    table = np.empty((18 if offsets else 11, n), dt)
    for i in range(n):
        for c in range(3):
            a = vd[f[i, 0], c]
            v0[i, c] = a
            e1[i, c] = vd[f[i, 1], c] - a
            e2[i, c] = vd[f[i, 2], c] - a
        x0, x1, x2 = e1[i, 0], e1[i, 1], e1[i, 2]
        y0, y1, y2 = e2[i, 0], e2[i, 1], e2[i, 2]
        # sliver test: |e1 x e2| > sliver * longest squared edge, finite
        c0, c1, c2 = x1 * y2 - x2 * y1, x2 * y0 - x0 * y2, x0 * y1 - x1 * y0
        area2 = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
        w0, w1, w2 = vd[f[i, 2], 0] - vd[f[i, 1], 0], vd[f[i, 2], 1] - vd[f[i, 1], 1], vd[f[i, 2], 2] - vd[f[i, 1], 2]
        longest = np.maximum(np.maximum(x0 * x0 + x1 * x1 + x2 * x2, y0 * y0 + y1 * y1 + y2 * y2),
                             w0 * w0 + w1 * w1 + w2 * w2)
        valid = (area2 > sliver * longest) and np.isfinite(area2) and not skip[i]
        z0, z1, z2 = origin[0] - v0[i, 0], origin[1] - v0[i, 1], origin[2] - v0[i, 2]  # T0
        n0, n1, n2 = y1 * x2 - y2 * x1, y2 * x0 - y0 * x2, y0 * x1 - y1 * x0  # e2 x e1
        q0, q1, q2 = z1 * x2 - z2 * x1, z2 * x0 - z0 * x2, z0 * x1 - z1 * x0  # T0 x e1
        s0 = y0 * q0 + y1 * q1 + y2 * q2
        floor = cos_min * np.sqrt(n0 * n0 + n1 * n1 + n2 * n2) if valid else np.inf
        col = (n0, n1, n2, y1 * z2 - y2 * z1, y2 * z0 - y0 * z2, y0 * z1 - y1 * z0, q0, q1, q2, s0)
        if offsets:
            for k in range(10):
                table[k, i] = col[k]
            table[10, i] = floor
            a0, a1, a2 = axis[0], axis[1], axis[2]
            table[11, i], table[12, i], table[13, i] = y1 * a2 - y2 * a1, y2 * a0 - y0 * a2, y0 * a1 - y1 * a0
            p0, p1, p2 = a1 * x2 - a2 * x1, a2 * x0 - a0 * x2, a0 * x1 - a1 * x0  # axis x e1
            table[14, i], table[15, i], table[16, i] = p0, p1, p2
            table[17, i] = y0 * p0 + y1 * p1 + y2 * p2
        else:  # rows 0..9 times sign(t*det) (exact); a face whose plane holds the origin is never hit
            sign = np.sign(s0)
            for k in range(10):
                table[k, i] = col[k] * sign
            table[10, i] = floor if sign != 0 else np.inf
    return v0, e1, e2, table


def face_test_table(vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray, cos_min: float,
                    axis: np.ndarray | None, skip: np.ndarray | None, sliver: float, *, checked: bool = False
                    ) -> tuple[np.ndarray, ...]:
    """(v0, e1, e2, table) of :func:`robustbench3d.sensors.raycast.face_test_geometry` for float32 or float64
    ``vertices`` (V, 3), ``origin`` and ``axis`` (3,) or None of that dtype and faces (F, 3) int64 in range (checked
    here unless ``checked``: the caller knows them (F, 3) int64 indices of the vertices); ``sliver`` its dtype's
    sliver ratio."""
    dt = vertices.dtype.type
    offsets = axis is not None
    ax = np.zeros(3, vertices.dtype) if axis is None else np.ascontiguousarray(axis)
    sk = np.zeros(len(faces), np.bool_) if skip is None else np.ascontiguousarray(skip, np.bool_)
    fa = np.ascontiguousarray(faces, np.int64) if checked else _checked_faces(faces, len(vertices), "face_test_table")
    return _face_test_table(np.ascontiguousarray(vertices), fa, np.ascontiguousarray(origin), ax, offsets, sk,
                            dt(sliver), dt(cos_min))


@njit(cache=True, nogil=True, inline="always")
def _reach_lasers(c: np.ndarray, r: np.ndarray, i: int, rho: float, first: int, last: int, neg_phi: np.ndarray,
                  top_down: bool, h_lo: float, h_hi: float) -> tuple:  # pragma: no cover - compiled
    """The lasers first..last of sphere i (centre ``c[i]``, radius ``r[i]``, ``rho`` = |c_xy|), narrowed, with
    the lasers ordered top down, to those within the sphere's reach from any apex height in [h_lo, h_hi]."""
    lo_l, hi_l = first, last
    if top_down:
        d_min = np.hypot(rho, c[i, 2] - np.minimum(np.maximum(c[i, 2], h_lo), h_hi))
        if r[i] >= d_min:
            top, bottom = np.inf, -np.inf
        else:
            reach = np.arcsin(np.minimum(r[i] / d_min, 1.0)) + 1e-9
            top = np.arctan2(c[i, 2] - h_lo, rho) + reach
            bottom = np.arctan2(c[i, 2] - h_hi, rho) - reach
        lo_l = max(first, np.searchsorted(neg_phi, -top, side="left"))
        hi_l = min(last, np.searchsorted(neg_phi, -bottom, side="right") - 1)
    return lo_l, hi_l


@njit(cache=True, nogil=True, inline="always")
def _laser_interval(rs: float, rho_s: float, dz: float, sin_phi: float, cos_phi: float, theta: float
                    ) -> tuple:  # pragma: no cover - compiled
    """(reached, lo, hi, wrap) of one laser (elevation sin / cos ``sin_phi``, ``cos_phi``, apex ``dz`` below the
    centre) and a sphere (radius ``rs``, centre at ``rho_s`` from the axis, azimuth ``theta``): whether its cone
    reaches the sphere, the azimuth interval of the rays that can pass through it (degrees, -1..500 for all) and
    whether rays a turn away may reach it too (:meth:`BeamPattern.sphere_rays`' test)."""
    dist2 = rho_s * rho_s + dz * dz
    kappa = (np.sqrt(np.maximum(dist2 - rs * rs, 0.0)) - sin_phi * dz) / (cos_phi * rho_s)
    kappa = kappa - 1e-9
    full = (rs >= rho_s) or (dist2 <= rs * rs) or (kappa <= -1.0)
    if not (full or kappa <= 1.0):
        return False, 0.0, 0.0, False
    if full:
        return True, -1.0, 500.0, False
    half = np.degrees(np.arccos(np.minimum(np.maximum(kappa, -1.0), 1.0))) + 1e-7
    a, b = theta - half, theta + half
    return True, a, b, a < 1.0 or b > 359.0


@njit(cache=True, nogil=True, error_model="numpy")
def _sphere_ray_ranges(c: np.ndarray, r: np.ndarray, first: np.ndarray, last: np.ndarray, phi: np.ndarray,
                       sin_phi: np.ndarray, cos_phi: np.ndarray, origin_z: np.ndarray, top_down: bool, h_lo: float,
                       h_hi: float, keys: np.ndarray, band: float) -> tuple:  # pragma: no cover - compiled
    m = len(r)
    neg_phi = -phi
    rho = np.empty(m)
    lo_l, hi_l = first.copy(), last.copy()
    for i in range(m):
        rho[i] = np.hypot(c[i, 0], c[i, 1])
        lo_l[i], hi_l[i] = _reach_lasers(c, r, i, rho[i], first[i], last[i], neg_phi, top_down, h_lo, h_hi)
    count = 0
    for i in range(m):
        count += max(hi_l[i] - lo_l[i] + 1, 0)
    sph, las = np.empty(3 * count, np.int64), np.empty(3 * count, np.int64)
    lo, hi = np.empty(3 * count), np.empty(3 * count)
    wrap = np.empty(count, np.int64)
    n, n_wrap = 0, 0
    for i in range(m):
        theta = np.degrees(np.arctan2(c[i, 1], c[i, 0])) % 360.0
        for k in range(lo_l[i], hi_l[i] + 1):
            reached, a, b, wraps = _laser_interval(r[i], rho[i], c[i, 2] - origin_z[k], sin_phi[k], cos_phi[k], theta)
            if not reached:
                continue
            if wraps:
                wrap[n_wrap] = n
                n_wrap += 1
            sph[n], las[n], lo[n], hi[n] = i, k, a, b
            n += 1
    for turn in (360.0, -360.0):  # a sphere near azimuth 0 may also reach rays a turn away
        for w in range(n_wrap):
            j = wrap[w]
            sph[n], las[n], lo[n], hi[n] = sph[j], las[j], lo[j] + turn, hi[j] + turn
            n += 1
    total = 0
    start, stop = np.empty(n, np.int64), np.empty(n, np.int64)
    for j in range(n):
        a, b = np.minimum(np.maximum(lo[j], -1.0), 500.0), np.minimum(np.maximum(hi[j], -1.0), 500.0)
        start[j] = np.searchsorted(keys, las[j] * band + a, side="left")
        stop[j] = np.searchsorted(keys, las[j] * band + b, side="right")
        total += max(stop[j] - start[j], 0)
    out_s, out_r = np.empty(total, np.int64), np.empty(total, np.int64)
    q = 0
    for j in range(n):
        for ray in range(start[j], stop[j]):
            out_s[q], out_r[q] = sph[j], ray
            q += 1
    return out_s, out_r


def sphere_ray_ranges(centers: np.ndarray, radii: np.ndarray, first: np.ndarray, last: np.ndarray,
                      phi: np.ndarray, origin_z: np.ndarray, keys: np.ndarray, band: float
                      ) -> tuple[np.ndarray, np.ndarray]:
    """(sphere (K,), ray (K,)) of :meth:`robustbench3d.sensors.lidar_beams.BeamPattern.sphere_rays` (its
    docstring) for float64 ``centers`` (M, 3), ``radii`` (M,), int64 laser bounds (M,), the lasers' elevations
    ``phi`` (L,) (rad) and apex heights ``origin_z`` (L,) (m), the pattern's sorted ray ``keys`` and ``band``."""
    if len(first) != len(radii) or len(last) != len(radii) or len(centers) != len(radii):
        raise ValueError(f"sphere_ray_ranges: {len(centers)} centres, {len(radii)} radii, {len(first)} / {len(last)} "
                         "laser bounds")
    # the lasers that exist (the numpy code's reach test clips them so for lasers ordered top down)
    first, last = np.maximum(first, 0), np.minimum(last, len(phi) - 1)
    top_down = bool(np.all(np.diff(phi) < 0))
    h_lo, h_hi = float(origin_z.min()), float(origin_z.max())
    return _sphere_ray_ranges(np.ascontiguousarray(centers, np.float64), np.ascontiguousarray(radii, np.float64),
                              np.ascontiguousarray(first, np.int64), np.ascontiguousarray(last, np.int64),
                              np.ascontiguousarray(phi), np.sin(phi), np.cos(phi),
                              np.ascontiguousarray(origin_z, np.float64), top_down, h_lo, h_hi,
                              np.ascontiguousarray(keys), float(band))


@njit(cache=True, nogil=True)
def _rows_but(rows: np.ndarray, removed: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover - compiled
    q, prev = 0, 0
    for r in range(len(removed) + 1):
        stop = removed[r] if r < len(removed) else len(rows)
        n = stop - prev
        out[q:q + n] = rows[prev:stop]
        q += n
        prev = stop + 1


def rows_but(rows: np.ndarray, removed: np.ndarray, extra: int = 0) -> np.ndarray:
    """The rows of ``rows`` (N, C) but those of ``removed`` (increasing, distinct, in [0, N)), in order, copied as
    their raw bytes (uint32 words: any float bits, NaN payloads included, stay as they are), in an array of
    N - len(removed) + ``extra`` rows and ``rows``' dtype whose last ``extra`` rows are left for the caller."""
    rows = np.ascontiguousarray(rows)
    removed = np.ascontiguousarray(removed, np.int64)
    if rows.ndim != 2 or rows.itemsize != 4:
        raise ValueError(f"rows_but: field 'rows': expected (N, C) of 4-byte items, got {rows.shape} {rows.dtype}")
    if len(removed) and (removed[0] < 0 or removed[-1] >= len(rows) or np.any(removed[1:] <= removed[:-1])):
        raise ValueError(f"rows_but: field 'removed': indices must increase within [0, {len(rows)})")
    out = np.empty((len(rows) - len(removed) + extra, rows.shape[1]), rows.dtype)
    _rows_but(rows.view(np.uint32), removed, out.view(np.uint32))
    return out


@njit(cache=True, nogil=True, inline="always")
def _first_at_least(p: float, steps: np.ndarray, n: int, v: float) -> int:  # pragma: no cover - compiled
    """The first j < n with p + steps[j] >= v (n if none): p + steps[j] does not decrease with j."""
    lo, hi = 0, n
    while lo < hi:
        mid = (lo + hi) >> 1
        if p + steps[mid] >= v:
            hi = mid
        else:
            lo = mid + 1
    return lo


@njit(cache=True, nogil=True)
def _beam_table(phases: np.ndarray, shift: float, steps: np.ndarray, sec_first: np.ndarray, sec_last: np.ndarray,
                sec_lo: np.ndarray, sec_hi: np.ndarray, sec_wrap: np.ndarray) -> tuple:  # pragma: no cover - compiled
    n_lasers, n = len(phases), len(steps)
    az = np.empty(n_lasers * n)
    start = np.zeros(n_lasers + 1, np.int64)
    cut_lo, cut_hi = np.empty(len(sec_first) + 1, np.int64), np.empty(len(sec_first) + 1, np.int64)
    q = 0
    for k in range(n_lasers):
        start[k] = q
        p = phases[k]
        # firings p + steps[j] do not decrease with j: those below 360 are a prefix (none if p is NaN), and each
        # sector of the laser drops a range of them ([from, to), and with to past 360 those below to - 360)
        n_valid = 0 if not p < 360.0 else _first_at_least(p, steps, n, 360.0)
        n_cut = 0
        for s in range(len(sec_first)):
            if sec_first[s] <= k <= sec_last[s]:
                cut_lo[n_cut] = _first_at_least(p, steps, n_valid, sec_lo[s])
                cut_hi[n_cut] = _first_at_least(p, steps, n_valid, sec_hi[s])
                n_cut += 1
                if sec_hi[s] > 360.0:
                    cut_lo[n_cut], cut_hi[n_cut] = 0, _first_at_least(p, steps, n_valid, sec_wrap[s])
                    n_cut += 1
        j = 0
        while j < n_valid:
            cut = -1
            for c in range(n_cut):
                if cut_lo[c] <= j < cut_hi[c]:
                    cut = c
            if cut >= 0:  # j is cut: go on from the cut's end
                j = cut_hi[cut]
                continue
            stop = n_valid  # the kept run from j: up to the first cut that starts after j
            for c in range(n_cut):
                if j < cut_lo[c] < stop and cut_hi[c] > cut_lo[c]:
                    stop = cut_lo[c]
            for i in range(j, stop):
                az[q + i - j] = (p + steps[i]) + shift
            q += stop - j
            j = stop
    start[n_lasers] = q
    lowest, highest = np.inf, -np.inf
    if np.isfinite(shift):  # each laser's azimuths (no NaN) do not decrease: its first and last are its extremes
        for k in range(n_lasers):
            if start[k + 1] > start[k]:
                lowest, highest = min(lowest, az[start[k]]), max(highest, az[start[k + 1] - 1])
    else:
        for i in range(q):
            if az[i] != az[i]:  # as numpy's min and max: NaN
                lowest, highest = np.nan, np.nan
                break
            lowest, highest = min(lowest, az[i]), max(highest, az[i])
    return az[:q], start, lowest, highest


def beam_table(phases: np.ndarray, shift: float, steps: np.ndarray,
               sectors: tuple[tuple[int, int, float, float], ...]) -> tuple[np.ndarray, np.ndarray, float, float]:
    """The rays of a revolution as :meth:`robustbench3d.sensors.hdl64e.HDL64E.ray_azimuths` forms them and
    ``BeamPattern`` turns them, in one pass: laser k's firings at ``phases[k] + steps`` (float64, below 360) but
    those in an occluded sector of that laser (``sectors``: (first laser, last laser, from, to) degrees, ``to``
    past 360 wrapping), turned by ``shift``. Returns (azimuth (R,) = firing + shift, laser by laser, start (L + 1,)
    index of each laser's first ray and the total, the lowest and highest azimuth (+-inf without rays)): the same
    values as the numpy code, element by element."""
    sec = np.array([[f, last, lo, hi, hi - 360.0] for f, last, lo, hi in sectors], np.float64).reshape(-1, 5)
    return _beam_table(np.ascontiguousarray(phases, np.float64), float(shift), np.ascontiguousarray(steps, np.float64),
                       sec[:, 0].astype(np.int64), sec[:, 1].astype(np.int64), sec[:, 2].copy(), sec[:, 3].copy(),
                       sec[:, 4].copy())


@njit(cache=True, nogil=True, inline="always")
def _key_search(az: np.ndarray, lo: int, hi: int, k: int, band: float, v: float,
                right: bool) -> int:  # pragma: no cover - compiled
    """``lo + np.searchsorted(keys[lo:hi], v, side)`` (side "right" if ``right`` else "left") of the keys
    ``k * band + az[i]`` of laser k's rays lo..hi - 1, each formed as the key table's, in numpy's order (NaN
    last)."""
    while lo < hi:
        mid = (lo + hi) >> 1
        key = k * band + az[mid]
        # right: v sorts before the key; left: the key does not sort before v (the answer is then at or below mid)
        before = (v < key or (key != key and v == v)) if right else not (key < v or (v != v and key == key))
        if before:
            hi = mid
        else:
            lo = mid + 1
    return lo


@njit(cache=True, nogil=True)
def _nearest_rays(ring: np.ndarray, az: np.ndarray, ring_start: np.ndarray, raz: np.ndarray, lowest: float,
                  highest: float, max_deg: float, band: float) -> np.ndarray:  # pragma: no cover - compiled
    n_lasers = len(ring_start) - 1
    out = np.full(len(ring), -1, np.int64)
    reach_down = lowest + 360.0 - max_deg - 1e-6
    reach_up = highest - 360.0 + max_deg + 1e-6
    for i in range(len(ring)):
        r = ring[i]
        if r < 0 or r >= n_lasers:
            continue
        a = az[i]
        first, last = ring_start[r], ring_start[r + 1] - 1
        best, gap = -1, np.inf
        for turn in (-360.0, 0.0, 360.0):
            if (turn < 0.0 and not a >= reach_down) or (turn > 0.0 and not a <= reach_up):
                continue
            pos = _key_search(raz, ring_start[r], ring_start[r + 1], r, band, r * band + a + turn, False)
            for cand in (pos - 1, pos):
                if cand >= first and cand <= last:
                    g = np.abs(raz[cand] - (a + turn))
                    if g < gap:
                        best, gap = cand, g
        if gap <= max_deg:
            out[i] = best
    return out


def nearest_rays(ring: np.ndarray, az: np.ndarray, ring_start: np.ndarray, raz: np.ndarray,
                 az_range: tuple[float, float], max_deg: float, band: float) -> np.ndarray:
    """:meth:`robustbench3d.sensors.lidar_beams.BeamPattern.nearest_ray`'s numpy code point by point: per point
    (laser ``ring`` (N,), azimuth ``az`` (N,) already taken modulo 360) the ray of its laser nearest in azimuth
    among the pattern's (azimuths ``raz`` (R,), laser k's from ``ring_start[k]`` (L + 1,), lowest and highest
    ``az_range``) within ``max_deg``, or -1. The pattern's sorted keys k x ``band`` + raz are searched laser by
    laser, which ends where the search over all keys does when the caller keeps the rays' azimuths in [-1, 361)
    and ``band`` >= 1000 (a point's key, k x band + [-360, 720), then sorts between the lower and the higher
    lasers' rays)."""
    ring, az = np.ascontiguousarray(ring, np.int64), np.ascontiguousarray(az, np.float64)
    if len(ring) != len(az) or len(ring_start) < 1 or ring_start[-1] != len(raz) or np.any(np.diff(ring_start) < 0):
        raise ValueError(f"nearest_rays: {len(ring)} lasers for {len(az)} azimuths, or laser starts {ring_start} "
                         f"for {len(raz)} rays")
    return _nearest_rays(ring, az, np.ascontiguousarray(ring_start, np.int64), np.ascontiguousarray(raz, np.float64),
                         float(az_range[0]), float(az_range[1]), float(max_deg), float(band))


@njit(cache=True, nogil=True)
def _near_bins(ring: np.ndarray, az: np.ndarray, grid: np.ndarray, bins: int, max_deg: float,
               out: np.ndarray) -> int:  # pragma: no cover - compiled
    for i in range(len(az)):
        if not (az[i] > -360.0 and az[i] < 360.0):  # NaN too: numpy's modulo
            return -1
    width = bins + 1
    for i in range(len(az)):
        a = az[i]
        m = a + 360.0 if a < 0.0 else a + 0.0  # _mod360's fast path
        col = int(np.floor(m / max_deg))
        r = ring[i]
        if r < 0 or r * width >= len(grid) or col < 0 or col > bins:
            return i
        out[i] = grid[r * width + col]
    return -2


def near_bins(ring: np.ndarray, az: np.ndarray, grid: np.ndarray, bins: int, max_deg: float) -> np.ndarray | None:
    """``grid.reshape(-1)[ring * (bins + 1) + floor(_mod360(az) / max_deg)]`` of
    :meth:`robustbench3d.sensors.lidar_beams.BeamPattern.near_rays` for points (lasers ``ring`` (N,), azimuths
    ``az`` (N,) degrees) and a per-laser ``grid`` (L, bins + 1) bool of near bins of ``max_deg``: the same
    arithmetic point by point; None when an azimuth lies outside (-360, 360) or is NaN (the numpy code then
    takes it modulo 360)."""
    grid = np.ascontiguousarray(grid, np.bool_)
    if grid.ndim != 2 or grid.shape[1] != bins + 1 or len(ring) != len(az):
        raise ValueError(f"near_bins: grid {grid.shape} for {bins} bins, {len(ring)} lasers for {len(az)} azimuths")
    out = np.empty(len(az), np.bool_)
    status = _near_bins(np.ascontiguousarray(ring, np.int64), np.ascontiguousarray(az, np.float64),
                        grid.reshape(-1), int(bins), float(max_deg), out)
    if status == -1:
        return None
    if status >= 0:
        raise ValueError(f"near_bins: point {status} (laser {ring[status]}, azimuth {az[status]}) outside the grid")
    return out


@njit(cache=True, nogil=True)
def _cull_runs(rays: np.ndarray, counts: np.ndarray, ring_start: np.ndarray, idx: np.ndarray
               ) -> tuple:  # pragma: no cover - compiled
    n_lasers = len(ring_start) - 1
    n_runs = 0
    start, stop, pos = np.empty(len(rays), np.int64), np.empty(len(rays), np.int64), np.empty(len(rays), np.int64)
    ptr = np.zeros(len(counts) * n_lasers + 1, np.int64)
    q = 0
    for m in range(len(counts)):
        laser = -1
        for j in range(q, q + counts[m]):
            ray = rays[j]
            if j > q and ray == rays[j - 1] + 1 and ray < ring_start[laser + 1]:  # the run goes on
                stop[n_runs - 1] = ray + 1
                continue
            laser = np.searchsorted(ring_start, ray, side="right") - 1
            start[n_runs], stop[n_runs] = ray, ray + 1
            pos[n_runs] = np.searchsorted(idx, ray)
            ptr[m * n_lasers + laser + 1] += 1
            n_runs += 1
        q += counts[m]
    for k in range(len(ptr) - 1):
        ptr[k + 1] += ptr[k]
    return ptr, start[:n_runs], stop[:n_runs], pos[:n_runs]


def cull_runs(rays: np.ndarray, counts: np.ndarray, ring_start: np.ndarray, idx: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The culled rays of M meshes as runs of consecutive rays of one laser: ``rays`` the meshes' culls (each
    increasing) concatenated, ``counts`` (M,) their lengths, ``ring_start`` (L + 1,) the index of each laser's first
    ray (and the total), ``idx`` the sorted union of the culls. Returns (ptr (M * L + 1,): runs ptr[m L + k] to
    ptr[m L + k + 1] - 1 are mesh m's on laser k, in ray order; start, stop (end, exclusive) rays of each run; pos:
    position of its first ray in ``idx``, the others following it there)."""
    rays, counts = np.ascontiguousarray(rays, np.int64), np.ascontiguousarray(counts, np.int64)
    ring_start, idx = np.ascontiguousarray(ring_start, np.int64), np.ascontiguousarray(idx, np.int64)
    if counts.sum() != len(rays) or (len(rays) and (rays.min() < 0 or rays.max() >= ring_start[-1])):
        raise ValueError(f"cull_runs: {len(rays)} rays for counts summing to {counts.sum()}, or rays outside "
                         f"[0, {ring_start[-1]})")
    return _cull_runs(rays, counts, ring_start, idx)


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _test_face_rays(p_lo: int, p_hi: int, f: int, g0: float, g1: float, g2: float, g3: float, g4: float, g5: float,
                    g6: float, g7: float, g8: float, g9: float, g10: float, g11: float, g12: float, g13: float,
                    g14: float, g15: float, g16: float, g17: float, d_cols: np.ndarray, h: np.ndarray, t_min: float,
                    tol: float, best_face: np.ndarray, best_t: np.ndarray) -> None:  # pragma: no cover - compiled
    """Face f (its column g0..g17 of the offset test table) against the consecutive rays p_lo..p_hi - 1: the
    arithmetic of :func:`_nearest_of_pairs` (offsets on; ``np.sign`` spelled out as numba evaluates it) and the
    choice of :func:`_keep_if_nearer`, with the verdict's tests all evaluated and the nearest kept by selects, so
    that the loop has no branch (vectorised); t = t*det / det is used only where the verdict holds (det > 0)."""
    for p in range(p_lo, p_hi):
        d0, d1, d2 = d_cols[0, p], d_cols[1, p], d_cols[2, p]
        det = g0 * d0 + g1 * d1 + g2 * d2
        un = g3 * d0 + g4 * d1 + g5 * d2
        vn = g6 * d0 + g7 * d1 + g8 * d2
        tn = g9
        hr = h[p]
        un = un + hr * (g11 * d0 + g12 * d1 + g13 * d2)
        vn = vn + hr * (g14 * d0 + g15 * d1 + g16 * d2)
        tn = tn + hr * g17
        sign = 1.0 if tn > 0.0 else (-1.0 if tn < 0.0 else tn)
        det, un, vn, tn = det * sign, un * sign, vn * sign, np.abs(tn)
        slack = tol * det
        ok = (det > g10) & (un >= -slack) & (vn >= -slack) & (un + vn <= det + slack) & (tn > t_min * det)
        t = tn / det
        bt, bf = best_t[p], best_face[p]
        better = ok & ((t < bt) | ((t == bt) & (f < bf)))
        best_t[p] = t if better else bt
        best_face[p] = f if better else bf


@njit(cache=True, nogil=True, error_model="numpy")
def _sphere_pairs_nearest(c: np.ndarray, r: np.ndarray, face_mesh: np.ndarray, mesh_first: np.ndarray,
                          mesh_last: np.ndarray, ptr: np.ndarray, run_start: np.ndarray, run_stop: np.ndarray,
                          run_pos: np.ndarray, phi: np.ndarray, sin_phi: np.ndarray, cos_phi: np.ndarray,
                          origin_z: np.ndarray, top_down: bool, h_lo: float, h_hi: float, az: np.ndarray,
                          band: float, table: np.ndarray, d_cols: np.ndarray, h: np.ndarray, t_min: float,
                          tol: float, best_face: np.ndarray, best_t: np.ndarray) -> int:  # pragma: no cover - compiled
    n_lasers = len(phi)
    neg_phi = -phi
    tests = 0
    for i in range(len(r)):
        m = face_mesh[i]
        rho = np.hypot(c[i, 0], c[i, 1])
        lo_l, hi_l = _reach_lasers(c, r, i, rho, mesh_first[m], mesh_last[m], neg_phi, top_down, h_lo, h_hi)
        theta = np.degrees(np.arctan2(c[i, 1], c[i, 0])) % 360.0
        # face i's column of the test table (the arithmetic of _nearest_of_pairs, offsets on)
        g0, g1, g2, g3, g4, g5 = table[0, i], table[1, i], table[2, i], table[3, i], table[4, i], table[5, i]
        g6, g7, g8, g9, g10 = table[6, i], table[7, i], table[8, i], table[9, i], table[10, i]
        g11, g12, g13, g14 = table[11, i], table[12, i], table[13, i], table[14, i]
        g15, g16, g17 = table[15, i], table[16, i], table[17, i]
        for k in range(lo_l, hi_l + 1):
            q0, q1 = ptr[m * n_lasers + k], ptr[m * n_lasers + k + 1]
            if q0 == q1:  # the mesh culled no ray of this laser
                continue
            reached, a, b, wraps = _laser_interval(r[i], rho, c[i, 2] - origin_z[k], sin_phi[k], cos_phi[k], theta)
            if not reached:
                continue
            for turn in range(3 if wraps else 1):  # a sphere near azimuth 0 may also reach rays a turn away
                lo, hi = a, b
                if turn == 1:
                    lo, hi = a + 360.0, b + 360.0
                elif turn == 2:
                    lo, hi = a - 360.0, b - 360.0
                lo, hi = np.minimum(np.maximum(lo, -1.0), 500.0), np.minimum(np.maximum(hi, -1.0), 500.0)
                key_lo, key_hi = k * band + lo, k * band + hi
                for q in range(q0, q1):
                    rs, re = run_start[q], run_stop[q]
                    # the range's rays among the run's: the whole pattern's key search clipped to [rs, re]
                    s = _key_search(az, rs, re, k, band, key_lo, False)
                    e = _key_search(az, rs, re, k, band, key_hi, True)
                    if e > s:
                        tests += e - s
                        _test_face_rays(run_pos[q] + s - rs, run_pos[q] + e - rs, i, g0, g1, g2, g3, g4, g5, g6, g7,
                                        g8, g9, g10, g11, g12, g13, g14, g15, g16, g17, d_cols, h, t_min, tol,
                                        best_face, best_t)
    return tests


def sphere_pairs_nearest(centers: np.ndarray, radii: np.ndarray, face_mesh: np.ndarray,
                         runs: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], phi: np.ndarray,
                         origin_z: np.ndarray, az: np.ndarray, band: float, table: np.ndarray, d_cols: np.ndarray,
                         h: np.ndarray, t_min: float, tol: float) -> tuple[np.ndarray, np.ndarray, int]:
    """The nearest face of each culled ray among the faces whose bounding sphere it can pass through: (face (R,)
    int64 or -1, t (R,) or +inf, pairs tested), the search of
    :func:`robustbench3d.sensors.raycast.search_pairs` (:func:`nearest_of_pairs`, offsets on) over the pairs of
    :func:`sphere_ray_ranges` (each face's sphere, ``centers`` (F, 3), ``radii`` (F,), on the lasers of its mesh's
    cull) whose ray is in the face's mesh's cull, without forming the pairs: the same verdicts, nearest faces,
    t and count.

    Args:
        face_mesh: (F,) mesh of each face, indexing the meshes of ``runs`` (:func:`cull_runs` of their culls,
            whose ``idx`` numbers the R rays).
        phi, origin_z, az, band: the lasers' elevations (rad) and apex heights, the pattern's ray azimuths
            (degrees; laser k's ray i has the key k x ``band`` + az[i] of the pattern's sorted keys).
        table: (18, F) per-face test table with offsets (:func:`robustbench3d.sensors.raycast._face_tables`),
            float64; ``d_cols`` (3, R) the rays' directions by component, ``h`` (R,) their apex heights.
    """
    ptr, run_start, run_stop, run_pos = runs
    n_lasers, n_rays = len(phi), d_cols.shape[1]
    n_meshes = (len(ptr) - 1) // max(n_lasers, 1)
    face_mesh = np.ascontiguousarray(face_mesh, np.int64)
    if table.dtype != np.float64 or d_cols.dtype != np.float64 or h.dtype != np.float64:
        raise ValueError(f"sphere_pairs_nearest: table {table.dtype}, directions {d_cols.dtype} and heights "
                         f"{h.dtype} must be float64")
    if (len(face_mesh) != len(radii) or table.shape != (18, len(radii)) or len(h) != n_rays
            or (len(face_mesh) and (face_mesh.min() < 0 or face_mesh.max() >= n_meshes))
            or (len(run_start) and (run_start.min() < 0 or run_stop.max() > len(az) or run_pos.min() < 0
                                    or (run_pos + run_stop - run_start).max() > n_rays))):
        raise ValueError(f"sphere_pairs_nearest: {len(radii)} spheres, {len(face_mesh)} meshes of faces, table "
                         f"{table.shape}, {n_rays} rays and {len(h)} heights, or runs outside {n_meshes} meshes, "
                         f"{len(az)} pattern rays or {n_rays} rays")
    has = np.diff(ptr).reshape(n_meshes, n_lasers) > 0
    lasers = np.arange(n_lasers)
    mesh_first = np.where(has, lasers, n_lasers).min(axis=1) if n_meshes else np.zeros(0, np.int64)
    mesh_last = np.where(has, lasers, -1).max(axis=1) if n_meshes else np.zeros(0, np.int64)
    best_face = np.full(n_rays, -1, np.int64)
    best_t = np.full(n_rays, np.inf)
    top_down = bool(np.all(np.diff(phi) < 0))
    h_lo, h_hi = float(origin_z.min()), float(origin_z.max())
    tests = _sphere_pairs_nearest(
        np.ascontiguousarray(centers, np.float64), np.ascontiguousarray(radii, np.float64), face_mesh,
        mesh_first.astype(np.int64), mesh_last.astype(np.int64), ptr, run_start, run_stop, run_pos,
        np.ascontiguousarray(phi), np.sin(phi), np.cos(phi), np.ascontiguousarray(origin_z, np.float64), top_down,
        h_lo, h_hi, np.ascontiguousarray(az, np.float64), float(band), np.ascontiguousarray(table),
        np.ascontiguousarray(d_cols), np.ascontiguousarray(h), float(t_min), float(tol), best_face, best_t)
    return best_face, best_t, int(tests)


@njit(cache=True, nogil=True, error_model="numpy")
def _cone_cull(c: np.ndarray, radii: np.ndarray, sin_phi: np.ndarray, cos_phi: np.ndarray, origin_z: np.ndarray,
               margin_deg: float, az: np.ndarray, ring_start: np.ndarray, band: float
               ) -> tuple:  # pragma: no cover - compiled
    m, n_lasers = len(radii), len(sin_phi)
    counts = np.zeros(m, np.int64)
    chunks = []
    for i in range(m):
        r = radii[i] * (1 + 1e-9) + 1e-9
        r2 = r * r
        rho = np.hypot(c[i, 0], c[i, 1])
        theta = np.degrees(np.arctan2(c[i, 1], c[i, 0])) % 360.0
        starts = np.empty(3 * n_lasers, np.int64)
        stops = np.empty(3 * n_lasers, np.int64)
        n = 0
        for k in range(n_lasers):
            cz = c[i, 2] - origin_z[k]
            dist2 = rho * rho + cz * cz
            if dist2 <= r2:
                kappa = -np.inf
            else:
                kappa = (np.sqrt(np.maximum(dist2 - r2, 0.0)) - sin_phi[k] * cz) / (cos_phi[k] * rho)
                if np.isnan(kappa):
                    kappa = np.inf
            kappa = kappa - 1e-9
            if not kappa <= 1.0:
                continue
            half = np.degrees(np.arccos(np.minimum(np.maximum(kappa, -1.0), 1.0))) + margin_deg
            for turn in (-360.0, 0.0, 360.0):  # a full laser gets its whole range three times (merged below)
                if half >= 180.0:
                    lo, hi = -1.0, 500.0
                else:
                    lo = np.minimum(np.maximum(theta - half + turn, -1.0), 500.0)
                    hi = np.minimum(np.maximum(theta + half + turn, -1.0), 500.0)
                a = _key_search(az, ring_start[k], ring_start[k + 1], k, band, k * band + lo, False)
                b = _key_search(az, ring_start[k], ring_start[k + 1], k, band, k * band + hi, True)
                if b > a:
                    starts[n], stops[n] = a, b
                    n += 1
        order = np.argsort(starts[:n])
        rays = np.empty(0, np.int64)
        if n:
            total = 0
            for j in range(n):
                total += stops[j] - starts[j]
            rays = np.empty(total, np.int64)
            q, reach = 0, -1  # rays below reach are out already
            for j in order:
                for ray in range(max(starts[j], reach), stops[j]):
                    rays[q] = ray
                    q += 1
                reach = max(reach, stops[j])
            rays = rays[:q]
        counts[i] = len(rays)
        chunks.append(rays)
    out = np.empty(counts.sum(), np.int64)
    q = 0
    for i in range(m):
        out[q:q + counts[i]] = chunks[i]
        q += counts[i]
    return out, counts


def cone_cull(centers: np.ndarray, radii: np.ndarray, phi: np.ndarray, origin_z: np.ndarray, margin_deg: float,
              az: np.ndarray, ring_start: np.ndarray, band: float) -> list[np.ndarray]:
    """Per sphere (float64 ``centers`` (M, 3), ``radii`` (M,)) the sorted rays of
    :meth:`robustbench3d.sensors.lidar_beams.BeamPattern.cull_many` (its docstring): lasers' elevations ``phi``
    (L,) (rad), apex heights ``origin_z`` (L,) (m), the pattern's ray azimuths ``az`` (R,), laser k's from
    ``ring_start[k]`` (L + 1,), whose sorted keys k x ``band`` + az are searched laser by laser. The caller makes
    sure that the azimuths lie in [-1, 361) degrees and ``band`` >= 1000: then a key of laser k's band,
    k x band + [-1, 500], sorts after every lower laser's ray and before every higher laser's, so that the search
    over all keys ends within the laser's rays."""
    if len(ring_start) != len(phi) + 1 or ring_start[-1] != len(az) or np.any(np.diff(ring_start) < 0):
        raise ValueError(f"cone_cull: {len(az)} rays, laser starts {ring_start} for {len(phi)} lasers")
    rays, counts = _cone_cull(np.ascontiguousarray(centers, np.float64), np.ascontiguousarray(radii, np.float64),
                              np.sin(phi), np.cos(phi), np.ascontiguousarray(origin_z, np.float64), float(margin_deg),
                              np.ascontiguousarray(az, np.float64), np.ascontiguousarray(ring_start, np.int64),
                              float(band))
    return np.split(rays, np.cumsum(counts)[:-1])


@njit(cache=True, nogil=True)
def _shade_exposure(lit: np.ndarray, slot: np.ndarray, u: np.ndarray, v: np.ndarray, fade: np.ndarray,
                    haze: np.ndarray, one: float, quarter: float, knee: float) -> tuple:  # pragma: no cover
    k = len(slot)
    dt = lit.dtype
    dl1, dl2, emh = np.empty((3, k), dt), np.empty((3, k), dt), np.empty((3, k), dt)
    den, x, xm = np.empty((3, k), dt), np.empty((3, k), dt), np.empty((3, k), dt)
    for i in range(k):
        s, f = slot[i], fade[i]
        for c in range(3):
            g0 = lit[s, c]
            d1, d2 = lit[s, 3 + c] - g0, lit[s, 6 + c] - g0
            e = haze[c] * (one - f) + f * (g0 + u[i] * d1 + v[i] * d2)
            dn = one + quarter * e
            xx = e / dn
            dl1[c, i], dl2[c, i], emh[c, i], den[c, i], x[c, i] = d1, d2, e - haze[c], dn, xx
            xm[c, i] = np.maximum(xx, knee)
    return dl1, dl2, emh, den, x, xm


def shade_exposure(lit: np.ndarray, slot: np.ndarray, u: np.ndarray, v: np.ndarray, fade: np.ndarray,
                   haze: np.ndarray) -> tuple[np.ndarray, ...]:
    """Per hit (K) of its face's lit vertex colours ``lit`` (U, 9) (L0, L1, L2, by channel), at barycentrics u, v
    (K,), hazed by ``fade`` (K,) towards ``haze`` (3,) (all one float dtype): (dl1 = L1 - L0, dl2 = L2 - L0,
    exposed - haze, den = 1 + exposed / 4, x = exposed / den, max(x, 0.0031308)), each (3, K), with exposed =
    haze (1 - fade) + fade (L0 + u dl1 + v dl2): :class:`~robustbench3d.sensors.camera_render._ShadeHits`'
    numpy arithmetic, constants in that dtype."""
    dt = lit.dtype.type
    return _shade_exposure(np.ascontiguousarray(lit), np.ascontiguousarray(slot, np.int64), np.ascontiguousarray(u),
                           np.ascontiguousarray(v), np.ascontiguousarray(fade), np.ascontiguousarray(haze), dt(1.0),
                           dt(0.25), dt(0.0031308))


@njit(cache=True, nogil=True, error_model="numpy")
def _shade_tone(x: np.ndarray, den: np.ndarray, power: np.ndarray, base: np.ndarray, owner: np.ndarray,
                weight: np.ndarray, consts: tuple) -> tuple:  # pragma: no cover - compiled
    knee, lin, gain, offset, gamma, zero, one = consts
    k = x.shape[1]
    slope_w = np.empty((3, k), x.dtype)
    acc = np.zeros(base.shape, x.dtype)
    for i in range(k):
        p, w = owner[i], weight[i]
        for c in range(3):
            xx = x[c, i]
            low = xx <= knee
            y = lin * xx if low else gain * power[c, i] - offset
            sl = (lin if low else (y + offset) / (gamma * xx)) / (den[c, i] * den[c, i])
            if not (y >= zero and y <= one):
                sl = zero
            slope_w[c, i] = sl * w
            acc[c, p] += (np.minimum(np.maximum(y, zero), one) - base[c, p]) * w
    return acc, slope_w


def shade_tone(x: np.ndarray, den: np.ndarray, power: np.ndarray, base: np.ndarray, owner: np.ndarray,
               weight: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The tone curve and compositing of :class:`~robustbench3d.sensors.camera_render._ShadeHits` per hit (K) and
    channel: y = 12.92 x where x <= 0.0031308, else 1.055 ``power`` - 0.055 (``power`` = max(x, 0.0031308)^(1/2.4),
    from numpy), its slope d y / d exposed (0 where y leaves [0, 1]) times the hit's ``weight`` (K,), and the sum
    per pixel (``owner`` (K,) into ``base`` (3, P)) of weight (clip(y, 0, 1) - base) in hit order: (acc (3, P),
    slope * weight (3, K)), numpy's arithmetic with the constants in the arrays' dtype."""
    dt = x.dtype.type
    consts = (dt(0.0031308), dt(12.92), dt(1.055), dt(0.055), dt(2.4), dt(0.0), dt(1.0))
    _checked_index(owner, x.shape[1], base.shape[1], "shade_tone")
    return _shade_tone(np.ascontiguousarray(x), np.ascontiguousarray(den), np.ascontiguousarray(power),
                       np.ascontiguousarray(base), np.ascontiguousarray(owner, np.int64), np.ascontiguousarray(weight),
                       consts)


@njit(cache=True, nogil=True)
def _shade_grads(gn: np.ndarray, owner: np.ndarray, slope_w: np.ndarray, fade: np.ndarray, emh: np.ndarray,
                 dl1: np.ndarray, dl2: np.ndarray, u: np.ndarray, v: np.ndarray, slot: np.ndarray, n_faces: int,
                 t_scale: float, one: float) -> tuple:  # pragma: no cover - compiled
    k = len(owner)
    dt = gn.dtype
    g_t, g_u, g_v = np.empty(k, dt), np.empty(k, dt), np.empty(k, dt)
    g_lit = np.zeros((n_faces, 9))
    for i in range(k):
        p, f, s = owner[i], fade[i], slot[i]
        w0 = one - u[i] - v[i]
        gl0 = gn[0, p] * slope_w[0, i]
        gl1 = gn[1, p] * slope_w[1, i]
        gl2 = gn[2, p] * slope_w[2, i]
        g_t[i] = (gl0 * emh[0, i] + gl1 * emh[1, i] + gl2 * emh[2, i]) * t_scale
        a0, a1, a2 = gl0 * f, gl1 * f, gl2 * f  # d / d((1 - u - v) L0 + u L1 + v L2)
        g_u[i] = a0 * dl1[0, i] + a1 * dl1[1, i] + a2 * dl1[2, i]
        g_v[i] = a0 * dl2[0, i] + a1 * dl2[1, i] + a2 * dl2[2, i]
        g_lit[s, 0] += w0 * a0
        g_lit[s, 1] += w0 * a1
        g_lit[s, 2] += w0 * a2
        g_lit[s, 3] += u[i] * a0
        g_lit[s, 4] += u[i] * a1
        g_lit[s, 5] += u[i] * a2
        g_lit[s, 6] += v[i] * a0
        g_lit[s, 7] += v[i] * a1
        g_lit[s, 8] += v[i] * a2
    return g_t, g_u, g_v, g_lit


def shade_grads(gn: np.ndarray, owner: np.ndarray, slope_w: np.ndarray, fade: np.ndarray, emh: np.ndarray,
                dl1: np.ndarray, dl2: np.ndarray, u: np.ndarray, v: np.ndarray, slot: np.ndarray, n_faces: int,
                haze_distance: float) -> tuple[np.ndarray, ...]:
    """The backward of :func:`shade_exposure` / :func:`shade_tone` per hit, from the pixels' gradients ``gn``
    (3, P): (g_t, g_u, g_v (K,) in the arrays' dtype, and per face (``slot`` (K,) into ``n_faces``) the gradients
    w.r.t. its lit colours L0, L1, L2 by channel, (n_faces, 9) summed in float64 in hit order): numpy's arithmetic
    of :class:`~robustbench3d.sensors.camera_render._ShadeHits.backward`."""
    dt = gn.dtype.type
    _checked_index(owner, len(u), gn.shape[1], "shade_grads")
    _checked_index(slot, len(u), n_faces, "shade_grads")
    return _shade_grads(np.ascontiguousarray(gn), np.ascontiguousarray(owner, np.int64),
                        np.ascontiguousarray(slope_w), np.ascontiguousarray(fade), np.ascontiguousarray(emh),
                        np.ascontiguousarray(dl1), np.ascontiguousarray(dl2), np.ascontiguousarray(u),
                        np.ascontiguousarray(v), np.ascontiguousarray(slot, np.int64), n_faces,
                        dt(-1.0 / haze_distance), dt(1.0))


@njit(cache=True, nogil=True)
def _touching_faces(lo: np.ndarray, hi: np.ndarray, crossing: np.ndarray, unreachable: np.ndarray,
                    mask: np.ndarray, u0: int, v0: int) -> np.ndarray:  # pragma: no cover - compiled
    mh, mw = mask.shape
    area = np.zeros((mh + 1, mw + 1), np.int64)  # summed-area table of the mask
    for i in range(mh):
        row = 0
        for j in range(mw):
            row += mask[i, j]
            area[i + 1, j + 1] = area[i, j + 1] + row
    n = lo.shape[0]
    out = np.zeros(n, np.bool_)
    for f in range(n):
        if unreachable[f]:
            continue
        if crossing[f]:
            b0, b1, b2, b3 = 0, 0, mw, mh
        else:
            b0 = int(np.minimum(np.maximum(np.ceil(lo[f, 0] - 0.5) - u0, 0.0), mw))
            b1 = int(np.minimum(np.maximum(np.ceil(lo[f, 1] - 0.5) - v0, 0.0), mh))
            b2 = int(np.minimum(np.maximum(np.floor(hi[f, 0] + 0.5) + 1 - u0, 0.0), mw))
            b3 = int(np.minimum(np.maximum(np.floor(hi[f, 1] + 0.5) + 1 - v0, 0.0), mh))
        if b2 > b0 and b3 > b1:
            out[f] = area[b3, b2] - area[b1, b2] - area[b3, b0] + area[b1, b0] > 0
    return out


def touching_faces(lo: np.ndarray, hi: np.ndarray, crossing: np.ndarray, unreachable: np.ndarray,
                   mask: np.ndarray, origin: tuple[int, int]) -> np.ndarray:
    """(F,) bool: the faces (pixel boxes ``lo``, ``hi`` (F, 2), flags ``crossing`` (whole region) and
    ``unreachable`` (none)) whose box overlaps the footprint [c - 0.5, c + 0.5]^2 of a True pixel of ``mask``
    (H', W'), whose pixel (0, 0) is image pixel ``origin`` (u0, v0)."""
    return _touching_faces(np.ascontiguousarray(lo, np.float64), np.ascontiguousarray(hi, np.float64),
                           np.ascontiguousarray(crossing, np.bool_), np.ascontiguousarray(unreachable, np.bool_),
                           np.ascontiguousarray(mask, np.bool_), int(origin[0]), int(origin[1]))
