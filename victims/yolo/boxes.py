"""Axis-aligned 2D boxes in pixels: IoU, conversions and greedy NMS.

Boxes are (left, top, right, bottom) ("xyxy") or (centre x, centre y, width, height) ("cxcywh"),
continuous pixel coordinates: area = width x height (no "+1"). Divisions are guarded: an empty
union gives IoU 0. NMS and the numpy IoU are those of :mod:`.postprocess` (one implementation,
shared with the ONNX victim); the functions here adapt torch tensors to them.
"""

from __future__ import annotations

import numpy as np
import torch

from robustbench3d.victims.yolo import postprocess

_EPS = 1e-9


def cxcywh_to_xyxy(b: torch.Tensor) -> torch.Tensor:
    half = b[..., 2:4] / 2
    return torch.cat([b[..., 0:2] - half, b[..., 0:2] + half], dim=-1)


def xyxy_to_cxcywh(b: torch.Tensor) -> torch.Tensor:
    return torch.cat([(b[..., 0:2] + b[..., 2:4]) / 2, b[..., 2:4] - b[..., 0:2]], dim=-1)


def box_iou(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(N, M) IoU of xyxy boxes a (N, 4) and b (M, 4)."""
    lt = torch.maximum(a[:, None, :2], b[None, :, :2])
    rb = torch.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = (rb - lt).clamp_min(0).prod(dim=-1)
    area_a = (a[:, 2:] - a[:, :2]).clamp_min(0).prod(dim=-1)
    area_b = (b[:, 2:] - b[:, :2]).clamp_min(0).prod(dim=-1)
    union = area_a[:, None] + area_b[None, :] - inter
    return inter / union.clamp_min(_EPS)


def box_iou_np(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """numpy version of :func:`box_iou` (float64)."""
    return postprocess.box_iou(a, b)


def wh_iou(wh_a: torch.Tensor, wh_b: torch.Tensor) -> torch.Tensor:
    """(N, M) IoU of boxes sharing a centre, from their (w, h) — anchor/box shape similarity."""
    inter = torch.minimum(wh_a[:, None, 0], wh_b[None, :, 0]) * torch.minimum(wh_a[:, None, 1], wh_b[None, :, 1])
    union = (wh_a[:, 0] * wh_a[:, 1])[:, None] + (wh_b[:, 0] * wh_b[:, 1])[None, :] - inter
    return inter / union.clamp_min(_EPS)


def nms(boxes: torch.Tensor, scores: torch.Tensor, iou_threshold: float) -> torch.Tensor:
    """Greedy NMS (:func:`robustbench3d.victims.yolo.postprocess.nms`, IoU in float64): indices
    (int64, decreasing score, ties by lower index) of the kept xyxy boxes."""
    keep = postprocess.nms(_np(boxes), _np(scores), iou_threshold)
    return torch.as_tensor(keep, dtype=torch.int64)


def batched_nms(boxes: torch.Tensor, scores: torch.Tensor, classes: torch.Tensor,
                iou_threshold: float) -> torch.Tensor:
    """:func:`nms` within each class; kept indices sorted by decreasing score."""
    keep = postprocess.batched_nms(_np(boxes), _np(scores), classes.detach().cpu().numpy(), iou_threshold)
    return torch.as_tensor(keep, dtype=torch.int64)


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().cpu().double().numpy()
