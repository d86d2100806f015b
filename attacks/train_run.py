"""The loop of ``attack train``: run :class:`~robustbench3d.attacks.train.UniversalTrainer` to the step
budget with a progress bar and checkpoints (``--resume``), then write the object file and its sidecar.

Written once: the object file ``OBJ.ply``, its sidecar ``OBJ.json`` and the checkpoint ``OBJ.train.pt`` are
never replaced unless ``force`` (``--force``), with one exception, the resume rule: ``resume`` continues the
checkpoint, and replaces ``OBJ.ply`` and ``OBJ.json`` if they are that training's earlier result (the
sidecar's configuration, victim and training data are the checkpoint's). Both are checked before training.
"""

from __future__ import annotations

import hashlib
import sys
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from robustbench3d.attacks.train import UniversalTrainer, format_losses
from robustbench3d.attacks.train_config import COUNTS, TrainConfig, TrainingError, check_oracles
from robustbench3d.errors import RobustBenchError
from robustbench3d.kitti.dataset import KittiDataset
from robustbench3d.kitti.labels import Labels


def checkpoint_path(out: str | Path) -> Path:
    """Where the training of object file ``out`` keeps its checkpoint: ``NAME.train.pt`` beside it."""
    out = Path(out)
    return out.with_name(out.stem + ".train.pt")


def output_files(out: str | Path) -> tuple[Path, Path, Path]:
    """(object file, its sidecar, its checkpoint) of ``--out`` ``out``."""
    from robustbench3d.attacks.objectfile import sidecar_path

    out = Path(out)
    return out, sidecar_path(out), checkpoint_path(out)


def check_outputs(out: str | Path, *, force: bool = False, resume: bool = False) -> list[str]:
    """Before any work: refuse an ``--out`` that is not a ``.ply`` name or whose files cannot be written, and
    (the module doc's written-once rule) an existing object file, sidecar or checkpoint unless ``force``; with
    ``resume`` and a checkpoint the object file is decided once the checkpoint is read (:func:`check_resumed`).
    Returns the lines to print: what ``force`` replaces."""
    from robustbench3d.fileio import check_output_file, replacing_note

    ply, side, ckpt = output_files(out)
    if ply.suffix.lower() != ".ply":
        raise TrainingError(f"--out {ply}: an object file must end in .ply")
    for path in (ply, side, ckpt):
        check_output_file(path, "--out" if path == ply else f"--out {ply}: its file")
    resuming = resume and ckpt.is_file()
    if force:
        return [note for p in ((ply, side) if resuming else (ply, side, ckpt)) if (note := replacing_note(p))]
    if resuming:
        return []
    if ckpt.exists():
        raise TrainingError(f"--out {ply}: the checkpoint {ckpt.name} of an earlier training exists; pass --resume "
                            "to continue it or --force to start afresh (nothing was written)")
    for path in (ply, side):
        if path.exists():
            raise TrainingError(f"--out {ply}: {path.name} exists; pass --force to replace the object file and its "
                                "sidecar (nothing was written)")
    return []


def check_resumed(out: Path, made_by: dict[str, Any], force: bool) -> list[str]:
    """After the checkpoint beside ``out`` was read: the lines to print about the object file and sidecar it
    will replace; refuses (unless ``force``) a pair the checkpoint's training did not write (``made_by``: the
    record that training writes, compared on its configuration, victim and training data)."""
    import json

    from robustbench3d.attacks.objectfile import read_object_file

    ply, side, ckpt = output_files(out)
    if force or not (ply.exists() or side.exists()):
        return []
    skip = ("steps", "checkpoint_every")
    want = json.loads(json.dumps({"config": {k: v for k, v in made_by["config"].items() if k not in skip},
                                  "victim": made_by["victim"], "training_data": made_by["training_data"]}))
    try:
        have = read_object_file(ply).made_by
    except RobustBenchError as exc:
        raise TrainingError(f"--out {ply}: exists but is not a readable object file ({exc}); pass --force to "
                            "replace it (nothing was written)") from None
    have = {"config": {k: v for k, v in (have.get("config") or {}).items() if k not in skip},
            "victim": have.get("victim"), "training_data": have.get("training_data")}
    if have != want:
        differ = ", ".join(k for k in want if have[k] != want[k])
        raise TrainingError(f"--out {ply}: exists and was not made by the training {ckpt.name} continues ({differ} "
                            "differ); pass --force to replace it (nothing was written)")
    return [f"replacing {ply} and {side.name}, the earlier result of the training {ckpt.name} continues (--resume)"]


def _progress(total: int, initial: int, enabled: bool, desc: str) -> Any:
    from tqdm import tqdm

    return tqdm(total=total, initial=initial, disable=not enabled, file=sys.stderr, unit="step", desc=desc)


def train_universal(victim: Any, victim_info: dict[str, Any], kitti: KittiDataset, frame_ids: list[str],
                    labels: list[Labels], config: TrainConfig, out: str | Path, *,
                    data_identity: dict[str, Any] | None = None, resume: bool = False, force: bool = False,
                    progress: bool = True, on_step: Callable[[UniversalTrainer], None] | None = None,
                    log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Optimise the object (module doc), write it to ``out`` (an object file; its checkpoint beside it,
    :func:`checkpoint_path`) and return its sidecar's ``made_by``.

    ``victim_info``: at least ``name``; ``data_identity``: the training data's record; ``resume``, ``force``:
    the module doc's written-once rule (refusals raise :class:`TrainingError` before training); ``log``
    receives the lines saying what is replaced; ``on_step`` is called after every step (tests use it to
    interrupt a run).
    """
    from robustbench3d import __version__
    from robustbench3d.attacks.objectfile import save_object

    out = Path(out)
    notes = check_outputs(out, force=force, resume=resume)
    name = str(victim_info.get("name", type(victim).__name__))
    check_oracles(victim, config.mode, name, config.lidar_boxes, config.lidar_loss)
    trainer = UniversalTrainer(victim, kitti, frame_ids, labels, config)
    identity = {"config": config.identity(), "victim": victim_info, "data": data_identity or {}}
    ckpt = checkpoint_path(out)
    trainer.ckpt = ckpt
    if resume and ckpt.is_file():
        trainer.load_checkpoint(ckpt, identity)
        notes += check_resumed(out, {"config": {**asdict(config), "eot": list(config.eot)}, "victim": victim_info,
                                     "training_data": data_identity or {}}, force)
    for line in notes if log is not None else ():
        log(line)
    bar = _progress(config.steps, min(trainer.step, config.steps), progress, config.mode)
    try:
        while trainer.step < config.steps:
            t0 = time.perf_counter()
            result = trainer.compute_step(trainer.step)
            trainer.apply_step(result)
            trainer.elapsed_s += time.perf_counter() - t0
            drop = trainer.drop_estimate()
            bar.set_postfix_str(format_losses(result.losses) + (f" drop~{drop:.0%}" if drop is not None else ""))
            bar.update(1)
            if trainer.step % config.checkpoint_every == 0 or trainer.step == config.steps:
                trainer.save_checkpoint(ckpt, identity)
            if on_step is not None:
                on_step(trainer)
    finally:
        bar.close()
    hist = trainer.history
    made_by = {
        "attack": config.mode, "tool": "robustbench3d attack train", "package_version": __version__,
        "victim": victim_info, "training_data": data_identity or {},
        "config": {**asdict(config), "eot": list(config.eot)},
        "seed": config.seed, "steps": trainer.step, "cars": len(trainer.cars),
        "parametrisation": {"shape": "tanh box: v = b tanh(atanh(0.999 v0 / b) + delta)" if config.kind.shape
                            else "fixed: the undeformed sphere",
                            "colour": "sigmoid(logits)" if config.kind.colour else "fixed: neutral grey 128/255"},
        "lidar_proposals": ({"gt": "ground-truth 2D boxes", "detector": "the victim's 2D detections on the "
                                                                          "attacked image"}[config.lidar_boxes]
                            if config.kind.lidar else None),
        "losses": {"weights": config.weights(), "first_step": hist[0] if hist else None,
                   "last_step": hist[-1] if hist else None,
                   "mean_last_10": _mean_losses(hist[-10:])},
        "drop_estimate": trainer.drop_estimate(), "wall_time_s": round(trainer.elapsed_s, 3),
    }
    save_object(out, trainer.current_object(), made_by)
    return made_by


def _mean_losses(hist: list[dict[str, float]]) -> dict[str, float] | None:
    if not hist:
        return None
    return {k: float(np.mean([h[k] for h in hist])) for k in hist[0] if k not in COUNTS}


def data_identity(identity: dict[str, Any], root: Path) -> dict[str, Any]:
    """The training data's record: a dataset identity (:func:`robustbench3d.datasets.dataset_identity`)
    with the generator manifest replaced by its file's sha256 (if the dataset has one)."""
    from robustbench3d.synth.writer import MANIFEST

    rec = {k: v for k, v in identity.items() if k != "manifest"}
    manifest = Path(root) / MANIFEST
    rec["manifest_sha256"] = hashlib.sha256(manifest.read_bytes()).hexdigest() if manifest.is_file() else None
    return rec
