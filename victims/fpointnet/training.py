"""Training of Frustum-PointNet v1 on GT-box frustums of a KITTI-layout dataset (reference §1.8).

Defaults follow the PyTorch port: Adam (lr 1e-3, β 0.9/0.999), lr × 0.7 every 20 epochs with a
1e-5 floor, batch 32, car-only frustums, 5 perturbed copies per train box, flip and the faithful
shift augmentation; BatchNorm momentum follows the TF schedule (0.5·0.5^⌊samples/800k⌋, ≥ 0.01).
For short CPU runs, ``lr_schedule="cosine"`` decays from lr to the floor over the whole run and
``bn_decay_step`` compresses the BatchNorm schedule to the run length.
Frustum sets are cached in the output directory (``frustums_<split>.npz``); with ``cache`` the
train set is read from (or first written to) a portable, compact cache file
(:mod:`~robustbench3d.victims.fpointnet.cache`), so a machine without the dataset can train.

Speed (the model is unchanged): the per-point layers run as ``Linear`` on (B·N, C) rows
(``layout="rows"``, same state dict and outputs as the 1x1 convolutions); ``precision="bf16"``
runs the network under bfloat16 autocast (float32 master weights, optimizer and loss); batches are
drawn by tensor indexing from the whole train set held on the training device
(:mod:`~robustbench3d.victims.fpointnet.batches`); ``device`` may be ``"cuda"``.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from robustbench3d.errors import RobustBenchError
from robustbench3d.fileio import atomic_write_text
from robustbench3d.victims import training as loop
from robustbench3d.victims.fpointnet.batches import TensorFrustums
from robustbench3d.victims.fpointnet.box_coding import class_to_size
from robustbench3d.victims.fpointnet.data import FrustumItem, FrustumSet, ShiftMode, make_item
from robustbench3d.victims.fpointnet.losses import FPointNetTargets, fpointnet_loss
from robustbench3d.victims.fpointnet.model import (
    CONFIGS,
    FPointNetOutput,
    bn_momentum_at,
    build_model,
    set_bn_momentum,
)


@dataclass(frozen=True)
class FPointNetTrainConfig:
    model: str = "full"
    types: tuple[str, ...] = ("Car",)
    augment_x: int = 5
    lr: float = 1e-3
    lr_decay: float = 0.7
    lr_decay_every: int = 20
    lr_min: float = 1e-5
    lr_schedule: str = "step"
    bn_decay_step: int = 800_000
    flip: bool = True
    shift: ShiftMode = "faithful"
    double_size_residual: bool = True
    train_split: str = "train"
    val_split: str = "val"
    precision: Literal["fp32", "bf16"] = "fp32"
    layout: Literal["conv", "rows"] = "rows"
    cache: bool = False  # train set read from a frustum cache file (quantized points)


def collate(items: Sequence[FrustumItem]) -> tuple[torch.Tensor, torch.Tensor, FPointNetTargets]:
    """Stack items into (points (B, N, 4), one_hot (B, 3), targets)."""
    targets = FPointNetTargets(
        seg=torch.from_numpy(np.stack([it.seg for it in items])),
        center=torch.tensor(np.stack([it.center for it in items]), dtype=torch.float32),
        heading_class=torch.tensor([it.heading_class for it in items], dtype=torch.int64),
        heading_residual=torch.tensor([it.heading_residual for it in items], dtype=torch.float32),
        size_class=torch.tensor([it.size_class for it in items], dtype=torch.int64),
        size_residual=torch.tensor(np.stack([it.size_residual for it in items]), dtype=torch.float32),
    )
    return (torch.from_numpy(np.stack([it.points for it in items])),
            torch.from_numpy(np.stack([it.one_hot for it in items])), targets)


def _set_key(dataset: Any, split: str, cfg: FPointNetTrainConfig, seed: int, train: bool) -> dict[str, Any]:
    return {"split": split, "frames": dataset.frame_ids, "types": list(cfg.types),
            "augment_x": cfg.augment_x if train else 1, "perturb": train, "seed": seed}


def cached_frustum_set(data_dir: Path, split: str, out_dir: Path, cfg: FPointNetTrainConfig, seed: int,
                       train: bool) -> FrustumSet:
    """Build (or reuse from ``out_dir``) the frustum set of one split."""
    from robustbench3d.kitti.dataset import KittiDataset
    from robustbench3d.victims.fpointnet.data import build_frustum_set

    dataset = KittiDataset(data_dir, split=split)
    key = {"data": str(data_dir.resolve()), **_set_key(dataset, split, cfg, seed, train)}
    npz, meta = out_dir / f"frustums_{split}.npz", out_dir / f"frustums_{split}.json"
    if npz.exists() and meta.exists() and json.loads(meta.read_text()) == key:
        return FrustumSet.load(npz)
    fs = build_frustum_set(dataset, np.random.default_rng([seed, 1]), cfg.types,
                           augment_x=key["augment_x"], perturb=train)
    fs.save(npz)
    atomic_write_text(meta, json.dumps(key))
    return fs


def cache_train_set(data_dir: Path, cache: Path, out_dir: Path, cfg: FPointNetTrainConfig, seed: int) -> FrustumSet:
    """The train frustum set read from the cache file ``cache``; written there first (from the
    dataset) if absent. The cache must have been built with this run's split, types, augmentation
    copies and seed; where the dataset is at hand its frame list must match too."""
    from robustbench3d.victims.fpointnet.cache import read_frustum_cache, write_frustum_cache

    split = cfg.train_split
    if not cache.exists():
        from robustbench3d.kitti.dataset import KittiDataset
        from robustbench3d.kitti.image import image_size
        from robustbench3d.victims.fpointnet.frustum import project_scan

        dataset = KittiDataset(data_dir, split=split)
        fs = cached_frustum_set(data_dir, split, out_dir, cfg, seed, train=True)
        frames = {}
        for fid in dict.fromkeys(str(f) for f in fs.frame_ids):
            calib = dataset.calib(fid)
            p = project_scan(dataset.scan(fid), calib, image_size(dataset.path("image", fid)))
            frames[fid] = (p.points_rect[p.in_fov], calib.P2)
        cache.parent.mkdir(parents=True, exist_ok=True)
        write_frustum_cache(cache, fs, frames, _set_key(dataset, split, cfg, seed, True))
    fs, key = read_frustum_cache(cache)
    want = {"split": split, "types": list(cfg.types), "augment_x": cfg.augment_x, "perturb": True, "seed": seed}
    got = {k: key.get(k) for k in want}
    if got != want:
        raise RobustBenchError(f"{cache}: frustum cache was built with {got}, this run needs {want}; "
                               "delete it (or name another --cache) to rebuild it")
    if (data_dir / "ImageSets" / f"{split}.txt").exists():
        from robustbench3d.kitti.dataset import KittiDataset

        if KittiDataset(data_dir, split=split).frame_ids != key.get("frames"):
            raise RobustBenchError(f"{cache}: frustum cache was built from other {split!r} frames than {data_dir}'s")
    return fs


def _float32(out: FPointNetOutput) -> FPointNetOutput:
    """The output with every floating tensor in float32 (losses are computed in float32)."""
    return replace(out, **{f.name: getattr(out, f.name).float() for f in fields(out)
                           if getattr(out, f.name).is_floating_point()})


class FPointNetTask:
    """:class:`~robustbench3d.victims.training.TrainingTask` for F-PN v1."""

    def __init__(self, train_set: FrustumSet, val_set: FrustumSet | None, cfg: FPointNetTrainConfig, seed: int,
                 val_limit: int | None = None, total_steps: int = 0, device: str = "cpu"):
        if cfg.precision not in ("fp32", "bf16"):
            raise ValueError(f"unknown precision {cfg.precision!r} (expected 'fp32' or 'bf16')")
        self.cfg = cfg
        self.total_steps = total_steps
        self.seed = seed
        self.device = torch.device(device)
        self.train_set, self.val_set = train_set, val_set
        self.batches = TensorFrustums.from_set(train_set, self.device)
        self.val_limit = val_limit
        self.model = build_model(cfg.model, seed).set_layout(cfg.layout).to(self.device)
        self.num_points = CONFIGS[cfg.model].num_points
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=cfg.lr, betas=(0.9, 0.999), eps=1e-8)

    def num_items(self) -> int:
        return len(self.train_set)

    def config_dict(self) -> dict[str, Any]:
        return {**asdict(self.cfg), "seed": self.seed, "train_frustums": len(self.train_set)}

    def schedule(self, epoch: int, step: int, samples_seen: int) -> None:
        if self.cfg.lr_schedule == "cosine":
            lr = loop.cosine_lr(self.cfg.lr, step, self.total_steps, self.cfg.lr_min)
        elif self.cfg.lr_schedule == "step":
            lr = loop.step_lr(self.cfg.lr, epoch, self.cfg.lr_decay, self.cfg.lr_decay_every, self.cfg.lr_min)
        else:
            raise ValueError(f"unknown lr_schedule {self.cfg.lr_schedule!r} (expected 'step' or 'cosine')")
        loop.set_lr(self.optimizer, lr)
        set_bn_momentum(self.model, bn_momentum_at(samples_seen, decay_step=self.cfg.bn_decay_step))

    def loss(self, indices: np.ndarray, rng: np.random.Generator,
             generator: torch.Generator) -> tuple[torch.Tensor, dict[str, float]]:
        if self.device.type != "cpu":  # dropout and augmentation draw on the training device
            generator = torch.Generator(self.device).manual_seed(generator.initial_seed())
        points, one_hot, targets = self.batches.batch(indices, self.num_points, generator, self.cfg.flip,
                                                      self.cfg.shift)
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.cfg.precision == "bf16"):
            out = self.model(points, one_hot, gather="random", rng=rng, generator=generator)
        total, terms = fpointnet_loss(_float32(out), targets, double_size_residual=self.cfg.double_size_residual)
        values = torch.stack(list(terms.values())).tolist()
        return total, dict(zip(terms, values, strict=True))

    def evaluate(self, batch_size: int = 64) -> dict[str, float]:
        """Loss and simple accuracies on the val frustums (exact GT boxes, no augmentation)."""
        if self.val_set is None:
            return {}
        n = len(self.val_set) if self.val_limit is None else min(self.val_limit, len(self.val_set))
        sums: dict[str, float] = {}
        for start in range(0, n, batch_size):
            idx = range(start, min(n, start + batch_size))
            items = [make_item(self.val_set, i, self.num_points, np.random.default_rng([self.seed, i])) for i in idx]
            points, one_hot, t = collate(items)
            t = FPointNetTargets(**{f.name: getattr(t, f.name).to(self.device) for f in fields(t)})
            out = self.model(points.to(self.device), one_hot.to(self.device), gather="random",
                             rng=np.random.default_rng([self.seed, start, 2]))
            total, _ = fpointnet_loss(out, t, double_size_residual=self.cfg.double_size_residual)
            out, t = (replace(x, **{f.name: getattr(x, f.name).cpu() for f in fields(x)}) for x in (out, t))
            k = torch.arange(len(items))
            size_pred = class_to_size(out.size_scores.argmax(1).numpy(),
                                      out.size_residuals[k, out.size_scores.argmax(1)].numpy())
            size_gt = class_to_size(t.size_class.numpy(), t.size_residual.numpy())
            stats = {
                "loss": total.item() * len(items),
                "seg_accuracy": float((out.seg_logits.argmax(-1) == t.seg).float().mean()) * len(items),
                "center_error_m": float((out.center - t.center).norm(dim=1).sum()),
                "heading_class_accuracy": float((out.heading_scores.argmax(1) == t.heading_class).float().sum()),
                "size_error_m": float(np.linalg.norm(size_pred - size_gt, axis=1).sum()),
            }
            for key, v in stats.items():
                sums[key] = sums.get(key, 0.0) + v
        return {k: v / max(n, 1) for k, v in sums.items()}

    def export(self) -> dict[str, Any]:
        return {"config": self.model.cfg.to_dict(),
                "state_dict": {k: v.detach().cpu() for k, v in self.model.state_dict().items()},
                "train_config": asdict(self.cfg)}


def train(data_dir: str | Path, out_dir: str | Path, cfg: FPointNetTrainConfig, options: loop.LoopOptions,
          resume: bool = False, val_limit: int | None = None, cache: str | Path | None = None,
          device: str = "cpu") -> dict[str, Any]:
    """Build / load the frustum sets and run the training loop (see :mod:`..training`).

    ``cache``: read the train set from this frustum cache file (written first if absent);
    ``val_limit=0`` skips validation and never reads the val split.
    """
    data, out = Path(data_dir), Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if cache is not None:
        cfg = replace(cfg, cache=True)
        train_set = cache_train_set(data, Path(cache), out, cfg, options.seed)
    else:
        train_set = cached_frustum_set(data, cfg.train_split, out, cfg, options.seed, train=True)
    val_set = None if val_limit == 0 else cached_frustum_set(data, cfg.val_split, out, cfg, options.seed, train=False)
    steps = len(loop.epoch_batches(len(train_set), options.batch_size, options.seed, 0))
    task = FPointNetTask(train_set, val_set, cfg, options.seed, val_limit, total_steps=steps * options.epochs,
                         device=device)
    return loop.run(task, out, options, resume)
