"""The run's printed table: one row per cell, Car BEV and 3D AP (R40 and R11) per difficulty."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from robustbench3d.eval.rules import DIFFICULTIES
from robustbench3d.results import CellResult
from robustbench3d.texttable import format_table

#: (metric, recall sampling) column groups of the table.
COLUMNS: tuple[tuple[str, str], ...] = (("bev", "R40"), ("bev", "R11"), ("3d", "R40"), ("3d", "R11"))
_LABEL = {"bev": "BEV", "3d": "3D"}


def _group(cell: CellResult, cls: str, metric: str, recall: str) -> str:
    result = cell.result
    if result is None or metric not in result.metrics(cls):
        return "-"
    return " ".join(f"{result.ap(cls, metric, recall, d):6.2f}" for d in DIFFICULTIES)


def summary_table(cells: Sequence[dict[str, Any]], cls: str = "Car") -> str:
    """Plain-text table of summary cells, then one line per skipped or failed cell."""
    results = [CellResult(c) for c in cells]
    iou = next((r.result.iou(cls, "bev") for r in results
                if r.result is not None and "bev" in r.result.metrics(cls)), 0.7)
    head = ["victim", "attack", "proposals", "status"] + [f"{_LABEL[m]} {r} (E M H)" for m, r in COLUMNS]
    rows = [[r.victim, r.attack, r.proposals, r.status] + [_group(r, cls, m, rec) for m, rec in COLUMNS]
            for r in results]
    frames = next((r.frames for r in results), 0)
    lines = [f"{cls} AP in % at IoU {iou:.2f}, easy / moderate / hard, {frames} frames", format_table(head, rows)]
    lines += [f"{r.status}: {r.victim} / {r.attack} / {r.proposals}: {r.reason}" for r in results if r.status != "ok"]
    return "\n".join(lines)
