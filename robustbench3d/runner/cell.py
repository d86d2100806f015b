"""Running one victim x attack x proposals cell: stream frames, attack, detect, write, evaluate.

Frames are read one batch at a time (labels come from the :class:`GroundTruth` read up front).
Each frame is attacked with a generator seeded from (run seed, frame id) only, then handed to the
victim *without* labels in every mode (:func:`~robustbench3d.victims.base.victim_inputs`): for
``proposals="gt"`` the victim gets the ground-truth 2D boxes (and their types) as
:class:`~robustbench3d.victims.base.Proposals` and nothing 3D, so it cannot peek at the answers. For the
frustum protocols of :data:`RECORDED_SOURCES` (``gt-object``: each target car's GT box united with its
object's projected box; ``gt-append``: the GT-box frustum plus that car's object returns) the frame is
attacked with :meth:`~robustbench3d.attacks.base.Attack.apply_recorded` and the harness builds the proposals
from its :class:`~robustbench3d.attacks.record.ObjectRecord`; the record itself never reaches the victim.
Detections are written as KITTI result files into ``data.partial/`` (one file per frame, empty
for no detection), parsed back and evaluated: the metrics are those of the files on disk.
``data.partial/`` becomes ``data/`` once the cell is done.

:func:`detect_frames` (attack, detect, write) is the one loop over frames: :func:`run_cell` runs it over
the whole cell in this process, the frame shards of :mod:`robustbench3d.runner.shards` over their
frames in worker processes.
"""

from __future__ import annotations

import shutil
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from robustbench3d.attacks.base import ATTACK_STREAM, Attack, attack_rng, target_cars  # noqa: F401 (re-exported)
from robustbench3d.attacks.record import ObjectRecord
from robustbench3d.datasets import GroundTruth
from robustbench3d.errors import DataFormatError, RobustBenchError
from robustbench3d.fileio import atomic_write_text
from robustbench3d.kitti.dataset import DeferredImageError, Frame, KittiDataset
from robustbench3d.kitti.labels import RESULT_PRECISION, Labels, parse_labels
from robustbench3d.victims.base import victim_inputs
from robustbench3d.victims.spec import OBJECT_PROPOSAL_SOURCES

# ATTACK_STREAM and attack_rng (the attack generators) belong to the attack contract (attacks.base), shared with
# attack train's held-out curve; imported above for this module and its users (grid, the trade-off study).
PARTIAL = "data.partial"
DATA = "data"
#: Per-shard completion records of a cell computed in frame shards (:mod:`robustbench3d.runner.shards`).
SHARD_MARKS = "shards.partial"
#: The proposal sources whose boxes or frustums the harness builds from each object's placement
#: (:data:`~robustbench3d.victims.spec.OBJECT_PROPOSAL_SOURCES`): their cells attack with
#: ``Attack.apply_recorded`` and pass the records to ``victim_inputs``.
RECORDED_SOURCES: tuple[str, ...] = OBJECT_PROPOSAL_SOURCES


class CellFailure(RobustBenchError):
    """The victim or the attack of a cell failed; the run records an error cell and goes on."""


@dataclass(frozen=True)
class CellInputs:
    """What every cell of a run shares: the dataset, its ground truth and run settings."""

    kitti: KittiDataset
    gt: GroundTruth
    seed: int
    batch_size: int
    classes: tuple[str, ...]
    progress: bool
    #: Bootstrap resamples of the cells' AP intervals (0: none), see :mod:`robustbench3d.runner.effect`.
    bootstrap: int = 0


def _attacked(attack: Attack, name: str, frame: Frame, gt: Labels, seed: int,
              recorded: bool = False) -> tuple[Frame, ObjectRecord | None]:
    """The attacked frame of ``frame`` and, when ``recorded``, the attack's record of its placements (else None).
    Raises :class:`CellFailure` when the attack fails or returns something else."""
    targets = target_cars(gt)
    rng = attack_rng(seed, frame.frame_id)
    record = None
    try:
        if recorded:
            out, record = attack.apply_recorded(frame, targets, rng)
        else:
            out = attack.apply(frame, targets, rng)
    except Exception as exc:
        raise CellFailure(f"attack {name!r} failed on frame {frame.frame_id}: {type(exc).__name__}: {exc}") from exc
    if not isinstance(out, Frame) or out.frame_id != frame.frame_id:
        raise CellFailure(f"attack {name!r} returned {type(out).__name__} for frame {frame.frame_id}; "
                          "expected a Frame with the same frame_id")
    if recorded and (not isinstance(record, ObjectRecord) or len(record) != len(targets)):
        got = f"{len(record)} targets" if isinstance(record, ObjectRecord) else type(record).__name__
        raise CellFailure(f"attack {name!r} recorded {got} for frame {frame.frame_id}; expected an ObjectRecord "
                          f"of its {len(targets)} target cars")
    return out, record


def _detect(victim: Any, name: str, frames: Sequence[Frame], labels: Sequence[Labels], proposals: str,
            attack_name: str, records: Sequence[ObjectRecord | None] | None = None) -> list[Labels]:
    ids = f"{frames[0].frame_id}..{frames[-1].frame_id}"
    if records is None:
        bare, given = victim_inputs(frames, labels, proposals)
    else:
        bare, given = victim_inputs(frames, labels, proposals, objects=list(records))
    try:
        out = victim.detect(bare, given)
    except DeferredImageError as exc:  # an attacked image is rendered when the victim first reads it
        raise CellFailure(f"attack {attack_name!r} failed: {exc}") from exc
    except DataFormatError:
        raise  # a bad input file (e.g. a clean image, decoded when first read): the command exits 2
    except Exception as exc:
        raise CellFailure(f"victim {name!r} failed on frames {ids}: {type(exc).__name__}: {exc}") from exc
    if not isinstance(out, list | tuple) or len(out) != len(frames):
        got = len(out) if isinstance(out, list | tuple) else type(out).__name__
        raise CellFailure(f"victim {name!r} returned {got} results for {len(frames)} frames ({ids})")
    for frame, det in zip(frames, out, strict=True):
        if not isinstance(det, Labels) or not det.has_score:
            raise CellFailure(f"victim {name!r}: result of frame {frame.frame_id} is not a scored Labels")
    return list(out)


def _as_result_file(det: Labels, path: Path, victim_name: str) -> tuple[str, Labels]:
    """Result-file text of a frame's detections and the detections parsed back from it.

    A rejected result is described by detection (row) and field, not by ``path``: its file is
    never written, and the cell's result directory is removed with the error.
    """
    where = f"victim {victim_name!r} returned an invalid result for frame {path.stem}"
    text = ""
    try:
        text = det.to_text(RESULT_PRECISION)
        return text, parse_labels(text, path, scored=True)
    except DataFormatError as exc:
        rows = text.split("\n")
        row = f" {rows[exc.line - 1].strip()!r}" if exc.line is not None and exc.line <= len(rows) else ""
        field = f", field '{exc.field}'" if exc.field is not None else ""
        at = f"detection {exc.line}{row}{field}: " if exc.line is not None else ""
        raise CellFailure(f"{where}: {at}{exc.problem}") from exc
    except (ValueError, TypeError) as exc:
        raise CellFailure(f"{where}: {exc}") from exc


def detect_frames(victim: Any, victim_name: str, attack: Attack, attack_name: str, proposals: str,
                  kitti: KittiDataset, seed: int, batch_size: int, pairs: Sequence[tuple[str, Labels]],
                  out_dir: Path, done: Callable[[int], object] | None = None) -> list[tuple[str, Labels]]:
    """Attack, detect and write ``out_dir/NNNNNN.txt`` (atomically) for every frame of ``pairs``
    (frame id, ground truth), in batches of ``batch_size`` counted from the first pair; return each
    frame's result-file text and the detections parsed back from it. ``attack`` must be prepared. A source of
    :data:`RECORDED_SOURCES` attacks with ``apply_recorded`` (the same frames) and hands the records to
    ``victim_inputs``; the others call ``apply`` and ``victim_inputs`` as they always did.
    Raises :class:`CellFailure` if the victim or the attack fails."""
    found_all: list[tuple[str, Labels]] = []
    recorded = proposals in RECORDED_SOURCES
    for start in range(0, len(pairs), batch_size):
        batch = pairs[start:start + batch_size]
        frames, records = [], []
        for fid, gt in batch:
            clean = kitti.lazy_frame(fid, gt)  # the image is decoded only if the victim or the attack reads it
            frame, record = _attacked(attack, attack_name, clean, gt, seed, recorded)
            frames.append(frame)
            records.append(record)
        labels = [gt for _, gt in batch]
        found = _detect(victim, victim_name, frames, labels, proposals, attack_name, records if recorded else None)
        for frame, det in zip(frames, found, strict=True):
            path = out_dir / f"{frame.frame_id}.txt"
            text, parsed = _as_result_file(det, path, victim_name)
            atomic_write_text(path, text)
            found_all.append((text, parsed))
        if done is not None:
            done(len(batch))
    return found_all


def prepare_attack(attack: Attack, attack_name: str, victim: Any) -> None:
    """``attack.prepare(victim)``; raises :class:`CellFailure` if it fails."""
    try:
        attack.prepare(victim)
    except Exception as exc:
        raise CellFailure(f"attack {attack_name!r} could not be prepared: {type(exc).__name__}: {exc}") from exc


def run_cell(victim: Any, victim_name: str, attack: Attack, attack_name: str, proposals: str,
             inputs: CellInputs, cell_dir: Path) -> dict[str, Any]:
    """Run the cell, write ``cell_dir/data/NNNNNN.txt`` for every frame and return the metrics
    (the evaluator's JSON). Raises :class:`CellFailure` if the victim or the attack fails."""
    from tqdm import tqdm

    partial = cell_dir / PARTIAL
    shutil.rmtree(partial, ignore_errors=True)
    shutil.rmtree(cell_dir / SHARD_MARKS, ignore_errors=True)
    partial.mkdir(parents=True)
    prepare_attack(attack, attack_name, victim)
    pairs = list(zip(inputs.gt.frame_ids, inputs.gt.labels, strict=True))
    bar = tqdm(total=len(pairs), unit="frame", file=sys.stderr, disable=not inputs.progress,
               desc=f"{victim_name}/{attack_name}/{proposals}", dynamic_ncols=True, leave=False)
    try:
        found = detect_frames(victim, victim_name, attack, attack_name, proposals, inputs.kitti, inputs.seed,
                              inputs.batch_size, pairs, partial, bar.update)
    finally:
        bar.close()
    metrics = evaluate_cell(inputs, [parsed for _, parsed in found])
    promote(cell_dir)
    return metrics


def evaluate_cell(inputs: CellInputs, detections: Sequence[Labels]) -> dict[str, Any]:
    """The evaluator's JSON of a cell's detections (one :class:`Labels` per frame of ``inputs.gt``)."""
    from robustbench3d.eval.kitti_eval import evaluate
    from robustbench3d.eval.rules import METRICS

    return evaluate(inputs.gt.labels, list(detections), classes=inputs.classes, metrics=METRICS)


def victim_failure(name: str, exc: Exception) -> CellFailure:
    """The :class:`CellFailure` of a victim that could not be created (with a hint on factory arguments)."""
    from robustbench3d.registry import RegistryError, UnknownNameError

    # a registry error (a plugin that fails to import, a name clash) is not about factory arguments
    hint = (f" (factory arguments are given with --victim-arg {name}:KEY=VALUE)"
            if isinstance(exc, RobustBenchError | TypeError) and not isinstance(exc, RegistryError | UnknownNameError)
            else "")
    failure = CellFailure(f"victim {name!r} could not be created: {type(exc).__name__}: {exc}{hint}")
    failure.__cause__ = exc
    return failure


def promote(cell_dir: Path) -> None:
    """Replace ``data/`` by the finished ``data.partial/``."""
    final, old = cell_dir / DATA, cell_dir / "data.old"
    shutil.rmtree(old, ignore_errors=True)
    if final.exists():
        final.rename(old)
    (cell_dir / PARTIAL).rename(final)
    shutil.rmtree(old, ignore_errors=True)


def remove_results(cell_dir: Path) -> None:
    """Delete a cell's result files (finished or partial), e.g. before recording a skip or an error."""
    for sub in (DATA, PARTIAL, "data.old", SHARD_MARKS):
        shutil.rmtree(cell_dir / sub, ignore_errors=True)


def results_complete(cell_dir: Path, frame_ids: Sequence[str]) -> bool:
    """True if ``data/`` holds exactly one result file per frame."""
    data = cell_dir / DATA
    if not data.is_dir():
        return False
    return sorted(p.name for p in data.iterdir()) == sorted(f"{fid}.txt" for fid in frame_ids)
