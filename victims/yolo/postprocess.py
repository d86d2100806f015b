"""The 2D stage's inference glue in numpy, shared by the torch and the ONNX victim.

letterbox (:mod:`.preprocess`) -> network (any backend: raw head tensors) -> :func:`decode_heads`
-> :func:`select_detections` (score threshold, pre-NMS top-k, per-class greedy NMS, back to
original pixels). Detections are (left, top, right, bottom) boxes in original image pixels,
clipped to the image, with confidence = σ(objectness)·σ(class) (YOLOv3's ranking score).

Head layout (as :func:`robustbench3d.victims.yolo.model.flatten`, the differentiable twin used by
training and the objectness oracle): each head is (B, A·(5 + C), H, W), channels per anchor
t_x, t_y, t_w, t_h, t_obj, class logits; priors are flattened head by head, then anchor, row,
column; centre = (σ(t_x) + column)·stride, size = anchor·exp(min(t_w, 8)) in input pixels.

Imports numpy only (no torch).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from robustbench3d.victims.yolo.config import Yolo, YoloConfig
from robustbench3d.victims.yolo.preprocess import Letterbox, letterbox_image

#: At most this many highest-scoring priors per image enter NMS.
PRE_NMS_TOP_K = 1000
#: exp(t_w) is evaluated on t_w clamped to this, so decoded sizes stay finite.
MAX_LOG_SCALE = 8.0
_EPS = 1e-9

#: A network backend: (B, 3, H_in, W_in) float32 letterboxed images -> raw head tensors.
HeadsFn = Callable[[np.ndarray], Sequence[np.ndarray]]


@dataclass(frozen=True)
class Detections2D:
    """One image's detections: boxes (K, 4) original pixels, scores (K,), classes (K,) int64."""

    boxes: np.ndarray
    scores: np.ndarray
    classes: np.ndarray


def sigmoid(x: np.ndarray) -> np.ndarray:
    """Logistic function in the input's dtype, without overflow."""
    x = np.asarray(x)
    e = np.exp(-np.abs(x))
    one = np.ones((), dtype=x.dtype)
    return np.where(x >= 0, one / (one + e), e / (one + e)).astype(x.dtype)


def head_masks(cfg: YoloConfig) -> list[tuple[int, ...]]:
    """Anchor indices of each detection head, in head order."""
    return [spec.mask for spec in cfg.layers() if isinstance(spec, Yolo)]


def decode_heads(heads: Sequence[np.ndarray], cfg: YoloConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Raw head tensors -> (boxes (B, P, 4) cx, cy, w, h input px; objectness logits (B, P);
    class logits (B, P, C)), float32. The stride of a head is input width / grid width."""
    masks = head_masks(cfg)
    if len(heads) != len(masks):
        raise ValueError(f"{len(heads)} head tensors for a {cfg.layout!r} layout with {len(masks)} heads")
    nout = 5 + cfg.num_classes
    w_in, h_in = cfg.input_size
    boxes, preds = [], []
    for raw, mask in zip(heads, masks, strict=True):
        raw = np.asarray(raw, dtype=np.float32)
        b, ch, gh, gw = raw.shape
        a = len(mask)
        if ch != a * nout or w_in % gw or h_in % gh or w_in // gw != h_in // gh:
            raise ValueError(f"head of shape {raw.shape} does not fit {a} anchors x {nout} channels at input "
                             f"{w_in}x{h_in}")
        stride = np.float32(w_in // gw)
        p = raw.reshape(b, a, nout, gh, gw).transpose(0, 1, 3, 4, 2).reshape(b, a * gh * gw, nout)
        gy, gx = np.meshgrid(np.arange(gh), np.arange(gw), indexing="ij")
        grid = np.tile(np.stack([gx, gy], axis=-1).reshape(gh * gw, 2), (a, 1)).astype(np.float32)
        anchors = np.array([cfg.anchors[k] for k in mask], dtype=np.float32)
        anc = np.repeat(anchors, gh * gw, axis=0)
        xy = (sigmoid(p[..., 0:2]) + grid) * stride
        wh = anc * np.exp(np.minimum(p[..., 2:4], np.float32(MAX_LOG_SCALE)))
        boxes.append(np.concatenate([xy, wh], axis=-1))
        preds.append(p)
    allp = np.concatenate(preds, axis=1)
    return np.concatenate(boxes, axis=1), allp[..., 4], allp[..., 5:]


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, M) IoU of xyxy boxes a (N, 4) and b (M, 4), float64; an empty union gives 0."""
    a = np.asarray(a, dtype=np.float64).reshape(-1, 4)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 4)
    inter = np.minimum(a[:, None, 2], b[None, :, 2])
    inter -= np.maximum(a[:, None, 0], b[None, :, 0])
    np.maximum(inter, 0, out=inter)
    height = np.minimum(a[:, None, 3], b[None, :, 3])
    height -= np.maximum(a[:, None, 1], b[None, :, 1])
    np.maximum(height, 0, out=height)
    inter *= height
    area_a = np.clip(a[:, 2] - a[:, 0], 0, None) * np.clip(a[:, 3] - a[:, 1], 0, None)
    area_b = np.clip(b[:, 2] - b[:, 0], 0, None) * np.clip(b[:, 3] - b[:, 1], 0, None)
    union = area_a[:, None] + area_b[None, :]
    union -= inter
    return inter / np.maximum(union, _EPS)


def nms_clusters(boxes: np.ndarray, scores: np.ndarray, iou_threshold: float) -> list[np.ndarray]:
    """Greedy NMS with the suppressed boxes: one index array per kept box (kept box first, then
    the boxes it suppressed), clusters in decreasing score of their kept box.

    Visit boxes by decreasing score (ties by lower index); keep a box unless a kept box overlaps
    it with IoU > ``iou_threshold``; a kept box suppresses the remaining boxes it overlaps so.
    """
    n = len(boxes)
    if n == 0:
        return []
    order = np.argsort(-np.asarray(scores), kind="stable")
    iou = box_iou(np.asarray(boxes)[order], np.asarray(boxes)[order])
    suppressed = np.zeros(n, dtype=bool)
    clusters: list[np.ndarray] = []
    for i in range(n):
        if suppressed[i]:
            continue
        members = ~suppressed & (iou[i] > iou_threshold)
        members[i] = False
        clusters.append(order[np.concatenate([[i], np.flatnonzero(members)]).astype(np.int64)])
        suppressed |= members
        suppressed[i] = True
    return clusters


def nms(boxes: np.ndarray, scores: np.ndarray, iou_threshold: float) -> np.ndarray:
    """Greedy NMS (:func:`nms_clusters`): indices (int64, decreasing score) of the kept xyxy boxes."""
    return np.array([c[0] for c in nms_clusters(boxes, scores, iou_threshold)], dtype=np.int64)


def batched_nms_clusters(boxes: np.ndarray, scores: np.ndarray, classes: np.ndarray,
                         iou_threshold: float) -> list[np.ndarray]:
    """:func:`nms_clusters` within each class; clusters sorted by decreasing score of their kept box."""
    classes = np.asarray(classes)
    clusters = [np.flatnonzero(classes == c)[cl] for c in np.unique(classes)
                for cl in nms_clusters(boxes[classes == c], scores[classes == c], iou_threshold)]
    order = np.argsort([-np.asarray(scores)[c[0]] for c in clusters], kind="stable")
    return [clusters[k] for k in order]


def batched_nms(boxes: np.ndarray, scores: np.ndarray, classes: np.ndarray, iou_threshold: float) -> np.ndarray:
    """:func:`nms` within each class; kept indices sorted by decreasing score (stable)."""
    return np.array([c[0] for c in batched_nms_clusters(boxes, scores, classes, iou_threshold)], dtype=np.int64)


def merge_clusters(boxes: np.ndarray, scores: np.ndarray, clusters: Sequence[np.ndarray]) -> np.ndarray:
    """(K, 4) score-weighted mean box of each NMS cluster (the 2019 PyTorch-YOLOv3 "merge")."""
    out = np.zeros((len(clusters), 4), dtype=np.float64)
    for k, c in enumerate(clusters):
        w = np.asarray(scores, dtype=np.float64)[c]
        out[k] = (w[:, None] * np.asarray(boxes, dtype=np.float64)[c]).sum(axis=0) / max(float(w.sum()), _EPS)
    return out


def prior_scores(obj_logit: np.ndarray, cls_logit: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per prior: float32 score σ(objectness)·σ(class) of its best class, and that class (int64)."""
    conf = sigmoid(np.asarray(obj_logit, dtype=np.float32))[:, None] * sigmoid(np.asarray(cls_logit, np.float32))
    cls = conf.argmax(axis=1)
    return conf[np.arange(len(conf)), cls], cls


def select_detections(boxes: np.ndarray, obj_logit: np.ndarray, cls_logit: np.ndarray, geo: Letterbox,
                      cfg: YoloConfig) -> Detections2D:
    """One image's priors (boxes (P, 4) cx, cy, w, h input px; logits (P,), (P, C)) -> detections:
    score threshold, at most :data:`PRE_NMS_TOP_K` priors, per-class NMS (with ``cfg.nms_merge``
    each kept box becomes the score-weighted mean of the boxes it suppressed and itself),
    ``max_detections``, mapped to original pixels and clipped to the image."""
    score, cls = prior_scores(obj_logit, cls_logit)
    keep = np.flatnonzero(score >= np.float32(cfg.conf_threshold))
    if len(keep) > PRE_NMS_TOP_K:  # bound NMS cost (IoU matrix) for untrained / noisy nets
        keep = keep[np.argsort(-score[keep], kind="stable")[:PRE_NMS_TOP_K]]
    b = np.asarray(boxes, dtype=np.float32)[keep]
    half = b[:, 2:4] / np.float32(2.0)
    xyxy = np.concatenate([b[:, 0:2] - half, b[:, 0:2] + half], axis=1).astype(np.float64)
    score64 = score[keep].astype(np.float64)
    clusters = batched_nms_clusters(xyxy, score64, cls[keep], cfg.nms_threshold)[: cfg.max_detections]
    kept = np.array([c[0] for c in clusters], dtype=np.int64)
    w, h = geo.image_size
    img_boxes = geo.to_image(merge_clusters(xyxy, score64, clusters) if cfg.nms_merge else xyxy[kept])
    img_boxes[:, 0::2] = np.clip(img_boxes[:, 0::2], 0, w - 1)
    img_boxes[:, 1::2] = np.clip(img_boxes[:, 1::2], 0, h - 1)
    return Detections2D(img_boxes, score64[kept], cls[keep][kept].astype(np.int64))


def image_priors(images: Sequence[np.ndarray], run_heads: HeadsFn,
                 cfg: YoloConfig) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, Letterbox]]:
    """Per (H, W, 3) uint8 image (each letterboxed on its own, all through ``run_heads`` at once):
    its priors (boxes (P, 4) cx, cy, w, h input px; objectness logits (P,); class logits (P, C))
    and letterbox. With ``cfg.flip_tta`` the mirrored images' priors, mirrored back, follow."""
    boxed = [letterbox_image(im, cfg.input_size, cfg.fill) for im in images]
    boxes, obj, cls = decode_heads(run_heads(np.stack([x for x, _ in boxed])), cfg)
    if cfg.flip_tta:
        fb, fo, fc = decode_heads(run_heads(np.stack([letterbox_image(np.ascontiguousarray(im[:, ::-1]),
                                                                      cfg.input_size, cfg.fill)[0]
                                                      for im in images])), cfg)
        for b, (_, geo) in enumerate(boxed):
            fb[b, :, 0] = geo.mirror_x(fb[b, :, 0])
        boxes, obj, cls = (np.concatenate(pair, axis=1) for pair in ((boxes, fb), (obj, fo), (cls, fc)))
    return [(boxes[b], obj[b], cls[b], geo) for b, (_, geo) in enumerate(boxed)]


def detect_images(images: Sequence[np.ndarray], run_heads: HeadsFn, cfg: YoloConfig,
                  batch_size: int = 1) -> list[Detections2D]:
    """Detections for (H, W, 3) uint8 images: each is letterboxed on its own, ``batch_size`` of
    them go through ``run_heads`` at a time (:func:`image_priors`, then :func:`select_detections`)."""
    out: list[Detections2D] = []
    for start in range(0, len(images), batch_size):
        out.extend(select_detections(b, o, c, geo, cfg)
                   for b, o, c, geo in image_priors(images[start:start + batch_size], run_heads, cfg))
    return out
