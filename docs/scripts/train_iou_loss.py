"""`robustbench3d attack train` with the image loss of ``texture_bound.py``'s ``iou`` (an experiment, not an option).

Runs the CLI with its arguments after two substitutions in this process only: the cascade's objectness candidates
keep their decoded boxes and IoUs differentiable (the oracle detaches them), and ``--image-loss sum``'s per-car sum
of ``-log(1 - o c)`` over the candidates of IoU >= 0.5 becomes the sum of ``-log(1 - o c IoU)``. The object file
still records ``image_loss: sum``; the measurement is in ``docs/attacks.md``.

Usage: python docs/scripts/train_iou_loss.py attack train adv-texture --victim fpointnet-v1-lite --image-loss sum ...
"""

from __future__ import annotations

import sys

import torch

import robustbench3d.attacks.train as train
import robustbench3d.victims.cascade as cascade
from robustbench3d.attacks.losses import SUM_MIN_IOU
from robustbench3d.cli import main
from robustbench3d.victims.yolo.boxes import box_iou, cxcywh_to_xyxy
from robustbench3d.victims.yolo.detector import candidates_for_targets


def candidates_with_box_gradients(pred, geo, target_boxes: torch.Tensor, iou_threshold: float,
                                  image_index: int) -> dict[str, torch.Tensor]:
    """The candidates of ``victims.yolo.detector.candidates_for_targets``, their boxes and IoUs recomputed from the
    predictions without detaching (the same arithmetic: every prior decoded, its IoU with every target)."""
    chosen = candidates_for_targets(pred, geo, target_boxes, iou_threshold, image_index)
    boxes = geo.to_image(cxcywh_to_xyxy(pred.boxes[image_index]))
    iou = box_iou(boxes, target_boxes.to(boxes.dtype).reshape(-1, 4))
    return {**chosen, "boxes": boxes[chosen["prior"]], "iou": iou[chosen["prior"], chosen["target"]]}


def iou_weighted_losses(cands, n_targets: int, image_index: int = 0, use_class: bool = True,
                        reduce: str = "sum") -> torch.Tensor:
    """(n_targets,) sum over each target's candidates of IoU >= 0.5 of ``-log(1 - o c IoU)``."""
    keep = (cands.image_index == image_index) & (cands.iou.detach() >= SUM_MIN_IOU)
    score = torch.sigmoid(cands.objectness_logit[keep].double()) * torch.sigmoid(cands.class_logit[keep].double())
    # clamped: o c rounds to 1 in float64 for logits above about 37
    per = -torch.log1p(-(score * cands.iou[keep].double()).clamp(max=1.0 - 1e-9))
    return torch.zeros(n_targets, dtype=per.dtype).index_add(0, cands.target_index[keep], per)


if __name__ == "__main__":
    cascade.candidates_for_targets = candidates_with_box_gradients
    train.image_target_losses = iou_weighted_losses
    sys.exit(main(sys.argv[1:]))
