"""What an attack placed on each target car, for the harness's frustum protocols (standard library, numpy and
the scan-row check of :mod:`robustbench3d.kitti.velodyne` only).

An :class:`ObjectRecord` is the harness-side account of one attacked frame: per target car (in
:func:`~robustbench3d.attacks.base.target_cars` order) the image-2 box of the object's **bounds box** as placed
(the partner of the car's GT 2D box in the ``gt-object`` protocol's union box), the rows of the attacked scan
that are that car's object returns (the ``gt-append`` protocol adds them to the car's GT-box frustum) and the
car's row in the frame's labels. :meth:`~robustbench3d.attacks.base.Attack.apply_recorded` returns it beside
the attacked frame; the runner hands it to :func:`~robustbench3d.victims.base.victim_inputs`, never to a victim.

The bounds box of an object is its local axis-aligned box ``|v| <= bounds`` (:mod:`robustbench3d.attacks.object`),
posed by the placement (:class:`~robustbench3d.attacks.placement.Pose`: ``rect = rotation @ v + centre``); its
image box is the extent of its 8 projected corners under P2, the solid first cut at the plane rect z = 0.1 m
and the extent clipped to [0, W-1] x [0, H-1] like KITTI's 2D labels
(:func:`robustbench3d.geometry.project_boxes_to_image`). A box that lies wholly behind that plane or outside
the image is the **empty box** :data:`EMPTY_BOX` ``(+inf, +inf, -inf, -inf)``: the identity of
:func:`union_box` (min of the left/top, max of the right/bottom edges), so the union is then the GT box itself.

:func:`nominal_record` is the record of the default object (:data:`~robustbench3d.attacks.object.BOUNDS`,
the 0.40 m sphere's box) at the roof-centre placement without jitter and with no returns: what the clean
control ``none`` and attacks without their own record report, so a clean ``gt-object`` cell gets the union
boxes of an attacked cell of the benign sphere without EOT, and a clean ``gt-append`` cell the bare GT frustums.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from robustbench3d.kitti.velodyne import row_indices

if TYPE_CHECKING:
    from robustbench3d.attacks.object import Family
    from robustbench3d.attacks.placement import Pose
    from robustbench3d.kitti.calib import Calibration
    from robustbench3d.kitti.dataset import Frame
    from robustbench3d.kitti.labels import Labels

#: The image box of an object that shows nowhere in the image (left, top, right, bottom): the identity of
#: :func:`union_box`.
EMPTY_BOX = (np.inf, np.inf, -np.inf, -np.inf)
#: Rect-frame depth (m) at which a bounds box is cut before projecting (the projection's near plane).
NEAR_M = 0.1
#: Object-frame corner signs of a bounds box in KITTI corner order (:mod:`robustbench3d.geometry`): x along
#: the car, 0-3 the bottom face (object-frame y down: +y), 4-7 the top face, z across the car.
_CORNER_SIGNS = np.array([[1, 1, 1], [1, 1, -1], [-1, 1, -1], [-1, 1, 1],
                          [1, -1, 1], [1, -1, -1], [-1, -1, -1], [-1, -1, 1]], dtype=np.float64)


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.array(a, copy=True)
    a.flags.writeable = False
    return a


@dataclass(frozen=True, eq=False)
class ObjectRecord:
    """Where an attack put its object on each of a frame's T target cars (module doc). Harness-side only.

    Attributes:
        boxes: (T, 4) float64 image-2 box (left, top, right, bottom; px) of each car's placed bounds box,
            clipped to the image; :data:`EMPTY_BOX` where it shows nowhere in the image.
        returns: T sorted, unique int64 arrays of row indices into the attacked scan: each car's object
            returns (empty: none, e.g. the clean control).
        target_index: (T,) int64 row of each target car in the frame's labels (-1 where a target is no row
            of them: a frame without labels, or targets not taken from its labels).

    The arrays are read-only copies; shapes and index types are checked (ValueError).
    """

    boxes: np.ndarray
    returns: tuple[np.ndarray, ...]
    target_index: np.ndarray

    def __post_init__(self) -> None:
        boxes = np.asarray(self.boxes, dtype=np.float64)
        if boxes.ndim != 2 or boxes.shape[1] != 4:
            raise ValueError(f"ObjectRecord: field 'boxes': expected shape (T, 4), got {boxes.shape}")
        t = len(boxes)
        index = np.asarray(self.target_index)
        if index.shape != (t,) or (t and index.dtype.kind not in "iu"):
            raise ValueError(f"ObjectRecord: field 'target_index': expected ({t},) integers, got {index.shape} "
                             f"{index.dtype}")
        returns = tuple(self.returns)
        if len(returns) != t:
            raise ValueError(f"ObjectRecord: field 'returns': expected {t} arrays (one per target), got {len(returns)}")
        rows = tuple(row_indices(r, f"ObjectRecord: field 'returns': target {k}") for k, r in enumerate(returns))
        object.__setattr__(self, "boxes", _frozen(boxes))
        object.__setattr__(self, "target_index", _frozen(index.astype(np.int64)))
        object.__setattr__(self, "returns", rows)

    def __len__(self) -> int:
        return len(self.boxes)

    @classmethod
    def empty(cls) -> ObjectRecord:
        """The record of a frame without target cars."""
        return cls(np.zeros((0, 4)), (), np.zeros(0, dtype=np.int64))


def bounds_corners(bounds: Sequence[float] | np.ndarray, pose: Pose) -> np.ndarray:
    """(8, 3) float64 rect-frame corners (KITTI corner order) of the bounds box ``|v| <= bounds`` (half extents,
    m) posed by ``pose``: ``rotation @ v + centre``."""
    b = np.asarray(bounds, dtype=np.float64).reshape(3)
    local = _CORNER_SIGNS * b
    return local @ np.asarray(pose.rotation, dtype=np.float64).T + np.asarray(pose.centre, dtype=np.float64)


def image_boxes(corners: np.ndarray, calib: Calibration, image_size: tuple[int, int]) -> np.ndarray:
    """(T, 4) float64 image-2 boxes of T boxes' rect corners (T, 8, 3): the extent of the projected corners,
    cut at rect z = :data:`NEAR_M` and clipped to [0, W-1] x [0, H-1] (``image_size`` is (W, H) px);
    :data:`EMPTY_BOX` for a box wholly behind the plane or outside the image."""
    from robustbench3d.geometry import project_boxes_to_image

    c = np.asarray(corners, dtype=np.float64).reshape(-1, 8, 3)
    if len(c) == 0:
        return np.zeros((0, 4))
    boxes, valid = project_boxes_to_image(c, calib, image_size, near=NEAR_M)
    boxes[~valid] = EMPTY_BOX
    return boxes


def placed_object_boxes(bounds: Sequence[float] | np.ndarray, poses: Sequence[Pose], calib: Calibration,
                        image_size: tuple[int, int]) -> np.ndarray:
    """(T, 4) image-2 boxes of the bounds box ``bounds`` (half extents, m) at each of ``poses``
    (:func:`bounds_corners`, :func:`image_boxes`)."""
    corners = np.array([bounds_corners(bounds, p) for p in poses]).reshape(-1, 8, 3)
    return image_boxes(corners, calib, image_size)


def union_box(gt_box: np.ndarray, object_box: np.ndarray) -> np.ndarray:
    """The smallest box holding both (..., 4) boxes (left, top, right, bottom): min of left/top, max of
    right/bottom; an :data:`EMPTY_BOX` object box leaves the GT box as it is."""
    a, b = np.asarray(gt_box, dtype=np.float64), np.asarray(object_box, dtype=np.float64)
    return np.concatenate([np.minimum(a[..., :2], b[..., :2]), np.maximum(a[..., 2:], b[..., 2:])], axis=-1)


def added_rows(n_scan: int, n_removed: int, object_index: np.ndarray, n_targets: int) -> tuple[np.ndarray, ...]:
    """Per target, the rows of its object returns in an attacked scan laid out as the LiDAR render lays it out
    (:class:`~robustbench3d.sensors.lidar_render.LidarRenderResult`: the ``n_scan`` original rows minus the
    ``n_removed`` removed ones, then the added returns, ``object_index`` the mesh (= target) of each)."""
    first = n_scan - n_removed
    owner = np.asarray(object_index, dtype=np.int64).reshape(-1)
    return tuple(first + np.flatnonzero(owner == k).astype(np.int64) for k in range(n_targets))


def target_rows(labels: Labels | None, targets: Labels) -> np.ndarray:
    """(T,) int64: the row of ``labels`` each target car is (the first unused row of a target type with the
    same type, 2D box, dimensions, location and yaw), -1 where none is (``labels`` None, or another car)."""
    from robustbench3d.attacks.targets import TARGET_TYPES
    from robustbench3d.kitti.labels import type_mask

    out = np.full(len(targets), -1, dtype=np.int64)
    if labels is None or len(targets) == 0:
        return out
    rows = np.flatnonzero(type_mask(labels.type, TARGET_TYPES))
    if len(rows) == len(targets) and _same_rows(labels.select(rows), targets):  # the runner's case: all of them
        return rows.astype(np.int64)
    candidates = [int(i) for i in rows]
    for k in range(len(targets)):
        for i in candidates:
            if _same_object(labels, i, targets, k):
                out[k] = i
                candidates.remove(i)
                break
    return out


def _same_rows(a: Labels, b: Labels) -> bool:
    """Whether two label sets of equal length hold the same objects row by row (type, boxes, pose)."""
    return (np.array_equal(a.type.astype(str), b.type.astype(str)) and np.array_equal(a.bbox, b.bbox)
            and np.array_equal(a.dimensions, b.dimensions) and np.array_equal(a.location, b.location)
            and np.array_equal(a.rotation_y, b.rotation_y))


def _same_object(a: Labels, i: int, b: Labels, k: int) -> bool:
    return (str(a.type[i]) == str(b.type[k]) and np.array_equal(a.bbox[i], b.bbox[k])
            and np.array_equal(a.dimensions[i], b.dimensions[k]) and np.array_equal(a.location[i], b.location[k])
            and float(a.rotation_y[i]) == float(b.rotation_y[k]))


def nominal_poses(targets: Labels, family: Family | None = None) -> list[Pose]:
    """The pose of the undeformed template of ``family`` (default: the default family's) on each target car at
    the roof-centre placement without jitter (:func:`~robustbench3d.attacks.placement.place_on_roof`)."""
    from robustbench3d.attacks.object import DEFAULT_FAMILY, template_vertices
    from robustbench3d.attacks.placement import cars_of, place_on_roof

    v0 = template_vertices(family or DEFAULT_FAMILY)
    return [place_on_roof(v0, car)[1] for car in cars_of(targets)]


def nominal_record(frame: Frame, targets: Labels, family: Family | None = None) -> ObjectRecord:
    """The record of the undeformed object of ``family`` (default: the default family, bounds
    :data:`~robustbench3d.attacks.object.BOUNDS`, +-0.40 m) on each of ``targets`` (rect) of ``frame`` at the
    roof-centre placement without jitter, with no returns (module doc)."""
    from robustbench3d.attacks.object import DEFAULT_FAMILY

    if len(targets) == 0:
        return ObjectRecord.empty()
    fam = family or DEFAULT_FAMILY
    boxes = placed_object_boxes(fam.bounds, nominal_poses(targets, fam), frame.calib, frame.image_size)
    return ObjectRecord(boxes, tuple(np.zeros(0, dtype=np.int64) for _ in range(len(targets))),
                        target_rows(frame.labels, targets))


__all__ = ["EMPTY_BOX", "NEAR_M", "ObjectRecord", "added_rows", "bounds_corners", "image_boxes", "nominal_poses",
           "nominal_record", "placed_object_boxes", "target_rows", "union_box"]
