"""Box conventions, centre-heatmap targets (encode) and their decoding (numpy, float64 geometry).

Velodyne boxes are (K, 7) float64 rows ``x, y, z, l, w, h, yaw``: the box's centre (velodyne frame,
m), length along the heading, width, height (m), and yaw about velodyne z (rad, 0 along +x, counter-
clockwise). KITTI labels (rect frame) give the bottom centre and ``rotation_y`` about rect y; the
heading of ``rotation_y`` is rect (cos ry, 0, −sin ry), i.e. velodyne yaw = −ry − π/2 (the rect axes are
the velodyne ones up to the calibration's small tilt, which the yaw conversion ignores, as KITTI does).

Output cell (row j, column i) of a map at stride ``out_stride`` pillars covers
``x in [x_min + i·c, x_min + (i+1)·c)``, ``y in [y_min + j·c, ...)`` with ``c = pillar_size·out_stride``.
A box is encoded at the cell holding its centre: offset (dx, dy) = centre/c − (i, j) in [0, 1), z,
log l, log w, log h, sin yaw, cos yaw; the heatmap is a Gaussian around that cell (CenterPoint).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from robustbench3d.kitti.calib import Calibration
from robustbench3d.kitti.labels import Labels
from robustbench3d.victims.pointpillars.config import PointPillarsConfig, output_shape

#: Heatmap Gaussian: CenterPoint's minimum overlap and minimum radius (output cells).
MIN_OVERLAP = 0.1
MIN_RADIUS = 2


def wrap_angle(a: np.ndarray | float) -> np.ndarray:
    """Angle(s) wrapped to [−π, π)."""
    return (np.asarray(a, dtype=np.float64) + np.pi) % (2 * np.pi) - np.pi


def labels_to_velo_boxes(labels: Labels, calib: Calibration, types: tuple[str, ...] = ("Car",)) -> np.ndarray:
    """(K, 7) velodyne boxes of the labels of ``types`` (rect bottom centre -> velodyne centre)."""
    sel = labels.of_types(types)
    h, w, l_ = (sel.dimensions[:, i] for i in range(3))
    centre_rect = sel.location - np.stack([np.zeros_like(h), h / 2, np.zeros_like(h)], axis=1)
    centre = calib.rect_to_velo_points(centre_rect) if len(sel) else np.zeros((0, 3))
    yaw = wrap_angle(-sel.rotation_y - np.pi / 2)
    return np.concatenate([centre, np.stack([l_, w, h, yaw], axis=1)], axis=1).reshape(-1, 7)


def velo_boxes_to_rect(boxes: np.ndarray, calib: Calibration) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(location (K, 3) rect bottom centre, dimensions (K, 3) h w l, rotation_y (K,)) of velodyne boxes."""
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    centre = calib.velo_to_rect_points(b[:, :3]) if len(b) else np.zeros((0, 3))
    loc = centre + np.stack([np.zeros(len(b)), b[:, 5] / 2, np.zeros(len(b))], axis=1)
    return loc, b[:, [5, 4, 3]], wrap_angle(-b[:, 6] - np.pi / 2)


def gaussian_radius(length: float, width: float, min_overlap: float = MIN_OVERLAP) -> float:
    """CenterNet's radius (in the units of the sizes) keeping IoU >= ``min_overlap`` (smallest root)."""
    a1, b1, c1 = 1, length + width, width * length * (1 - min_overlap) / (1 + min_overlap)
    r1 = (b1 + math.sqrt(b1 ** 2 - 4 * a1 * c1)) / 2
    a2, b2, c2 = 4, 2 * (length + width), (1 - min_overlap) * width * length
    r2 = (b2 + math.sqrt(b2 ** 2 - 4 * a2 * c2)) / 2
    a3, b3, c3 = 4 * min_overlap, -2 * min_overlap * (length + width), (min_overlap - 1) * width * length
    r3 = (b3 + math.sqrt(b3 ** 2 - 4 * a3 * c3)) / 2
    return min(r1, r2, r3)


@dataclass(frozen=True)
class CentreTargets:
    """Training targets of one frame: heatmap (H, W) float32 in [0, 1]; for each of K boxes the flat
    output-cell index (K,) int64 and the regression row (K, 8) float32
    (dx, dy, z, log l, log w, log h, sin yaw, cos yaw)."""

    heatmap: np.ndarray
    index: np.ndarray
    regression: np.ndarray


def cell_size(cfg: PointPillarsConfig) -> float:
    """Side of an output cell (m)."""
    return cfg.grid.pillar_size * cfg.out_stride


def encode(boxes: np.ndarray, cfg: PointPillarsConfig) -> CentreTargets:
    """Targets of velodyne ``boxes`` (K, 7); boxes whose centre is outside the grid are left out.
    Two boxes in one cell: the later one's regression wins (it is listed once)."""
    g, c = cfg.grid, cell_size(cfg)
    h, w = output_shape(cfg)
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    u, v = (b[:, 0] - g.x_min) / c, (b[:, 1] - g.y_min) / c
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h) & (b[:, 0] < g.x_max) & (b[:, 1] < g.y_max)
    b, u, v = b[inside], u[inside], v[inside]
    i, j = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    heat = np.zeros((h, w), dtype=np.float64)
    for k in range(len(b)):
        r = max(MIN_RADIUS, int(gaussian_radius(b[k, 3] / c, b[k, 4] / c)))
        sigma = (2 * r + 1) / 6
        jj, ii = np.mgrid[max(j[k] - r, 0):min(j[k] + r + 1, h), max(i[k] - r, 0):min(i[k] + r + 1, w)]
        g_k = np.exp(-((ii - i[k]) ** 2 + (jj - j[k]) ** 2) / (2 * sigma ** 2))
        heat[jj, ii] = np.maximum(heat[jj, ii], g_k)
    reg = np.stack([u - i, v - j, b[:, 2], np.log(b[:, 3]), np.log(b[:, 4]), np.log(b[:, 5]),
                    np.sin(b[:, 6]), np.cos(b[:, 6])], axis=1)
    flat = j * w + i
    _, last = np.unique(flat[::-1], return_index=True)
    keep = np.sort(len(flat) - 1 - last)
    return CentreTargets(heat.astype(np.float32), flat[keep], reg[keep].astype(np.float32).reshape(-1, 8))


def decode_cells(out: np.ndarray, rows: np.ndarray, cols: np.ndarray, cfg: PointPillarsConfig) -> np.ndarray:
    """(K, 7) velodyne boxes decoded (float64) from the (9, H, W) output at cells (rows, cols)."""
    g, c = cfg.grid, cell_size(cfg)
    o = np.asarray(out, dtype=np.float64)[:, rows, cols]
    x = g.x_min + (cols + o[1]) * c
    y = g.y_min + (rows + o[2]) * c
    return np.stack([x, y, o[3], np.exp(o[4]), np.exp(o[5]), np.exp(o[6]), np.arctan2(o[7], o[8])], axis=1)


def peaks(heatmap_logits: np.ndarray, threshold_logit: float, max_detections: int) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of the 3×3 local maxima of the (H, W) logits above ``threshold_logit``, best first
    (ties broken by flat index), at most ``max_detections``. A cell is a peak when no 3×3 neighbour is
    larger (plateaus keep every cell)."""
    z = np.asarray(heatmap_logits, dtype=np.float64)
    padded = np.pad(z, 1, constant_values=-np.inf)
    h, w = z.shape
    neigh = np.max(np.stack([padded[dy:dy + h, dx:dx + w] for dy in range(3) for dx in range(3)]), axis=0)
    flat = np.flatnonzero(((z >= neigh) & (z > threshold_logit)).reshape(-1))
    order = np.lexsort((flat, -z.reshape(-1)[flat]))[:max_detections]
    flat = flat[order]
    return flat // w, flat % w
