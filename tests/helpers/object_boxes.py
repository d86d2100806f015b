"""The object record's image boxes computed independently of the library: the object box's corners, their
projection under P2 and the clipped extent, written out with plain numpy (references of the frustum-protocol
tests, ``tests/attacks/test_frustum_protocols.py`` and ``tests/trust/test_trust_integrity.py``)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from kitti_files import calib_p2, image_size, label_rows

from robustbench3d.attacks.object import BOUNDS, template_vertices
from robustbench3d.attacks.record import EMPTY_BOX

#: The camera's near plane (m): object corners nearer than this are behind it.
NEAR = 0.1


def ry_matrix(a: float) -> np.ndarray:
    """KITTI yaw about rect y (x' = c x + s z, z' = -s x + c z), written out."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def project(p2: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """(N, 2) pixel coordinates of (N, 3) rect points under the 3x4 matrix ``p2``."""
    h = pts @ p2[:, :3].T + p2[:, 3]
    return h[:, :2] / h[:, 2:3]


def cube_corners(centre: np.ndarray, rotation: np.ndarray, half: np.ndarray) -> np.ndarray:
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
    return (signs * half) @ rotation.T + centre


def extent_box(uv: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """The clipped extent of points all in front of the camera; the empty box when it misses the image."""
    w, h = size
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    if hi[0] < 0 or hi[1] < 0 or lo[0] > w - 1 or lo[1] > h - 1:
        return np.array(EMPTY_BOX)
    return np.array([np.clip(lo[0], 0, w - 1), np.clip(lo[1], 0, h - 1), np.clip(hi[0], 0, w - 1),
                     np.clip(hi[1], 0, h - 1)])


def nominal_boxes_from_files(dataset: Path, frame_id: str) -> tuple[list[list[str]], np.ndarray, np.ndarray]:
    """(label rows but DontCare, their GT boxes (K, 4), the expected gt-object boxes (K, 4)): each Car's GT box
    united with the clipped projection of the +-0.40 m cube on its roof (cars whose cube reaches behind the
    camera's near plane keep NaN: not checked here)."""
    rows = [r for r in label_rows(dataset, frame_id) if r[0] != "DontCare"]
    p2, size = calib_p2(dataset, frame_id), image_size(dataset, frame_id)
    gt = np.array([[float(v) for v in r[4:8]] for r in rows]).reshape(-1, 4)
    want = gt.copy()
    y_low = template_vertices()[:, 1].max()
    for k, r in enumerate(rows):
        if r[0] != "Car":
            continue
        h, loc, ry = float(r[8]), np.array([float(v) for v in r[11:14]]), float(r[14])
        corners = cube_corners(loc - [0.0, h + y_low, 0.0], ry_matrix(ry), np.array(BOUNDS))
        if np.any(corners[:, 2] <= NEAR):
            want[k] = np.nan
            continue
        obj = extent_box(project(p2, corners), size)
        want[k] = gt[k] if np.isinf(obj).any() else [min(gt[k, 0], obj[0]), min(gt[k, 1], obj[1]),
                                                     max(gt[k, 2], obj[2]), max(gt[k, 3], obj[3])]
    return rows, gt, want
