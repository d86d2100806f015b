"""Training of the YOLO 2D detector (default: the mini-YOLO of §2.3) on a KITTI-layout dataset.

Loss variant ``"iou"`` by default (several priors per GT, GIoU, IoU objectness targets;
``"v3"`` is the 2019 loss, see :data:`~robustbench3d.victims.yolo.config.LOSSES`).
Adam (lr 1e-3) with a linear warm-up and ×0.1 steps at 80 % and 90 % of the epochs (darknet's
step schedule, compressed; or ``lr_schedule="cosine"`` down to lr/100). ``precision="bf16"``
runs the network's forward/backward under bfloat16 autocast (weights, decoding and loss stay
float32): about 2x faster on CPUs with AVX512-BF16, bit-reproducible on the same CPU type.
Augmentation: horizontal flips (p = 0.5) and, with ``scale_jitter`` = j, a zoom by U(1 − j, 1 + j)
with a random shift. Anchors by k-means (IoU distance) on the training Car boxes unless
``anchors="config"``. Fine-tuning: ``init`` names a trained ``model.pt`` (or a cascade weights
file) whose network weights and anchors (scaled to the input size) start the run; its layout is
the same or a prefix (``mini`` → ``mini3``, whose extra head starts fresh); ``input_size``
overrides the layout's input (e.g. 960x288 to resolve small cars at stride 8).
Validation: loss, and Car AP at IoU 0.5 / 0.7 (all-point interpolated, every GT counted,
DontCare / Van detections not excused — a training monitor, not the KITTI metric).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from robustbench3d.errors import DataFormatError, RobustBenchError
from robustbench3d.fileio import sha256_file
from robustbench3d.kitti.dataset import KittiDataset
from robustbench3d.victims import training as loop
from robustbench3d.victims.torchfile import load_network_part, one_line
from robustbench3d.victims.yolo.anchors import kmeans_anchors
from robustbench3d.victims.yolo.boxes import box_iou_np
from robustbench3d.victims.yolo.config import CONFIGS, LAYOUTS, LOSSES, YoloConfig
from robustbench3d.victims.yolo.data import YoloImageSet, build_image_set, make_batch
from robustbench3d.victims.yolo.detector import YoloDetector
from robustbench3d.victims.yolo.letterbox import letterbox_geometry
from robustbench3d.victims.yolo.loss import build_targets, yolo_loss
from robustbench3d.victims.yolo.model import build_model, flatten


@dataclass(frozen=True)
class YoloTrainConfig:
    layout: str = "mini"
    loss: Literal["v3", "iou"] = "iou"
    anchors: Literal["kmeans", "config"] = "kmeans"
    lr: float = 1e-3
    weight_decay: float = 0.0
    warmup_steps: int = 100
    lr_schedule: Literal["step", "cosine"] = "step"
    precision: Literal["fp32", "bf16"] = "fp32"
    scale_jitter: float = 0.0
    val_limit: int | None = None
    flip: bool = True
    train_split: str = "train"
    val_split: str = "val"
    input_size: tuple[int, int] | None = None
    init: str | None = None
    init_sha256: str | None = None


def average_precision(scores: list[np.ndarray], boxes: list[np.ndarray], gts: list[np.ndarray],
                      iou_threshold: float) -> float:
    """All-point interpolated AP of detections (per image scores (K,), boxes (K, 4)) against GT
    boxes (G, 4); greedy matching by decreasing score, each GT matched once."""
    n_gt = sum(len(g) for g in gts)
    if n_gt == 0:
        return float("nan")
    recs: list[tuple[float, bool]] = []
    for s, b, g in zip(scores, boxes, gts, strict=True):
        order = np.argsort(-s, kind="stable")
        used = np.zeros(len(g), dtype=bool)
        iou = box_iou_np(b[order], g) if len(g) and len(b) else np.zeros((len(b), len(g)))
        for r, k in enumerate(order):
            j = int(np.argmax(np.where(used, -1.0, iou[r]))) if len(g) else -1
            hit = j >= 0 and not used[j] and iou[r, j] >= iou_threshold
            if hit:
                used[j] = True
            recs.append((float(s[k]), hit))
    recs.sort(key=lambda t: -t[0])
    tp = np.cumsum([h for _, h in recs]) if recs else np.zeros(0)
    precision = tp / np.arange(1, len(recs) + 1) if recs else np.zeros(0)
    recall = tp / n_gt
    mrec = np.concatenate([[0.0], recall, [1.0]])
    mpre = np.concatenate([[0.0], precision, [0.0]])
    mpre = np.maximum.accumulate(mpre[::-1])[::-1]
    return float(np.sum((mrec[1:] - mrec[:-1]) * mpre[1:]))


class YoloTask:
    """:class:`~robustbench3d.victims.training.TrainingTask` for the YOLO detector."""

    def __init__(self, train_set: YoloImageSet, val_set: YoloImageSet, net_cfg: YoloConfig, cfg: YoloTrainConfig,
                 seed: int, epochs: int, steps_per_epoch: int, init_state: dict[str, torch.Tensor] | None = None):
        self.train_set, self.val_set = train_set, val_set
        self.cfg, self.net_cfg, self.seed = cfg, net_cfg, seed
        self.epochs, self.steps_per_epoch = epochs, steps_per_epoch
        self.model = build_model(net_cfg, seed)
        stride = max(self.model.head_strides)
        if any(v % stride for v in net_cfg.input_size):
            raise RobustBenchError(f"input size {net_cfg.input_size} is not a multiple of the {net_cfg.layout} "
                                   f"layout's largest stride {stride}")
        if init_state is not None:
            load_prefix(self.model, init_state, cfg.init)
        # channels-last convolutions are ~1.6x faster on these CPUs; the weights' values are unchanged
        self.model = self.model.to(memory_format=torch.channels_last)
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)

    def num_items(self) -> int:
        return len(self.train_set)

    def config_dict(self) -> dict[str, Any]:
        return {**asdict(self.cfg), "net": self.net_cfg.to_dict(), "seed": self.seed, "epochs": self.epochs,
                "train_images": len(self.train_set)}

    def schedule(self, epoch: int, step: int, samples_seen: int) -> None:
        lr = self.cfg.lr * min(1.0, (step + 1) / max(self.cfg.warmup_steps, 1))
        if self.cfg.lr_schedule == "cosine":
            lr = min(lr, loop.cosine_lr(self.cfg.lr, step, self.epochs * self.steps_per_epoch, self.cfg.lr * 1e-2))
        elif epoch >= int(0.9 * self.epochs) and self.epochs >= 10:
            lr *= 0.01
        elif epoch >= int(0.8 * self.epochs) and self.epochs >= 10:
            lr *= 0.1
        loop.set_lr(self.optimizer, lr)

    def _loss(self, images: torch.Tensor, gt: list[torch.Tensor], ign: list[torch.Tensor]) -> tuple[torch.Tensor, dict]:
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=self.cfg.precision == "bf16"):
            heads = self.model(images.contiguous(memory_format=torch.channels_last))
        pred = flatten([h.float() for h in heads], self.model)  # decoding and loss in float32
        classes = [torch.zeros(len(g), dtype=torch.int64) for g in gt]
        targets = build_targets(pred, self.net_cfg, gt, classes, ign)
        return yolo_loss(pred, targets, self.net_cfg)

    def loss(self, indices: np.ndarray, rng: np.random.Generator,
             generator: torch.Generator) -> tuple[torch.Tensor, dict[str, float]]:
        images, gt, ign = make_batch(self.train_set, indices, rng, self.cfg.flip, self.cfg.scale_jitter,
                                     fill=round(self.net_cfg.fill * 255))
        total, terms = self._loss(images, gt, ign)
        return total, {k: v.item() for k, v in terms.items()}

    def evaluate(self, batch_size: int = 16) -> dict[str, float]:
        """Loss and AP on the first ``val_limit`` val images (all if None), float32 forward."""
        det = YoloDetector(self.model)
        losses, scores, boxes, gts = [], [], [], []
        wi, hi = self.net_cfg.input_size
        geo = letterbox_geometry((wi, hi), (wi, hi))  # identity: cached images are already letterboxed
        n = len(self.val_set) if self.cfg.val_limit is None else min(self.cfg.val_limit, len(self.val_set))
        for start in range(0, n, batch_size):
            idx = np.arange(start, min(n, start + batch_size))
            images, gt, ign = make_batch(self.val_set, idx, None, False)
            pred = flatten(self.model(images), self.model)
            targets = build_targets(pred, self.net_cfg, gt, [torch.zeros(len(g), dtype=torch.int64) for g in gt], ign)
            losses.append(yolo_loss(pred, targets, self.net_cfg)[0].item() * len(idx))
            for d, g in zip(det.postprocess(pred, geo), gt, strict=True):
                scores.append(d.scores)
                boxes.append(d.boxes)
                gts.append(g.numpy())
        return {"loss": sum(losses) / max(n, 1), "ap50": average_precision(scores, boxes, gts, 0.5),
                "ap70": average_precision(scores, boxes, gts, 0.7)}

    def export(self) -> dict[str, Any]:
        return {"config": self.net_cfg.to_dict(), "state_dict": self.model.state_dict(),
                "train_config": asdict(self.cfg)}


def train(data_dir: str | Path, out_dir: str | Path, cfg: YoloTrainConfig, options: loop.LoopOptions,
          resume: bool = False) -> dict[str, Any]:
    """Letterbox / cache the images, fit anchors, and run the training loop."""
    data, out = Path(data_dir), Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    net_cfg = replace(CONFIGS[cfg.layout], **LOSSES[cfg.loss])
    init_cfg, init_state = None, None
    if cfg.init is not None:
        init_cfg, init_state, digest = load_init(cfg.init, cfg.layout)
        cfg = replace(cfg, init_sha256=digest)
        if init_cfg.layout == cfg.layout:
            net_cfg = replace(net_cfg, input_size=init_cfg.input_size)
    if cfg.input_size is not None:
        net_cfg = replace(net_cfg, input_size=tuple(cfg.input_size))
    train_set = build_image_set(KittiDataset(data, split=cfg.train_split), net_cfg.input_size, net_cfg.fill,
                                out / f"images_{cfg.train_split}")
    val_set = build_image_set(KittiDataset(data, split=cfg.val_split), net_cfg.input_size, net_cfg.fill,
                              out / f"images_{cfg.val_split}")
    if init_cfg is not None:
        net_cfg = replace(net_cfg, anchors=init_anchors(
            init_cfg, net_cfg, train_set.boxes if cfg.anchors == "kmeans" else None, options.seed))
    elif cfg.anchors == "kmeans":
        net_cfg = replace(net_cfg, anchors=fit_anchors(train_set.boxes, len(net_cfg.anchors), options.seed))
    steps = len(loop.epoch_batches(len(train_set), options.batch_size, options.seed, 0))
    task = YoloTask(train_set, val_set, net_cfg, cfg, options.seed, options.epochs, steps, init_state)
    return loop.run(task, out, options, resume)


def init_anchors(init_cfg: YoloConfig, net_cfg: YoloConfig, boxes: np.ndarray | None,
                 seed: int) -> tuple[tuple[float, float], ...]:
    """Anchors of a fine-tuned network: the initialising network's, scaled from its input size to
    ``net_cfg.input_size`` (anchors are in input pixels). For the anchors it lacks (a layout with
    more heads): the largest clusters of a k-means (k = all anchors) on the training boxes
    ``(N, 4)`` x1 y1 x2 y2, or ``net_cfg``'s own when ``boxes`` is None."""
    sx = net_cfg.input_size[0] / init_cfg.input_size[0]
    sy = net_cfg.input_size[1] / init_cfg.input_size[1]
    anchors = [(round(w * sx, 2), round(h * sy, 2)) for w, h in init_cfg.anchors]
    extra = len(net_cfg.anchors) - len(anchors)
    if extra > 0 and boxes is None:
        anchors += list(net_cfg.anchors[len(anchors):])
    elif extra > 0:
        anchors += fit_anchors(boxes, len(net_cfg.anchors), seed)[-extra:]
    return tuple(anchors[: len(net_cfg.anchors)])


def fit_anchors(boxes: np.ndarray, k: int, seed: int) -> tuple[tuple[float, float], ...]:
    """``k`` anchors (w, h px, sorted by area, rounded to 0.01) by k-means on the training boxes
    ``(N, 4)`` x1 y1 x2 y2, seeded by ``seed``."""
    try:
        anchors, _ = kmeans_anchors(boxes[:, 2:] - boxes[:, :2], k, np.random.default_rng([seed, 3]))
    except ValueError as exc:  # too few training boxes
        raise RobustBenchError(f"k-means anchors: {exc} in the training split; use --anchors config") from None
    return tuple((round(float(w), 2), round(float(h), 2)) for w, h in anchors)


def load_init(path: str | Path, layout: str) -> tuple[YoloConfig, dict[str, torch.Tensor], str]:
    """Configuration, state dict and sha256 of the YOLO in ``path`` (a trainer ``model.pt`` or a
    cascade weights file); its layout must be ``layout`` or one whose layers begin ``layout``'s
    (``mini`` for ``mini3``: the layers it lacks keep their seeded initialisation)."""
    path = Path(path)
    if not path.is_file():
        raise RobustBenchError(f"{path}: no such YOLO weights file (--init)")
    data = load_network_part(path, "yolo")
    try:
        init_cfg = YoloConfig.from_dict(data["config"])
        init_layers = LAYOUTS[init_cfg.layout]()
    except Exception as exc:
        raise DataFormatError(path, f"the yolo configuration is not usable ({one_line(exc)})", field="config") from None
    if LAYOUTS[layout]()[: len(init_layers)] != init_layers:
        raise RobustBenchError(f"{path}: layout {init_cfg.layout!r} is not the start of --layout {layout!r}")
    return init_cfg, data["state_dict"], sha256_file(path)


def load_prefix(model: torch.nn.Module, state: dict[str, torch.Tensor], origin: str | Path | None = None) -> None:
    """Load ``state``, the weights of a network whose layers are ``model``'s first layers: every
    tensor in it must fit ``model``; the blocks it lacks must all come after its last block.
    Errors name ``origin`` (the file the weights came from)."""
    where = origin if origin is not None else "initialising weights"
    try:
        missing, unexpected = model.load_state_dict(state, strict=False)
    except RuntimeError as exc:
        raise DataFormatError(where, f"the weights do not fit the network ({one_line(exc)})",
                              field="state_dict") from None
    if not state:
        raise DataFormatError(where, "initialising weights hold no tensors", field="state_dict")
    if unexpected:
        raise DataFormatError(where, f"initialising weights have tensors the network lacks: {unexpected[:3]}",
                              field="state_dict")
    last = max(int(k.split(".")[1]) for k in state)
    early = [k for k in missing if int(k.split(".")[1]) <= last]
    if early:
        raise DataFormatError(where, f"initialising weights lack tensors of their own layers: {early[:3]}",
                              field="state_dict")
