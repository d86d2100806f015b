"""Frustum-PointNet v1 training loss (reference §1.7), in the frustum frame (m, rad).

total = mask + 1.0·(centre + heading-class + size-class + 20·heading-residual
                    + 20·size-residual + stage-1 centre + 10·corner)

``double_size_residual=True`` (default, faithful) reproduces the original corner construction,
which adds the predicted size residual to the template twice; False adds it once.
Norms use a guarded square root so gradients stay finite when a prediction is exact.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from robustbench3d.victims.fpointnet.box_coding import HEADING_BIN_WIDTH, MEAN_SIZES, NUM_HEADING_BIN
from robustbench3d.victims.fpointnet.model import FPointNetOutput

_TINY = 1e-12


@dataclass(frozen=True)
class LossWeights:
    box: float = 1.0
    heading_residual: float = 20.0
    size_residual: float = 20.0
    corner: float = 10.0


@dataclass
class FPointNetTargets:
    """Per-frustum training targets (frustum frame).

    seg (B, N) int64 0/1; center (B, 3) m (geometric box centre); heading_class (B,) int64;
    heading_residual (B,) rad; size_class (B,) int64; size_residual (B, 3) m (l, w, h).
    """

    seg: torch.Tensor
    center: torch.Tensor
    heading_class: torch.Tensor
    heading_residual: torch.Tensor
    size_class: torch.Tensor
    size_residual: torch.Tensor


def huber(x: torch.Tensor, delta: float) -> torch.Tensor:
    """Mean of 0.5·min(|x|, δ)² + δ·(|x| − min(|x|, δ))."""
    ax = x.abs()
    quad = ax.clamp(max=delta)
    return (0.5 * quad**2 + delta * (ax - quad)).mean()


def safe_norm(x: torch.Tensor, dim: int = -1) -> torch.Tensor:
    """Euclidean norm with a finite (zero) gradient at the origin."""
    return (x * x).sum(dim=dim).clamp_min(_TINY).sqrt()


def box_corners(center: torch.Tensor, heading: torch.Tensor, size_lwh: torch.Tensor) -> torch.Tensor:
    """(…, 8, 3) corners from centres (…, 3), headings (…) about y and sizes (…, 3) l, w, h;
    same layout as :func:`~robustbench3d.victims.fpointnet.box_coding.corners_from_center`."""
    l, w, h = (size_lwh[..., i:i + 1] / 2 for i in range(3))
    x = torch.cat([l, l, -l, -l, l, l, -l, -l], dim=-1)
    y = torch.cat([h, h, h, h, -h, -h, -h, -h], dim=-1)
    z = torch.cat([w, -w, -w, w, w, -w, -w, w], dim=-1)
    c, s = torch.cos(heading)[..., None], torch.sin(heading)[..., None]
    return torch.stack([c * x + s * z, y, -s * x + c * z], dim=-1) + center[..., None, :]


def corner_loss(out: FPointNetOutput, t: FPointNetTargets, double_size_residual: bool = True) -> torch.Tensor:
    """Huber(δ=1) of the per-corner min distance to the GT corners and to the GT box turned by π.

    Predicted box: final centre, GT heading bin centre + its predicted residual, GT size template
    + its predicted residual (twice if ``double_size_residual``).
    """
    b = torch.arange(len(t.heading_class), device=out.center.device)
    mean = torch.as_tensor(MEAN_SIZES, dtype=out.center.dtype, device=out.center.device)
    bin_centre = t.heading_class.to(out.center.dtype) * HEADING_BIN_WIDTH
    heading_pred = bin_centre + out.heading_residuals[b, t.heading_class]
    res_pred = out.size_residuals[b, t.size_class]
    size_pred = mean[t.size_class] + res_pred * (2.0 if double_size_residual else 1.0)
    pred = box_corners(out.center, heading_pred, size_pred)
    heading_gt = bin_centre + t.heading_residual
    size_gt = mean[t.size_class] + t.size_residual
    gt = box_corners(t.center, heading_gt, size_gt)
    gt_flip = box_corners(t.center, heading_gt + np.pi, size_gt)
    dist = torch.minimum(safe_norm(pred - gt), safe_norm(pred - gt_flip))
    return huber(dist, 1.0)


def fpointnet_loss(out: FPointNetOutput, t: FPointNetTargets, weights: LossWeights = LossWeights(),
                   double_size_residual: bool = True) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Total loss and its terms (unweighted) as a dict."""
    b = torch.arange(len(t.heading_class), device=out.center.device)
    mean = torch.as_tensor(MEAN_SIZES, dtype=out.center.dtype, device=out.center.device)
    terms = {
        "mask": F.cross_entropy(out.seg_logits.reshape(-1, 2), t.seg.reshape(-1)),
        "center": huber(safe_norm(out.center - t.center), 2.0),
        "stage1_center": huber(safe_norm(out.stage1_center - t.center), 1.0),
        "heading_class": F.cross_entropy(out.heading_scores, t.heading_class),
        "heading_residual": huber(
            out.heading_residuals_normalized[b, t.heading_class] - t.heading_residual / (np.pi / NUM_HEADING_BIN),
            1.0),
        "size_class": F.cross_entropy(out.size_scores, t.size_class),
        "size_residual": huber(
            safe_norm(out.size_residuals_normalized[b, t.size_class] - t.size_residual / mean[t.size_class]), 1.0),
        "corner": corner_loss(out, t, double_size_residual),
    }
    box = (terms["center"] + terms["heading_class"] + terms["size_class"]
           + weights.heading_residual * terms["heading_residual"]
           + weights.size_residual * terms["size_residual"]
           + terms["stage1_center"] + weights.corner * terms["corner"])
    return terms["mask"] + weights.box * box, terms
