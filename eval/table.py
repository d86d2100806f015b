"""All frames' objects as one column table (ground truth or detections), frame-major."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from robustbench3d.kitti.labels import KITTI_TYPES, Labels

#: KITTI type name -> integer code used in tables.
TYPE_CODE: dict[str, int] = {name: i for i, name in enumerate(KITTI_TYPES)}


@dataclass(frozen=True, eq=False)
class ObjectTable:
    """Objects of ``n_frames`` frames concatenated; rows sorted by frame, file order within a frame.

    Attributes:
        frame: (N,) int64 frame index in [0, n_frames).
        type: (N,) int64 code into :data:`~robustbench3d.kitti.labels.KITTI_TYPES`.
        truncated: (N,) float64, GT truncation (results: whatever the file says).
        occluded: (N,) int64 occlusion level.
        alpha: (N,) float64 observation angle, rad.
        bbox: (N, 4) float64 image-2 box left, top, right, bottom, px.
        box3d: (N, 7) float64 ``h, w, l`` (m), bottom centre ``x, y, z`` (rect frame, m), ``ry`` (rad).
        score: (N,) float64 detection score, or None for ground truth.
        n_frames: number of frames (frames may hold no objects).
    """

    frame: np.ndarray
    type: np.ndarray
    truncated: np.ndarray
    occluded: np.ndarray
    alpha: np.ndarray
    bbox: np.ndarray
    box3d: np.ndarray
    score: np.ndarray | None
    n_frames: int

    def __len__(self) -> int:
        return len(self.frame)

    def of_type(self, name: str) -> np.ndarray:
        """(N,) bool mask of rows of KITTI type ``name``."""
        return self.type == TYPE_CODE[name]

    def count_by_type(self) -> dict[str, int]:
        """Rows per KITTI type (types that occur only)."""
        counts = np.bincount(self.type, minlength=len(KITTI_TYPES))
        return {name: int(counts[i]) for i, name in enumerate(KITTI_TYPES) if counts[i]}

    @classmethod
    def from_columns(cls, frame: np.ndarray, types: np.ndarray, numeric: np.ndarray, n_frames: int,
                     scored: bool) -> ObjectTable:
        """Build from label-file columns: ``numeric`` is (N, 14 or 15) columns 2..15(16)."""
        return cls(
            frame=np.asarray(frame, dtype=np.int64), type=np.asarray(types, dtype=np.int64),
            truncated=numeric[:, 0].copy(), occluded=numeric[:, 1].astype(np.int64),
            alpha=numeric[:, 2].copy(), bbox=numeric[:, 3:7].copy(), box3d=np.concatenate(
                [numeric[:, 7:10], numeric[:, 10:13], numeric[:, 13:14]], axis=1),
            score=numeric[:, 14].copy() if scored else None, n_frames=n_frames,
        )

    @classmethod
    def from_labels(cls, frames: Sequence[Labels], scored: bool) -> ObjectTable:
        """Concatenate per-frame :class:`Labels`; ``scored`` demands (and keeps) scores."""
        n = [len(f) for f in frames]
        frame = np.repeat(np.arange(len(frames), dtype=np.int64), n)
        if not frames or sum(n) == 0:
            return cls.from_columns(frame, np.empty(0, np.int64), np.empty((0, 15 if scored else 14)),
                                    len(frames), scored)
        cols = []
        for f in frames:
            if scored and f.score is None:
                raise ValueError("detections must carry scores (16-column results)")
            parts = [f.truncated, f.occluded, f.alpha, f.bbox, f.dimensions, f.location, f.rotation_y]
            if scored:
                parts.append(f.score)
            cols.append(np.column_stack([np.asarray(p, dtype=np.float64) for p in parts]))
            if not np.isfinite(cols[-1]).all():
                raise ValueError(f"frame {len(cols) - 1}: non-finite value in the labels")
        unknown = {str(t) for f in frames for t in f.type} - set(TYPE_CODE)
        if unknown:
            raise ValueError(f"unknown object type(s) {sorted(unknown)}; expected KITTI types")
        types = np.array([TYPE_CODE[t] for f in frames for t in f.type], dtype=np.int64)
        return cls.from_columns(frame, types, np.concatenate(cols), len(frames), scored)
