"""Training of the PointPillars-style Car detector on a KITTI-layout dataset (the loop of :mod:`..training`).

Each train frame is read once (scan cut to the camera's field of view and the grid's region, Car
boxes in the velodyne frame) and held in memory. A step augments each frame of the batch from the
loop's rng (flip about the velodyne x axis with probability 1/2, rotation about z uniform in
±``rotation`` rad, scaling uniform in 1 ± ``scaling``), pillarises it, encodes the centre targets
and computes the loss: CenterNet focal loss on the heatmap plus ``reg_weight`` × L1 on the
regression at the boxes' centre cells (both normalised by the number of boxes). Adam(W), linear
warm-up then cosine decay. Validation: Car BEV AP R40 (easy / moderate / hard) of the detector on the
first ``val_limit`` val frames, with the project's evaluator.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from robustbench3d.victims import training as loop
from robustbench3d.victims.pointpillars.config import PointPillarsConfig
from robustbench3d.victims.pointpillars.glue import crop_scan, decode_output
from robustbench3d.victims.pointpillars.model import build_model
from robustbench3d.victims.pointpillars.pillars import assign_pillars, pillar_features
from robustbench3d.victims.pointpillars.targets import encode, labels_to_velo_boxes, wrap_angle


@dataclass(frozen=True)
class PointPillarsTrainConfig:
    lr: float = 2e-3
    lr_min: float = 1e-5
    weight_decay: float = 1e-2
    warmup_steps: int = 200
    reg_weight: float = 0.25
    flip: bool = True
    rotation: float = np.pi / 16
    scaling: float = 0.05
    train_split: str = "train"
    val_split: str = "val"
    precision: Literal["fp32", "bf16"] = "fp32"


@dataclass(frozen=True)
class FrameData:
    """One frame held for training: cropped velodyne points (N, 4) float32 and Car boxes (K, 7)."""

    points: np.ndarray
    boxes: np.ndarray


def load_frames(data_dir: Path, split: str, cfg: PointPillarsConfig,
                limit: int | None = None) -> tuple[list[str], list[FrameData]]:
    """Frame ids and :class:`FrameData` of a split (the first ``limit`` frames)."""
    from robustbench3d.kitti.dataset import KittiDataset

    ds = KittiDataset(data_dir, split=split)
    ids = ds.frame_ids if limit is None else ds.frame_ids[:limit]
    frames = []
    for fid in ids:
        calib, labels = ds.calib(fid), ds.labels(fid)
        points = crop_scan(ds.scan(fid), calib, ds.image_size(fid), cfg.grid)
        boxes = labels_to_velo_boxes(labels, calib) if labels is not None else np.zeros((0, 7))
        frames.append(FrameData(points, boxes))
    return ids, frames


def augment(frame: FrameData, rng: np.random.Generator, tcfg: PointPillarsTrainConfig) -> FrameData:
    """The frame flipped / rotated / scaled (velodyne frame, about the origin); float64 boxes."""
    pts = frame.points.astype(np.float64)
    boxes = frame.boxes.astype(np.float64).copy()
    flip = tcfg.flip and rng.random() < 0.5
    angle = rng.uniform(-tcfg.rotation, tcfg.rotation)
    scale = rng.uniform(1 - tcfg.scaling, 1 + tcfg.scaling)
    if flip:
        pts[:, 1] *= -1
        boxes[:, 1] *= -1
        boxes[:, 6] = -boxes[:, 6]
    c, s = np.cos(angle), np.sin(angle)
    rot = np.array([[c, -s], [s, c]])
    pts[:, :2] = pts[:, :2] @ rot.T
    boxes[:, :2] = boxes[:, :2] @ rot.T
    boxes[:, 6] = wrap_angle(boxes[:, 6] + angle)
    pts[:, :3] *= scale
    boxes[:, :6] *= scale
    return FrameData(pts, boxes)


def batch_inputs(frames: list[FrameData], cfg: PointPillarsConfig) -> tuple[torch.Tensor, ...]:
    """Network inputs of a batch: features (P, M, 9), coords (P, 2), mask (P, M), frame index (P,)."""
    feats, coords, masks, index = [], [], [], []
    for b, f in enumerate(frames):
        a = assign_pillars(f.points, cfg.grid)
        x, m = pillar_features(torch.from_numpy(np.asarray(f.points, dtype=np.float32)), a, cfg.grid)
        feats.append(x)
        masks.append(m)
        coords.append(torch.from_numpy(a.coords))
        index.append(torch.full((a.num_pillars,), b, dtype=torch.int64))
    return torch.cat(feats), torch.cat(coords), torch.cat(masks), torch.cat(index)


def focal_loss(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """CenterNet's penalty-reduced focal loss (α 2, β 4), summed (not normalised)."""
    p = torch.sigmoid(logits).clamp(1e-4, 1 - 1e-4)
    pos = target >= 1.0 - 1e-6
    pos_loss = -torch.log(p) * (1 - p) ** 2
    neg_loss = -torch.log(1 - p) * p ** 2 * (1 - target) ** 4
    return torch.where(pos, pos_loss, neg_loss).sum()


def centre_loss(out: torch.Tensor, frames: list[FrameData], cfg: PointPillarsConfig,
                reg_weight: float) -> tuple[torch.Tensor, dict[str, float]]:
    """Focal heatmap loss + reg_weight × L1 regression loss of a batch's (B, 9, H, W) output."""
    targets = [encode(f.boxes, cfg) for f in frames]
    heat = torch.from_numpy(np.stack([t.heatmap for t in targets]))
    n = max(sum(len(t.index) for t in targets), 1)
    hm = focal_loss(out[:, 0], heat) / n
    b, c, h, w = out.shape
    rows = out[:, 1:].reshape(b, c - 1, h * w)
    pred = torch.cat([rows[i][:, torch.from_numpy(t.index)].T for i, t in enumerate(targets)])
    want = torch.from_numpy(np.concatenate([t.regression for t in targets]))
    reg = (pred - want).abs().sum() / n
    return hm + reg_weight * reg, {"heatmap": hm.item(), "regression": reg.item()}


class PointPillarsTask:
    """:class:`~robustbench3d.victims.training.TrainingTask` for the PointPillars-style detector."""

    def __init__(self, frames: list[FrameData], val: tuple[Any, list[FrameData]] | None,
                 cfg: PointPillarsConfig, tcfg: PointPillarsTrainConfig, seed: int, total_steps: int):
        self.cfg, self.tcfg, self.seed, self.total_steps = cfg, tcfg, seed, total_steps
        self.frames, self.val = frames, val
        self.model = build_model(cfg, seed)
        self.optimizer = torch.optim.AdamW(self.model.parameters(), lr=tcfg.lr, weight_decay=tcfg.weight_decay)

    def num_items(self) -> int:
        return len(self.frames)

    def config_dict(self) -> dict[str, Any]:
        return {"model": self.cfg.to_dict(), "train": asdict(self.tcfg), "seed": self.seed,
                "train_frames": len(self.frames), "total_steps": self.total_steps}

    def schedule(self, epoch: int, step: int, samples_seen: int) -> None:
        t = self.tcfg
        if step < t.warmup_steps:
            lr = t.lr * (step + 1) / t.warmup_steps
        else:
            lr = loop.cosine_lr(t.lr, step - t.warmup_steps, self.total_steps - t.warmup_steps, t.lr_min)
        loop.set_lr(self.optimizer, lr)

    def loss(self, indices: np.ndarray, rng: np.random.Generator,
             generator: torch.Generator) -> tuple[torch.Tensor, dict[str, float]]:
        frames = [augment(self.frames[int(i)], rng, self.tcfg) for i in indices]
        feats, coords, mask, index = batch_inputs(frames, self.cfg)
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=self.tcfg.precision == "bf16"):
            out = self.model(feats, coords, mask, index, len(frames))
        return centre_loss(out.float(), frames, self.cfg, self.tcfg.reg_weight)

    def evaluate(self) -> dict[str, float]:
        """Car BEV AP R40 (easy / moderate / hard) on the held val frames (empty without them)."""
        if self.val is None:
            return {}
        from robustbench3d.eval.kitti_eval import evaluate

        meta, frames = self.val
        dets = [decode_output(network_output(self.model, f.points, self.cfg), self.cfg, calib, size)
                for f, (calib, size) in zip(frames, meta["calib_size"], strict=True)]
        ap = evaluate(meta["labels"], dets, metrics=("bev",))["Car"]["bev"]["R40"]
        return {f"bev_r40_{k}": float(v) for k, v in ap.items()}

    def export(self) -> dict[str, Any]:
        return {"config": self.cfg.to_dict(),
                "state_dict": {k: v.detach().cpu() for k, v in self.model.state_dict().items()},
                "train_config": asdict(self.tcfg)}


def network_output(model: torch.nn.Module, points: np.ndarray, cfg: PointPillarsConfig) -> np.ndarray:
    """(9, H, W) float32 output of the model (eval mode, no gradients) on cropped velodyne points."""
    a = assign_pillars(points, cfg.grid)
    feats, mask = pillar_features(torch.from_numpy(np.asarray(points, dtype=np.float64)), a, cfg.grid)
    with torch.no_grad():
        return model(feats, torch.from_numpy(a.coords), mask)[0].numpy()


def load_val(data_dir: Path, split: str, cfg: PointPillarsConfig, limit: int) -> tuple[dict, list[FrameData]]:
    """The first ``limit`` val frames with what validation needs (labels, calibration, image size)."""
    from robustbench3d.kitti.dataset import KittiDataset

    ds = KittiDataset(data_dir, split=split)
    ids, frames = load_frames(data_dir, split, cfg, limit)
    meta = {"labels": [ds.labels(f) for f in ids], "calib_size": [(ds.calib(f), ds.image_size(f)) for f in ids]}
    return meta, frames


def train(data_dir: str | Path, out_dir: str | Path, cfg: PointPillarsConfig, tcfg: PointPillarsTrainConfig,
          options: loop.LoopOptions, resume: bool = False, val_limit: int = 100) -> dict[str, Any]:
    """Read the train frames (and ``val_limit`` val frames; 0: none) and run the training loop."""
    data, out = Path(data_dir), Path(out_dir)
    _, frames = load_frames(data, tcfg.train_split, cfg)
    val = load_val(data, tcfg.val_split, cfg, val_limit) if val_limit else None
    steps = len(loop.epoch_batches(len(frames), options.batch_size, options.seed, 0))
    task = PointPillarsTask(frames, val, cfg, tcfg, options.seed, total_steps=steps * options.epochs)
    return loop.run(task, out, options, resume)
