"""Overlaps of KITTI boxes, float64, vectorised over box pairs.

Frames and units: image boxes are (left, top, right, bottom) in image-2 pixels. 3D boxes are
(N, 7) arrays in label-file column order ``h, w, l, x, y, z, ry``: dimensions in m, the bottom
centre in the rectified camera frame (x right, y down, z forward; m) and the yaw about rect y
(rad). The bird's-eye view (BEV) is the rect x-z plane; a box's footprint there is the rectangle
of length ``l`` and width ``w`` around (x, z), turned like the devkit's ``toPolygon``:
``x = x0 + cos(ry) u + sin(ry) v``, ``z = z0 - sin(ry) u + cos(ry) v`` for local (u, v).

Footprint intersections are exact convex-polygon clipping (Sutherland-Hodgman against the four
half-planes of the other rectangle) in coordinates relative to one box's centre, so boxes far
from the origin keep their precision, identical boxes give 1 and nothing returns NaN.

Overlap "criteria" follow the devkit: ``"union"`` is IoU, ``"det"`` is the intersection over the
first (detection) box's own area/volume, used for DontCare regions.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

Criterion = Literal["union", "det"]

#: Column layout of a 3D box array (label-file order).
BOX_COLUMNS = ("h", "w", "l", "x", "y", "z", "ry")
_H, _W, _L, _X, _Y, _Z, _RY = range(7)
#: Vertex capacity of a clipped polygon (a quadrilateral clipped by 4 half-planes has <= 8).
_CAPACITY = 16


def _safe_ratio(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    """num / den where den > 0 and both are finite, else 0; clipped to [0, 1]."""
    ok = (den > 0) & np.isfinite(num) & np.isfinite(den)
    out = np.divide(num, den, out=np.zeros(np.broadcast(num, den).shape), where=ok)
    return np.clip(out, 0.0, 1.0)


def image_overlap(det: np.ndarray, gt: np.ndarray, criterion: Criterion = "union") -> np.ndarray:
    """Overlap of paired image boxes (P, 4) -> (P,), computed with the devkit's operations.

    ``"union"``: intersection / (det area + gt area - intersection); ``"det"``: intersection /
    det area. Pairs whose intersection has no positive width and height overlap 0.
    """
    a = np.asarray(det, dtype=np.float64).reshape(-1, 4)
    b = np.asarray(gt, dtype=np.float64).reshape(-1, 4)
    w = np.minimum(a[:, 2], b[:, 2]) - np.maximum(a[:, 0], b[:, 0])
    h = np.minimum(a[:, 3], b[:, 3]) - np.maximum(a[:, 1], b[:, 1])
    hit = (w > 0) & (h > 0)
    inter = np.where(hit, w * h, 0.0)
    a_area = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    if criterion == "det":
        return np.where(hit, _safe_ratio(inter, a_area), 0.0)
    b_area = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    return np.where(hit, _safe_ratio(inter, a_area + b_area - inter), 0.0)


def footprint_corners(boxes: np.ndarray, origin: np.ndarray | None = None) -> np.ndarray:
    """BEV footprint corners (N, 4, 2) as (x, z) in m, counter-clockwise in the x-z plane.

    Args:
        boxes: (N, 7) boxes ``h, w, l, x, y, z, ry``; negative l or w are taken by magnitude
            (the devkit's DontCare lines carry -1 dimensions).
        origin: (N, 2) or (2,) point (x, z) subtracted from the centres before the corners are
            built, to keep precision far from the rect origin. Default: no shift.
    """
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    half_l = np.abs(b[:, _L]) / 2
    half_w = np.abs(b[:, _W]) / 2
    u = np.stack([half_l, -half_l, -half_l, half_l], axis=1)  # local length axis
    v = np.stack([half_w, half_w, -half_w, -half_w], axis=1)  # local width axis
    c, s = np.cos(b[:, _RY])[:, None], np.sin(b[:, _RY])[:, None]
    cx, cz = b[:, _X], b[:, _Z]
    if origin is not None:
        o = np.broadcast_to(np.asarray(origin, dtype=np.float64), (len(b), 2))
        cx, cz = cx - o[:, 0], cz - o[:, 1]
    return np.stack([cx[:, None] + c * u + s * v, cz[:, None] - s * u + c * v], axis=2)


def polygon_area(poly: np.ndarray, count: np.ndarray | None = None) -> np.ndarray:
    """Shoelace area of polygons (P, K, 2) with ``count`` (P,) valid leading vertices (default K)."""
    p = np.asarray(poly, dtype=np.float64)
    k = np.arange(p.shape[1])
    n = np.full(len(p), p.shape[1]) if count is None else np.asarray(count)
    nxt = np.where(k + 1 < n[:, None], k + 1, 0)
    q = np.take_along_axis(p, nxt[..., None], axis=1)
    cross = p[..., 0] * q[..., 1] - p[..., 1] * q[..., 0]
    return 0.5 * np.where(k < n[:, None], cross, 0.0).sum(axis=1)


def clip_convex(subject: np.ndarray, clip: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """Intersect convex polygons pairwise by Sutherland-Hodgman clipping.

    Args:
        subject: (P, 4, 2) counter-clockwise quadrilaterals.
        clip: (P, 4, 2) counter-clockwise convex quadrilaterals (the clipping half-planes).
    Returns:
        (vertices (P, K, 2) with K <= 16, vertex counts (P,), overflow flag). Points on a clip edge
        count as inside. The flag is True if some row produced more vertices than the capacity
        (only possible through round-off on degenerate slivers; the extra vertices are dropped).
    """
    subj = np.asarray(subject, dtype=np.float64)
    cl = np.asarray(clip, dtype=np.float64)
    n_rows = len(subj)
    rows = np.arange(n_rows)
    x, y = subj[..., 0].copy(), subj[..., 1].copy()
    count = np.full(n_rows, subj.shape[1])
    overflow = False
    for e in range(cl.shape[1]):
        ax, ay = cl[:, e, 0:1], cl[:, e, 1:2]
        ex = cl[:, (e + 1) % cl.shape[1], 0:1] - ax
        ey = cl[:, (e + 1) % cl.shape[1], 1:2] - ay
        cap_in = x.shape[1]
        valid = np.arange(cap_in) < count[:, None]
        # Signed area of (edge, p - a): >= 0 on or left of the edge, i.e. inside for CCW clips.
        d = ex * (y - ay) - ey * (x - ax)
        last = np.maximum(count - 1, 0)
        x_next, y_next, d_next = np.roll(x, -1, axis=1), np.roll(y, -1, axis=1), np.roll(d, -1, axis=1)
        x_next[rows, last], y_next[rows, last], d_next[rows, last] = x[:, 0], y[:, 0], d[:, 0]
        inside = d >= 0
        keep = valid & inside
        crossing = valid & (inside != (d_next >= 0))
        denom = np.where(crossing, d - d_next, 1.0)  # nonzero: d and d_next straddle 0
        t = np.clip(np.where(crossing, d / denom, 0.0), 0.0, 1.0)
        cand_x = np.stack([x, x + t * (x_next - x)], axis=2).reshape(n_rows, 2 * cap_in)
        cand_y = np.stack([y, y + t * (y_next - y)], axis=2).reshape(n_rows, 2 * cap_in)
        take = np.stack([keep, crossing], axis=2).reshape(n_rows, 2 * cap_in)
        cap_out = min(2 * cap_in, _CAPACITY)
        slot = np.cumsum(take, axis=1) - 1
        count = take.sum(axis=1)
        if count.size and count.max() > cap_out:
            overflow = True
            take &= slot < cap_out
            count = np.minimum(count, cap_out)
        r, c = np.nonzero(take)
        x, y = np.zeros((n_rows, cap_out)), np.zeros((n_rows, cap_out))
        x[r, slot[r, c]], y[r, slot[r, c]] = cand_x[r, c], cand_y[r, c]
    return np.stack([x, y], axis=2), count, overflow


def _footprints_pair(det: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Det and GT footprint corners relative to the GT centre (precision far from the origin)."""
    origin = gt[:, [_X, _Z]]
    return footprint_corners(det, origin), footprint_corners(gt, origin)


def _may_touch(det: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """False where the footprints' circumscribed circles are apart (then they surely miss)."""
    r = 0.5 * (np.hypot(det[:, _L], det[:, _W]) + np.hypot(gt[:, _L], gt[:, _W]))
    dist2 = (det[:, _X] - gt[:, _X]) ** 2 + (det[:, _Z] - gt[:, _Z]) ** 2
    return ~(dist2 > (r * (1 + 1e-9)) ** 2)


def footprint_intersection(det: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Intersection area of paired footprints and the two footprint areas, (P,) each, m^2.

    Footprint areas are the shoelace areas of the corners (what the devkit's polygon area gives),
    or |l w| for pairs whose footprints cannot touch.
    """
    det = np.asarray(det, dtype=np.float64).reshape(-1, 7)
    gt = np.asarray(gt, dtype=np.float64).reshape(-1, 7)
    area_d = np.abs(det[:, _L] * det[:, _W])
    area_g = np.abs(gt[:, _L] * gt[:, _W])
    inter = np.zeros(len(det))
    near = np.flatnonzero(_may_touch(det, gt))
    if near.size:
        cd, cg = _footprints_pair(det[near], gt[near])
        area_d[near], area_g[near] = polygon_area(cd), polygon_area(cg)
        poly, count, _ = clip_convex(cd, cg)
        inter[near] = polygon_area(poly, count)
    inter = np.nan_to_num(inter, nan=0.0, posinf=0.0, neginf=0.0)
    inter = np.clip(inter, 0.0, np.maximum(np.minimum(area_d, area_g), 0.0))
    return inter, area_d, area_g


def bev_ratio(inter: np.ndarray, area_d: np.ndarray, area_g: np.ndarray,
              criterion: Criterion = "union") -> np.ndarray:
    """BEV overlap from a footprint intersection and the footprint areas (m^2), in [0, 1]."""
    if criterion == "det":
        return _safe_ratio(inter, area_d)
    return _safe_ratio(inter, area_d + area_g - inter)


def box3d_ratio(inter_area: np.ndarray, area_d: np.ndarray, area_g: np.ndarray, det: np.ndarray, gt: np.ndarray,
                criterion: Criterion = "union") -> np.ndarray:
    """3D overlap of paired boxes (P, 7) from their footprint intersection and areas (m^2), in [0, 1].

    A box spans rect y in [y - h, y] (y points down, y is the bottom). The intersection volume is
    the footprint intersection times the y overlap; volumes are the y extent times the footprint
    area (the devkit's ``h * l * w`` up to round-off, and exactly the intersection for identical
    boxes).
    """
    top_d, top_g = det[:, _Y] - det[:, _H], gt[:, _Y] - gt[:, _H]
    inter = inter_area * np.maximum(0.0, np.minimum(det[:, _Y], gt[:, _Y]) - np.maximum(top_d, top_g))
    vol_d = area_d * (det[:, _Y] - top_d)
    if criterion == "det":
        return _safe_ratio(inter, vol_d)
    vol_g = area_g * (gt[:, _Y] - top_g)
    return _safe_ratio(inter, vol_d + vol_g - inter)


def bev_overlap(det: np.ndarray, gt: np.ndarray, criterion: Criterion = "union") -> np.ndarray:
    """BEV overlap of paired boxes (P, 7) -> (P,) in [0, 1] (see the module doc for criteria)."""
    return bev_ratio(*footprint_intersection(det, gt), criterion)


def box3d_overlap(det: np.ndarray, gt: np.ndarray, criterion: Criterion = "union") -> np.ndarray:
    """3D overlap of paired boxes (P, 7) -> (P,) in [0, 1] (see :func:`box3d_ratio`)."""
    det = np.asarray(det, dtype=np.float64).reshape(-1, 7)
    gt = np.asarray(gt, dtype=np.float64).reshape(-1, 7)
    return box3d_ratio(*footprint_intersection(det, gt), det, gt, criterion)


def _all_pairs(a: np.ndarray, b: np.ndarray, cols: int) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    a = np.asarray(a, dtype=np.float64).reshape(-1, cols)
    b = np.asarray(b, dtype=np.float64).reshape(-1, cols)
    return np.repeat(a, len(b), axis=0), np.tile(b, (len(a), 1)), (len(a), len(b))


def bev_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, M) BEV IoU between every box of ``a`` (N, 7) and of ``b`` (M, 7)."""
    pa, pb, shape = _all_pairs(a, b, 7)
    return bev_overlap(pa, pb).reshape(shape)


def box3d_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, M) 3D IoU between every box of ``a`` (N, 7) and of ``b`` (M, 7)."""
    pa, pb, shape = _all_pairs(a, b, 7)
    return box3d_overlap(pa, pb).reshape(shape)


def image_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, M) image-box IoU between every box of ``a`` (N, 4) and of ``b`` (M, 4)."""
    pa, pb, shape = _all_pairs(a, b, 4)
    return image_overlap(pa, pb).reshape(shape)
