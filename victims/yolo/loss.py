"""YOLOv3 target assignment and the 2019-style loss (reference §2.1, §2.3), in input pixels.

Assignment (YOLOv3 paper semantics): each GT box is assigned to the single prior whose anchor
shape best matches it (IoU of (w, h) boxes sharing a centre, over the anchors of all heads), in
the cell of that anchor's head containing the GT centre. That prior gets objectness target 1 and
the coordinate and class targets. Priors whose decoded box overlaps any GT box or ignore box
(e.g. Van, DontCare) with IoU > ``ignore_thresh`` get no objectness loss (as darknet), nor does
the best prior of an ignore box; all other priors get target 0.

With ``cfg.assign == "multi"`` a GT also trains every other anchor whose width and height ratios
to it are below ``cfg.anchor_ratio``; a prior claimed by two GT boxes keeps the better-shaped one.

Loss: MSE on σ(t_x), σ(t_y) and on t_w, t_h of assigned priors (``box_loss="mse"``) or
1 − GIoU of the decoded box (``"giou"``); objectness
``obj_scale·BCE(assigned, target) + noobj_scale·BCE(unassigned, 0)`` with target 1
(``obj_target="binary"``) or the detached IoU of the decoded box with its GT (``"iou"``); class
BCE on assigned priors. BCEs are computed from logits (``binary_cross_entropy_with_logits``);
every mean over an empty set is 0.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from robustbench3d.victims.yolo.boxes import box_iou, cxcywh_to_xyxy, wh_iou
from robustbench3d.victims.yolo.config import YoloConfig
from robustbench3d.victims.yolo.model import YoloPredictions

_MIN_SIZE = 1e-3
_EPS = 1e-9


@dataclass
class YoloTargets:
    """Assigned targets of a batch (K assigned priors; B images, P priors each).

    obj_index: (K,) int64 flat index b·P + p; txy (K, 2) in [0, 1]; twh (K, 2) log(size/anchor);
    cls (K, C) 0/1; noobj: (B, P) bool, priors trained towards objectness 0; box (K, 4) the
    assigned GT box, xyxy input pixels.
    """

    obj_index: torch.Tensor
    txy: torch.Tensor
    twh: torch.Tensor
    cls: torch.Tensor
    noobj: torch.Tensor
    box: torch.Tensor


def _prior_in_cell(pred: YoloPredictions, box: torch.Tensor, a: int) -> int:
    """Prior index of anchor ``a`` in the cell (of a's head) containing the centre of xyxy ``box``."""
    head = next(h for h in pred.layout if a in h.mask)
    cx, cy = float(box[0] + box[2]) / 2, float(box[1] + box[3]) / 2
    gi = min(max(int(cx // head.stride), 0), head.cols - 1)
    gj = min(max(int(cy // head.stride), 0), head.rows - 1)
    return head.offset + (head.mask.index(a) * head.rows + gj) * head.cols + gi


def best_prior(pred: YoloPredictions, box: torch.Tensor, anchors: torch.Tensor) -> tuple[int, int]:
    """(prior index p, anchor index) assigned to one xyxy box (input pixels)."""
    wh = (box[2:] - box[:2]).clamp_min(_MIN_SIZE)
    a = int(wh_iou(wh[None], anchors)[0].argmax())
    return _prior_in_cell(pred, box, a), a


def matching_anchors(wh: torch.Tensor, anchors: torch.Tensor, cfg: YoloConfig) -> list[int]:
    """Anchors trained by a GT of size ``wh`` (px): the best-shaped one first, then (``"multi"``)
    every other anchor with max(w/a_w, a_w/w, h/a_h, a_h/h) < ``cfg.anchor_ratio``."""
    shape_iou = wh_iou(wh[None], anchors)[0]
    best = int(shape_iou.argmax())
    if cfg.assign == "best":
        return [best]
    if cfg.assign != "multi":
        raise ValueError(f"unknown assign mode {cfg.assign!r} (expected 'best' or 'multi')")
    ratio = torch.maximum(wh[None] / anchors, anchors / wh[None]).amax(dim=1)
    return [best] + [int(a) for a in torch.nonzero(ratio < cfg.anchor_ratio).reshape(-1) if int(a) != best]


def build_targets(pred: YoloPredictions, cfg: YoloConfig, gt_boxes: Sequence[torch.Tensor],
                  gt_classes: Sequence[torch.Tensor],
                  ignore_boxes: Sequence[torch.Tensor] | None = None) -> YoloTargets:
    """Assign per-image GT boxes ((G_b, 4) xyxy input px, classes (G_b,)) to priors."""
    b, p = pred.obj_logit.shape
    anchors = torch.tensor(cfg.anchors, dtype=torch.float64)
    boxes_xyxy = cxcywh_to_xyxy(pred.boxes.detach().double())
    noobj = torch.ones(b, p, dtype=torch.bool)
    # prior -> (shape IoU of the claim, txy, twh, class, GT box)
    assigned: dict[int, tuple[float, list[float], list[float], int, list[float]]] = {}
    for i in range(b):
        gt = gt_boxes[i].double().reshape(-1, 4)
        ign = (ignore_boxes[i].double().reshape(-1, 4) if ignore_boxes is not None else gt.new_zeros((0, 4)))
        both = torch.cat([gt, ign])
        if len(both):
            noobj[i] &= ~(box_iou(boxes_xyxy[i], both).amax(dim=1) > cfg.ignore_thresh)
        for box in ign:
            k, _ = best_prior(pred, box, anchors)
            noobj[i, k] = False
        for box, c in zip(gt, gt_classes[i].reshape(-1).tolist(), strict=True):
            wh = box[2:] - box[:2]
            if float(wh.min()) < _MIN_SIZE:
                continue
            shape_iou = wh_iou(wh[None], anchors)[0]
            cx, cy = float(box[0] + box[2]) / 2, float(box[1] + box[3]) / 2
            for a in matching_anchors(wh, anchors, cfg):
                k = _prior_in_cell(pred, box, a)
                claim = float(shape_iou[a])
                if i * p + k in assigned and assigned[i * p + k][0] >= claim:
                    continue
                stride = float(pred.stride[k])
                gi, gj = pred.grid[k].tolist()
                txy = [min(max(cx / stride - gi, 0.0), 1.0), min(max(cy / stride - gj, 0.0), 1.0)]
                twh = [float(torch.log(wh[0] / anchors[a, 0])), float(torch.log(wh[1] / anchors[a, 1]))]
                assigned[i * p + k] = (claim, txy, twh, int(c), box.tolist())
                noobj[i, k] = False
    idx = sorted(assigned)
    cls = torch.zeros(len(idx), cfg.num_classes)
    for r, k in enumerate(idx):
        cls[r, assigned[k][3]] = 1.0
    return YoloTargets(
        obj_index=torch.tensor(idx, dtype=torch.int64),
        txy=torch.tensor([assigned[k][1] for k in idx], dtype=torch.float32).reshape(-1, 2),
        twh=torch.tensor([assigned[k][2] for k in idx], dtype=torch.float32).reshape(-1, 2),
        cls=cls, noobj=noobj,
        box=torch.tensor([assigned[k][4] for k in idx], dtype=torch.float32).reshape(-1, 4),
    )


def _mean_or_zero(x: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    return x.mean() if x.numel() else like.sum() * 0.0


def giou(a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(IoU, GIoU) of paired xyxy boxes (K, 4); divisions guarded, finite for degenerate boxes."""
    lt, rb = torch.maximum(a[:, :2], b[:, :2]), torch.minimum(a[:, 2:], b[:, 2:])
    inter = (rb - lt).clamp_min(0).prod(dim=1)
    area_a = (a[:, 2:] - a[:, :2]).clamp_min(0).prod(dim=1)
    area_b = (b[:, 2:] - b[:, :2]).clamp_min(0).prod(dim=1)
    union = area_a + area_b - inter
    iou = inter / union.clamp_min(_EPS)
    hull = (torch.maximum(a[:, 2:], b[:, 2:]) - torch.minimum(a[:, :2], b[:, :2])).clamp_min(0).prod(dim=1)
    return iou, iou - (hull - union) / hull.clamp_min(_EPS)


def yolo_loss(pred: YoloPredictions, targets: YoloTargets,
              cfg: YoloConfig) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Total loss and its terms (``xy`` and ``wh`` are the MSE terms, ``box`` the GIoU term)."""
    obj = pred.obj_logit.reshape(-1)
    raw = pred.raw.reshape(-1, 4)[targets.obj_index]
    cls = pred.cls_logit.reshape(-1, cfg.num_classes)[targets.obj_index]
    decoded = cxcywh_to_xyxy(pred.boxes.reshape(-1, 4)[targets.obj_index])
    iou, g = giou(decoded, targets.box.to(decoded.dtype))
    zero = obj.sum() * 0.0
    if cfg.box_loss == "mse":
        txy, twh = targets.txy.to(raw.dtype), targets.twh.to(raw.dtype)
        xy = _mean_or_zero(F.mse_loss(torch.sigmoid(raw[:, :2]), txy, reduction="none"), obj).mul(2.0)
        wh = _mean_or_zero(F.mse_loss(raw[:, 2:], twh, reduction="none"), obj).mul(2.0)
        box = zero
    elif cfg.box_loss == "giou":
        xy = wh = zero
        box = _mean_or_zero(1.0 - g, obj).mul(2.0)
    else:
        raise ValueError(f"unknown box_loss {cfg.box_loss!r} (expected 'mse' or 'giou')")
    if cfg.obj_target == "binary":
        obj_t = torch.ones_like(obj[targets.obj_index])
    elif cfg.obj_target == "iou":
        obj_t = iou.detach().clamp(0.0, 1.0).to(obj.dtype)
    else:
        raise ValueError(f"unknown obj_target {cfg.obj_target!r} (expected 'binary' or 'iou')")
    terms = {
        "xy": xy, "wh": wh, "box": box,
        "obj": _mean_or_zero(F.binary_cross_entropy_with_logits(obj[targets.obj_index], obj_t, reduction="none"), obj),
        "noobj": _mean_or_zero(F.binary_cross_entropy_with_logits(
            obj[targets.noobj.reshape(-1)], torch.zeros_like(obj[targets.noobj.reshape(-1)]), reduction="none"), obj),
        "cls": _mean_or_zero(F.binary_cross_entropy_with_logits(cls, targets.cls.to(cls.dtype), reduction="none"), obj),
    }
    total = (terms["xy"] + terms["wh"] + terms["box"] + cfg.obj_scale * terms["obj"]
             + cfg.noobj_scale * terms["noobj"] + terms["cls"])
    return total, terms
