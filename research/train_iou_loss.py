"""`robustbench3d attack train` with the box-IoU-weighted image loss ``iou`` (an experiment, not an option).

Registers the image loss ``iou`` (:func:`robustbench3d.attacks.losses.register_image_loss`) in this process: per
car the sum over its candidates of IoU >= 0.5 of ``-log(1 - o c IoU)`` (``--image-loss sum``'s candidates and
terms, each weighted by the candidate box's IoU with the car), and trains with it by name: the object file records
``image_loss: iou``. So that the IoU carries gradient (the boxes that survive can also be moved off the car), the
2D detector's candidate selection keeps the decoded boxes' gradients inside :func:`box_gradients`: the one
substitution of product code left, since the victim's oracle detaches boxes and IoUs by contract
(:class:`~robustbench3d.victims.base.ObjectnessCandidates`); the loss refuses to run on detached IoUs. The
measurement is in ``docs/attacks.md``.

Usage: python research/train_iou_loss.py adv-texture --victim fpointnet-v1-lite --out OBJ.ply ...
       (the options of ``robustbench3d attack train``, without ``--image-loss``)
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator
from contextlib import contextmanager

import torch

import robustbench3d.victims.yolo.detector as detector
from robustbench3d.attacks.losses import IMAGE_LOSSES, SUM_MIN_IOU, register_image_loss
from robustbench3d.commands.attack_train import add_arguments, run
from robustbench3d.errors import RobustBenchError
from robustbench3d.victims.yolo.boxes import box_iou, cxcywh_to_xyxy
from robustbench3d.victims.yolo.detector import candidates_for_targets

#: The name the loss is registered and recorded under.
IOU_LOSS = "iou"


def candidates_with_box_gradients(pred, geo, target_boxes: torch.Tensor, iou_threshold: float,
                                  image_index: int) -> dict[str, torch.Tensor]:
    """The candidates of ``victims.yolo.detector.candidates_for_targets``, their boxes and IoUs recomputed from the
    predictions without detaching (the same arithmetic: every prior decoded, its IoU with every target)."""
    chosen = candidates_for_targets(pred, geo, target_boxes, iou_threshold, image_index)
    boxes = geo.to_image(cxcywh_to_xyxy(pred.boxes[image_index]))
    iou = box_iou(boxes, target_boxes.to(boxes.dtype).reshape(-1, 4))
    return {**chosen, "boxes": boxes[chosen["prior"]], "iou": iou[chosen["prior"], chosen["target"]]}


@contextmanager
def box_gradients() -> Iterator[None]:
    """Inside the block the 2D detector's candidates keep their boxes' and IoUs' gradients
    (:func:`candidates_with_box_gradients` in place of ``detector.candidates_for_targets``, which the
    detector's ``target_candidates`` calls); restored on leaving."""
    saved = detector.candidates_for_targets
    detector.candidates_for_targets = candidates_with_box_gradients
    try:
        yield
    finally:
        detector.candidates_for_targets = saved


def iou_weighted_losses(cands, n_targets: int, image_index: int = 0, use_class: bool = True) -> torch.Tensor:
    """(n_targets,) sum over each target's candidates of IoU >= 0.5 of ``-log(1 - o c IoU)`` (``-log(1 - o IoU)``
    if not ``use_class``)."""
    keep = (cands.image_index == image_index) & (cands.iou.detach() >= SUM_MIN_IOU)
    if bool(keep.any()) and cands.objectness_logit.requires_grad and not cands.iou.requires_grad:
        raise RuntimeError("iou_weighted_losses: the candidates' IoUs are detached; run inside box_gradients()")
    score = torch.sigmoid(cands.objectness_logit[keep].double())
    if use_class:
        score = score * torch.sigmoid(cands.class_logit[keep].double())
    # clamped: o c rounds to 1 in float64 for logits above about 37
    per = -torch.log1p(-(score * cands.iou[keep].double()).clamp(max=1.0 - 1e-9))
    return torch.zeros(n_targets, dtype=per.dtype).index_add(0, cands.target_index[keep], per)


def build_parser() -> argparse.ArgumentParser:
    """``attack train``'s parser under this script's name."""
    parser = argparse.ArgumentParser(prog="python research/train_iou_loss.py",
                                     description="robustbench3d attack train with the image loss 'iou' (module doc)")
    add_arguments(parser)
    return parser


def main(argv: list[str]) -> int:
    parser = build_parser()
    parser.set_defaults(image_loss=None)  # None unless given (a parser default overrides the option's)
    args = parser.parse_args(argv)
    if args.image_loss is not None:
        parser.error(f"--image-loss: this script trains with '{IOU_LOSS}'; leave the option out")
    if IOU_LOSS not in IMAGE_LOSSES:
        register_image_loss(IOU_LOSS, iou_weighted_losses, candidate_iou=SUM_MIN_IOU)
    args.image_loss = IOU_LOSS
    with box_gradients():
        try:
            return int(run(args) or 0)
        except RobustBenchError as exc:
            print(f"robustbench3d: error: {exc}", file=sys.stderr)
            return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
