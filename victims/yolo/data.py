"""YOLO training images from a KITTI-layout dataset: letterboxed once and cached.

Each frame's image is letterboxed to the network input (same function as inference), stored as
uint8 in a ``.npy`` memmap; Car boxes become targets and Van / DontCare boxes ignore regions
(reference §2.3), all in input pixels (xyxy).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from robustbench3d.fileio import atomic_open, atomic_write_text
from robustbench3d.kitti.dataset import KittiDataset
from robustbench3d.kitti.labels import Labels
from robustbench3d.victims.yolo.letterbox import image_to_tensor, letterbox

TARGET_TYPES: tuple[str, ...] = ("Car",)
IGNORE_TYPES: tuple[str, ...] = ("Van", "DontCare")


@dataclass
class YoloImageSet:
    """images (F, H_in, W_in, 3) uint8 (memmap); boxes (T, 4) input px; box_offsets (F + 1,);
    ignore (U, 4); ignore_offsets (F + 1,); frame_ids (F,) str."""

    images: np.ndarray
    boxes: np.ndarray
    box_offsets: np.ndarray
    ignore: np.ndarray
    ignore_offsets: np.ndarray
    frame_ids: np.ndarray

    def __len__(self) -> int:
        return len(self.frame_ids)

    def targets(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """(boxes (G, 4), ignore boxes (I, 4)) of image ``i``, input pixels."""
        return (self.boxes[self.box_offsets[i]:self.box_offsets[i + 1]],
                self.ignore[self.ignore_offsets[i]:self.ignore_offsets[i + 1]])


def build_image_set(dataset: KittiDataset, input_size: tuple[int, int], fill: float, cache: Path) -> YoloImageSet:
    """Letterbox every frame of ``dataset`` into ``cache`` (``<cache>.npy`` + ``<cache>.npz``),
    reusing a cache built from the same data and settings."""
    key = {"data": str(dataset.root.resolve()), "split": dataset.split, "frames": dataset.frame_ids,
           "input_size": list(input_size), "fill": fill}
    npy, npz, meta = cache.with_suffix(".npy"), cache.with_suffix(".npz"), cache.with_suffix(".json")
    if npy.exists() and npz.exists() and meta.exists() and json.loads(meta.read_text()) == key:
        with np.load(npz, allow_pickle=False) as z:
            rest = {k: z[k] for k in ("boxes", "box_offsets", "ignore", "ignore_offsets", "frame_ids")}
        return YoloImageSet(images=np.load(npy, mmap_mode="r", allow_pickle=False), **rest)
    wi, hi = input_size
    tmp = npy.with_name(f".{npy.name}.{os.getpid()}.tmp")
    images = np.lib.format.open_memmap(tmp, mode="w+", dtype=np.uint8, shape=(len(dataset), hi, wi, 3))
    boxes: list[np.ndarray] = []
    ignore: list[np.ndarray] = []
    for i, fid in enumerate(dataset.frame_ids):
        x, geo = letterbox(image_to_tensor(dataset.image(fid)), input_size, fill)
        images[i] = (x[0].permute(1, 2, 0).clamp(0, 1) * 255).round().to(torch.uint8).numpy()
        labels = dataset.labels(fid)
        labels = labels if labels is not None else Labels.empty()
        boxes.append(np.asarray(geo.to_input(labels.of_types(TARGET_TYPES).bbox)).reshape(-1, 4))
        ignore.append(np.asarray(geo.to_input(labels.of_types(IGNORE_TYPES).bbox)).reshape(-1, 4))
    images.flush()
    del images
    os.replace(tmp, npy)

    def offsets(parts: list[np.ndarray]) -> np.ndarray:
        return np.concatenate([[0], np.cumsum([len(p) for p in parts])]).astype(np.int64)

    rest = {"boxes": np.concatenate(boxes) if boxes else np.zeros((0, 4)), "box_offsets": offsets(boxes),
            "ignore": np.concatenate(ignore) if ignore else np.zeros((0, 4)), "ignore_offsets": offsets(ignore),
            "frame_ids": np.asarray(dataset.frame_ids, dtype=str)}
    with atomic_open(npz, "wb") as f:
        np.savez(f, **rest)
    atomic_write_text(meta, json.dumps(key))
    return YoloImageSet(images=np.load(npy, mmap_mode="r", allow_pickle=False), **rest)


def zoom(img: np.ndarray, boxes: list[np.ndarray], scale: float, offset: tuple[float, float], fill: int,
         min_visible: float = 0.4, min_size: float = 2.0) -> tuple[np.ndarray, list[np.ndarray]]:
    """Zoom an (H, W, 3) uint8 image by ``scale`` about the origin then shift by ``offset`` (px):
    output pixel (x, y) shows source point ((x − ox)/scale, (y − oy)/scale) (bilinear, ``fill``
    outside). Each xyxy box array is mapped the same way, clipped to the image and dropped when
    less than ``min_visible`` of its mapped area or less than ``min_size`` px in width or height
    remains."""
    h, w = img.shape[:2]
    ox, oy = offset
    xs = (np.arange(w) + 0.5 - ox) / scale - 0.5
    ys = (np.arange(h) + 0.5 - oy) / scale - 0.5
    x0, y0 = np.floor(xs).astype(np.int64), np.floor(ys).astype(np.int64)
    fx, fy = (xs - x0)[None, :, None], (ys - y0)[:, None, None]
    src = np.concatenate([np.full((1, w, 3), fill, np.float32), img.astype(np.float32),
                          np.full((1, w, 3), fill, np.float32)])
    src = np.concatenate([np.full((h + 2, 1, 3), fill, np.float32), src, np.full((h + 2, 1, 3), fill, np.float32)],
                         axis=1)
    cx0, cx1 = np.clip(x0 + 1, 0, w + 1), np.clip(x0 + 2, 0, w + 1)
    cy0, cy1 = np.clip(y0 + 1, 0, h + 1), np.clip(y0 + 2, 0, h + 1)
    top = src[cy0][:, cx0] * (1 - fx) + src[cy0][:, cx1] * fx
    bottom = src[cy1][:, cx0] * (1 - fx) + src[cy1][:, cx1] * fx
    out = np.clip(np.rint(top * (1 - fy) + bottom * fy), 0, 255).astype(np.uint8)
    mapped: list[np.ndarray] = []
    for b in boxes:
        m = b * scale + np.array([ox, oy, ox, oy])
        area = np.prod(np.clip(m[:, 2:] - m[:, :2], 0, None), axis=1)
        c = np.clip(m, 0, [w, h, w, h])
        wh = c[:, 2:] - c[:, :2]
        keep = (wh.min(axis=1) >= min_size) & (np.prod(np.clip(wh, 0, None), axis=1) >= min_visible * area)
        mapped.append(c[keep])
    return out, mapped


def make_batch(ds: YoloImageSet, indices: np.ndarray, rng: np.random.Generator | None,
               flip: bool, scale_jitter: float = 0.0,
               fill: int = 128) -> tuple[torch.Tensor, list[torch.Tensor], list[torch.Tensor]]:
    """(images (B, 3, H, W) float in [0, 1], target boxes, ignore boxes); with ``flip`` each image
    is mirrored left-right with probability 0.5, with ``scale_jitter`` = j > 0 zoomed by
    U(1 − j, 1 + j) and shifted uniformly within the range that keeps the view inside the zoomed
    image (or the zoomed image inside the view) — all drawn from ``rng``."""
    imgs, tboxes, iboxes = [], [], []
    w = ds.images.shape[2]
    h = ds.images.shape[1]
    for i in indices:
        img = np.array(ds.images[int(i)])
        gt, ign = (b.astype(np.float64).copy() for b in ds.targets(int(i)))
        if flip and rng is not None and rng.random() < 0.5:
            img = img[:, ::-1]
            for b in (gt, ign):
                b[:, [0, 2]] = w - b[:, [2, 0]]
        if scale_jitter > 0 and rng is not None:
            s = float(rng.uniform(1 - scale_jitter, 1 + scale_jitter))
            ox = float(rng.uniform(min(0.0, w - s * w), max(0.0, w - s * w)))
            oy = float(rng.uniform(min(0.0, h - s * h), max(0.0, h - s * h)))
            img, (gt, ign) = zoom(np.ascontiguousarray(img), [gt, ign], s, (ox, oy), fill)
        imgs.append(torch.from_numpy(np.ascontiguousarray(img)).permute(2, 0, 1).float() / 255.0)
        tboxes.append(torch.from_numpy(gt))
        iboxes.append(torch.from_numpy(ign))
    return torch.stack(imgs), tboxes, iboxes
