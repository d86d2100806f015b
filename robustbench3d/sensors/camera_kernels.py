"""Compiled (numba) kernels of the camera render: the per-face cull and the fused shading (conventions:
:mod:`robustbench3d.sensors.array_kernels`).

* :func:`face_cull` is the per-face part of :meth:`robustbench3d.sensors.camera_cull.FaceCull.of` (the numpy
  reference is ``_face_cull_reference`` of ``tests/sensors/test_sensors_camera_render.py``); :func:`touching_faces` is
  :meth:`~robustbench3d.sensors.camera_cull.FaceCull.touching` (``compiled=False``: its numpy code).
* :func:`shade_exposure`, :func:`shade_tone` and :func:`shade_grads` are the per-hit arithmetic of the fused
  shading :class:`~robustbench3d.sensors.camera_shade.ShadeHits` (forward and backward).

The camera's search of the nearest face per sample (the walk of each face's box and spans) is
:func:`robustbench3d.sensors.ray_kernels.walk_faces`, beside the ray test it shares with the LiDAR.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from robustbench3d.sensors.array_kernels import checked_faces, checked_index


@njit(cache=True, nogil=True, error_model="numpy")
def _face_cull(uv: np.ndarray, depth: np.ndarray, verts: np.ndarray, faces: np.ndarray, skip: np.ndarray,
               centre: np.ndarray, near: float, box_margin: float, span_margin: float, eps64: float, depth_ratio: float
               ) -> tuple:  # pragma: no cover - compiled
    n = faces.shape[0]
    lo, hi = np.empty((n, 2)), np.empty((n, 2))
    crossing, unreachable, tight = np.zeros(n, np.bool_), np.zeros(n, np.bool_), np.zeros(n, np.bool_)
    edge_fn = np.zeros((n, 3, 3))
    edge = np.empty((3, 2))
    e3 = np.empty((3, 3))
    p = np.empty((3, 2))
    v3 = np.empty((3, 3))
    for f in range(n):
        # a skipped face reads no vertex: unreachable, its box 0 -/+ the margin (what the formulas below give it)
        if skip[f]:
            unreachable[f] = True
        else:
            d0, d1, d2 = depth[faces[f, 0]], depth[faces[f, 1]], depth[faces[f, 2]]
            unreachable[f] = (d0 <= 0) and (d1 <= 0) and (d2 <= 0)
            crossing[f] = ((d0 <= near) or (d1 <= near) or (d2 <= near)) and not unreachable[f]
        ahead = not (crossing[f] or unreachable[f])
        if ahead:
            for i in range(3):
                for a in range(2):
                    p[i, a] = uv[faces[f, i], a]
        for a in range(2):
            if ahead:
                x0, x1, x2 = p[0, a], p[1, a], p[2, a]
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
        for i in range(3):
            for c in range(3):
                v3[i, c] = verts[faces[f, i], c]
        for k in range(3):  # edge k runs from vertex (k + 1) % 3 to (k + 2) % 3
            i, j = (k + 1) % 3, (k + 2) % 3
            edge[k, 0], edge[k, 1] = p[j, 0] - p[i, 0], p[j, 1] - p[i, 1]
            for c in range(3):
                e3[k, c] = v3[j, c] - v3[i, c]
        area2 = edge[1, 0] * edge[2, 1] - edge[1, 1] * edge[2, 0]
        # n3 = e3[2] x (-e3[1])
        b0, b1, b2 = -e3[1, 0], -e3[1, 1], -e3[1, 2]
        n0 = e3[2, 1] * b2 - e3[2, 2] * b1
        n1 = e3[2, 2] * b0 - e3[2, 0] * b2
        n2 = e3[2, 0] * b1 - e3[2, 1] * b0
        r0 = (v3[0, 0] + v3[1, 0] + v3[2, 0]) / 3 - centre[0]
        r1 = (v3[0, 1] + v3[1, 1] + v3[2, 1]) / 3 - centre[1]
        r2 = (v3[0, 2] + v3[1, 2] + v3[2, 2]) / 3 - centre[2]
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
        d0, d1, d2 = depth[faces[f, 0]], depth[faces[f, 1]], depth[faces[f, 2]]
        ok = ((np.maximum(np.maximum(d0, d1), d2) <= depth_ratio * np.minimum(np.minimum(d0, d1), d2))
              and (np.abs(area2) > 1e-6 * np.maximum(np.maximum(l0, l1), l2)) and np.isfinite(delta))
        sign = np.sign(area2)
        widen = (delta if ok else 0.0) * np.abs(area2)
        for k in range(3):
            i = (k + 1) % 3
            edge_fn[f, k, 0] = -edge[k, 1] * sign
            edge_fn[f, k, 1] = edge[k, 0] * sign
            edge_fn[f, k, 2] = (edge[k, 1] * p[i, 0] - edge[k, 0] * p[i, 1]) * sign + widen
        tight[f] = ok
    return lo, hi, crossing, unreachable, edge_fn, tight


def face_cull(uv: np.ndarray, depth: np.ndarray, vertices: np.ndarray, faces: np.ndarray, skip: np.ndarray,
              centre: np.ndarray, *, near: float, box_margin: float, span_margin: float, eps64: float,
              depth_ratio: float) -> tuple[np.ndarray, ...]:
    """Per face: (lo, hi, crossing, unreachable, edge, tight) of
    :class:`robustbench3d.sensors.camera_cull.FaceCull` (its docstring) of ``faces`` (F, 3) int64 (checked here)
    into the vertices' projections ``uv`` (V, 2) (pixels), camera depths ``depth`` (V,) and rect positions
    ``vertices`` (V, 3) (all float64), the mask ``skip`` (F,) of faces never hit (their vertices are not read) and
    the camera centre (3,); the constants as named there (``eps64``: 64 machine epsilons of the ray test's dtype).
    Each face reads its own vertices (no (F, 3, .) copies of them are made)."""
    n = len(depth)
    if uv.shape != (n, 2) or vertices.shape != (n, 3):
        raise ValueError(f"face_cull: field 'uv' / 'vertices': {uv.shape} and {vertices.shape} for {n} depths")
    return _face_cull(np.ascontiguousarray(uv, np.float64), np.ascontiguousarray(depth, np.float64),
                      np.ascontiguousarray(vertices, np.float64), checked_faces(faces, n, "face_cull"),
                      np.ascontiguousarray(skip, np.bool_), np.ascontiguousarray(centre, np.float64), near, box_margin,
                      span_margin, eps64, depth_ratio)


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
    haze (1 - fade) + fade (L0 + u dl1 + v dl2): :class:`~robustbench3d.sensors.camera_shade.ShadeHits`'
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
    """The tone curve and compositing of :class:`~robustbench3d.sensors.camera_shade.ShadeHits` per hit (K) and
    channel: y = 12.92 x where x <= 0.0031308, else 1.055 ``power`` - 0.055 (``power`` = max(x, 0.0031308)^(1/2.4),
    from numpy), its slope d y / d exposed (0 where y leaves [0, 1]) times the hit's ``weight`` (K,), and the sum
    per pixel (``owner`` (K,) into ``base`` (3, P)) of weight (clip(y, 0, 1) - base) in hit order: (acc (3, P),
    slope * weight (3, K)), numpy's arithmetic with the constants in the arrays' dtype."""
    dt = x.dtype.type
    consts = (dt(0.0031308), dt(12.92), dt(1.055), dt(0.055), dt(2.4), dt(0.0), dt(1.0))
    checked_index(owner, x.shape[1], base.shape[1], "shade_tone")
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
    of :class:`~robustbench3d.sensors.camera_shade.ShadeHits.backward`."""
    dt = gn.dtype.type
    checked_index(owner, len(u), gn.shape[1], "shade_grads")
    checked_index(slot, len(u), n_faces, "shade_grads")
    return _shade_grads(np.ascontiguousarray(gn), np.ascontiguousarray(owner, np.int64),
                        np.ascontiguousarray(slope_w), np.ascontiguousarray(fade), np.ascontiguousarray(emh),
                        np.ascontiguousarray(dl1), np.ascontiguousarray(dl2), np.ascontiguousarray(u),
                        np.ascontiguousarray(v), np.ascontiguousarray(slot, np.int64), n_faces,
                        dt(-1.0 / haze_distance), dt(1.0))
