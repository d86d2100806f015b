"""What an attack did to a victim: AP drop against the clean cell and the attack success rate.

An attacked cell (attack other than ``none``) is compared with the **clean cell** of the same victim,
proposal source and dataset: the ``none`` cell, which the runner adds to any run that has attacked
cells (:func:`with_clean_cells`). The comparison (the cell's ``attack_effect``, recomputed whenever
the summary is written, so it always refers to the clean cell on disk) holds:

* ``clean``: the clean cell's AP, per class, metric, recall sampling and difficulty (percent);
* ``drop``: clean AP - attacked AP (percentage points; negative when the attack helps);
* ``relative_drop``: drop / clean AP (a fraction; null where the clean AP is 0);
* ``success``: the attack success rate (ASR): of the Cars matched in the clean cell, the share not
  matched in the attacked cell. "Matched" is the evaluator's own greedy matching
  (:mod:`robustbench3d.eval.matches`): Car, BEV IoU > 0.7, moderate difficulty, at the score threshold
  that maximises F1 on the clean cell; the same threshold applies to the attacked cell. Null when the
  clean cell matches no Car.

Both cells' numbers come from their result files on disk (``cells/<cell>/data/*.txt``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from robustbench3d.kitti.labels import Labels, read_labels
from robustbench3d.results import APResult
from robustbench3d.runner.config import CellKey, RunConfig

CLEAN_ATTACK = "none"
#: The success-rate criterion: class, metric, difficulty (the IoU is the evaluator's for the metric).
SUCCESS_CLASS, SUCCESS_METRIC, SUCCESS_DIFFICULTY = "Car", "bev", "moderate"


def with_clean_cells(config: RunConfig) -> RunConfig:
    """``config`` with the clean control ``none`` first among the attacks when it has attacked cells
    but no clean one (unchanged otherwise)."""
    if CLEAN_ATTACK in config.attacks or not config.attacks:
        return config
    return dataclasses.replace(config, attacks=(CLEAN_ATTACK, *config.attacks))


def clean_key(key: CellKey) -> CellKey:
    """The clean cell compared with ``key``."""
    return CellKey(key.victim, CLEAN_ATTACK, key.proposals)


def read_results(data_dir: Path, frame_ids: Sequence[str]) -> list[Labels]:
    """A cell's detections, one :class:`Labels` per frame (its result files)."""
    return [read_labels(data_dir / f"{fid}.txt", scored=True) for fid in frame_ids]


def _tables(clean: APResult, attacked: APResult) -> tuple[dict, dict, dict]:
    """Clean AP, drop and relative drop for every value both evaluations have."""
    out: tuple[dict, dict, dict] = ({}, {}, {})
    for v in clean.values():
        if v.cls not in attacked.classes or v.metric not in attacked.metrics(v.cls):
            continue
        drop = v.ap - attacked.ap(v.cls, v.metric, v.recall, v.difficulty)
        for table, value in zip(out, (v.ap, drop, drop / v.ap if v.ap > 0 else None), strict=True):
            table.setdefault(v.cls, {}).setdefault(v.metric, {}).setdefault(v.recall, {})[v.difficulty] = value
    return out


def success_rate(gt: Sequence[Labels], clean: Sequence[Labels], attacked: Sequence[Labels],
                 iou: float) -> dict[str, Any]:
    """The ``success`` record of the module doc from the frames' GT and both cells' detections."""
    from robustbench3d.eval.matches import best_f1_threshold, matched_ground_truth

    crit = {"cls": SUCCESS_CLASS, "metric": SUCCESS_METRIC, "difficulty": SUCCESS_DIFFICULTY}
    threshold = best_f1_threshold(gt, clean, **crit)
    before = matched_ground_truth(gt, clean, threshold, **crit).matched
    after = matched_ground_truth(gt, attacked, threshold, **crit).matched
    n_clean = int(sum(int(b.sum()) for b in before))
    missed = int(sum(int((b & ~a).sum()) for b, a in zip(before, after, strict=True)))
    return {"class": SUCCESS_CLASS, "metric": SUCCESS_METRIC, "iou": iou, "difficulty": SUCCESS_DIFFICULTY,
            "score_threshold": threshold, "clean_matched": n_clean, "attacked_missed": missed,
            "rate": missed / n_clean if n_clean else None}


def attack_effect(clean_cell: dict[str, Any], attacked_cell: dict[str, Any], clean_dir: Path, attacked_dir: Path,
                  gt: Sequence[Labels], frame_ids: Sequence[str]) -> dict[str, Any]:
    """The ``attack_effect`` record of an ``ok`` attacked cell against its ``ok`` clean cell."""
    clean_ap, attacked_ap = APResult(clean_cell["metrics"]), APResult(attacked_cell["metrics"])
    clean, drop, relative = _tables(clean_ap, attacked_ap)
    iou = (clean_ap.iou(SUCCESS_CLASS, SUCCESS_METRIC)
           if SUCCESS_CLASS in clean_ap.classes and SUCCESS_METRIC in clean_ap.metrics(SUCCESS_CLASS) else 0.7)
    success = success_rate(gt, read_results(clean_dir / "data", frame_ids),
                           read_results(attacked_dir / "data", frame_ids), iou)
    return {"clean_cell": clean_dir.name, "clean_fingerprint": clean_cell["provenance"]["fingerprint"],
            "clean": clean, "drop": drop, "relative_drop": relative, "success": success}


def attach_effects(cells: list[dict[str, Any]], cells_dir: Path, gt: Sequence[Labels],
                   frame_ids: Sequence[str]) -> list[int]:
    """Set ``attack_effect`` on every attacked cell of ``cells`` (in place): the record for an ``ok`` one whose
    clean cell is among ``cells`` and ``ok``, else null (clean cells are left as they are). Returns the
    indices of changed cells."""
    clean = {(c["victim"], c["proposals"]): c for c in cells
             if c["attack"] == CLEAN_ATTACK and c["status"] == "ok"}
    changed = []
    for i, cell in enumerate(cells):
        if cell["attack"] == CLEAN_ATTACK:  # the clean cells themselves carry no comparison (no key)
            continue
        key = CellKey(cell["victim"], cell["attack"], cell["proposals"])
        base = clean.get((key.victim, key.proposals))
        effect = None
        if cell["status"] == "ok" and base is not None:
            effect = attack_effect(base, cell, cells_dir / clean_key(key).dirname, cells_dir / key.dirname, gt,
                                   frame_ids)
        if cell.get("attack_effect", None) != effect or "attack_effect" not in cell:
            cell["attack_effect"] = effect
            changed.append(i)
    return changed


__all__ = ["CLEAN_ATTACK", "attach_effects", "attack_effect", "clean_key", "read_results", "success_rate",
           "with_clean_cells"]
