"""The loop of ``attack train``: run :class:`~robustbench3d.attacks.train.UniversalTrainer` to the step
budget with a progress bar and checkpoints (``--resume``), evaluate the object on held-out frames every
``eval_every`` steps and stop on a plateau (:mod:`~robustbench3d.attacks.train_curve`), then write the object
file (the best held-out state) and its sidecar.

Before the first step, :func:`warm_depths` computes the exact-occlusion scene depths (on a generated dataset,
:mod:`~robustbench3d.attacks.depth_cache`) of every frame the remaining steps draw and of the held-out frames
that are not cached yet, in worker processes (``attack train --workers``): a step then reads them (a few ms per
frame) where it would otherwise rebuild the frame's scene (0.1-0.65 s). The values are the same either way.

Written once: the object file ``OBJ.ply``, its sidecar ``OBJ.json``, the checkpoint ``OBJ.train.pt`` and the
curve files ``OBJ.curve.csv`` and ``OBJ.curve.png`` (with evaluation) are never replaced unless ``force``
(``--force``), with one exception, the resume rule: ``resume`` continues the checkpoint, and replaces
``OBJ.ply`` and ``OBJ.json`` if they are that training's earlier result (the sidecar's configuration, victim
and training data are the checkpoint's), and the curve files if they are its curve (every row of the CSV
at a step the checkpoint holds a row for equals that row, and none is later than the checkpoint's step).
All are checked before training.
"""

from __future__ import annotations

import hashlib
import sys
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from robustbench3d.attacks.train import UniversalTrainer, format_losses
from robustbench3d.attacks.train_config import (
    COUNTS,
    TrainConfig,
    TrainingError,
    check_oracles,
    comparable_config,
)
from robustbench3d.attacks.train_curve import (
    CRITERION,
    HeldOut,
    best_of,
    csv_text,
    curve_paths,
    eval_proposals,
    make_row,
    plateau,
    read_csv_rows,
    split_held_out,
    write_curve,
)
from robustbench3d.errors import RobustBenchError
from robustbench3d.kitti.dataset import KittiDataset
from robustbench3d.kitti.labels import Labels
from robustbench3d.victims.spec import PROTOCOL_LABELS


def checkpoint_path(out: str | Path) -> Path:
    """Where the training of object file ``out`` keeps its checkpoint: ``NAME.train.pt`` beside it."""
    out = Path(out)
    return out.with_name(out.stem + ".train.pt")


def output_files(out: str | Path) -> tuple[Path, Path, Path]:
    """(object file, its sidecar, its checkpoint) of ``--out`` ``out``."""
    from robustbench3d.attacks.objectfile import sidecar_path

    out = Path(out)
    return out, sidecar_path(out), checkpoint_path(out)


def check_outputs(out: str | Path, *, force: bool = False, resume: bool = False, curve: bool = False,
                  ckpt: Path | None = None) -> list[str]:
    """Before any work: refuse an ``--out`` that is not a ``.ply`` name or whose files cannot be written, and
    (the module doc's written-once rule) an existing object file, sidecar, checkpoint or (``curve``: with
    evaluation) curve file unless ``force``; with ``resume`` and a checkpoint the object and curve files are
    decided once the checkpoint is read (:func:`check_resumed`). Returns the lines to print: what ``force``
    replaces. ``ckpt``: the run's checkpoint (default :func:`checkpoint_path`; the black-box optimiser keeps
    its own, :mod:`~robustbench3d.attacks.blackbox_run`)."""
    from robustbench3d.fileio import check_output_file, replacing_note

    ply, side, default_ckpt = output_files(out)
    ckpt = default_ckpt if ckpt is None else ckpt
    if ply.suffix.lower() != ".ply":
        raise TrainingError(f"--out {ply}: an object file must end in .ply")
    curves = curve_paths(ply) if curve else ()
    for path in (ply, side, ckpt, *curves):
        check_output_file(path, "--out" if path == ply else f"--out {ply}: its file")
    resuming = resume and ckpt.is_file()
    if force:
        mine = (ply, side, *curves) if resuming else (ply, side, ckpt, *curves)
        return [note for p in mine if (note := replacing_note(p))]
    if resuming:
        return []
    if ckpt.exists():
        raise TrainingError(f"--out {ply}: the checkpoint {ckpt.name} of an earlier training exists; pass --resume "
                            "to continue it or --force to start afresh (nothing was written)")
    for path in (ply, side):
        if path.exists():
            raise TrainingError(f"--out {ply}: {path.name} exists; pass --force to replace the object file and its "
                                "sidecar (nothing was written)")
    for path in curves:
        if path.exists():
            raise TrainingError(f"--out {ply}: {path.name} exists (the held-out curve of another training); pass "
                                "--force to replace it, or --eval-every 0 to train without a curve (nothing was "
                                "written)")
    return []


def check_resumed(out: Path, made_by: dict[str, Any], force: bool, rows: list[dict[str, Any]] | None = None,
                  step: int = 0, ckpt: Path | None = None) -> list[str]:
    """After the checkpoint beside ``out`` was read: the lines to print about the object file, sidecar and
    (``rows``: the checkpoint's curve rows, ``step`` its step; None without evaluation) curve files it will
    replace; refuses (unless ``force``) a pair the checkpoint's training did not write (``made_by``: the
    record that training writes, compared on its configuration, victim and training data) and curve files
    that are not its curve (module doc). ``ckpt``: as :func:`check_outputs`."""
    import json

    from robustbench3d.attacks.objectfile import read_object_file

    ply, side, default_ckpt = output_files(out)
    ckpt = default_ckpt if ckpt is None else ckpt
    if force:
        return []
    notes = _check_resumed_curve(out, rows, step, ckpt) if rows is not None else []
    if not (ply.exists() or side.exists()):
        return notes
    want = json.loads(json.dumps({"config": comparable_config(made_by["config"]), "victim": made_by["victim"],
                                  "training_data": made_by["training_data"]}))
    try:
        have = read_object_file(ply).made_by
    except RobustBenchError as exc:
        raise TrainingError(f"--out {ply}: exists but is not a readable object file ({exc}); pass --force to "
                            "replace it (nothing was written)") from None
    have = {"config": comparable_config(have.get("config") or {}), "victim": have.get("victim"),
            "training_data": have.get("training_data")}
    if have != want:
        differ = ", ".join(k for k in want if have[k] != want[k])
        raise TrainingError(f"--out {ply}: exists and was not made by the training {ckpt.name} continues ({differ} "
                            "differ); pass --force to replace it (nothing was written)")
    return [f"replacing {ply} and {side.name}, the earlier result of the training {ckpt.name} continues (--resume)",
            *notes]


def _check_resumed_curve(out: Path, rows: list[dict[str, Any]], step: int, ckpt: Path) -> list[str]:
    """The line about the curve files a resumed run replaces; refuses files that are not the curve of the
    checkpoint's training (module doc)."""
    csv_path, png_path = curve_paths(out)
    if not csv_path.exists():
        if png_path.exists():
            raise TrainingError(f"--out {out}: {png_path.name} exists without {csv_path.name}, so it is not the curve "
                                f"of the training {ckpt.name} continues; pass --force to replace it (nothing was "
                                "written)")
        return []
    cells = read_csv_rows(csv_path)
    mine = {str(r["step"]): line for r, line in zip(rows, _csv_lines(rows), strict=True)}
    bad = cells is None or any(not c or not c[0].isdigit() or int(c[0]) > step
                               or (c[0] in mine and c != mine[c[0]]) for c in cells[1:])
    if bad:
        raise TrainingError(f"--out {out}: {csv_path.name} exists and is not the curve of the training {ckpt.name} "
                            "continues; pass --force to replace it (nothing was written)")
    return [f"replacing {csv_path.name} and {png_path.name}, the curve of the training {ckpt.name} continues "
            "(--resume)"]


def _csv_lines(rows: list[dict[str, Any]]) -> list[list[str]]:
    import csv
    import io

    return list(csv.reader(io.StringIO(csv_text(rows))))[1:]


def progress_bar(total: int, initial: int, enabled: bool, desc: str, unit: str = "step") -> Any:
    """The run loops' tqdm bar on stderr (``unit``: step, or query for the black-box loop)."""
    from tqdm import tqdm

    return tqdm(total=total, initial=initial, disable=not enabled, file=sys.stderr, unit=unit, desc=desc)


def train_universal(victim: Any, victim_info: dict[str, Any], kitti: KittiDataset, frame_ids: list[str],
                    labels: list[Labels], config: TrainConfig, out: str | Path, *,
                    data_identity: dict[str, Any] | None = None, resume: bool = False, force: bool = False,
                    progress: bool = True, on_step: Callable[[UniversalTrainer], None] | None = None,
                    log: Callable[[str], None] | None = None, workers: int = 1) -> dict[str, Any]:
    """Optimise the object (module doc) on ``frame_ids`` but the held-out ones, write it to ``out`` (an object
    file; its checkpoint and curve files beside it, :func:`checkpoint_path`,
    :func:`~robustbench3d.attacks.train_curve.curve_paths`) and return its sidecar's ``made_by``.

    ``victim_info``: at least ``name``; ``data_identity``: the training data's record; ``resume``, ``force``:
    the module doc's written-once rule (refusals raise :class:`TrainingError` before training); ``log``
    receives the lines saying what is replaced, which frames are held out, each evaluation and why training
    stopped; ``on_step`` is called after every step (tests use it to interrupt a run). Before the first step the
    exact-occlusion scene depths the run will read are computed by ``workers`` processes where not cached
    (:func:`warm_depths`), so no step rebuilds a scene.
    """
    from robustbench3d.attacks.objectfile import save_object

    out = Path(out)
    say = log if log is not None else (lambda line: None)
    train_ids, train_labels, held_ids, held_labels = split_held_out(frame_ids, labels,
                                                                    config.held_out(len(frame_ids)))
    heldout = (HeldOut(victim, kitti, held_ids, held_labels, eval_proposals(config, victim), config.seed)
               if held_ids else None)
    held_line = held_out_line(config, heldout, len(frame_ids))
    if heldout is not None and heldout.cars == 0:
        heldout = None
    notes = check_outputs(out, force=force, resume=resume, curve=heldout is not None)
    name = str(victim_info.get("name", type(victim).__name__))
    check_oracles(victim, config.mode, name, config.lidar_boxes, config.lidar_loss)
    trainer = UniversalTrainer(victim, kitti, train_ids, train_labels, config)
    identity = {"config": config.identity(), "victim": victim_info, "data": data_identity or {}}
    ckpt = checkpoint_path(out)
    trainer.ckpt = ckpt
    if resume and ckpt.is_file():
        trainer.load_checkpoint(ckpt, identity)
        notes += check_resumed(out, {"config": config.record(), "victim": victim_info,
                                     "training_data": data_identity or {}}, force,
                               trainer.run_state.get("rows", []) if heldout is not None else None, trainer.step)
    for line in notes:
        say(line)
    say(held_line)
    warm_depths(trainer, heldout, workers=workers, progress=progress, log=say)
    run = _Run(trainer, heldout, config, out, identity, say)
    run.train(progress, on_step)
    obj, object_step, rows = run.finish()
    made_by = _made_by(out, trainer, config, victim_info, data_identity or {}, heldout, rows, object_step, run)
    save_object(out, obj, made_by)
    return made_by


def warm_depths(trainer: UniversalTrainer, heldout: HeldOut | None, *, workers: int = 1, progress: bool = False,
                log: Callable[[str], None] | None = None) -> Any:
    """Compute the exact-occlusion cache files (:func:`~robustbench3d.attacks.depth_cache.warm_scene_depths`)
    that the remaining steps (``trainer.step`` to the step budget) and the held-out evaluations (the trainer's
    held-out losses and the benchmark-cell attack of the object) will read, with ``workers`` processes; the
    :class:`~robustbench3d.attacks.depth_cache.WarmReport`, None when the run reads none (no exact occlusion)."""
    from robustbench3d.attacks.depth_cache import synth_key, warm_scene_depths

    held = heldout.frame_ids if heldout is not None else []
    jobs = trainer.depth_jobs(trainer.step_frames(trainer.step, trainer.config.steps) + held)
    if heldout is not None:
        jobs += heldout.depth_jobs(trainer.current_object())
    key = synth_key(trainer.kitti.root)
    if not jobs or key is None:
        return None
    return warm_scene_depths(Path(trainer.kitti.root).resolve(), key, jobs, workers=workers, progress=progress,
                             log=log)


def held_out_line(config: TrainConfig, heldout: HeldOut | None, frames: int) -> str:
    """The line saying which frames the curve holds out (or why there is no curve)."""
    if config.eval_every == 0:
        return "no held-out curve (--eval-every 0): training on every frame of the split"
    if heldout is None:
        return (f"no held-out curve: a split of {frames} frame(s) leaves no frame to hold out (at most a fifth of "
                "the frames are held out); training on every frame")
    d = heldout.describe()
    capped = f" (--eval-frames {config.eval_frames}: at most a fifth of the split)" \
        if d["frames"] < config.eval_frames else ""
    if heldout.cars == 0:
        return (f"no held-out curve: the held-out frames {d['first_frame']}..{d['last_frame']} (the last "
                f"{d['frames']} of the split's {frames}{capped}) have no target car; they are not trained on either")
    return (f"held out for the curve: the last {d['frames']} of the split's {frames} frames{capped}, frames "
            f"{d['first_frame']}..{d['last_frame']} ({d['cars']} cars), never trained on; evaluated every "
            f"{config.eval_every} steps with proposals {d['proposals']!r}")


class _Run:
    """The training loop with its evaluations, checkpoints and curve files (module doc)."""

    def __init__(self, trainer: UniversalTrainer, heldout: HeldOut | None, config: TrainConfig, out: Path,
                 identity: dict[str, Any], say: Callable[[str], None]) -> None:
        self.trainer, self.heldout, self.config, self.out, self.identity, self.say = (
            trainer, heldout, config, out, identity, say)
        state = trainer.run_state
        state.setdefault("rows", [])
        state.setdefault("best", None)
        state.setdefault("eval_s", 0.0)
        self.stop: str | None = None
        self.title = f"{config.name} against {identity['victim'].get('name', '?')}"

    @property
    def rows(self) -> list[dict[str, Any]]:
        """The rows of the regular evaluations (steps 0, K, 2K, ...), kept in the checkpoint."""
        return self.trainer.run_state["rows"]

    def train(self, progress: bool, on_step: Callable[[UniversalTrainer], None] | None) -> None:
        trainer, config = self.trainer, self.config
        if self.heldout is not None:
            if trainer.step == 0 and not self.rows:
                self._evaluate_regular()
            if self.rows and self.rows[-1]["step"] == trainer.step:  # a resumed run that stopped here stops again
                self.stop = plateau(self.rows, config.plateau_window, config.plateau_tol)
        bar = progress_bar(config.steps, min(trainer.step, config.steps), progress, config.name)
        try:
            while self.stop is None and trainer.step < config.steps:
                t0 = time.perf_counter()
                result = trainer.compute_step(trainer.step)
                trainer.apply_step(result)
                trainer.elapsed_s += time.perf_counter() - t0
                drop = trainer.drop_estimate()
                bar.set_postfix_str(format_losses(result.losses) + (f" drop~{drop:.0%}" if drop is not None else ""))
                bar.update(1)
                if self.heldout is not None and trainer.step % config.eval_every == 0:
                    self._evaluate_regular()
                    self.stop = plateau(self.rows, config.plateau_window, config.plateau_tol)
                if trainer.step % config.checkpoint_every == 0 or trainer.step == config.steps or self.stop:
                    trainer.save_checkpoint(trainer.ckpt, self.identity)
                    if self.heldout is not None:
                        write_curve(self.out, self.rows, self.title)
                if on_step is not None:
                    on_step(trainer)
        finally:
            bar.close()
        if self.stop is not None:
            self.say(self.stop)

    def _train_loss(self, step: int) -> float | None:
        """Mean total training loss of the steps since the previous regular evaluation (before ``step``)."""
        since = self.rows[-1]["step"] if self.rows else step
        hist = self.trainer.history[since:step]
        return float(np.mean([h["total"] for h in hist])) if hist else None

    def _evaluate(self, step: int) -> dict[str, Any]:
        """The curve row of the current object at ``step`` (the module doc of train_curve)."""
        assert self.heldout is not None
        t0 = time.perf_counter()
        losses = self.trainer.heldout_losses(self.heldout.frame_ids, f"the held-out evaluation at step {step}")
        effect = self.heldout.effect(self.trainer.current_object())
        row = make_row(step, self._train_loss(step), losses, effect, self.rows)
        took = time.perf_counter() - t0
        self.trainer.run_state["eval_s"] += took
        self.say(f"{_row_line(row)} ({took:.1f} s)")
        return row

    def _evaluate_regular(self) -> None:
        row = self._evaluate(self.trainer.step)
        self.rows.append(row)
        if row["best"]:
            self.trainer.run_state["best"] = {"step": row["step"], "delta": self.trainer.delta.detach().clone(),
                                              "colour_logit": self.trainer.colour_logit.detach().clone()}

    def finish(self) -> tuple[Any, int, list[dict[str, Any]]]:
        """(the object to write, the step of its state, every curve row): the best held-out state, evaluating
        the last step first if it is not a regular evaluation's; the current object without evaluation."""
        trainer = self.trainer
        if self.heldout is None:
            return trainer.current_object(), trainer.step, []
        rows = list(self.rows)
        if not rows or rows[-1]["step"] != trainer.step:
            rows.append(self._evaluate(trainer.step))
        write_curve(self.out, rows, self.title)
        best = best_of(rows)
        assert best is not None
        if best["step"] == trainer.step:
            return trainer.current_object(), trainer.step, rows
        kept = trainer.run_state["best"]
        assert kept is not None and kept["step"] == best["step"]
        return trainer.object_at(kept["delta"], kept["colour_logit"]), best["step"], rows


def _row_line(row: dict[str, Any]) -> str:
    """One line per evaluation."""
    def pct(v: float | None) -> str:
        return "n/a" if v is None else f"{v:.1%}"

    return (f"step {row['step']}: held-out loss {row['heldout_loss']:.4g}{' (best)' if row['best'] else ''}, "
            f"relative drop {pct(row['relative_drop'])}, ASR {pct(row['asr'])}")


def _made_by(out: Path, trainer: UniversalTrainer, config: TrainConfig, victim_info: dict[str, Any],
             data_identity: dict[str, Any], heldout: HeldOut | None, rows: list[dict[str, Any]], object_step: int,
             run: _Run) -> dict[str, Any]:
    """The sidecar's ``made_by`` of the finished run."""
    from robustbench3d import __version__

    hist = trainer.history
    if run.stop is not None:
        stopped = {"reason": "plateau", "step": trainer.step, "line": run.stop}
    else:
        stopped = {"reason": "steps", "step": trainer.step, "line": f"reached --steps {config.steps}"}
    curve = None if heldout is None else curve_record(out, config, heldout, rows, object_step,
                                                      float(trainer.run_state.get("eval_s", 0.0)))
    return {
        "attack": config.mode, "tool": "robustbench3d attack train", "package_version": __version__,
        "victim": victim_info, "training_data": data_identity,
        "config": config.record(),
        "seed": config.seed, "steps": trainer.step, "cars": len(trainer.cars),
        "object_step": object_step, "stopped": stopped, "curve": curve,
        "parametrisation": parametrisation_record(config),
        "lidar_proposals": (_LIDAR_PROPOSALS.get(config.lidar_boxes, PROTOCOL_LABELS.get(config.lidar_boxes))
                            if trainer.frustums else _OWN_OBJECTS) if config.kind.lidar else None,
        "losses": {"weights": config.weights(), "first_step": hist[0] if hist else None,
                   "last_step": hist[-1] if hist else None,
                   "mean_last_10": _mean_losses(hist[-10:])},
        "drop_estimate": trainer.drop_estimate(), "wall_time_s": round(trainer.elapsed_s, 3),
    }


def curve_record(out: Path, config: TrainConfig, heldout: HeldOut, rows: list[dict[str, Any]], object_step: int,
                 eval_s: float) -> dict[str, Any]:
    """The sidecar's ``curve`` of a run with a held-out curve (``rows``: its evaluations; ``eval_s``: seconds spent
    on them), written alike by the white-box and the black-box loops."""
    csv_path, png_path = curve_paths(out)
    return {"eval_every": config.eval_every, "held_out": heldout.describe(), "criterion": CRITERION,
            "best_step": object_step, "best": best_of(rows), "final": rows[-1], "evaluations": len(rows),
            "plateau": {"window": config.plateau_window, "tol": config.plateau_tol},
            "files": {"csv": csv_path.name, "png": png_path.name}, "eval_time_s": round(eval_s, 3)}


def parametrisation_record(config: TrainConfig, **extra: str) -> dict[str, str]:
    """The sidecar's ``parametrisation``: how the mode's shape and colours are parametrised (``extra``: further
    entries, e.g. the black-box loop's ``object``)."""
    return {"shape": "tanh box: v = b tanh(atanh(0.999 v0 / b) + delta)" if config.kind.shape
            else "fixed: the undeformed sphere",
            "colour": "sigmoid(logits)" if config.kind.colour else "fixed: neutral grey 128/255", **extra}


#: The sidecar's words for the LiDAR loss's 2D boxes (as recorded since the first objects; the frustum protocols
#: use robustbench3d.victims.spec.PROTOCOL_LABELS).
_LIDAR_PROPOSALS = {"gt": "ground-truth 2D boxes", "detector": "the victim's 2D detections on the attacked image"}
#: ``lidar_proposals`` of a victim without frustum oracles (:mod:`~robustbench3d.attacks.train`, "Any victim").
_OWN_OBJECTS = "none: the victim finds the cars itself (target_scores of the whole scene)"


def _mean_losses(hist: list[dict[str, float]]) -> dict[str, float] | None:
    if not hist:
        return None
    return {k: float(np.mean([h[k] for h in hist])) for k in hist[0] if k not in COUNTS}


def victim_record(name: str, kwargs: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The victim as a trained object's sidecar records it (``made_by.victim``): its registered name, weights
    sha256 and factory keyword arguments (as strings, sorted)."""
    from robustbench3d.victims import VICTIMS

    return {"name": name, "weights_sha256": VICTIMS.get(name).info.weights_sha256,
            "kwargs": {k: str(v) for k, v in sorted((kwargs or {}).items())}}


@dataclass(frozen=True)
class TrainingSplit:
    """The frames an object is trained on: the dataset, its ground truth and its record (:func:`data_identity`)."""

    dataset: Any
    gt: Any
    identity: dict[str, Any]


def training_split(data: str | Path | None, split: str, max_frames: int | None, **resolve: Any) -> TrainingSplit:
    """Resolve the training data (``resolve``: :func:`robustbench3d.datasets.resolve_dataset`'s other options; with
    ``lazy`` it generates only the first ``max_frames`` frames), load those frames' ground truth and record their
    identity."""
    from robustbench3d.datasets import dataset_identity, load_ground_truth, resolve_dataset

    dataset = resolve_dataset(data, split, max_frames=max_frames, **resolve)
    gt = load_ground_truth(dataset, max_frames)
    return TrainingSplit(dataset, gt, data_identity(dataset_identity(dataset, gt), dataset.root))


def data_identity(identity: dict[str, Any], root: Path) -> dict[str, Any]:
    """The training data's record: a dataset identity (:func:`robustbench3d.datasets.dataset_identity`)
    with the generator manifest replaced by its file's sha256 (if the dataset has one)."""
    from robustbench3d.synth.writer import MANIFEST

    rec = {k: v for k, v in identity.items() if k != "manifest"}
    manifest = Path(root) / MANIFEST
    rec["manifest_sha256"] = hashlib.sha256(manifest.read_bytes()).hexdigest() if manifest.is_file() else None
    return rec
