"""LiDAR-only car detector: ground removal, BEV clustering, L-shape box fitting (numpy only).

Frames: velodyne (x forward, y left, z up; m) for all fitting; results are converted to the KITTI
rect frame (x right, y down, z forward), bottom-centre location, rotation_y about rect y.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from robustbench3d.geometry import alpha_from_rotation_y, box_corners, project_boxes_to_image
from robustbench3d.kitti.calib import Calibration
from robustbench3d.kitti.dataset import Frame
from robustbench3d.kitti.labels import Labels
from robustbench3d.victims.base import AttackedScene, AttackTargets, ProposalsArg, TargetScores


@dataclass(frozen=True)
class ClusterSettings:
    """Tuning of :class:`LidarClusterDetector` (lengths in m, angles in degrees)."""

    seed: int = 0
    ransac_iterations: int = 150
    ground_candidate_z: float = -1.2  # only points below this (velodyne z) seed the ground plane
    ground_inlier: float = 0.15
    min_height: float = 0.25  # points closer to the ground plane are ground
    max_height: float = 2.5
    max_range: float = 70.0
    cell: float = 0.25
    min_points: int = 12
    min_car: tuple[float, float] = (3.9, 1.6)  # (length, width) partially seen boxes are grown to
    max_length: float = 6.5
    max_width: float = 2.6
    min_extent: float = 1.0  # the longer observed side must reach this
    box_height: tuple[float, float] = (0.9, 2.4)
    angle_step: float = 1.0


def fit_ground(points: np.ndarray, s: ClusterSettings, rng: np.random.Generator) -> np.ndarray:
    """Plane (a, b, c, d), unit normal with c > 0, a·x + b·y + c·z + d = height above ground."""
    cand = points[points[:, 2] < s.ground_candidate_z]
    if len(cand) < 3:
        return np.array([0.0, 0.0, 1.0, 1.73])  # KITTI mounting height as a fallback
    best, best_count = np.array([0.0, 0.0, 1.0, 1.73]), -1
    for _ in range(s.ransac_iterations):
        p = cand[rng.choice(len(cand), 3, replace=False)]
        n = np.cross(p[1] - p[0], p[2] - p[0])
        norm = np.linalg.norm(n)
        if norm < 1e-9:
            continue
        n = n / norm
        if n[2] < 0:
            n = -n
        if n[2] < 0.9:  # not a near-horizontal plane
            continue
        d = -float(n @ p[0])
        count = int((np.abs(cand @ n + d) < s.ground_inlier).sum())
        if count > best_count:
            best, best_count = np.append(n, d), count
    return best


def connected_cells(cells: np.ndarray) -> np.ndarray:
    """Component label per row of integer BEV cells (N, 2), 8-connectivity."""
    index = {tuple(c): i for i, c in enumerate(map(tuple, cells))}
    labels = np.full(len(cells), -1, dtype=np.int64)
    current = 0
    for start in range(len(cells)):
        if labels[start] >= 0:
            continue
        labels[start] = current
        stack = [start]
        while stack:
            i = stack.pop()
            cx, cy = cells[i]
            for dx in (-1, 0, 1):
                for dy in (-1, 0, 1):
                    j = index.get((cx + dx, cy + dy))
                    if j is not None and labels[j] < 0:
                        labels[j] = current
                        stack.append(j)
        current += 1
    return labels


def lshape_yaw(xy: np.ndarray, step_deg: float) -> float:
    """Yaw (rad, in [0, π/2)) of the rectangle edges maximising the closeness criterion."""
    best, best_score = 0.0, -np.inf
    for theta in np.deg2rad(np.arange(0.0, 90.0, step_deg)):
        e1 = np.array([np.cos(theta), np.sin(theta)])
        e2 = np.array([-np.sin(theta), np.cos(theta)])
        c1, c2 = xy @ e1, xy @ e2
        d1 = np.minimum(c1.max() - c1, c1 - c1.min())
        d2 = np.minimum(c2.max() - c2, c2 - c2.min())
        score = float((1.0 / np.maximum(np.minimum(d1, d2), 0.01)).sum())
        if score > best_score:
            best, best_score = float(theta), score
    return best


def fit_box(xy: np.ndarray, s: ClusterSettings) -> tuple[np.ndarray, float, float, float] | None:
    """Oriented BEV box of a cluster: (centre (2,), yaw rad, length, width) or None if not car-like.

    Sides shorter than the minimum car size are grown away from the sensor (the unseen side).
    """
    theta = lshape_yaw(xy, s.angle_step)
    axes = np.array([[np.cos(theta), np.sin(theta)], [-np.sin(theta), np.cos(theta)]])
    proj = xy @ axes.T  # (N, 2) coordinates along the two edges
    lo, hi = proj.min(axis=0), proj.max(axis=0)
    ext = hi - lo
    long_axis = int(np.argmax(ext))
    if ext[long_axis] < s.min_extent or ext[long_axis] > s.max_length or ext[1 - long_axis] > s.max_width:
        return None
    mins = np.empty(2)
    mins[long_axis], mins[1 - long_axis] = s.min_car
    sensor = -axes @ xy.mean(axis=0)  # sensor (origin) relative to the cluster, in edge coordinates
    for k in range(2):
        if ext[k] < mins[k]:
            grow = mins[k] - ext[k]
            if sensor[k] < 0:  # sensor on the low side: grow towards high
                hi[k] += grow
            else:
                lo[k] -= grow
    centre = axes.T @ ((lo + hi) / 2)
    yaw = theta if long_axis == 0 else theta + np.pi / 2
    ext = hi - lo
    return centre, float(yaw), float(ext[long_axis]), float(ext[1 - long_axis])


def velo_yaw_to_rotation_y(yaw: float, calib: Calibration) -> float:
    """Heading about velodyne z (rad, from +x) -> KITTI rotation_y about rect y."""
    d = calib.velo_to_rect[:3, :3] @ np.array([np.cos(yaw), np.sin(yaw), 0.0])
    return float(np.arctan2(-d[2], d[0]))


#: Width (m) of the soft edges of :meth:`LidarClusterDetector.target_scores`' footprint and height window.
SOFT_EDGE = 0.1


class LidarClusterDetector:
    """:class:`robustbench3d.victims.base.Detector` for Cars from the scan alone, with a differentiable
    surrogate score (:meth:`target_scores`)."""

    supported_proposals: tuple[str, ...] = ("detector",)

    def __init__(self, settings: ClusterSettings | None = None):
        self.settings = settings or ClusterSettings()

    def target_scores(self, scene: AttackedScene, targets: AttackTargets, *, with_box: bool = False) -> TargetScores:
        """:class:`~robustbench3d.victims.base.TargetScoreOracle`: per target, a soft count of the scene's points
        inside its bird's-eye-view footprint between ``min_height`` and ``max_height`` over the fitted ground,
        minus ``min_points`` -- fewer points than a cluster needs gives a negative logit, as ``detect`` then drops
        the car. Differentiable in ``scene.points_rect`` (the ground plane, fitted on ``scene.frame.scan``, held
        fixed); a surrogate of the clustering, not the clustering (no boxes: ``with_box`` gives none)."""
        import torch

        s, frame = self.settings, scene.frame
        plane = fit_ground(np.asarray(frame.scan[:, :3], dtype=np.float64), s, np.random.default_rng(s.seed))
        to_velo = torch.from_numpy(np.array(frame.calib.rect_to_velo, dtype=np.float64))
        pts = scene.points_rect[:, :3].to(torch.float64)
        height = (pts @ to_velo[:3, :3].T + to_velo[:3, 3]) @ torch.from_numpy(plane[:3]) + plane[3]

        def soft(margin: torch.Tensor) -> torch.Tensor:  # 1 well inside, 0 well outside
            return torch.sigmoid(margin / SOFT_EDGE)

        in_height = soft(height - s.min_height) * soft(s.max_height - height)
        logits = []
        for x, _, z, _, w, length, ry in targets.boxes3d:  # bottom-centre x, y, z; h, w, l; rotation_y
            dx, dz = pts[:, 0] - x, pts[:, 2] - z
            along, across = np.cos(ry) * dx - np.sin(ry) * dz, np.sin(ry) * dx + np.cos(ry) * dz
            inside = soft(length / 2 - along.abs()) * soft(w / 2 - across.abs()) * in_height
            logits.append(inside.sum() - s.min_points)
        logit = torch.stack(logits) if logits else torch.zeros(0, dtype=torch.float64)
        return TargetScores(logit=logit, present=np.ones(len(targets), dtype=bool))

    def detect(self, frames: Sequence[Frame], proposals: ProposalsArg = "detector") -> list[Labels]:
        """Detections per frame from the scan alone. The harness gives frames without labels; a
        ``"gt"`` cell would pass ground-truth 2D boxes (``Proposals``), which this victim cannot use."""
        if not isinstance(proposals, str) or proposals != "detector":
            raise ValueError("lidar-cluster is LiDAR-only: it supports proposals='detector' only")
        return [self.detect_frame(f) for f in frames]

    def detect_frame(self, frame: Frame) -> Labels:
        s = self.settings
        pts = np.asarray(frame.scan[:, :3], dtype=np.float64)
        uv, depth = frame.calib.rect_to_image(frame.calib.velo_to_rect_points(pts))
        w, h = frame.image_size
        in_fov = ((pts[:, 0] > 0) & (depth > 0.1) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0)
                  & (uv[:, 1] < h) & (np.hypot(pts[:, 0], pts[:, 1]) < s.max_range))
        pts = pts[in_fov]
        plane = fit_ground(pts, s, np.random.default_rng(s.seed))
        height = pts @ plane[:3] + plane[3]
        keep = (height > s.min_height) & (height < s.max_height)
        pts, height = pts[keep], height[keep]
        rows = []
        if len(pts):
            cells = np.floor(pts[:, :2] / s.cell).astype(np.int64)
            uniq, inverse = np.unique(cells, axis=0, return_inverse=True)
            comp = connected_cells(uniq)[inverse.reshape(-1)]
            for c in range(int(comp.max()) + 1):
                sel = comp == c
                if sel.sum() < s.min_points:
                    continue
                top = float(height[sel].max())
                if not s.box_height[0] <= top <= s.box_height[1]:
                    continue
                fit = fit_box(pts[sel, :2], s)
                if fit is None:
                    continue
                centre, yaw, length, width = fit
                ground_z = -(plane[0] * centre[0] + plane[1] * centre[1] + plane[3]) / plane[2]
                bottom_velo = np.array([centre[0], centre[1], ground_z])
                rows.append((bottom_velo, yaw, length, width, top, int(sel.sum())))
        return self._to_labels(rows, frame)

    def _to_labels(self, rows: list, frame: Frame) -> Labels:
        if not rows:
            return Labels.empty(with_score=True)
        calib = frame.calib
        loc = calib.velo_to_rect_points(np.stack([r[0] for r in rows]))
        ry = np.array([velo_yaw_to_rotation_y(r[1], calib) for r in rows])
        ry = (ry + np.pi) % (2 * np.pi) - np.pi
        dims = np.array([[r[4], r[3], r[2]] for r in rows])  # h, w, l
        boxes, valid = project_boxes_to_image(box_corners(dims, loc, ry), calib, frame.image_size)
        score = np.array([1.0 - np.exp(-r[5] / 50.0) for r in rows])
        n = int(valid.sum())
        return Labels(
            type=np.array(["Car"] * n, dtype=object), truncated=np.full(n, -1.0),
            occluded=np.full(n, -1, dtype=np.int64), alpha=alpha_from_rotation_y(ry[valid], loc[valid]),
            bbox=boxes[valid], dimensions=dims[valid], location=loc[valid], rotation_y=ry[valid], score=score[valid],
        )
