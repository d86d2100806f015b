"""The run's printed table: one row per cell, Car BEV and 3D AP (R40 and R11) per difficulty."""

from __future__ import annotations

import contextlib
from collections.abc import Sequence
from typing import Any

from robustbench3d.eval.rules import DIFFICULTIES
from robustbench3d.results import CellResult
from robustbench3d.texttable import format_table

#: (metric, recall sampling) column groups of the table.
COLUMNS: tuple[tuple[str, str], ...] = (("bev", "R40"), ("bev", "R11"), ("3d", "R40"), ("3d", "R11"))
_LABEL = {"bev": "BEV", "3d": "3D"}


def _value(cell: CellResult, cls: str, metric: str, recall: str, difficulty: str) -> str:
    """AP, followed for an attacked cell by its change against the clean cell, e.g. ``71.20(-8.15)``."""
    text = f"{cell.ap(cls, metric, recall, difficulty):6.2f}"
    if cell.effect is not None:
        with contextlib.suppress(LookupError):
            text += f"({-cell.drop(cls, metric, recall, difficulty):+.2f})"
    return text


def _group(cell: CellResult, cls: str, metric: str, recall: str) -> str:
    result = cell.result
    if result is None or metric not in result.metrics(cls):
        return "-"
    return " ".join(_value(cell, cls, metric, recall, d) for d in DIFFICULTIES)


def _asr(cell: CellResult) -> str:
    rate = cell.attack_success_rate
    return "-" if rate is None else f"{100 * rate:.1f}"


def summary_table(cells: Sequence[dict[str, Any]], cls: str = "Car") -> str:
    """Plain-text table of summary cells, then one line per skipped or failed cell."""
    results = [CellResult(c) for c in cells]
    iou = next((r.result.iou(cls, "bev") for r in results
                if r.result is not None and "bev" in r.result.metrics(cls)), 0.7)
    attacked = any(r.effect is not None for r in results)
    head = ["victim", "attack", "proposals", "status"] + [f"{_LABEL[m]} {r} (E M H)" for m, r in COLUMNS]
    rows = [[r.victim, r.attack, r.proposals, r.status] + [_group(r, cls, m, rec) for m, rec in COLUMNS]
            + ([_asr(r)] if attacked else []) for r in results]
    frames = next((r.frames for r in results), 0)
    title = f"{cls} AP in % at IoU {iou:.2f}, easy / moderate / hard, {frames} frames"
    if attacked:
        head.append("ASR %")
        title += ("; attacked cells: (AP change against the clean cell 'none'), ASR = Cars matched clean "
                  "and missed attacked (moderate, BEV IoU 0.7)")
    lines = [title, format_table(head, rows)]
    lines += [f"{r.status}: {r.victim} / {r.attack} / {r.proposals}: {r.reason}" for r in results if r.status != "ok"]
    return "\n".join(lines)
