"""Frustum extraction for Frustum-PointNet v1 (reference §1.3-§1.4), numpy only.

Shared by the torch model path, the training data and a later ONNX path.

Frames: *rect* is the rectified camera-0 frame (x right, y down, z forward; m). The *frustum
frame* is rect rotated about y by ``rot_angle = π/2 + frustum_angle``:
``x' = x·cos a − z·sin a``, ``z' = x·sin a + z·cos a`` (y unchanged), which maps the ray through
the 2D-box centre onto +z. Headings in the frustum frame are ``ry − rot_angle``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from robustbench3d.kitti.calib import Calibration

#: Points with velodyne x at or below this (m) are outside the camera FOV (``clip_distance``).
CLIP_DISTANCE = 2.0
#: Depth (m) at which the 2D-box centre pixel is back-projected for the frustum angle.
CENTER_DEPTH = 20.0


@dataclass(frozen=True)
class ProjectedScan:
    """A scan prepared for frustum extraction (computed once per frame).

    Attributes:
        points_rect: (P, 4) float64 rect xyz (m) and reflectance, in scan order.
        uv: (P, 2) image-2 pixel coordinates.
        in_fov: (P,) bool, inside [0, W) x [0, H) and velodyne x > :data:`CLIP_DISTANCE`.
        in_front: (P,) bool, velodyne x > :data:`CLIP_DISTANCE` (the FOV test's depth clause: in front of
            the camera, wherever it projects); None if unknown (then no extra rows can be added).
    """

    points_rect: np.ndarray
    uv: np.ndarray
    in_fov: np.ndarray
    in_front: np.ndarray | None = None

    @cached_property
    def fov_rows(self) -> tuple[np.ndarray, np.ndarray]:
        """The rows inside the FOV (ascending int64) and their (F, 2) pixel coordinates: what each
        box's test needs, computed once per frame rather than once per box over the whole scan."""
        rows = np.flatnonzero(self.in_fov)
        return rows, self.uv[rows]


@dataclass(frozen=True)
class Frustum:
    """The points of one 2D box's frustum, before rotation and resampling.

    Attributes:
        indices: (M,) int64 indices into the scan (scan order).
        points: (M, 4) float64 rect xyz (m) and reflectance.
        box2d: (4,) left, top, right, bottom (image-2 pixels) that defined it.
        frustum_angle: -atan2(z, x) of the back-projected box centre (rad).
    """

    indices: np.ndarray
    points: np.ndarray
    box2d: np.ndarray
    frustum_angle: float

    @property
    def rot_angle(self) -> float:
        """Rotation about rect y (rad) taking rect to the frustum frame."""
        return rotation_angle(self.frustum_angle)

    def __len__(self) -> int:
        return len(self.indices)


def fov_mask(points_velo_x: np.ndarray, uv: np.ndarray, image_size: tuple[int, int],
             clip_distance: float = CLIP_DISTANCE) -> np.ndarray:
    """(P,) bool: projection inside [0, W) x [0, H) and velodyne x > ``clip_distance`` m."""
    w, h = image_size
    return ((uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
            & (np.asarray(points_velo_x) > clip_distance))


def project_scan(scan: np.ndarray, calib: Calibration, image_size: tuple[int, int],
                 clip_distance: float = CLIP_DISTANCE) -> ProjectedScan:
    """Transform a velodyne scan (P, 4) to rect, project it with P2 and mark the image FOV."""
    scan = np.asarray(scan)
    rect = calib.velo_to_rect_points(scan[:, :3])
    uv, _ = calib.rect_to_image(rect)
    points = np.concatenate([rect, scan[:, 3:4].astype(np.float64)], axis=1)
    return ProjectedScan(points, uv, fov_mask(scan[:, 0], uv, image_size, clip_distance),
                         np.asarray(scan[:, 0]) > clip_distance)


def project_rect_points(points_rect: np.ndarray, calib: Calibration, image_size: tuple[int, int],
                        clip_distance: float = CLIP_DISTANCE) -> ProjectedScan:
    """Like :func:`project_scan` for points already in rect (P, 4); the velodyne-x clip is applied
    after transforming back to the velodyne frame."""
    pts = np.asarray(points_rect, dtype=np.float64)
    uv, _ = calib.rect_to_image(pts[:, :3])
    velo_x = calib.rect_to_velo_points(pts[:, :3])[:, 0]
    return ProjectedScan(pts, uv, fov_mask(velo_x, uv, image_size, clip_distance), velo_x > clip_distance)


def frustum_angle(box2d: np.ndarray, calib: Calibration, depth: float = CENTER_DEPTH) -> float:
    """-atan2(z, x) of the 2D-box centre pixel back-projected to rect depth ``depth`` m.

    Uses the original code's back-projection x = (u − c_u)·z/f_u + b_x with
    b_x = −P2[0,3]/f_u (which ignores P2[2,3], a few mm in KITTI).
    """
    xmin, _, xmax, _ = np.asarray(box2d, dtype=np.float64).reshape(4)
    fu, cu = calib.P2[0, 0], calib.P2[0, 2]
    u = (xmin + xmax) / 2.0
    x = (u - cu) * depth / fu + (-calib.P2[0, 3] / fu)
    return float(-np.arctan2(depth, x))


def rotation_angle(angle_of_frustum: float) -> float:
    """``rot_angle = π/2 + frustum_angle`` (rad)."""
    return float(np.pi / 2 + angle_of_frustum)


def box_mask(uv: np.ndarray, box2d: np.ndarray) -> np.ndarray:
    """(P,) bool: xmin <= u < xmax and ymin <= v < ymax."""
    xmin, ymin, xmax, ymax = np.asarray(box2d, dtype=np.float64).reshape(4)
    return (uv[:, 0] >= xmin) & (uv[:, 0] < xmax) & (uv[:, 1] >= ymin) & (uv[:, 1] < ymax)


def extract_frustum(projected: ProjectedScan, box2d: np.ndarray, calib: Calibration,
                    extra_rows: np.ndarray | None = None) -> Frustum:
    """The FOV points whose projection falls inside ``box2d`` (half-open), and the frustum angle.

    ``extra_rows`` (int64 rows of the scan, e.g. :attr:`~robustbench3d.victims.base.Proposals.extra_points`)
    adds those of them in front of the camera (``projected.in_front``) wherever they project; the frustum
    keeps scan order and holds each row once. None or empty: the box's points alone.
    """
    box = np.asarray(box2d, dtype=np.float64).reshape(4)
    if extra_rows is not None and len(extra_rows):
        idx = np.flatnonzero((projected.in_fov & box_mask(projected.uv, box)) | _extra_mask(projected, extra_rows))
    else:
        rows, uv = projected.fov_rows
        idx = rows[box_mask(uv, box)]
    return Frustum(idx.astype(np.int64), projected.points_rect[idx], box, frustum_angle(box, calib))


def _extra_mask(projected: ProjectedScan, extra_rows: np.ndarray) -> np.ndarray:
    """(P,) bool: the rows ``extra_rows`` that are in front of the camera (ValueError for rows outside the scan
    or a scan whose ``in_front`` is unknown)."""
    rows = np.asarray(extra_rows).reshape(-1)
    count = len(projected.points_rect)
    if rows.dtype.kind not in "iu" or rows.min() < 0 or rows.max() >= count:
        raise ValueError(f"extra frustum rows must be integer rows of the {count}-point scan, got "
                         f"{rows.dtype} in [{rows.min()}, {rows.max()}]")
    if projected.in_front is None:
        raise ValueError("extra frustum rows need ProjectedScan.in_front (project_scan / project_rect_points set it)")
    mask = np.zeros(count, dtype=bool)
    mask[rows] = True
    return mask & projected.in_front


def rotate_to_frustum(points: np.ndarray, rot_angle: float) -> np.ndarray:
    """Rotate (…, ≥3) rect points about y by ``rot_angle`` into the frustum frame (copy)."""
    out = np.array(points, dtype=np.float64, copy=True)
    c, s = np.cos(rot_angle), np.sin(rot_angle)
    x, z = out[..., 0].copy(), out[..., 2].copy()
    out[..., 0] = c * x - s * z
    out[..., 2] = s * x + c * z
    return out


def rotate_from_frustum(points: np.ndarray, rot_angle: float) -> np.ndarray:
    """Inverse of :func:`rotate_to_frustum`."""
    return rotate_to_frustum(points, -rot_angle)


def resample_indices(count: int, num_points: int, rng: np.random.Generator) -> np.ndarray:
    """``num_points`` indices drawn uniformly with replacement from ``range(count)`` (count >= 1)."""
    if count < 1:
        raise ValueError("cannot resample an empty frustum")
    return rng.integers(0, count, size=num_points, dtype=np.int64)


def perturb_box2d(box2d: np.ndarray, rng: np.random.Generator, ratio: float = 0.1) -> np.ndarray:
    """Training augmentation of a 2D box (§1.3 step 7): centre shifted by U(−r, r)·w and
    U(−r, r)·h, width and height rescaled independently by U(1 − r, 1 + r)."""
    xmin, ymin, xmax, ymax = np.asarray(box2d, dtype=np.float64).reshape(4)
    w, h = xmax - xmin, ymax - ymin
    cx, cy = (xmin + xmax) / 2, (ymin + ymax) / 2
    u = rng.random(4)
    cx2 = cx + w * ratio * (2 * u[0] - 1)
    cy2 = cy + h * ratio * (2 * u[1] - 1)
    h2 = h * (1 + 2 * ratio * u[2] - ratio)
    w2 = w * (1 + 2 * ratio * u[3] - ratio)
    return np.array([cx2 - w2 / 2, cy2 - h2 / 2, cx2 + w2 / 2, cy2 + h2 / 2])
