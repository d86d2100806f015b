"""The run's printed table: one row per cell, Car BEV and 3D AP (R40 and R11) per difficulty."""

from __future__ import annotations

import contextlib
from collections.abc import Sequence
from typing import Any

from robustbench3d.eval.rules import DIFFICULTIES
from robustbench3d.results import CellResult
from robustbench3d.seed_table import interval, with_interval
from robustbench3d.texttable import format_table

#: (metric, recall sampling) column groups of the table.
COLUMNS: tuple[tuple[str, str], ...] = (("bev", "R40"), ("bev", "R11"), ("3d", "R40"), ("3d", "R11"))
_LABEL = {"bev": "BEV", "3d": "3D"}


def _value(cell: CellResult, cls: str, metric: str, recall: str, difficulty: str) -> str:
    """AP, followed for an attacked cell by its change against the clean cell, e.g. ``71.20(-8.15)``; each
    with its bootstrap interval where the cell has one, e.g. ``71.20 [69.8, 72.6](-8.15 [-9.9, -6.4])``."""
    text = with_interval(f"{cell.ap(cls, metric, recall, difficulty):6.2f}",
                         interval(cell, cls, metric, recall, difficulty))
    if cell.effect is not None:
        with contextlib.suppress(LookupError):
            drop_ci = interval(cell, cls, metric, recall, difficulty, drop=True)
            change = None if drop_ci is None else [-drop_ci[1], -drop_ci[0]]
            text += f"({with_interval(f'{-cell.drop(cls, metric, recall, difficulty):+.2f}', change)})"
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
    ci_meta = next((r.cell["metrics_ci"]["meta"] for r in results if "metrics_ci" in r.cell), None)
    if ci_meta is not None:
        title += (f"; [lo, hi] = {100 * ci_meta['level']:.0f} % bootstrap interval over frames "
                  f"({ci_meta['resamples']} resamples; AP changes: paired, the same frames for both cells)")
    lines = [title, format_table(head, rows)]
    lines += [f"{r.status}: {r.victim} / {r.attack} / {r.proposals}: {r.reason}" for r in results if r.status != "ok"]
    return "\n".join(lines)
