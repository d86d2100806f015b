"""The 2D stage as used by the harness: letterbox -> network -> decode -> NMS -> original pixels.

Detections are (left, top, right, bottom) boxes in the original image pixels, clipped to the
image, with confidence = σ(objectness)·σ(class) (YOLOv3's ranking score) and per-class greedy NMS.
Everything but the network is the numpy glue of :mod:`.postprocess`, shared with the ONNX victim.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from robustbench3d.victims.torchfile import build_network, load_network_part
from robustbench3d.victims.yolo.boxes import box_iou, cxcywh_to_xyxy
from robustbench3d.victims.yolo.config import YoloConfig
from robustbench3d.victims.yolo.letterbox import Letterbox, letterbox
from robustbench3d.victims.yolo.model import Darknet, YoloPredictions, build_model, flatten
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
    centre lies inside the target. Returns flat prior indices, target indices, IoUs and boxes.
    """
    boxes = geo.to_image(cxcywh_to_xyxy(pred.boxes[image_index].detach()))
    assert isinstance(boxes, torch.Tensor)
    tgt = target_boxes.to(boxes.dtype).reshape(-1, 4)
    iou = box_iou(boxes, tgt)  # (P, T)
    cx, cy = (boxes[:, 0] + boxes[:, 2]) / 2, (boxes[:, 1] + boxes[:, 3]) / 2
    inside = ((cx[:, None] >= tgt[None, :, 0]) & (cx[:, None] <= tgt[None, :, 2])
              & (cy[:, None] >= tgt[None, :, 1]) & (cy[:, None] <= tgt[None, :, 3]))
    prior, target = torch.nonzero((iou >= iou_threshold) | inside, as_tuple=True)
    return {"prior": prior, "target": target, "iou": iou[prior, target], "boxes": boxes[prior]}


__all__ = ["PRE_NMS_TOP_K", "Detections2D", "YoloDetector", "candidates_for_targets"]
