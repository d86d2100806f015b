"""The universal object's losses, computed from logits (never the log of a probability near 0 or 1).

LiDAR (the seed paper's, reference §3.7): per target car k,

    L_k = -max(IoU_k, floor) * log(1 - p_k),   p_k = max_i softmax(l_i)[object]

over the car's frustum points i (logits ``l_i = (l_i0, l_i1)``, channel 1 "object"). For two classes
``softmax(l)[1] = sigmoid(l1 - l0)`` and ``-log(1 - sigmoid(m)) = softplus(m)``, and both are increasing
in the margin ``m = l1 - l0``, so ``L_k = max(IoU_k, floor) * softplus(max_i m_i)``: the maximum is taken
over the logit margins. ``IoU_k`` is the victim's box IoU with the ground truth, detached; the floor
(default 0.1) keeps gradient on a car the victim already misses.

Every victim gives the trainer these through one interface,
:meth:`~robustbench3d.victims.base.TargetScoreOracle.target_scores`: per target car a logit (for the F-PN
cascades the largest margin ``max_i m_i`` above, in float64) and, for the box terms, the regressed box;
:func:`lidar_target_terms` turns them into the terms below (``softplus`` of the logit: the seed term of any
victim), :func:`image_logit_losses` into the image term of a victim without a 2D objectness oracle.

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
A target without candidates contributes 0. The image losses are a table, :data:`IMAGE_LOSSES` (name ->
:class:`ImageLoss`: the per-target function and the candidate set it reads), which the trainer looks the
configured name up in; an experiment adds a loss with :func:`register_image_loss` (``research/``).

Smoothness: ``lambda_lap`` times :func:`~robustbench3d.attacks.object.laplacian_smoothness_torch`.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
import torch.nn.functional as F

from robustbench3d.attacks.object import laplacian_smoothness_torch

if TYPE_CHECKING:
    from robustbench3d.victims.base import ObjectnessCandidates, TargetScores

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


def target_logit_loss(logit: torch.Tensor, iou: float, floor: float = IOU_FLOOR) -> torch.Tensor:
    """``max(iou, floor) * softplus(logit)`` of one target (``logit``: a scalar of
    :attr:`~robustbench3d.victims.base.TargetScores.logit`); for a frustum victim the same number as
    :func:`lidar_car_loss` of its frustum's logits. ValueError for a non-finite logit."""
    if not bool(torch.isfinite(logit)):
        raise ValueError("field 'logit': NaN or inf (the victim's score diverged)")
    return max(float(iou), float(floor)) * F.softplus(logit)


def lidar_target_terms(scores: TargetScores, iou: np.ndarray, gt_boxes: np.ndarray, *, lidar_loss: str,
                       lambda_box: float, floor: float = IOU_FLOOR) -> list[torch.Tensor]:
    """The LiDAR terms of the targets the victim has something for (``scores.present``), in target order:
    ``"seed"`` :func:`target_logit_loss` with ``iou`` (T,), the detached ``IoU_k``; ``"box"`` ``lambda_box`` x
    :func:`box_car_loss` of ``scores.box`` with ``gt_boxes`` (T, 5) (:func:`gt_bev_boxes`), whose value then
    replaces ``iou[n]`` (in place: ``IoU_k`` of a box term is the regressed box's); ``"seed+box"`` both, the seed
    term weighted by that box IoU. ValueError for a box term without boxes or a non-finite logit."""
    if lidar_loss != "seed" and scores.box is None:
        raise ValueError(f"field 'box': the victim's target_scores gave no boxes (needed by lidar_loss {lidar_loss!r})")
    terms = []
    for n in np.flatnonzero(scores.present).tolist():
        if lidar_loss == "seed":
            terms.append(target_logit_loss(scores.logit[n], float(iou[n]), floor))
            continue
        assert scores.box is not None
        box = scores.box[n]
        box_iou = box_car_loss(box[:3], box[3:6], box[6], gt_boxes[n])
        iou[n] = box_iou.item()
        term = lambda_box * box_iou
        if lidar_loss == "seed+box":
            term = term + target_logit_loss(scores.logit[n], float(iou[n]), floor)
        terms.append(term)
    return terms


def image_logit_losses(scores: TargetScores) -> torch.Tensor:
    """(T,) image loss of each target of a victim scored through its logits: ``softplus(logit)`` =
    ``-log(1 - sigmoid(logit))`` where ``scores.present``, else 0. ValueError for a non-finite logit."""
    index = torch.from_numpy(np.flatnonzero(np.asarray(scores.present, dtype=bool)))
    logit = scores.logit.to(torch.float64)[index]  # an absent target's logit is ignored, even NaN
    if not bool(torch.isfinite(logit).all()):
        raise ValueError("field 'logit': NaN or inf (the victim's score diverged)")
    return torch.zeros(len(scores.present), dtype=torch.float64).index_put((index,), F.softplus(logit))


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


#: Candidates of IoU >= this with their target are those the ``sum`` loss reads.
SUM_MIN_IOU = 0.5
#: The 2D oracle's default candidate threshold (``objectness(iou_threshold=0.3)``): the ``mean`` loss's set.
MEAN_CANDIDATE_IOU = 0.3


@dataclass(frozen=True)
class ImageLoss:
    """One image loss of :data:`IMAGE_LOSSES`.

    ``terms(candidates, n_targets, image_index, use_class)`` is the (n_targets,) loss of each target box of
    image ``image_index`` (0 for a target without candidates), differentiable in the candidates' logits;
    ``use_class=False``: the objectness alone. ``candidate_iou``: the IoU threshold of the 2D oracle's
    candidate set the loss is defined on (``objectness(iou_threshold=...)``: IoU >= it with the target, or
    the prior's centre inside the target); the trainer asks for that set (never above its own score
    threshold, :data:`~robustbench3d.attacks.train_config.CANDIDATE_IOU`)."""

    terms: Callable[[ObjectnessCandidates, int, int, bool], torch.Tensor]
    candidate_iou: float

    def __call__(self, candidates: ObjectnessCandidates, n_targets: int, image_index: int = 0,
                 use_class: bool = True) -> torch.Tensor:
        return self.terms(candidates, n_targets, image_index, use_class)


def _candidate_terms(candidates: ObjectnessCandidates, image_index: int, use_class: bool,
                     min_iou: float | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Target index and ``-log(1 - o c)`` (``-log(1 - o)`` if not ``use_class``) of each candidate of image
    ``image_index`` (only those of IoU >= ``min_iou`` with their target, if given)."""
    on_image = candidates.image_index == image_index
    if min_iou is not None:
        on_image = on_image & (candidates.iou >= min_iou)
    a = candidates.objectness_logit[on_image]
    per = neg_log_one_minus_product(a, candidates.class_logit[on_image] if use_class else None)
    return candidates.target_index[on_image], per


def mean_candidate_losses(candidates: ObjectnessCandidates, n_targets: int, image_index: int = 0,
                          use_class: bool = True) -> torch.Tensor:
    """(n_targets,) mean over each target's candidates of ``-log(1 - o c)`` (the ``mean`` image loss)."""
    target, per = _candidate_terms(candidates, image_index, use_class)
    sums = torch.zeros(n_targets, dtype=per.dtype).index_add(0, target, per)
    counts = torch.zeros(n_targets, dtype=per.dtype).index_add(0, target, torch.ones_like(per))
    return sums / counts.clamp(min=1.0)


def sum_candidate_losses(candidates: ObjectnessCandidates, n_targets: int, image_index: int = 0,
                         use_class: bool = True) -> torch.Tensor:
    """(n_targets,) sum over each target's candidates of IoU >= :data:`SUM_MIN_IOU` of ``-log(1 - o c)``
    (the ``sum`` image loss: the predictions that can still detect the target)."""
    target, per = _candidate_terms(candidates, image_index, use_class, SUM_MIN_IOU)
    return torch.zeros(n_targets, dtype=per.dtype).index_add(0, target, per)


#: The image losses by name (``TrainConfig.image_loss``, ``--image-loss``): how a target's candidates
#: combine. ``mean`` and ``sum`` are the shipped objects' (never replaced); an experiment adds its own with
#: :func:`register_image_loss` and trains with it by name.
IMAGE_LOSSES: dict[str, ImageLoss] = {
    "mean": ImageLoss(mean_candidate_losses, MEAN_CANDIDATE_IOU),
    "sum": ImageLoss(sum_candidate_losses, SUM_MIN_IOU),
}
_LOSS_NAME = re.compile(r"^[a-z0-9][a-z0-9_.+-]*$")


def register_image_loss(name: str, terms: Callable[[ObjectnessCandidates, int, int, bool], torch.Tensor],
                        candidate_iou: float = MEAN_CANDIDATE_IOU) -> ImageLoss:
    """Add the image loss ``name`` (:class:`ImageLoss`) to :data:`IMAGE_LOSSES` for this process and return
    it; refuses a name already there (``mean`` and ``sum`` stay what the shipped objects were trained with).
    ``candidate_iou`` in [0, 1]: an IoU threshold (0: every prior of the image is a candidate)."""
    if not isinstance(name, str) or not _LOSS_NAME.match(name):
        raise ValueError(f"register_image_loss: field 'name': expected lowercase letters, digits and . _ + - "
                         f"(it is recorded in the object file), got {name!r}")
    if name in IMAGE_LOSSES:
        raise ValueError(f"register_image_loss: field 'name': {name!r} is already an image loss "
                         f"({', '.join(IMAGE_LOSSES)}); choose another name")
    if not callable(terms):
        raise ValueError(f"register_image_loss: field 'terms': expected a function, got {type(terms).__name__}")
    if not isinstance(candidate_iou, (int, float)) or not 0.0 <= candidate_iou <= 1.0:  # an IoU; 0: every prior
        raise ValueError(f"register_image_loss: field 'candidate_iou': expected 0 to 1, got {candidate_iou!r}")
    IMAGE_LOSSES[name] = ImageLoss(terms, float(candidate_iou))
    return IMAGE_LOSSES[name]


def image_target_losses(candidates: ObjectnessCandidates, n_targets: int, image_index: int = 0,
                        use_class: bool = True, reduce: str = "mean") -> torch.Tensor:
    """(n_targets,) image loss ``reduce`` (a name of :data:`IMAGE_LOSSES`) of each target box of image
    ``image_index``: by default the mean over its candidates of ``-log(1 - o * c)`` (``-log(1 - o)`` if not
    ``use_class``), with ``reduce="sum"`` the sum over its candidates of IoU >= :data:`SUM_MIN_IOU`; 0 for a
    target without (such) candidates."""
    if reduce not in IMAGE_LOSSES:
        raise ValueError(f"image_target_losses: field 'reduce': expected one of {', '.join(IMAGE_LOSSES)}, "
                         f"got {reduce!r}")
    out = IMAGE_LOSSES[reduce](candidates, n_targets, image_index, use_class)
    if tuple(out.shape) != (n_targets,):
        raise ValueError(f"image_target_losses: image loss {reduce!r} returned shape {tuple(out.shape)}, "
                         f"expected ({n_targets},)")
    return out


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
