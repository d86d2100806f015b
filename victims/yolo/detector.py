"""The 2D stage as used by the harness: letterbox -> network -> decode -> NMS -> original pixels.

Detections are (left, top, right, bottom) boxes in the original image pixels, clipped to the
image, with confidence = σ(objectness)·σ(class) (YOLOv3's ranking score) and per-class greedy NMS.
Everything but the network is the numpy glue of :mod:`.postprocess`, shared with the ONNX victim.

:meth:`YoloDetector.target_candidates` (the objectness oracle's core) picks the priors around target boxes;
with ``crop`` it runs the network only on the cells that can hold such a prior, from the slice of the
letterboxed input they read (:meth:`~robustbench3d.victims.yolo.model.Darknet.forward_window`): the same
candidates, logits, boxes, IoUs and image gradients as the whole input, bit for bit (:func:`candidate_region`
says why no prior outside those cells can be a candidate).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from robustbench3d.victims.torchfile import build_network, load_network_part
from robustbench3d.victims.yolo.boxes import box_iou, cxcywh_to_xyxy
from robustbench3d.victims.yolo.config import Yolo, YoloConfig
from robustbench3d.victims.yolo.letterbox import Letterbox, letterbox, letterbox_window, resize_for_letterbox
from robustbench3d.victims.yolo.model import (
    Darknet,
    Window,
    WindowedHead,
    YoloPredictions,
    build_model,
    flatten,
    flatten_window,
    window_hull,
)
from robustbench3d.victims.yolo.postprocess import PRE_NMS_TOP_K, Detections2D, detect_images, select_detections


class YoloDetector:
    """A :class:`Darknet` with its configuration, in eval mode."""

    def __init__(self, net: Darknet):
        self.net = net.eval()
        self.cfg: YoloConfig = net.cfg

    @classmethod
    def untrained(cls, cfg: YoloConfig | str = "mini", seed: int = 0) -> YoloDetector:
        return cls(build_model(cfg, seed))

    @classmethod
    def load(cls, path: str | Path) -> YoloDetector:
        """From a ``model.pt`` written by the YOLO trainer (``{"config", "state_dict"}``) or a
        cascade weights file, read as data only."""
        part = load_network_part(path, "yolo")
        return cls(build_network(lambda c: Darknet(YoloConfig.from_dict(c)), part, path, "yolo"))

    def predictions(self, images: torch.Tensor) -> tuple[YoloPredictions, Letterbox]:
        """Differentiable forward of (B, 3, H, W) images in [0, 1] (original resolution)."""
        x, geo = letterbox(images, self.cfg.input_size, self.cfg.fill)
        return flatten(self.net(x), self.net), geo

    def run_heads(self, images: np.ndarray) -> list[np.ndarray]:
        """Raw head tensors of (B, 3, H_in, W_in) float32 letterboxed images (no gradients)."""
        with torch.inference_mode():
            return [h.numpy() for h in self.net(torch.from_numpy(np.ascontiguousarray(images, dtype=np.float32)))]

    def detect(self, images: Sequence[np.ndarray]) -> list[Detections2D]:
        """Detections for (H, W, 3) uint8 images (each letterboxed on its own)."""
        return detect_images(images, self.run_heads, self.cfg)

    def target_candidates(self, images: torch.Tensor, targets: Sequence[np.ndarray], iou_threshold: float = 0.3,
                          crop: bool = True) -> list[TargetCandidates]:
        """Candidates (:func:`candidates_for_targets`) of each image's (T_b, 4) original-pixel target boxes
        in (B, 3, H, W) ``images`` in [0, 1], per view (the image, then with ``cfg.flip_tta`` the mirrored
        image, its boxes mirrored back) and image. With ``crop`` the network runs only where a candidate
        can be (module doc): one forward per group of targets whose input slices overlap (a group's slice
        is the union of its targets'; disjoint slices run apart, which costs less than their hull)."""
        if len(targets) != images.shape[0]:
            raise ValueError(f"{len(targets)} target sets for {images.shape[0]} images")
        boxes = [np.asarray(t, dtype=np.float64).reshape(-1, 4) for t in targets]
        out: list[TargetCandidates] = []
        for mirrored in (False, True) if self.cfg.flip_tta else (False,):
            view = torch.flip(images, dims=[-1]) if mirrored else images
            if crop:
                out += self._cropped_view(view, boxes, iou_threshold, mirrored)
                continue
            pred, geo = self.predictions(view)
            if mirrored:
                pred = _mirrored_back(pred, geo)
            for b, tgt in enumerate(boxes):
                out.append(_as_candidates(candidates_for_targets(pred, geo, torch.from_numpy(tgt), iou_threshold, b),
                                          pred, b, mirrored))
        return out

    def _cropped_view(self, view: torch.Tensor, boxes: list[np.ndarray], iou_threshold: float,
                      mirrored: bool) -> list[TargetCandidates]:
        """:meth:`target_candidates` of one view, the network run on crops."""
        resized, geo = resize_for_letterbox(view, self.cfg.input_size)
        hw = (self.cfg.input_size[1], self.cfg.input_size[0])
        out = []
        for b, tgt in enumerate(boxes):
            seen = _mirror_targets(tgt, geo.image_size[0]) if mirrored else tgt
            found = []
            for members, windows, reads in self._target_groups(geo.to_input(seen), iou_threshold, hw):
                x = WindowedHead(letterbox_window(resized[b:b + 1], geo, reads, self.cfg.fill), *_reads_origin(reads))
                heads = self.net.forward_window(x, windows, hw, batch=len(boxes))
                pred = flatten_window(heads, self.net, hw)
                if mirrored:
                    pred = _mirrored_back(pred, geo)
                c = candidates_for_targets(pred, geo, torch.from_numpy(tgt[members]), iou_threshold, 0)
                c["target"] = torch.from_numpy(members)[c["target"]]
                found.append(_as_candidates(c, pred, 0, mirrored))
            out.append(_merged(found, b, mirrored, len(tgt), self.cfg.num_classes))
        return out

    def _target_groups(self, targets_in: np.ndarray, iou_threshold: float,
                       hw: tuple[int, int]) -> list[tuple[np.ndarray, list[Window | None], Window]]:
        """Targets (input pixels) grouped by overlapping input slices: (target indices, head windows, the
        input window they read) each."""
        spans = []
        for t, box in enumerate(targets_in):
            if np.isnan(box).any():
                continue  # no prior passes an IoU or centre test against NaN
            windows = head_windows(candidate_region(box, iou_threshold), self.net, hw)
            if all(w is None for w in windows):
                continue
            _, image = self.net.needed_windows(windows, *hw)
            assert image is not None
            spans.append((image[1][0], image[1][1], t, windows))
        spans.sort(key=lambda s: (s[0], s[2]))
        groups: list[tuple[list[int], list[Window | None], int]] = []
        for lo, hi, t, windows in spans:
            if groups and lo < groups[-1][2]:
                members, acc, end = groups[-1]
                groups[-1] = ([*members, t], [window_hull(a, w) for a, w in zip(acc, windows, strict=True)],
                              max(end, hi))
            else:
                groups.append(([t], windows, hi))
        out = []
        for members, windows, _ in groups:
            reads = self.net.needed_windows(windows, *hw)[1]
            assert reads is not None
            out.append((np.array(sorted(members), dtype=np.int64), windows, reads))
        return out

    def postprocess(self, pred: YoloPredictions, geo: Letterbox) -> list[Detections2D]:
        """Threshold, NMS and map back to original pixels, per image of the batch."""
        def arr(t: torch.Tensor) -> np.ndarray:
            return t.detach().cpu().float().numpy()

        return [select_detections(arr(pred.boxes[b]), arr(pred.obj_logit[b]), arr(pred.cls_logit[b]), geo, self.cfg)
                for b in range(pred.obj_logit.shape[0])]


def candidates_for_targets(pred: YoloPredictions, geo: Letterbox, target_boxes: torch.Tensor,
                           iou_threshold: float, image_index: int) -> dict[str, torch.Tensor]:
    """Priors of image ``image_index`` around each target (T, 4) xyxy original-pixel box.

    A prior is a candidate of a target if IoU(decoded box, target) >= ``iou_threshold`` or its
    centre lies inside the target. Returns flat prior indices into ``pred`` (``prior``) and their
    positions among all the input's priors (``prior_id``), target indices, IoUs and boxes.
    """
    boxes = geo.to_image(cxcywh_to_xyxy(pred.boxes[image_index].detach()))
    assert isinstance(boxes, torch.Tensor)
    tgt = target_boxes.to(boxes.dtype).reshape(-1, 4)
    iou = box_iou(boxes, tgt)  # (P, T)
    cx, cy = (boxes[:, 0] + boxes[:, 2]) / 2, (boxes[:, 1] + boxes[:, 3]) / 2
    inside = ((cx[:, None] >= tgt[None, :, 0]) & (cx[:, None] <= tgt[None, :, 2])
              & (cy[:, None] >= tgt[None, :, 1]) & (cy[:, None] <= tgt[None, :, 3]))
    prior, target = torch.nonzero((iou >= iou_threshold) | inside, as_tuple=True)
    return {"prior": prior, "prior_id": pred.prior_id[prior], "target": target, "iou": iou[prior, target],
            "boxes": boxes[prior]}


#: Input pixels added on every side of :func:`candidate_region`: the candidate test runs in float32 on
#: corners rebuilt from centre and size, so a centre may be found a fraction of a pixel from where the
#: network put it (even for boxes ~1e5 px wide, exp(8) times an anchor, the corners' rounding is < 0.1 px).
REGION_MARGIN_PX = 2.0


def candidate_region(target: np.ndarray, iou_threshold: float) -> np.ndarray | None:
    """Input-pixel box (x0, y0, x1, y1) that holds the decoded centre of every prior that can be a
    candidate of ``target`` (an xyxy box in input pixels), whatever the network outputs; None: anywhere.

    Proof: let a prior's box B (width w_B, height h_B) have IoU >= t with the target T (w_T, h_T) and its
    centre c right of T's right edge x1. Union >= area(B) and the overlap <= i_x h_B (i_x: the overlap of
    the x ranges), so i_x >= t w_B; also i_x <= w_T, so w_B <= w_T / t. The overlap of the x ranges is at
    most B's left half beyond x1's left: i_x <= w_B / 2 - (c - x1), so c - x1 <= w_B (1/2 - t) <=
    w_T (1 / (2t) - 1). Likewise on every side and in y. A centre inside T is the other candidate rule.
    So the centre lies in T widened by k = max(0, 1/(2t) - 1) of its width / height on each side (k = 2/3
    at t = 0.3; 0 from t = 0.5), plus :data:`REGION_MARGIN_PX`. IoU and the centre test are the same in
    original and input pixels (an axis-aligned scaling). For t <= 0 every prior is a candidate.
    A prior's centre lies in its cell, so only the cells meeting this region need the network.
    """
    if iou_threshold <= 0:
        return None
    t = np.asarray(target, dtype=np.float64).reshape(4)
    k = max(0.0, 1.0 / (2.0 * iou_threshold) - 1.0)
    size = np.maximum(t[2:] - t[:2], 0.0)
    grow = (k * size if k > 0 else 0.0) + REGION_MARGIN_PX  # an infinite side times k = 0 stays 0
    return np.concatenate([t[:2] - grow, t[2:] + grow])


def head_windows(region: np.ndarray | None, net: Darknet, input_hw: tuple[int, int]) -> list[Window | None]:
    """Per head the cells (half-open row and column ranges) whose centre ranges [cell, cell + 1] x stride
    meet ``region`` (input pixels; None: every cell); None for a head with no such cell."""
    sizes = net.layer_sizes(*input_hw)
    grids = [sizes[i] for i, spec in enumerate(net.specs) if isinstance(spec, Yolo)]
    out: list[Window | None] = []
    for stride, (rows, cols) in zip(net.head_strides, grids, strict=True):
        if region is None:
            out.append(((0, rows), (0, cols)))
            continue
        spans = []
        for lo, hi, n in ((region[1], region[3], rows), (region[0], region[2], cols)):
            lo, hi = np.clip([lo, hi], -stride, (n + 1) * stride)  # finite, and outside the grid stays outside
            spans.append((max(0, math.ceil(lo / stride) - 1), min(n, math.floor(hi / stride) + 1)))
        out.append(None if any(a >= b for a, b in spans) else (spans[0], spans[1]))
    return out


@dataclass
class TargetCandidates:
    """Candidates of the targets of one image in one view (see :func:`candidates_for_targets`).

    Attributes:
        image: index of the image in the batch; mirrored: the flip-TTA view (boxes mirrored back).
        prior: (K,) int64 positions among all priors of that view's input.
        target: (K,) int64 target indices; iou: (K,) IoU with the target (detached).
        obj_logit: (K,) and cls_logit: (K, C), differentiable; boxes: (K, 4) original pixels (detached).
    """

    image: int
    mirrored: bool
    prior: torch.Tensor
    target: torch.Tensor
    iou: torch.Tensor
    obj_logit: torch.Tensor
    cls_logit: torch.Tensor
    boxes: torch.Tensor


def _mirror_targets(targets: np.ndarray, width: int) -> np.ndarray:
    """xyxy boxes of an image ``width`` px wide, mirrored about its vertical centre line."""
    return np.stack([width - targets[:, 2], targets[:, 1], width - targets[:, 0], targets[:, 3]], axis=1)


def _reads_origin(window: Window) -> tuple[int, int]:
    """(row, column) of a window's first position."""
    return window[0][0], window[1][0]


def _mirrored_back(pred: YoloPredictions, geo: Letterbox) -> YoloPredictions:
    """Predictions on the mirrored image with their boxes mirrored back into the image's letterbox."""
    return replace(pred, boxes=torch.cat([geo.mirror_x(pred.boxes[..., :1]), pred.boxes[..., 1:]], -1))


def _as_candidates(c: dict[str, torch.Tensor], pred: YoloPredictions, b: int, mirrored: bool) -> TargetCandidates:
    return TargetCandidates(image=b, mirrored=mirrored, prior=c["prior_id"], target=c["target"], iou=c["iou"],
                            obj_logit=pred.obj_logit[b, c["prior"]], cls_logit=pred.cls_logit[b, c["prior"]],
                            boxes=c["boxes"])


def _merged(parts: list[TargetCandidates], b: int, mirrored: bool, n_targets: int,
            num_classes: int) -> TargetCandidates:
    """The groups' candidates of one image in the whole input's order (prior, then target)."""
    if not parts:
        empty = torch.zeros(0, dtype=torch.int64)
        z = torch.zeros(0)
        return TargetCandidates(b, mirrored, empty, empty, z, z, torch.zeros(0, num_classes), torch.zeros(0, 4))
    prior, target = torch.cat([p.prior for p in parts]), torch.cat([p.target for p in parts])
    order = torch.argsort(prior * max(n_targets, 1) + target)
    return TargetCandidates(b, mirrored, prior[order], target[order], torch.cat([p.iou for p in parts])[order],
                            torch.cat([p.obj_logit for p in parts])[order],
                            torch.cat([p.cls_logit for p in parts])[order], torch.cat([p.boxes for p in parts])[order])


__all__ = ["PRE_NMS_TOP_K", "Detections2D", "TargetCandidates", "YoloDetector", "candidate_region",
           "candidates_for_targets", "head_windows"]
