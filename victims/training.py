"""A small, deterministic, resumable training loop shared by the YOLO and F-PN trainers.

Determinism: the epoch order is ``default_rng([seed, epoch]).permutation``; batch ``i`` of an
epoch draws its data augmentation from ``default_rng([seed, epoch, i])`` and its torch randomness
(dropout) from a ``torch.Generator`` seeded from that generator. Nothing uses global RNG state, so
a run resumed from a checkpoint (model, optimizer, progress counters) continues exactly as the
uninterrupted run would (same thread count assumed).

Outputs in ``out_dir``: ``last.pt`` (checkpoint, written atomically every ``checkpoint_every``
steps and at each epoch end: model and optimizer state dicts, progress counters, history and run
configuration — tensors and plain containers only, read back with ``torch.load(weights_only=True)``
through :func:`~robustbench3d.victims.torchfile.load_torch_data`, so a crafted file runs nothing),
``model.pt`` (``{"config", "state_dict"}`` after the last epoch),
``log.jsonl`` (one JSON line per finished epoch: losses and validation metrics).
"""

from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch
from torch import nn

from robustbench3d.errors import DataFormatError, RobustBenchError
from robustbench3d.fileio import atomic_open, atomic_write_text
from robustbench3d.victims.torchfile import load_torch_data, one_line

CHECKPOINT = "last.pt"
MODEL = "model.pt"
LOG = "log.jsonl"


@dataclass(frozen=True)
class LoopOptions:
    """epochs, batch_size, seed; checkpoint_every (steps, 0 = epoch ends only); max_steps (stop
    after this many steps in total, leaving a checkpoint — used to test resuming); progress (tqdm
    bar on stderr)."""

    epochs: int
    batch_size: int
    seed: int = 0
    checkpoint_every: int = 0
    max_steps: int | None = None
    progress: bool = True


class TrainingTask(Protocol):
    """What the loop needs from a model-specific trainer."""

    model: nn.Module
    optimizer: torch.optim.Optimizer

    def num_items(self) -> int: ...

    def schedule(self, epoch: int, step: int, samples_seen: int) -> None:
        """Set learning rate / BN momentum before a step."""

    def loss(self, indices: np.ndarray, rng: np.random.Generator,
             generator: torch.Generator) -> tuple[torch.Tensor, dict[str, float]]:
        """Training loss of the items ``indices`` (model in train mode)."""
        ...

    def evaluate(self) -> dict[str, float]:
        """Validation metrics (the loop switches the model to eval mode around the call)."""
        ...

    def export(self) -> dict[str, Any]:
        """``{"config": ..., "state_dict": ...}`` for ``model.pt``."""
        ...

    def config_dict(self) -> dict[str, Any]:
        """Everything that must match for a resume to be valid."""
        ...


def epoch_batches(n: int, batch_size: int, seed: int, epoch: int) -> list[np.ndarray]:
    """Shuffled batches of one epoch; a last partial batch is kept only if it has >= 2 items
    (BatchNorm needs two)."""
    order = np.random.default_rng([seed, epoch]).permutation(n)
    batches = [order[i:i + batch_size] for i in range(0, n, batch_size)]
    return [b for b in batches if len(b) >= 2]


_FRESH_START = "; delete it (or use another --out) to train from scratch"
_STATE_FIELDS = {"epoch": int, "batch": int, "step": int, "samples": int, "history": list, "finished": bool}


def read_checkpoint(path: str | Path, resumable: bool = False) -> dict[str, Any]:
    """A ``last.pt`` of :func:`run`, read as data only (tensors and plain containers; nothing in it
    runs) and checked: ``run_config`` and ``state`` always, ``model`` and ``optimizer`` state dicts
    and every progress counter too when ``resumable``."""
    path = Path(path)
    what = "training checkpoint (last.pt of `robustbench3d train`)"
    hint = _FRESH_START if resumable else ""
    ckpt = load_torch_data(path, what)
    need = {"run_config": dict, "state": dict, **({"model": dict, "optimizer": dict} if resumable else {})}
    missing = [key for key, kind in need.items() if not isinstance(ckpt, dict) or not isinstance(ckpt.get(key), kind)]
    if missing:
        raise DataFormatError(path, f"not a {what}: no {' / '.join(map(repr, missing))} dict{hint}")
    for key in ("run_config", "state"):
        try:
            json.dumps(ckpt[key])
        except (TypeError, ValueError) as exc:
            raise DataFormatError(path, f"not plain JSON-like data ({exc}){hint}", field=key) from None
    fields = {**_STATE_FIELDS, "running": dict} if resumable else {"step": int}
    for key, kind in fields.items():
        value = ckpt["state"].get(key, {} if key == "running" else None)
        if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
            raise DataFormatError(path, f"expected {kind.__name__} {key!r}{hint}", field="state")
    return ckpt


def _save(path: Path, payload: dict[str, Any]) -> None:
    with atomic_open(path, "wb") as f:
        torch.save(payload, f)


def run(task: TrainingTask, out_dir: str | Path, options: LoopOptions, resume: bool = False) -> dict[str, Any]:
    """Train; returns the final progress state (``epoch``, ``step``, ``history``, ``finished``)."""
    from tqdm import tqdm

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    state: dict[str, Any] = {"epoch": 0, "batch": 0, "step": 0, "samples": 0, "history": [], "finished": False}
    ckpt_path = out / CHECKPOINT
    run_config = {"task": task.config_dict(), "loop": {k: v for k, v in asdict(options).items()
                                                        if k in ("batch_size", "seed")}}
    if resume and ckpt_path.exists():
        ckpt = read_checkpoint(ckpt_path, resumable=True)
        if ckpt["run_config"] != run_config:
            raise RobustBenchError(f"{ckpt_path}: checkpoint was written with a different configuration; "
                                   "use another --out or drop --resume")
        try:
            task.model.load_state_dict(ckpt["model"])
            task.optimizer.load_state_dict(ckpt["optimizer"])
        except (RuntimeError, ValueError, KeyError, TypeError) as exc:
            raise DataFormatError(ckpt_path, f"its model or optimizer state does not fit this run ({one_line(exc)})"
                                  f"{_FRESH_START}") from None
        state = ckpt["state"]
    elif resume:
        print(f"no checkpoint at {ckpt_path}; starting from scratch", file=sys.stderr)

    def checkpoint() -> None:
        _save(ckpt_path, {"model": task.model.state_dict(), "optimizer": task.optimizer.state_dict(),
                          "state": state, "run_config": run_config})

    n = task.num_items()
    for epoch in range(state["epoch"], options.epochs):
        batches = epoch_batches(n, options.batch_size, options.seed, epoch)
        if not batches:
            raise RobustBenchError(f"training set has {n} items; need at least 2")
        bar = tqdm(total=len(batches), initial=state["batch"], desc=f"epoch {epoch + 1}/{options.epochs}",
                   file=sys.stderr, disable=not options.progress, leave=False)
        sums: dict[str, float] = state.get("running", {})
        t_epoch = time.perf_counter()
        for bi in range(state["batch"], len(batches)):
            rng = np.random.default_rng([options.seed, epoch, bi])
            generator = torch.Generator().manual_seed(int(rng.integers(0, 2**62)))
            task.schedule(epoch, state["step"], state["samples"])
            task.model.train()
            loss, metrics = task.loss(batches[bi], rng, generator)
            if not math.isfinite(loss.item()):
                raise RobustBenchError(f"non-finite training loss at epoch {epoch + 1}, batch {bi}")
            task.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            task.optimizer.step()
            state["step"] += 1
            state["samples"] += len(batches[bi])
            state["batch"] = bi + 1
            for k, v in {"loss": loss.item(), **metrics}.items():
                sums[k] = sums.get(k, 0.0) + v
            sums["_count"] = sums.get("_count", 0.0) + 1
            state["running"] = sums
            bar.update(1)
            bar.set_postfix(loss=f"{loss.item():.4f}")
            stop = options.max_steps is not None and state["step"] >= options.max_steps
            if stop or (options.checkpoint_every and state["step"] % options.checkpoint_every == 0):
                checkpoint()
            if stop:
                bar.close()
                return state
        bar.close()
        t_train = time.perf_counter() - t_epoch
        task.model.eval()
        with torch.no_grad():
            val = task.evaluate()
        count = max(sums.pop("_count", 1.0), 1.0)
        seconds = state.setdefault("seconds", {"train": 0.0, "val": 0.0})  # wall time, outside the log
        seconds["train"] += t_train
        seconds["val"] += time.perf_counter() - t_epoch - t_train
        record = {"epoch": epoch + 1, "step": state["step"],
                  **{f"train_{k}": v / count for k, v in sums.items()}, **{f"val_{k}": v for k, v in val.items()}}
        state["history"].append(record)
        state.update(epoch=epoch + 1, batch=0, running={})
        checkpoint()
        atomic_write_text(out / LOG, "".join(json.dumps(r, sort_keys=True) + "\n" for r in state["history"]))
        print(json.dumps({**record, "epoch_train_seconds": round(t_train, 3)}, sort_keys=True), file=sys.stderr)
    state["finished"] = True
    _save(out / MODEL, task.export())
    return state


def step_lr(base: float, epoch: int, decay: float, every: int, minimum: float) -> float:
    """base·decay^⌊epoch/every⌋, floored at ``minimum``."""
    return max(minimum, base * decay ** (epoch // every))


def cosine_lr(base: float, step: int, total_steps: int, minimum: float) -> float:
    """Cosine decay from ``base`` at step 0 to ``minimum`` at ``total_steps`` (held after it)."""
    t = min(max(step / max(total_steps, 1), 0.0), 1.0)
    return minimum + 0.5 * (base - minimum) * (1.0 + math.cos(math.pi * t))


def set_lr(optimizer: torch.optim.Optimizer, lr: float) -> None:
    for group in optimizer.param_groups:
        group["lr"] = lr
