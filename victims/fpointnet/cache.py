"""Portable cache of an F-PN training frustum set (``robustbench3d victims train-fpointnet --cache FILE``).

A :class:`~robustbench3d.victims.fpointnet.data.FrustumSet` holds every frustum's points, and the
5 perturbed copies of each train box overlap almost entirely, so it is large (the embedded train
split: 39153 frustums, 27.2 M points, 435 MB). The cache stores instead, per frame, the union of
the FOV points that fall inside any of its frustums' 2D boxes (5.5 M points), quantized
(xyz to :data:`XYZ_QUANTUM` m, reflectance to :data:`REFLECTANCE_QUANTUM`), delta-coded in scan
order and deflate-compressed (about 20 MB), with each frame's P2 and each frustum's 2D box, frame,
rotation and box. :func:`read_frustum_cache` rebuilds the frustum set from it with no dataset at
hand: a frustum's points are its frame's cached points whose P2 projection falls in its 2D box (scan
order, as :func:`~robustbench3d.victims.fpointnet.frustum.extract_frustum`), its labels those inside
its 3D box. Up to the quantization (<= 0.5 mm, which can move a point lying on a box edge), that is
the set :func:`~robustbench3d.victims.fpointnet.data.build_frustum_set` returned; the reading is
deterministic, so a run trained from a cache is the same on any machine that reads it.

Imports numpy only (no dataset reader), so a training machine needs only this file.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from robustbench3d.errors import DataFormatError
from robustbench3d.fileio import atomic_open
from robustbench3d.geometry import points_in_boxes
from robustbench3d.victims.fpointnet.data import FrustumSet
from robustbench3d.victims.fpointnet.frustum import box_mask

CACHE_FORMAT = "robustbench3d.fpointnet_frustum_cache/1"
#: Quantum of the cached rect coordinates (m) and of the reflectance.
XYZ_QUANTUM = 0.001
REFLECTANCE_QUANTUM = 0.01
_FIELDS = ("format", "key", "xyz_delta", "reflectance", "frame_offsets", "frame_names", "P2", "frame_index",
           "box2d", "rot_angle", "center", "ry", "size_lwh", "types")


def project_p2(points_rect: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """(P, 2) image pixels of rect points (P, ≥3) under P2 (3, 4); as ``Calibration.rect_to_image``."""
    h = np.asarray(points_rect, dtype=np.float64)[:, :3] @ p2[:, :3].T + p2[:, 3]
    depth = h[:, 2]
    safe = np.where(np.abs(depth) > 1e-12, depth, 1e-12)
    return h[:, :2] / safe[:, None]


def write_frustum_cache(path: str | Path, fs: FrustumSet, frames: dict[str, tuple[np.ndarray, np.ndarray]],
                        key: dict[str, Any]) -> None:
    """Write the cache of ``fs``.

    Args:
        frames: per frame id of ``fs``: (projected scan points (P, 4) rect xyz m + reflectance, in
            scan order, restricted to the camera FOV; P2 (3, 4)).
        key: the run configuration the set was built with (recorded; compared on reading).
    """
    names = list(dict.fromkeys(str(f) for f in fs.frame_ids))
    pos = {n: i for i, n in enumerate(names)}
    frame_index = np.array([pos[str(f)] for f in fs.frame_ids], dtype=np.int32)
    chunks, offsets, p2s = [], [0], []
    for i, name in enumerate(names):
        pts, p2 = frames[name]
        p2 = np.asarray(p2, dtype=np.float64).reshape(3, 4)
        uv = project_p2(pts, p2)
        keep = np.zeros(len(pts), dtype=bool)
        for j in np.flatnonzero(frame_index == i):
            keep |= box_mask(uv, fs.box2d[j])
        chunks.append(np.asarray(pts, dtype=np.float64)[keep])
        offsets.append(offsets[-1] + int(keep.sum()))
        p2s.append(p2)
    pts = np.concatenate(chunks) if chunks else np.zeros((0, 4))
    q = np.round(pts[:, :3] / XYZ_QUANTUM).astype(np.int64)
    r = np.round(pts[:, 3] / REFLECTANCE_QUANTUM)
    if len(q) and np.abs(q).max() >= 2**30:
        raise ValueError(f"{path}: a point lies beyond {2**30 * XYZ_QUANTUM:.0f} m")
    if len(r) and (r.min() < 0 or r.max() > 255):
        raise ValueError(f"{path}: reflectance outside [0, {255 * REFLECTANCE_QUANTUM}]")
    delta = np.diff(q, axis=0, prepend=np.zeros((1, 3), np.int64)).astype(np.int32)
    with atomic_open(path, "wb") as f:
        np.savez_compressed(
            f, format=np.array(CACHE_FORMAT), key=np.array(json.dumps(key, sort_keys=True)), xyz_delta=delta,
            reflectance=r.astype(np.uint8), frame_offsets=np.asarray(offsets, dtype=np.int64),
            frame_names=np.asarray(names, dtype=str), P2=np.asarray(p2s, dtype=np.float64).reshape(-1, 3, 4),
            frame_index=frame_index, box2d=fs.box2d, rot_angle=fs.rot_angle, center=fs.center, ry=fs.ry,
            size_lwh=fs.size_lwh, types=fs.types.astype(str))


def read_frustum_cache(path: str | Path) -> tuple[FrustumSet, dict[str, Any]]:
    """(frustum set, recorded key) of a cache written by :func:`write_frustum_cache`."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = [k for k in _FIELDS if k not in z.files]
            if missing:
                raise DataFormatError(path, f"not an F-PN frustum cache: no {', '.join(missing)}", field=missing[0])
            d = {k: z[k] for k in _FIELDS}
    except (OSError, ValueError) as exc:
        raise DataFormatError(path, f"not an F-PN frustum cache ({exc})") from None
    if str(d["format"]) != CACHE_FORMAT:
        raise DataFormatError(path, f"expected {CACHE_FORMAT!r}, got {str(d['format'])!r}", field="format")
    n_frames, n = len(d["frame_names"]), len(d["frame_index"])
    offsets = d["frame_offsets"]
    checks = {"frame_offsets": offsets.shape == (n_frames + 1,) and offsets[-1] == len(d["xyz_delta"]),
              "P2": d["P2"].shape == (n_frames, 3, 4), "reflectance": d["reflectance"].shape == (offsets[-1],),
              "frame_index": n == 0 or (d["frame_index"].min() >= 0 and d["frame_index"].max() < n_frames),
              **{k: len(d[k]) == n for k in ("box2d", "rot_angle", "center", "ry", "size_lwh", "types")}}
    bad = [k for k, ok in checks.items() if not ok]
    if bad:
        raise DataFormatError(path, "inconsistent array sizes", field=bad[0])
    xyz = np.cumsum(d["xyz_delta"].astype(np.int64), axis=0) * XYZ_QUANTUM
    pts = np.concatenate([xyz, d["reflectance"][:, None] * REFLECTANCE_QUANTUM], axis=1)
    out_pts = []
    by_frame = np.argsort(d["frame_index"], kind="stable")
    bounds = np.searchsorted(d["frame_index"][by_frame], np.arange(n_frames + 1))
    for i in range(n_frames):
        frame_pts = pts[offsets[i]:offsets[i + 1]]
        uv = project_p2(frame_pts, d["P2"][i])
        js = by_frame[bounds[i]:bounds[i + 1]]
        boxes = np.concatenate([d["center"][js], d["size_lwh"][js], d["ry"][js, None]], axis=1)
        uniq, which = np.unique(boxes, axis=0, return_inverse=True)  # the perturbed copies share a 3D box
        loc = uniq[:, :3] + np.stack([np.zeros(len(uniq)), uniq[:, 5] / 2, np.zeros(len(uniq))], axis=1)
        inside = points_in_boxes(frame_pts, uniq[:, [5, 4, 3]], loc, uniq[:, 6])  # (P, boxes)
        for k, j in zip(which.reshape(-1), js, strict=True):
            sel = box_mask(uv, d["box2d"][j])
            out_pts.append((j, frame_pts[sel].astype(np.float32), inside[sel, k].astype(np.uint8)))
    out_pts.sort(key=lambda t: t[0])
    counts = [len(p) for _, p, _ in out_pts]
    if any(c == 0 for c in counts):
        raise DataFormatError(path, "a frustum has no cached points", field="box2d")
    fs = FrustumSet(
        points=np.concatenate([p for _, p, _ in out_pts]) if n else np.zeros((0, 4), np.float32),
        seg=np.concatenate([s for _, _, s in out_pts]) if n else np.zeros(0, np.uint8),
        offsets=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        box2d=d["box2d"].astype(np.float64), rot_angle=d["rot_angle"].astype(np.float64),
        center=d["center"].astype(np.float64), ry=d["ry"].astype(np.float64),
        size_lwh=d["size_lwh"].astype(np.float64), types=d["types"].astype(str),
        frame_ids=d["frame_names"][d["frame_index"]].astype(str))
    return fs, json.loads(str(d["key"]))
