"""The universal object's losses, computed from logits (never the log of a probability near 0 or 1).

LiDAR (the seed paper's, reference §3.7): per target car k,

    L_k = -max(IoU_k, floor) * log(1 - p_k),   p_k = max_i softmax(l_i)[object]

over the car's frustum points i (logits ``l_i = (l_i0, l_i1)``, channel 1 "object"). For two classes
``softmax(l)[1] = sigmoid(l1 - l0)`` and ``-log(1 - sigmoid(m)) = softplus(m)``, and both are increasing
in the margin ``m = l1 - l0``, so ``L_k = max(IoU_k, floor) * softplus(max_i m_i)``: the maximum is taken
over the logit margins. ``IoU_k`` is the victim's box IoU with the ground truth, detached; the floor
(default 0.1) keeps gradient on a car the victim already misses.

Box (``lidar_loss="box"`` or ``"seed+box"``; not in the seed paper): per target car, the BEV IoU of the
3D box the victim regresses from the attacked frustum (:class:`~robustbench3d.victims.base.FrustumBoxOracle`)
with the car's ground-truth box, :func:`~robustbench3d.attacks.box_iou.bev_iou_torch`; minimising it moves
the box the benchmark scores (BEV IoU >= 0.7) rather than the segmentation behind it. The seed term alone
lowers the object probabilities of the frustum without moving the lite victim's boxes (measured, see
``docs/attacks.md``).

Image (reference §2.4, the "mirrors the LiDAR loss" reading): per target, the mean over its candidate
predictions of ``-log(1 - o * c)`` with ``o = sigmoid(a)`` the objectness and ``c = sigmoid(b)`` the
class probability (both logits); or (``image_loss="sum"``) the sum over its candidates of IoU >= 0.5 with
the target, the predictions that can still detect it (measured stronger, ``docs/attacks.md``). Since
``1 - o c = (1 + e^a + e^b) / ((1 + e^a)(1 + e^b))``,

    -log(1 - o c) = softplus(a) + softplus(b) - logsumexp(0, a, b),

finite with a finite gradient at any finite logits; without the class term it is ``softplus(a)``.
A target without candidates contributes 0.

Smoothness: ``lambda_lap`` times :func:`~robustbench3d.attacks.object.laplacian_smoothness_torch`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
import torch
import torch.nn.functional as F

from robustbench3d.attacks.object import laplacian_smoothness_torch

if TYPE_CHECKING:
    from robustbench3d.victims.base import ObjectnessCandidates

#: Lower bound of the IoU weight of the LiDAR loss (an undetected car still gets gradient).
IOU_FLOOR = 0.1


def max_object_margin(logits: torch.Tensor) -> torch.Tensor:
    """Largest "object minus background" logit margin over a frustum's (N, 2) logits (scalar);
    ``sigmoid`` of it is the largest object probability."""
    if logits.dim() != 2 or logits.shape[1] != 2 or logits.shape[0] == 0:
        raise ValueError(f"field 'logits': expected (N, 2) with N >= 1, got {tuple(logits.shape)}")
    if not bool(torch.isfinite(logits).all()):
        raise ValueError("field 'logits': contains NaN or inf (the victim's segmentation head diverged)")
    return (logits[:, 1] - logits[:, 0]).max()


def lidar_car_loss(logits: torch.Tensor, iou: float, floor: float = IOU_FLOOR) -> torch.Tensor:
    """``-max(iou, floor) * log(1 - p)`` of one car, ``p`` the largest object probability over its
    frustum's (N, 2) logits (module doc); ``iou`` is a plain number (detached)."""
    return max(float(iou), float(floor)) * F.softplus(max_object_margin(logits))


def box_car_loss(center: torch.Tensor, size_lwh: torch.Tensor, heading: torch.Tensor,
                 gt_box: np.ndarray) -> torch.Tensor:
    """BEV IoU of a regressed box (rect-frame centre (3,), l/w/h (3,), rotation_y) with the ground-truth
    ``gt_box`` (5,) ``x, z, l, w, ry`` (rect frame, m, rad); differentiable in the regressed box."""
    from robustbench3d.attacks.box_iou import bev_iou_torch

    pred = torch.stack([center[0], center[2], size_lwh[0], size_lwh[1], heading.reshape(())])
    return bev_iou_torch(pred.to(torch.float64), torch.as_tensor(np.asarray(gt_box, dtype=np.float64)))


def gt_bev_boxes(labels: Any) -> np.ndarray:
    """(K, 5) ``x, z, l, w, ry`` of KITTI label rows (rect frame)."""
    return np.column_stack([labels.location[:, 0], labels.location[:, 2], labels.dimensions[:, 2],
                            labels.dimensions[:, 1], labels.rotation_y]).astype(np.float64)


def neg_log_one_minus_product(a: torch.Tensor, b: torch.Tensor | None = None) -> torch.Tensor:
    """Elementwise ``-log(1 - sigmoid(a) * sigmoid(b))`` (``-log(1 - sigmoid(a))`` without ``b``),
    in the stable form of the module doc."""
    if b is None:
        return F.softplus(a)
    stacked = torch.stack([torch.zeros_like(a), a, b.to(a.dtype)])
    return F.softplus(a) + F.softplus(b.to(a.dtype)) - torch.logsumexp(stacked, dim=0)


#: How :func:`image_target_losses` combines a target's candidates: the mean over all of them, or the sum over
#: those of IoU >= :data:`SUM_MIN_IOU` with the target.
IMAGE_LOSSES = ("mean", "sum")
SUM_MIN_IOU = 0.5


def image_target_losses(candidates: ObjectnessCandidates, n_targets: int, image_index: int = 0,
                        use_class: bool = True, reduce: str = "mean") -> torch.Tensor:
    """(n_targets,) image loss of each target box of image ``image_index``: the mean over its candidates
    of ``-log(1 - o * c)`` (``-log(1 - o)`` if not ``use_class``), or with ``reduce="sum"`` the sum over its
    candidates of IoU >= :data:`SUM_MIN_IOU`; 0 for a target without (such) candidates."""
    if reduce not in IMAGE_LOSSES:
        raise ValueError(f"image_target_losses: field 'reduce': expected one of {', '.join(IMAGE_LOSSES)}, "
                         f"got {reduce!r}")
    on_image = candidates.image_index == image_index
    if reduce == "sum":
        on_image = on_image & (candidates.iou >= SUM_MIN_IOU)
    target = candidates.target_index[on_image]
    a = candidates.objectness_logit[on_image]
    per = neg_log_one_minus_product(a, candidates.class_logit[on_image] if use_class else None)
    sums = torch.zeros(n_targets, dtype=per.dtype).index_add(0, target, per)
    if reduce == "sum":
        return sums
    counts = torch.zeros(n_targets, dtype=per.dtype).index_add(0, target, torch.ones_like(per))
    return sums / counts.clamp(min=1.0)


def best_candidate_scores(candidates: ObjectnessCandidates, n_targets: int, image_index: int = 0,
                          min_iou: float = 0.5) -> np.ndarray:
    """(n_targets,) largest ``o * c`` over the candidates of each target with IoU >= ``min_iou`` (0 if
    none), detached: how confidently the 2D detector still sees each target."""
    out = np.zeros(n_targets)
    with torch.no_grad():
        keep = (candidates.image_index == image_index) & (candidates.iou >= min_iou)
        score = (candidates.objectness_logit[keep].sigmoid() * candidates.class_logit[keep].sigmoid()).double()
        for t, s in zip(candidates.target_index[keep].tolist(), score.tolist(), strict=True):
            out[t] = max(out[t], s)
    return out


def laplacian_loss(vertices: torch.Tensor, weight: float) -> torch.Tensor:
    """``weight`` times the uniform Laplacian smoothness of the (162, 3) object vertices."""
    return weight * laplacian_smoothness_torch(vertices)
