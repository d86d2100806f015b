"""Frustum-PointNet outputs -> KITTI result rows (reference §1.9).

Per frustum: argmax heading bin with its residual, argmax size template with its residual;
(l, w, h) = template + residual; ry = heading + rot_angle (wrapped to [−π, π)); the centre is
rotated back from the frustum frame to rect by −rot_angle and moved from the geometric centre to
the KITTI bottom centre (``y += h/2``, y points down). The 2D box is the proposal that produced
the frustum; alpha is computed from ry and the location; truncation and occlusion are −1.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from robustbench3d.geometry import alpha_from_rotation_y, wrap_angle
from robustbench3d.kitti.labels import Labels
from robustbench3d.victims.fpointnet.box_coding import class_to_angle, class_to_size
from robustbench3d.victims.fpointnet.frustum import rotate_from_frustum
from robustbench3d.victims.fpointnet.model import FPointNetOutput


@dataclass(frozen=True)
class DecodedBoxes:
    """Boxes in the frustum frame (K frustums).

    center (K, 3) geometric centre, m; heading (K,) rad in (−π, π]; size_lwh (K, 3) m;
    score_3d (K,) the GT-path confidence (see :func:`decode`).
    """

    center: np.ndarray
    heading: np.ndarray
    size_lwh: np.ndarray
    score_3d: np.ndarray


def decode(out: FPointNetOutput) -> DecodedBoxes:
    """Argmax decoding of a forward pass.

    ``score_3d`` = (mean object probability over the masked points) x (max heading-bin
    probability) x (max size probability): the exponential of the original code's log score. A
    frustum with an empty mask uses its maximum object probability instead of the mean.
    """
    with torch.no_grad():
        k = torch.arange(out.center.shape[0])
        hcls = out.heading_scores.argmax(dim=1)
        scls = out.size_scores.argmax(dim=1)
        hres = out.heading_residuals[k, hcls]
        sres = out.size_residuals[k, scls]
        prob = out.seg_logits.softmax(dim=-1)[..., 1]
        maskf = out.mask.to(prob.dtype)
        mean_obj = (prob * maskf).sum(1) / out.mask_count.clamp_min(1).to(prob.dtype)
        obj = torch.where(out.mask_count > 0, mean_obj, prob.amax(dim=1))
        score = obj * out.heading_scores.softmax(1).amax(1) * out.size_scores.softmax(1).amax(1)
    hcls_np, scls_np = hcls.cpu().numpy(), scls.cpu().numpy()
    return DecodedBoxes(
        center=out.center.detach().cpu().double().numpy(),
        heading=class_to_angle(hcls_np, hres.cpu().double().numpy()),
        size_lwh=class_to_size(scls_np, sres.cpu().double().numpy()),
        score_3d=score.cpu().double().numpy(),
    )


def to_labels(boxes: DecodedBoxes, rot_angles: np.ndarray, boxes2d: np.ndarray, scores: np.ndarray,
              type_name: str = "Car") -> Labels:
    """KITTI rows in the rect frame for K frustums (rotation angles (K,), 2D boxes (K, 4) pixels,
    scores (K,))."""
    k = len(boxes.heading)
    rot = np.asarray(rot_angles, dtype=np.float64).reshape(k)
    centers = np.stack([rotate_from_frustum(boxes.center[i], rot[i]) for i in range(k)]) if k else np.zeros((0, 3))
    lwh = boxes.size_lwh.reshape(k, 3)
    location = centers.copy()
    location[:, 1] += lwh[:, 2] / 2
    ry = wrap_angle(boxes.heading + rot) if k else np.zeros(0)
    return Labels(
        type=np.array([type_name] * k, dtype=object), truncated=np.full(k, -1.0),
        occluded=np.full(k, -1, dtype=np.int64), alpha=alpha_from_rotation_y(ry, location) if k else np.zeros(0),
        bbox=np.asarray(boxes2d, dtype=np.float64).reshape(k, 4), dimensions=lwh[:, [2, 1, 0]].copy(),
        location=location, rotation_y=np.asarray(ry, dtype=np.float64).reshape(k),
        score=np.asarray(scores, dtype=np.float64).reshape(k),
    )
