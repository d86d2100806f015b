"""Builders of small KITTI-layout datasets, shared by the tests and the benchmarks.

* :func:`synth_dataset` -- frames of the procedural generator (the embedded dataset's kind).
* :func:`write_kitti_frame` -- one hand-made frame (scan, image, labels, :data:`SIMPLE_CALIB`).
* :func:`box_car_dataset` -- flat ground and box-shaped cars whose LiDAR points and dark image
  rectangles match their labels (for the training tests).
* :func:`link_frames` -- a subset of an existing KITTI-layout dataset, as symlinks, with a split.

Nothing here is used by the benchmark runner itself; numpy and the data layer only (the
generator is imported when :func:`synth_dataset` runs).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from robustbench3d.geometry import alpha_from_rotation_y, box_corners, points_in_boxes, project_boxes_to_image
from robustbench3d.kitti import (
    Calibration,
    Labels,
    write_calibration,
    write_image,
    write_labels,
    write_scan,
    write_split,
)

#: Image size (width, height) of :data:`SIMPLE_CALIB` frames.
IMAGE_SIZE: tuple[int, int] = (1242, 375)

#: A KITTI-like calibration: the real 2011_09_26 P2 with an axis-permutation velodyne->camera
#: transform (camera 0.08 m above and 0.27 m ahead of the LiDAR).
SIMPLE_CALIB = Calibration(
    P0=np.eye(3, 4), P1=np.eye(3, 4),
    P2=np.array([[721.5377, 0.0, 609.5593, 44.85728], [0.0, 721.5377, 172.854, 0.2163791],
                 [0.0, 0.0, 1.0, 0.002745884]]),
    P3=np.eye(3, 4), R0_rect=np.eye(3),
    Tr_velo_to_cam=np.array([[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, -0.08], [1.0, 0.0, 0.0, -0.27]]),
    Tr_imu_to_velo=np.eye(3, 4),
)

#: Sub-directories of ``training/`` and the file suffix of each.
FRAME_FILES: dict[str, str] = {"image_2": ".png", "velodyne": ".bin", "calib": ".txt", "label_2": ".txt"}


def synth_dataset(root: str | Path, frames: int, *, seed: int = 0, val_fraction: float = 0.5) -> Path:
    """``frames`` procedural frames under ``root`` (one process, no progress bar); returns ``root``."""
    from robustbench3d.synth.writer import generate_dataset

    generate_dataset(root, frames, seed=seed, val_fraction=val_fraction, workers=1, progress=False)
    return Path(root)


def write_kitti_frame(root: str | Path, frame_id: str, *, scan: np.ndarray, labels: Labels | str = "",
                      image: np.ndarray | None = None, calib: Calibration = SIMPLE_CALIB) -> None:
    """Frame ``frame_id`` under ``root/training``: the (N, 4) velodyne ``scan``, ``image`` (default a
    black :data:`IMAGE_SIZE` image), ``calib`` and ``labels`` (a :class:`Labels`, or a label file's text)."""
    t = Path(root) / "training"
    write_scan(t / "velodyne" / f"{frame_id}.bin", scan)
    width, height = IMAGE_SIZE
    write_image(t / "image_2" / f"{frame_id}.png",
                np.zeros((height, width, 3), dtype=np.uint8) if image is None else image)
    write_calibration(t / "calib" / f"{frame_id}.txt", calib)
    label_file = t / "label_2" / f"{frame_id}.txt"
    if isinstance(labels, str):
        label_file.parent.mkdir(parents=True, exist_ok=True)
        label_file.write_text(labels)
    else:
        write_labels(label_file, labels)


def link_frames(source: str | Path, root: str | Path, frame_ids: Sequence[str], split: str = "val") -> Path:
    """A dataset at ``root`` whose ``training`` files are symlinks to ``source``'s frames
    ``frame_ids``, listed in ``ImageSets/<split>.txt``; returns ``root``."""
    source, root = Path(source), Path(root)
    for sub, suffix in FRAME_FILES.items():
        (root / "training" / sub).mkdir(parents=True, exist_ok=True)
        for fid in frame_ids:
            (root / "training" / sub / f"{fid}{suffix}").symlink_to(source / "training" / sub / f"{fid}{suffix}")
    write_split(root / "ImageSets" / f"{split}.txt", list(frame_ids))
    return root


def _box_car_points(rng: np.random.Generator, dims: np.ndarray, loc: np.ndarray, ry: np.ndarray) -> list[np.ndarray]:
    """600 rect-frame points on the faces of each box (random points pushed to a random face)."""
    cars = []
    for k in range(len(dims)):
        u = rng.uniform(-0.5, 0.5, (600, 3))
        axis = rng.integers(0, 3, 600)
        u[np.arange(600), axis] = np.sign(u[np.arange(600), axis]) * 0.48  # just inside a face
        local = u * dims[k][[2, 0, 1]] + [0, -dims[k, 0] / 2, 0]  # (l, h, w) extents, y up from the bottom
        c, s = np.cos(ry[k]), np.sin(ry[k])
        rect = np.stack([c * local[:, 0] + s * local[:, 2], local[:, 1], -s * local[:, 0] + c * local[:, 2]], 1)
        cars.append(rect + loc[k])
    return cars


def box_car_dataset(root: str | Path, n_train: int = 4, n_val: int = 2, seed: int = 0) -> Path:
    """Frames with a flat ground, 1-2 box-shaped cars (points on all faces) and an image where each
    car's 2D box is a dark rectangle; ``train`` and ``val`` splits. Returns ``root``."""
    root = Path(root)
    width, height = IMAGE_SIZE
    rng = np.random.default_rng(seed)
    ids = [f"{i:06d}" for i in range(n_train + n_val)]
    for fid in ids:
        gx, gz = np.meshgrid(np.arange(-12.0, 12.0, 0.4), np.arange(4.0, 35.0, 0.4))
        ground = np.stack([gx.ravel(), np.full(gx.size, 1.65), gz.ravel()], axis=1)
        n_cars = int(rng.integers(1, 3))
        dims = np.column_stack([rng.uniform(1.4, 1.6, n_cars), rng.uniform(1.5, 1.8, n_cars),
                                rng.uniform(3.6, 4.4, n_cars)])
        loc = np.column_stack([np.array([-3.5, 3.5])[:n_cars] + rng.uniform(-1, 1, n_cars), np.full(n_cars, 1.65),
                               rng.uniform(9, 22, n_cars)])
        ry = rng.uniform(-np.pi, np.pi, n_cars)
        corners = box_corners(dims, loc, ry)
        cars = _box_car_points(rng, dims, loc, ry)
        rect_pts = np.concatenate([ground[~points_in_boxes(ground, dims, loc, ry, margin=0.1).any(axis=1)], *cars])
        velo = SIMPLE_CALIB.rect_to_velo_points(rect_pts)
        scan = np.concatenate([velo, rng.uniform(0, 1, (len(velo), 1))], axis=1).astype(np.float32)
        bbox, valid = project_boxes_to_image(corners, SIMPLE_CALIB, IMAGE_SIZE)
        image = rng.integers(150, 200, (height, width, 3), dtype=np.uint8)
        for b in bbox[valid]:
            image[int(b[1]):int(b[3]), int(b[0]):int(b[2])] = (40, 40, 60)
        labels = Labels(type=np.array(["Car"] * n_cars, dtype=object), truncated=np.zeros(n_cars),
                        occluded=np.zeros(n_cars, dtype=np.int64), alpha=alpha_from_rotation_y(ry, loc), bbox=bbox,
                        dimensions=dims, location=loc, rotation_y=ry)
        write_kitti_frame(root, fid, scan=scan, labels=labels, image=image)
    write_split(root / "ImageSets" / "train.txt", ids[:n_train])
    write_split(root / "ImageSets" / "val.txt", ids[n_train:])
    return root


__all__ = ["FRAME_FILES", "IMAGE_SIZE", "SIMPLE_CALIB", "box_car_dataset", "link_frames", "synth_dataset",
           "write_kitti_frame"]
