"""Pillarisation: the glue between a velodyne scan and the PointPillars network (shared by torch and ONNX).

Frames: points are in the velodyne frame (x forward, y left, z up; m). The region of interest is the
box ``x in [x_min, x_max), y in [y_min, y_max), z in [z_min, z_max)`` (the camera's forward field),
cut into square pillars of ``pillar_size`` m; pillar ``(iy, ix)`` covers
``[x_min + ix·s, x_min + (ix+1)·s) × [y_min + iy·s, y_min + (iy+1)·s)``.

Two steps, split so the second can carry gradients:

- :func:`assign_pillars` (numpy, no gradients): which points are kept, the pillar of each and its slot
  in the pillar (the first ``max_points`` points of a pillar, in scan order, are kept; the others dropped).
- :func:`pillar_features` (torch, differentiable in the point coordinates; :func:`pillar_features_np` is
  the same in numpy float64, what ``detect`` uses): the (P, M, 9) features
  x, y, z, reflectance, offsets to the pillar's point mean (3) and to the pillar's centre (x, y), zero
  in empty slots, and the (P, M) valid mask.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import torch

#: Number of per-point features made by :func:`pillar_features`.
NUM_POINT_FEATURES = 9


@dataclass(frozen=True)
class PillarGrid:
    """Region of interest (velodyne frame, m), pillar size (m) and points kept per pillar."""

    x_min: float = 0.0
    x_max: float = 70.4
    y_min: float = -40.0
    y_max: float = 40.0
    z_min: float = -3.0
    z_max: float = 1.0
    pillar_size: float = 0.32
    max_points: int = 32

    @property
    def nx(self) -> int:
        """Pillars along x."""
        return round((self.x_max - self.x_min) / self.pillar_size)

    @property
    def ny(self) -> int:
        """Pillars along y."""
        return round((self.y_max - self.y_min) / self.pillar_size)

    def to_dict(self) -> dict[str, float | int]:
        return asdict(self)


@dataclass(frozen=True)
class PillarAssignment:
    """Where the kept points of one scan go.

    Attributes:
        rows: (K,) int64 indices (into the input points) of the kept points, ordered by pillar then slot.
        pillar: (K,) int64 pillar index (0..P-1) of each kept point.
        slot: (K,) int64 slot (0..M-1) of each kept point within its pillar.
        coords: (P, 2) int64 (iy, ix) of each non-empty pillar, in increasing flat index iy·nx + ix.
    """

    rows: np.ndarray
    pillar: np.ndarray
    slot: np.ndarray
    coords: np.ndarray

    @property
    def num_pillars(self) -> int:
        return int(self.coords.shape[0])


def in_region(points: np.ndarray, grid: PillarGrid) -> np.ndarray:
    """(N,) bool: the point lies in the region of interest (half-open box, velodyne frame)."""
    p = np.asarray(points, dtype=np.float64)
    return ((p[:, 0] >= grid.x_min) & (p[:, 0] < grid.x_max) & (p[:, 1] >= grid.y_min) & (p[:, 1] < grid.y_max)
            & (p[:, 2] >= grid.z_min) & (p[:, 2] < grid.z_max))


def cell_of(points: np.ndarray, grid: PillarGrid) -> tuple[np.ndarray, np.ndarray]:
    """(iy, ix) int64 pillar indices of points (floor of the float64 position; clipped to the grid)."""
    p = np.asarray(points, dtype=np.float64)
    ix = np.floor((p[:, 0] - grid.x_min) / grid.pillar_size).astype(np.int64)
    iy = np.floor((p[:, 1] - grid.y_min) / grid.pillar_size).astype(np.int64)
    return np.clip(iy, 0, grid.ny - 1), np.clip(ix, 0, grid.nx - 1)


def assign_pillars(points: np.ndarray, grid: PillarGrid) -> PillarAssignment:
    """Pillar and slot of each point of ``points`` (N, >=3, velodyne) inside the region of interest."""
    rows = np.flatnonzero(in_region(points, grid))
    iy, ix = cell_of(np.asarray(points)[rows], grid)
    flat = iy * grid.nx + ix
    order = np.argsort(flat, kind="stable")  # by pillar, scan order within a pillar
    rows, flat = rows[order], flat[order]
    cells, first, counts = np.unique(flat, return_index=True, return_counts=True)
    pillar = np.repeat(np.arange(len(cells), dtype=np.int64), counts)
    slot = np.arange(len(flat), dtype=np.int64) - np.repeat(first, counts)
    keep = slot < grid.max_points
    coords = np.stack([cells // grid.nx, cells % grid.nx], axis=1).astype(np.int64)
    return PillarAssignment(rows[keep].astype(np.int64), pillar[keep], slot[keep], coords.reshape(-1, 2))


def pillar_features(points: torch.Tensor, assignment: PillarAssignment, grid: PillarGrid,
                    dtype: torch.dtype | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """(P, M, 9) features and (P, M) bool mask of the pillars of ``assignment``.

    ``points``: (N, 4) velodyne x, y, z, reflectance (any float dtype; gradients flow to the kept rows).
    Features per kept point: x, y, z, r, x − x̄, y − ȳ, z − z̄ (x̄: mean of the pillar's kept points),
    x − x_c, y − y_c (x_c: the pillar's centre); empty slots are zero. Computed in ``points``' dtype and
    cast to ``dtype`` (default float32) at the end.
    """
    import torch

    dtype = dtype or torch.float32
    p_count, m = assignment.num_pillars, grid.max_points
    pillar = torch.from_numpy(assignment.pillar)
    slot = torch.from_numpy(assignment.slot)
    kept = points[torch.from_numpy(assignment.rows)]
    xyz = kept[:, :3]
    sums = torch.zeros(p_count, 3, dtype=points.dtype).index_add(0, pillar, xyz)
    counts = torch.zeros(p_count, dtype=points.dtype).index_add(0, pillar, torch.ones_like(xyz[:, 0]))
    mean = sums / counts.clamp(min=1.0)[:, None]
    coords = torch.from_numpy(assignment.coords).to(points.dtype)
    centre = torch.stack([grid.x_min + (coords[:, 1] + 0.5) * grid.pillar_size,
                          grid.y_min + (coords[:, 0] + 0.5) * grid.pillar_size], dim=1)
    feats = torch.cat([kept[:, :4], xyz - mean[pillar], xyz[:, :2] - centre[pillar]], dim=1)
    out = torch.zeros(p_count * m, NUM_POINT_FEATURES, dtype=points.dtype)
    out = out.index_put((pillar * m + slot,), feats)
    mask = torch.zeros(p_count * m, dtype=torch.bool)
    mask[pillar * m + slot] = True
    return out.reshape(p_count, m, NUM_POINT_FEATURES).to(dtype), mask.reshape(p_count, m)


def pillar_features_np(points: np.ndarray, assignment: PillarAssignment,
                       grid: PillarGrid) -> tuple[np.ndarray, np.ndarray]:
    """:func:`pillar_features` in numpy, float64 throughout, cast to float32 at the end: the glue of
    ``detect`` (torch and ONNX victims alike)."""
    p_count, m = assignment.num_pillars, grid.max_points
    kept = np.asarray(points, dtype=np.float64)[assignment.rows]
    xyz = kept[:, :3]
    sums = np.zeros((p_count, 3))
    np.add.at(sums, assignment.pillar, xyz)
    counts = np.bincount(assignment.pillar, minlength=p_count).astype(np.float64)
    mean = sums / np.maximum(counts, 1.0)[:, None]
    coords = assignment.coords.astype(np.float64)
    centre = np.stack([grid.x_min + (coords[:, 1] + 0.5) * grid.pillar_size,
                       grid.y_min + (coords[:, 0] + 0.5) * grid.pillar_size], axis=1).reshape(-1, 2)
    feats = np.concatenate([kept[:, :4], xyz - mean[assignment.pillar], xyz[:, :2] - centre[assignment.pillar]],
                           axis=1)
    out = np.zeros((p_count, m, NUM_POINT_FEATURES))
    out[assignment.pillar, assignment.slot] = feats
    mask = np.zeros((p_count, m), dtype=bool)
    mask[assignment.pillar, assignment.slot] = True
    return out.astype(np.float32), mask


def pillarise(points: np.ndarray, grid: PillarGrid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Numpy entry of the glue: (features (P, M, 9) float32, coords (P, 2) int64, mask (P, M) bool)."""
    a = assign_pillars(points, grid)
    feats, mask = pillar_features_np(points, a, grid)
    return feats, a.coords, mask
