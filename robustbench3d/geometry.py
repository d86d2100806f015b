"""3D box geometry in the KITTI rectified camera frame (x right, y down, z forward; metres).

A KITTI box is (h, w, l) dimensions, the bottom-face centre ``location`` and ``rotation_y`` about
rect y; with ry = 0 the length runs along +x and the width along z. Corner order follows the
KITTI devkit's ``compute_box_3d``: 0-3 the bottom face, 4-7 the top face (y = -h), corner k+4
above corner k.
"""

from __future__ import annotations

import numpy as np

from robustbench3d.kitti.calib import Calibration

#: The 12 edges of a box as corner-index pairs.
BOX_EDGES = np.array([[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4],
                      [0, 4], [1, 5], [2, 6], [3, 7]])


def wrap_angle(a: np.ndarray | float) -> np.ndarray:
    """Map angles (rad) to [-pi, pi)."""
    return (np.asarray(a, dtype=np.float64) + np.pi) % (2 * np.pi) - np.pi


def roty(angle: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations about rect y: x' = c x + s z, z' = -s x + c z."""
    a = np.asarray(angle, dtype=np.float64).reshape(-1)
    c, s = np.cos(a), np.sin(a)
    r = np.zeros((a.size, 3, 3))
    r[:, 0, 0], r[:, 0, 2], r[:, 1, 1], r[:, 2, 0], r[:, 2, 2] = c, s, 1.0, -s, c
    return r


def box_corners(dimensions: np.ndarray, location: np.ndarray, rotation_y: np.ndarray) -> np.ndarray:
    """Corners of KITTI boxes.

    Args:
        dimensions: (N, 3) h, w, l in m.
        location: (N, 3) bottom centre, rect frame, m.
        rotation_y: (N,) yaw in rad.
    Returns:
        (N, 8, 3) corners in the rect frame.
    """
    d = np.asarray(dimensions, dtype=np.float64).reshape(-1, 3)
    h, w, l = d[:, 0:1], d[:, 1:2], d[:, 2:3]
    x = np.concatenate([l, l, -l, -l, l, l, -l, -l], axis=1) / 2
    y = np.concatenate([0 * h] * 4 + [-h] * 4, axis=1)
    z = np.concatenate([w, -w, -w, w, w, -w, -w, w], axis=1) / 2
    local = np.stack([x, y, z], axis=2)  # (N, 8, 3)
    return np.einsum("nij,nkj->nki", roty(rotation_y), local) + np.asarray(location, np.float64).reshape(-1, 1, 3)


def points_in_boxes(points: np.ndarray, dimensions: np.ndarray, location: np.ndarray,
                    rotation_y: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """(P, N) bool: which rect-frame points (P, 3) lie inside each of N boxes (grown by ``margin`` m)."""
    pts = np.asarray(points, dtype=np.float64)[:, :3]
    d = np.asarray(dimensions, dtype=np.float64).reshape(-1, 3)
    loc = np.asarray(location, dtype=np.float64).reshape(-1, 3)
    rot = roty(rotation_y)  # local -> rect
    rel = pts[:, None, :] - loc[None, :, :]  # (P, N, 3)
    local = np.einsum("nji,pnj->pni", rot, rel)  # R^T (p - loc)
    h, w, l = d[:, 0], d[:, 1], d[:, 2]
    return (
        (np.abs(local[..., 0]) <= l / 2 + margin)
        & (local[..., 1] <= margin) & (local[..., 1] >= -h - margin)
        & (np.abs(local[..., 2]) <= w / 2 + margin)
    )


def alpha_from_rotation_y(rotation_y: np.ndarray, location: np.ndarray) -> np.ndarray:
    """Observation angle alpha = ry - atan2(x, z), wrapped to [-pi, pi)."""
    loc = np.asarray(location, dtype=np.float64).reshape(-1, 3)
    return wrap_angle(np.asarray(rotation_y, np.float64) - np.arctan2(loc[:, 0], loc[:, 2]))


def project_boxes_to_image(corners: np.ndarray, calib: Calibration, image_size: tuple[int, int],
                           near: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """2D boxes of 3D boxes: project, clipped to the image like KITTI labels.

    The box solid is first clipped at the plane rect z = ``near`` (edges crossing it are cut),
    so boxes reaching behind the camera project correctly.

    Args:
        corners: (N, 8, 3) rect-frame corners (see :func:`box_corners`).
        calib: supplies P2.
        image_size: (width, height) in pixels; boxes are clipped to [0, W-1] x [0, H-1].
    Returns:
        (boxes, valid): (N, 4) left, top, right, bottom pixels, and (N,) bool, False where the
        box lies entirely behind ``near`` or entirely outside the image (its row is zeros).
    """
    c = np.asarray(corners, dtype=np.float64).reshape(-1, 8, 3)
    n = c.shape[0]
    a, b = c[:, BOX_EDGES[:, 0]], c[:, BOX_EDGES[:, 1]]  # (N, 12, 3)
    za, zb = a[..., 2], b[..., 2]
    crosses = (za - near) * (zb - near) < 0
    denom = np.where(crosses, zb - za, 1.0)
    t = np.where(crosses, (near - za) / denom, 0.0)
    cut = a + t[..., None] * (b - a)  # (N, 12, 3) on the near plane where crosses
    pts = np.concatenate([c, cut], axis=1)  # (N, 20, 3)
    keep = np.concatenate([c[..., 2] >= near, crosses], axis=1)
    uv, _ = calib.rect_to_image(pts.reshape(-1, 3))
    uv = uv.reshape(n, 20, 2)
    big = np.inf
    umin = np.where(keep, uv[..., 0], big).min(axis=1)
    vmin = np.where(keep, uv[..., 1], big).min(axis=1)
    umax = np.where(keep, uv[..., 0], -big).max(axis=1)
    vmax = np.where(keep, uv[..., 1], -big).max(axis=1)
    w, h = image_size
    valid = keep.any(axis=1) & (umax >= 0) & (vmax >= 0) & (umin <= w - 1) & (vmin <= h - 1)
    boxes = np.stack([np.clip(umin, 0, w - 1), np.clip(vmin, 0, h - 1),
                      np.clip(umax, 0, w - 1), np.clip(vmax, 0, h - 1)], axis=1)
    boxes[~valid] = 0.0
    return boxes, valid
