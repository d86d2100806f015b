"""The PointPillars-style LiDAR-only Car victim: :class:`~robustbench3d.victims.base.Detector` and
:class:`~robustbench3d.victims.base.TargetScoreOracle`.

``detect``: the frame's scan (velodyne) is cut to the camera's field of view and the pillar grid
(:func:`~robustbench3d.victims.pointpillars.glue.crop_scan`), pillarised, run through the network and
decoded at the 3×3 heatmap peaks scoring at least ``score_threshold`` (default 0.05, so AP sees the whole
curve); no other NMS. ``target_scores``: see :meth:`PointPillarsDetector.target_scores`.

Weights file (``model.pt`` of ``robustbench3d victims train-pointpillars``): ``{"config", "state_dict"}``
read as data only (:func:`~robustbench3d.victims.torchfile.load_torch_data`).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from robustbench3d.errors import RobustBenchError
from robustbench3d.fileio import sha256_file
from robustbench3d.kitti.calib import Calibration
from robustbench3d.kitti.dataset import Frame
from robustbench3d.kitti.labels import Labels
from robustbench3d.victims.base import AttackedScene, AttackTargets, ProposalsArg, TargetScores
from robustbench3d.victims.pointpillars.config import PointPillarsConfig, output_shape
from robustbench3d.victims.pointpillars.glue import (
    DecodeOptions,
    crop_mask,
    crop_scan,
    decode_output,
    run_scan,
)
from robustbench3d.victims.pointpillars.model import PointPillars
from robustbench3d.victims.pointpillars.pillars import assign_pillars, pillar_features
from robustbench3d.victims.pointpillars.targets import cell_size
from robustbench3d.victims.torchfile import build_network, load_torch_data, network_part


def load_pointpillars(path: str | Path, sha256: str | None = None) -> PointPillars:
    """The network of a ``model.pt`` (read as data only); with ``sha256`` the file's hash is checked first."""
    path = Path(path)
    if sha256 is not None and path.is_file() and sha256_file(path) != sha256:
        raise RobustBenchError(f"{path}: sha256 does not match the registered weights ({sha256})")
    what = "PointPillars model.pt (robustbench3d victims train-pointpillars)"
    part = network_part(load_torch_data(path, what), path, what)
    return build_network(lambda c: PointPillars(PointPillarsConfig.from_dict(c)), part, path, "pointpillars")


def footprint_cells(box_velo: np.ndarray, cfg: PointPillarsConfig) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of the output cells whose centre lies in the BEV footprint (l × w rectangle) of a
    velodyne box (7,), plus the cell holding the box centre; cells off the map are left out."""
    g, c = cfg.grid, cell_size(cfg)
    h, w = output_shape(cfg)
    x, y, _, length, width, _, yaw = np.asarray(box_velo, dtype=np.float64)
    reach = 0.5 * np.hypot(length, width)
    i0, i1 = int(np.floor((x - reach - g.x_min) / c)), int(np.floor((x + reach - g.x_min) / c))
    j0, j1 = int(np.floor((y - reach - g.y_min) / c)), int(np.floor((y + reach - g.y_min) / c))
    jj, ii = np.meshgrid(np.arange(max(j0, 0), min(j1, h - 1) + 1), np.arange(max(i0, 0), min(i1, w - 1) + 1),
                         indexing="ij")
    dx, dy = g.x_min + (ii + 0.5) * c - x, g.y_min + (jj + 0.5) * c - y
    along, across = dx * np.cos(yaw) + dy * np.sin(yaw), -dx * np.sin(yaw) + dy * np.cos(yaw)
    inside = (np.abs(along) <= length / 2) & (np.abs(across) <= width / 2)
    ci, cj = int(np.floor((x - g.x_min) / c)), int(np.floor((y - g.y_min) / c))
    inside |= (ii == ci) & (jj == cj)
    return jj[inside].astype(np.int64), ii[inside].astype(np.int64)


def _rect_to_velo_torch(points_rect: torch.Tensor, calib: Calibration) -> torch.Tensor:
    """(N, 3+) rect xyz -> (N, 3) velodyne xyz, differentiable (the calibration's exact inverse)."""
    m = torch.tensor(np.array(calib.rect_to_velo), dtype=points_rect.dtype)
    return points_rect[:, :3] @ m[:3, :3].T + m[:3, 3]


class PointPillarsDetector:
    """The victim (module doc). ``dtype``: the network's dtype (float32; float64 for gradient checks)."""

    supported_proposals: tuple[str, ...] = ("detector",)

    def __init__(self, model: PointPillars, options: DecodeOptions | None = None,
                 dtype: torch.dtype = torch.float32):
        self.model = model.to(dtype).eval()
        self.cfg: PointPillarsConfig = model.cfg
        self.options = options or DecodeOptions()
        self.dtype = dtype

    # ---- detection ---------------------------------------------------------------------
    def network(self, feats: np.ndarray, coords: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """(9, H, W) output of the torch network on the glue's numpy inputs (no gradients)."""
        with torch.no_grad():
            out = self.model(torch.from_numpy(feats).to(self.dtype), torch.from_numpy(coords), torch.from_numpy(mask))
        return out[0].numpy()

    def output(self, scan: np.ndarray, calib: Calibration, image_size: tuple[int, int]) -> np.ndarray:
        """(9, H, W) output for a velodyne scan (N, 4) through the numpy glue (:func:`~.glue.run_scan`)."""
        return run_scan(self.network, crop_scan(scan, calib, image_size, self.cfg.grid), self.cfg)

    def detect(self, frames: Sequence[Frame], proposals: ProposalsArg = "detector") -> list[Labels]:
        """KITTI Car detections per frame (rect frame, 2D box = projected 3D box clipped to the image)."""
        if proposals != "detector":
            raise ValueError("pointpillars finds its own objects: proposals must be 'detector'")
        return [decode_output(self.output(f.scan, f.calib, f.image_size), self.cfg, f.calib, f.image_size,
                              self.options) for f in frames]

    # ---- white box ---------------------------------------------------------------------
    def scene_output(self, scene: AttackedScene) -> torch.Tensor:
        """(9, H, W) output (network dtype) on ``scene.points_rect``, differentiable w.r.t. its kept rows.

        The rows are moved to the velodyne frame in torch; the crop (field of view, region) and the
        pillar assignment use their detached values (floor: no gradient); the point features and
        everything after carry gradients."""
        frame = scene.frame
        pts = scene.points_rect
        velo = torch.cat([_rect_to_velo_torch(pts, frame.calib), pts[:, 3:4]], dim=1)
        v = velo.detach().numpy()
        rows = np.flatnonzero(crop_mask(v, frame.calib, frame.image_size, self.cfg.grid))
        kept = velo[torch.from_numpy(rows)]
        a = assign_pillars(v[rows], self.cfg.grid)
        feats, mask = pillar_features(kept, a, self.cfg.grid, self.dtype)
        return self.model(feats, torch.from_numpy(a.coords), mask)[0]

    def target_scores(self, scene: AttackedScene, targets: AttackTargets, *, with_box: bool = False) -> TargetScores:
        """Per target: the largest heatmap logit (float64) over the output cells of its BEV footprint
        (:func:`footprint_cells`: cells whose centre lies in the ground-truth box's l × w rectangle, and the
        cell of its centre) -- the cells whose peak would be the target's detection, so on a clean frame
        ``sigmoid(logit)`` is the score ``detect`` reports for a well-detected car. ``present`` is False
        where no such cell is on the map. ``with_box``: the box decoded at that argmax cell (geometric
        centre x, y, z rect, l, w, h, rotation_y), differentiable. ``scene.proposals`` is ignored."""
        from robustbench3d.victims.pointpillars.targets import labels_to_velo_boxes

        frame = scene.frame
        out = self.scene_output(scene).to(torch.float64)
        b3 = targets.boxes3d
        labels = Labels(type=np.array(["Car"] * len(b3), dtype=object), truncated=np.zeros(len(b3)),
                        occluded=np.zeros(len(b3), dtype=np.int64), alpha=np.zeros(len(b3)),
                        bbox=targets.boxes2d, dimensions=b3[:, 3:6], location=b3[:, 0:3], rotation_y=b3[:, 6])
        boxes = labels_to_velo_boxes(labels, frame.calib)
        logits, decoded = [], []
        present = np.zeros(len(b3), dtype=bool)
        for k in range(len(b3)):
            rows, cols = footprint_cells(boxes[k], self.cfg)
            if len(rows) == 0:
                logits.append(torch.zeros((), dtype=torch.float64))
                decoded.append(torch.zeros(7, dtype=torch.float64))
                continue
            present[k] = True
            cand = out[0, torch.from_numpy(rows), torch.from_numpy(cols)]
            best = int(torch.argmax(cand))
            logits.append(cand[best])
            if with_box:
                decoded.append(self._box_at(out, int(rows[best]), int(cols[best]), frame.calib))
        logit = torch.stack(logits) if logits else torch.zeros(0, dtype=torch.float64)
        box = None
        if with_box:
            box = torch.stack(decoded) if decoded else torch.zeros(0, 7, dtype=torch.float64)
        return TargetScores(logit=logit, present=present, box=box)

    def _box_at(self, out: torch.Tensor, row: int, col: int, calib: Calibration) -> torch.Tensor:
        """The box decoded at one output cell as (7,) rect centre x, y, z, l, w, h, rotation_y (float64)."""
        g, c = self.cfg.grid, cell_size(self.cfg)
        o = out[:, row, col]
        centre = torch.stack([g.x_min + (col + o[1]) * c, g.y_min + (row + o[2]) * c, o[3]])
        m = torch.tensor(np.array(calib.velo_to_rect), dtype=torch.float64)
        centre_rect = m[:3, :3] @ centre + m[:3, 3]
        yaw = torch.atan2(o[7], o[8])
        ry = -yaw - torch.pi / 2
        ry = torch.atan2(torch.sin(ry), torch.cos(ry))
        return torch.cat([centre_rect, torch.exp(o[4:7]), ry.reshape(1)])


def untrained(seed: int = 0, cfg: PointPillarsConfig | None = None) -> PointPillars:
    """A randomly initialised network (plumbing tests)."""
    from robustbench3d.victims.pointpillars.model import build_model

    return build_model(cfg or PointPillarsConfig(), seed).eval()

