"""Compiled (numba) kernels of the renderers: the camera's candidate search and the scatter-adds of the backwards.

A crop render tests a few thousand (sample, face) pairs and scatters a few thousand hits; in numpy each step
costs tens of operations on small arrays, which was most of a render's time. Each kernel here does exactly the
arithmetic of the numpy code it replaces, in the same order and dtype (numba compiles without fast-math: no
operation is reassociated or fused), so the results are the same bits; tests compare them with the numpy
references.

* :func:`nearest_in_region` walks each face's sample box and scanline spans
  (:meth:`robustbench3d.sensors.camera_render._FaceCull.boxes` / ``spans``, the numpy reference) and tests every
  sample there with the Möller–Trumbore test of :func:`robustbench3d.sensors.raycast.hit_pairs_np` (shared
  origin), keeping the choice of :func:`~robustbench3d.sensors.raycast.nearest_np` (the nearest t, equal t to the
  smallest face index), without materialising the pairs.
* :func:`scatter_rows` sums rows by an index in float64, in order (``np.bincount``'s arithmetic);
  :func:`scatter_add` in the values' dtype, in order (``np.add.at``'s).
* :func:`face_cull` is the per-face part of :meth:`robustbench3d.sensors.camera_render._FaceCull.of` (its numpy
  reference is :func:`robustbench3d.sensors.camera_render.face_cull_np`).
* :func:`scatter_pair_grads` is :meth:`robustbench3d.sensors.raycast.FaceRows.edge_grads`' per-pair products
  summed by face (``scatter_rows`` of the stacked columns).
* :func:`star_faces` is the per-face part of :func:`robustbench3d.sensors.raycast.back_faces`.
* :func:`cross_rows_same` is :func:`robustbench3d.sensors.mesh.cross_rows` of two float arrays of one dtype.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numba import njit

if TYPE_CHECKING:
    from robustbench3d.sensors.camera_render import _FaceCull as FaceCullArrays


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
                slack = tol * det
                if det > floor and un >= -slack and vn >= -slack and un + vn <= det + slack and tn > t_min * det:
                    t = tn / det
                    if t < best_t[r] or (t == best_t[r] and f < best_face[r]):
                        best_t[r] = t
                        best_face[r] = f
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
def _cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    out = np.empty((a.shape[0], 3), a.dtype)
    for i in range(a.shape[0]):
        out[i, 0] = a[i, 1] * b[i, 2] - a[i, 2] * b[i, 1]
        out[i, 1] = a[i, 2] * b[i, 0] - a[i, 0] * b[i, 2]
        out[i, 2] = a[i, 0] * b[i, 1] - a[i, 1] * b[i, 0]
    return out


def cross_rows_same(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise a x b of two (N, 3) float32 or float64 arrays of the same dtype (any strides), in that dtype: the
    components of np.cross, the same bits (the caller checks the shapes and dtypes)."""
    return _cross_rows(a, b)


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
                                        np.ascontiguousarray(faces, np.int64),
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
