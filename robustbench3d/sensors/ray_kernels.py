"""Compiled (numba) kernels of the Möller–Trumbore ray/triangle test both renderers share: the no-grad search of
the nearest hit and the rows of the recompute with gradients (conventions: :mod:`robustbench3d.sensors.array_kernels`).

* :func:`nearest_of_pairs` tests explicit (ray, face) pairs (shared origin or per-ray offsets along an axis) and
  keeps each ray's nearest hit: the arithmetic of :func:`~robustbench3d.sensors.pair_search.search_pairs_np`
  (:func:`~robustbench3d.sensors.pair_search.hit_pairs_np`, then
  :func:`~robustbench3d.sensors.pair_search.nearest_np`).
* :func:`walk_faces` is the camera's search without materialising the pairs: it walks each face's sample box and
  scanline spans (``FaceCull.boxes`` / ``spans`` and ``candidate_pairs`` of
  :mod:`robustbench3d.sensors.camera_cull`, the numpy reference; its caller is
  :func:`~robustbench3d.sensors.camera_cull.nearest_in_region`) and tests every sample there with the same test
  (shared origin) and choice (the nearest t, equal t the smallest face index). Both use :func:`_keep_if_nearer`,
  which is why the camera's walk lives here and not with the camera's kernels.
* :func:`face_test_table` is :func:`~robustbench3d.sensors.ray_faces.face_test_geometry` (edges, sliver test and
  the per-face table of the no-grad test); :func:`face_rows` and :func:`pair_tuv` are
  :class:`~robustbench3d.sensors.ray_rows.FaceRows`' rows and t, u, v; :func:`scatter_pair_grads` is
  ``FaceRows.edge_grads``' per-pair products summed by face; :func:`star_faces` is the per-face part of
  :func:`~robustbench3d.sensors.ray_faces.back_faces`.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from robustbench3d.sensors.array_kernels import checked_faces, checked_index


@njit(cache=True, nogil=True, inline="always")
def _keep_if_nearer(det: float, un: float, vn: float, tn: float, floor: float, t_min: float, tol: float, r: int,
                    f: int, best_face: np.ndarray, best_t: np.ndarray) -> None:  # pragma: no cover - compiled
    """The verdict of :func:`robustbench3d.sensors.pair_search.hit_pairs_np` on one pair (det, u*det, v*det, t*det with
    t*det's sign folded in, the face's grazing floor), and the choice of
    :func:`~robustbench3d.sensors.pair_search.nearest_np`: ray r keeps face f if it is hit nearer, or as near by a
    smaller face index."""
    slack = tol * det
    if det > floor and un >= -slack and vn >= -slack and un + vn <= det + slack and tn > t_min * det:
        t = tn / det
        if t < best_t[r] or (t == best_t[r] and f < best_face[r]):
            best_t[r] = t
            best_face[r] = f


@njit(cache=True, nogil=True)
def walk_faces(lo: np.ndarray, hi: np.ndarray, crossing: np.ndarray, skip: np.ndarray, tight: np.ndarray,
               edge: np.ndarray, lim: np.ndarray, s: int, pos: np.ndarray, mw: int, table: np.ndarray,
               d_cols: np.ndarray, t_min: float, tol: float, best_face: np.ndarray, best_t: np.ndarray
               ) -> int:  # pragma: no cover - compiled (run by the tests through nearest_in_region)
    row0, col0 = int(lim[1]), int(lim[0])
    s2 = s * s
    tests = 0
    for f in range(len(skip)):
        if skip[f]:
            continue
        # the face's sample box (FaceCull.boxes)
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
            if tight[f]:  # the scanline span of this row (FaceCull.spans)
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
    (:func:`robustbench3d.sensors.ray_faces._face_tables`, the same dtype) and update each ray's nearest hit in
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
    """(v0, e1, e2, table) of :func:`robustbench3d.sensors.ray_faces.face_test_geometry` for float32 or float64
    ``vertices`` (V, 3), ``origin`` and ``axis`` (3,) or None of that dtype and faces (F, 3) int64 in range (checked
    here unless ``checked``: the caller knows them (F, 3) int64 indices of the vertices); ``sliver`` its dtype's
    sliver ratio."""
    dt = vertices.dtype.type
    offsets = axis is not None
    ax = np.zeros(3, vertices.dtype) if axis is None else np.ascontiguousarray(axis)
    sk = np.zeros(len(faces), np.bool_) if skip is None else np.ascontiguousarray(skip, np.bool_)
    fa = np.ascontiguousarray(faces, np.int64) if checked else checked_faces(faces, len(vertices), "face_test_table")
    return _face_test_table(np.ascontiguousarray(vertices), fa, np.ascontiguousarray(origin), ax, offsets, sk,
                            dt(sliver), dt(cos_min))


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
    """(e1, e2, T0, q0, q1 or None, rows) of :meth:`robustbench3d.sensors.ray_rows.FaceRows.of` for float32 or
    float64 ``vertices`` (V, 3), ``origin`` (3,) and ``axis`` (3,) or None all of one dtype, faces (U, 3) int64 in
    range (the caller checks)."""
    offsets = axis is not None
    ax = np.zeros(3, vertices.dtype) if axis is None else np.ascontiguousarray(axis)
    e1, e2, t0, q0, q1, rows = _face_rows(vertices, checked_faces(faces, len(vertices), "face_rows"),
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
    """(ok, inv, t, u, v) (K,) of :meth:`robustbench3d.sensors.ray_rows.FaceRows.tuv` for ``rows`` (10 or 17, U),
    directions ``d`` (K, 3) and offsets ``h`` (K,) or None all of one float dtype; ``slot`` (K,) int64 in [0, U)
    (checked)."""
    slot = checked_index(slot, len(d), rows.shape[1], "pair_tuv")
    offsets = h is not None
    hh = np.zeros(0, d.dtype) if h is None else np.ascontiguousarray(h)
    return _pair_tuv(np.ascontiguousarray(rows), slot, np.ascontiguousarray(d), hh, offsets, d.dtype.type(1))


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
    slot = checked_index(slot, len(gdet), n, "scatter_pair_grads")
    hh = np.zeros(0, gdet.dtype) if h is None else np.ascontiguousarray(h)
    return _scatter_pair_grads(slot, np.ascontiguousarray(gdet), np.ascontiguousarray(gun), np.ascontiguousarray(gvn),
                               np.ascontiguousarray(gtn), np.ascontiguousarray(d), hh, h is not None, n)


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
    :func:`robustbench3d.sensors.ray_faces.back_faces`: the mask bit for bit, the sum up to its order)."""
    positive, angle, mask = _star_faces(np.ascontiguousarray(vertices, np.float64),
                                        checked_faces(faces, len(vertices), "star_faces"),
                                        np.ascontiguousarray(centroid, np.float64),
                                        np.ascontiguousarray(origin, np.float64))
    return bool(positive), float(angle), mask
