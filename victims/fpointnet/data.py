"""Frustum training data from a KITTI-layout dataset (reference §1.3-§1.4).

:func:`build_frustum_set` turns GT boxes into frustums once (train: each box used ``augment_x``
= 5 times with a perturbed 2D box; val: the exact box once), keeping those whose 2D box is at
least 25 px high and whose frustum has a point inside the GT 3D box. :func:`make_item` draws one
training example: rotation to the frustum frame, resampling to N points with replacement, the
heading/size targets, then the optional flip (p = 0.5) and shift augmentations.

Shift modes: ``"faithful"`` reproduces the original code — shift = clip(0.05·d·n, 0.8·d, 1.2·d)
with n ~ N(0, 1) and d = √(c_x² + c_y²) of the rotated centre, i.e. nearly always +0.8·d along z;
``"intended"`` the small Gaussian shift it was meant to be, clip(0.05·d·n, −0.2·d, 0.2·d);
``"off"``.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from robustbench3d.fileio import atomic_open
from robustbench3d.geometry import points_in_boxes
from robustbench3d.kitti.dataset import KittiDataset
from robustbench3d.kitti.image import image_size
from robustbench3d.kitti.labels import type_mask
from robustbench3d.victims.fpointnet.box_coding import angle_to_class, one_hot, size_to_class
from robustbench3d.victims.fpointnet.frustum import (
    extract_frustum,
    perturb_box2d,
    project_scan,
    resample_indices,
    rotate_to_frustum,
)

ShiftMode = Literal["faithful", "intended", "off"]
MIN_BOX_HEIGHT = 25.0


@dataclass
class FrustumSet:
    """F frustums with their points concatenated (rect frame, before rotation).

    points (T, 4) float32 xyz m + reflectance; seg (T,) uint8 (1 = inside the GT box);
    offsets (F + 1,) int64; box2d (F, 4) px; rot_angle (F,) rad; center (F, 3) geometric box
    centre in rect, m; ry (F,) rad; size_lwh (F, 3) m; types (F,) str; frame_ids (F,) str.
    """

    points: np.ndarray
    seg: np.ndarray
    offsets: np.ndarray
    box2d: np.ndarray
    rot_angle: np.ndarray
    center: np.ndarray
    ry: np.ndarray
    size_lwh: np.ndarray
    types: np.ndarray
    frame_ids: np.ndarray

    def __len__(self) -> int:
        return len(self.rot_angle)

    def frustum(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """(points (M, 4), seg (M,)) of frustum ``i``."""
        a, b = self.offsets[i], self.offsets[i + 1]
        return self.points[a:b], self.seg[a:b]

    def save(self, path: str | Path) -> None:
        with atomic_open(path, "wb") as f:
            np.savez(f, **{k: getattr(self, k) for k in self.__dataclass_fields__ if k not in ("types", "frame_ids")},
                     types=self.types.astype(str), frame_ids=self.frame_ids.astype(str))

    @classmethod
    def load(cls, path: str | Path) -> FrustumSet:
        with np.load(path, allow_pickle=False) as z:
            return cls(**{k: z[k] for k in cls.__dataclass_fields__})


def build_frustum_set(dataset: KittiDataset, rng: np.random.Generator, types: Iterable[str] = ("Car",),
                      augment_x: int = 1, perturb: bool = False, frame_ids: Iterable[str] | None = None) -> FrustumSet:
    """Frustums of the GT boxes of ``types`` in the dataset's frames (see module docstring)."""
    wanted = tuple(types)
    cols: dict[str, list] = {k: [] for k in ("points", "seg", "box2d", "rot", "center", "ry", "size", "type", "frame")}
    for fid in (frame_ids if frame_ids is not None else dataset.frame_ids):
        labels = dataset.labels(fid)
        if labels is None:
            continue
        sel = np.flatnonzero(type_mask(labels.type, wanted))
        if len(sel) == 0:
            continue
        calib = dataset.calib(fid)
        projected = project_scan(dataset.scan(fid), calib, image_size(dataset.path("image", fid)))
        for j in sel:
            h, w, l = labels.dimensions[j]
            loc, ry = labels.location[j], float(labels.rotation_y[j])
            for _ in range(augment_x):
                box = perturb_box2d(labels.bbox[j], rng) if perturb else labels.bbox[j].astype(np.float64)
                if box[3] - box[1] < MIN_BOX_HEIGHT:
                    continue
                fr = extract_frustum(projected, box, calib)
                inside = points_in_boxes(fr.points, labels.dimensions[j:j + 1], loc[None], np.array([ry]))[:, 0]
                if not inside.any():
                    continue
                cols["points"].append(fr.points.astype(np.float32))
                cols["seg"].append(inside.astype(np.uint8))
                cols["box2d"].append(box)
                cols["rot"].append(fr.rot_angle)
                cols["center"].append(loc - np.array([0.0, h / 2, 0.0]))
                cols["ry"].append(ry)
                cols["size"].append([l, w, h])
                cols["type"].append(str(labels.type[j]))
                cols["frame"].append(fid)
    counts = [len(p) for p in cols["points"]]
    return FrustumSet(
        points=np.concatenate(cols["points"]) if counts else np.zeros((0, 4), np.float32),
        seg=np.concatenate(cols["seg"]) if counts else np.zeros(0, np.uint8),
        offsets=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        box2d=np.asarray(cols["box2d"], dtype=np.float64).reshape(-1, 4),
        rot_angle=np.asarray(cols["rot"], dtype=np.float64), center=np.asarray(cols["center"]).reshape(-1, 3),
        ry=np.asarray(cols["ry"], dtype=np.float64), size_lwh=np.asarray(cols["size"], dtype=np.float64).reshape(-1, 3),
        types=np.asarray(cols["type"], dtype=str), frame_ids=np.asarray(cols["frame"], dtype=str),
    )


@dataclass
class FrustumItem:
    """One example in the frustum frame: points (N, 4) float32, seg (N,) int64, one_hot (3,),
    center (3,) m, heading_class, heading_residual (rad), size_class, size_residual (3,) m,
    rot_angle (rad)."""

    points: np.ndarray
    seg: np.ndarray
    one_hot: np.ndarray
    center: np.ndarray
    heading_class: int
    heading_residual: float
    size_class: int
    size_residual: np.ndarray
    rot_angle: float


def make_item(fs: FrustumSet, i: int, num_points: int, rng: np.random.Generator, flip: bool = False,
              shift: ShiftMode = "off") -> FrustumItem:
    """Training/validation example ``i`` (augmentations drawn from ``rng``)."""
    pts, seg = fs.frustum(i)
    rot = float(fs.rot_angle[i])
    idx = resample_indices(len(pts), num_points, rng)
    points = rotate_to_frustum(pts[idx], rot)
    center = rotate_to_frustum(fs.center[i], rot)
    heading = float(fs.ry[i]) - rot
    size_cls, size_res = size_to_class(fs.size_lwh[i][None], fs.types[i])
    if flip and rng.random() > 0.5:
        points[:, 0] *= -1
        center[0] *= -1
        heading = np.pi - heading
    if shift != "off":
        d = float(np.sqrt(center[0] ** 2 + center[1] ** 2))
        n = float(rng.standard_normal())
        lo, hi = (0.8 * d, 1.2 * d) if shift == "faithful" else (-0.2 * d, 0.2 * d)
        delta = float(np.clip(n * d * 0.05, lo, hi))
        points[:, 2] += delta
        center[2] += delta
    hcls, hres = angle_to_class(heading)
    return FrustumItem(points.astype(np.float32), seg[idx].astype(np.int64), one_hot(fs.types[i])[0], center,
                       int(hcls), float(hres), int(size_cls[0]), size_res[0], rot)
