"""Frustum-PointNet v1 box coding: 12 heading bins, 8 size templates (reference §1.4-§1.5).

Headings are yaw angles (rad) about the y axis of the frustum frame (the rect frame rotated about
y so the 2D-box centre ray is +z). Sizes are (l, w, h) in metres: l along the box's local x, h
along y, w along z (the KITTI label stores h, w, l).

Heading bin k (k = 0..11) is centred at k·30°; an angle is taken mod 2π, shifted by half a bin,
and the residual is its offset from the bin centre, in [-15°, 15°). Size class = the object type's
index in :data:`SIZE_TYPES` (one template per type, no clustering); residual = size - template.
"""

from __future__ import annotations

import numpy as np

NUM_HEADING_BIN = 12
NUM_SIZE_CLUSTER = 8
NUM_OBJECT_POINT = 512
#: Width of one heading bin (rad).
HEADING_BIN_WIDTH = 2 * np.pi / NUM_HEADING_BIN

#: KITTI types in size-class order.
SIZE_TYPES: tuple[str, ...] = ("Car", "Van", "Truck", "Pedestrian", "Person_sitting", "Cyclist", "Tram", "Misc")
#: Mean (l, w, h) in metres per size class (``g_mean_size_arr`` of the original code).
MEAN_SIZES = np.array([
    [3.88311640418, 1.62856739989, 1.52563191462],
    [5.06763659, 1.9007158, 2.20532825],
    [10.13586957, 2.58549199, 3.2520595],
    [0.84422524, 0.66068622, 1.76255119],
    [0.80057803, 0.5983815, 1.27450867],
    [1.76282397, 0.59706367, 1.73698127],
    [16.17150617, 2.53246914, 3.53079012],
    [3.64300781, 1.54298177, 1.92320313],
])
#: One-hot class index of the 3-class F-PN vector (Car, Pedestrian, Cyclist).
ONE_HOT_CLASSES: tuple[str, ...] = ("Car", "Pedestrian", "Cyclist")


def angle_to_class(angle: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
    """Encode headings (rad) as (bin index int64, residual rad in [-π/12, π/12))."""
    a = np.mod(np.asarray(angle, dtype=np.float64), 2 * np.pi)
    shifted = np.mod(a + HEADING_BIN_WIDTH / 2, 2 * np.pi)
    cls = np.minimum(np.floor(shifted / HEADING_BIN_WIDTH), NUM_HEADING_BIN - 1).astype(np.int64)
    residual = shifted - (cls * HEADING_BIN_WIDTH + HEADING_BIN_WIDTH / 2)
    return cls, residual


def class_to_angle(cls: np.ndarray | int, residual: np.ndarray | float, to_label_format: bool = True) -> np.ndarray:
    """Decode (bin, residual rad) to a heading; with ``to_label_format`` mapped to (-π, π]."""
    angle = np.asarray(cls, dtype=np.float64) * HEADING_BIN_WIDTH + np.asarray(residual, dtype=np.float64)
    if to_label_format:
        angle = np.where(angle > np.pi, angle - 2 * np.pi, angle)
    return angle


def type_to_size_class(types: np.ndarray | list[str] | str) -> np.ndarray:
    """Size class index of KITTI type names (raises KeyError for DontCare / unknown)."""
    names = np.atleast_1d(np.asarray(types, dtype=object))
    index = {t: i for i, t in enumerate(SIZE_TYPES)}
    return np.array([index[str(t)] for t in names], dtype=np.int64)


def size_to_class(size_lwh: np.ndarray, types: np.ndarray | list[str] | str) -> tuple[np.ndarray, np.ndarray]:
    """Encode (N, 3) sizes (l, w, h; m) of objects of the given types as (class, residual (N, 3) m)."""
    cls = type_to_size_class(types)
    return cls, np.asarray(size_lwh, dtype=np.float64).reshape(-1, 3) - MEAN_SIZES[cls]


def class_to_size(cls: np.ndarray | int, residual: np.ndarray) -> np.ndarray:
    """Decode (class, residual (…, 3) m) to (…, 3) sizes (l, w, h)."""
    return MEAN_SIZES[np.asarray(cls, dtype=np.int64)] + np.asarray(residual, dtype=np.float64)


def one_hot(types: np.ndarray | list[str] | str) -> np.ndarray:
    """(N, 3) float32 one-hot of Car / Pedestrian / Cyclist (other types give all zeros)."""
    names = np.atleast_1d(np.asarray(types, dtype=object))
    out = np.zeros((len(names), len(ONE_HOT_CLASSES)), dtype=np.float32)
    for i, t in enumerate(names):
        if t in ONE_HOT_CLASSES:
            out[i, ONE_HOT_CLASSES.index(t)] = 1.0
    return out


def car_one_hot(n: int) -> np.ndarray:
    """(n, 3) float32 one-hot rows of Car: the class vector of every frustum a cascade scores."""
    return np.repeat(one_hot("Car"), n, axis=0)


def corners_from_center(center: np.ndarray, heading: np.ndarray, size_lwh: np.ndarray) -> np.ndarray:
    """(N, 8, 3) corners of boxes given by their geometric centre (N, 3), heading about y (N,)
    and size (N, 3) l, w, h — the original ``get_3d_box`` layout: corners 0-3 at y = +h/2
    (bottom, y points down), 4-7 at y = -h/2."""
    c = np.asarray(center, dtype=np.float64).reshape(-1, 3)
    s = np.asarray(size_lwh, dtype=np.float64).reshape(-1, 3)
    h_ang = np.asarray(heading, dtype=np.float64).reshape(-1)
    l, w, h = s[:, 0:1] / 2, s[:, 1:2] / 2, s[:, 2:3] / 2
    x = np.concatenate([l, l, -l, -l, l, l, -l, -l], axis=1)
    y = np.concatenate([h, h, h, h, -h, -h, -h, -h], axis=1)
    z = np.concatenate([w, -w, -w, w, w, -w, -w, w], axis=1)
    cos, sin = np.cos(h_ang)[:, None], np.sin(h_ang)[:, None]
    xr = cos * x + sin * z
    zr = -sin * x + cos * z
    return np.stack([xr, y, zr], axis=2) + c[:, None, :]
