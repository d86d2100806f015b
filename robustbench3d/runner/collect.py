"""Finished cells of earlier runs in the same output directory, for the summary.

``summary.json`` and ``results.csv`` cover every finished cell under ``OUT/cells`` that is
comparable with the current run: the same dataset identity (root, split, frames, labels sha256,
generator), the same evaluation (evaluator version, classes, metrics, result precision) and the
same run seed. Other cells stay on disk but are left out, each with its reason. An ``ok`` cell
counts only with all its result files.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from robustbench3d.errors import DataFormatError
from robustbench3d.results import CellResult, read_json, validate_summary
from robustbench3d.runner.cell import results_complete

#: Dataset identity keys too long to print in a reason.
_LONG = ("sha256", "manifest")


@dataclass
class EarlierCells:
    """Cells of earlier runs: those the summary includes and ``"<dir>: <reason>"`` for the rest."""

    included: list[dict[str, Any]] = field(default_factory=list)
    left_out: list[str] = field(default_factory=list)


def incompatibility(cell: dict[str, Any], identity: dict[str, Any], evaluation: dict[str, Any],
                    seed: int) -> str | None:
    """Why ``cell`` cannot share a summary with the current run, or None if it can."""
    result = CellResult(cell)
    theirs = result.dataset
    differing = sorted(k for k in set(theirs) | set(identity) if theirs.get(k) != identity.get(k))
    if differing:
        parts = [f"{k} differs" if k in _LONG else f"{k} {theirs.get(k)!r} (this run: {identity.get(k)!r})"
                 for k in differing]
        return "another dataset: " + "; ".join(parts)
    if result.config.get("evaluation") != evaluation:
        return "evaluated with other settings (evaluator, classes, metrics or result precision)"
    if result.seed != seed:
        return f"seed {result.seed} (this run: {seed})"
    return None


def earlier_cells(cells_dir: Path, exclude: Collection[str], identity: dict[str, Any], evaluation: dict[str, Any],
                  seed: int, frame_ids: Sequence[str], cell_file: str = "cell.json") -> EarlierCells:
    """Every cell directory under ``cells_dir`` not named in ``exclude`` (the current grid), in
    directory-name order, sorted into included and left out (see the module docstring)."""
    out = EarlierCells()
    if not cells_dir.is_dir():
        return out
    for cell_dir in sorted(p for p in cells_dir.iterdir() if p.is_dir() and p.name not in exclude):
        path = cell_dir / cell_file
        if not path.is_file():
            out.left_out.append(f"{cell_dir.name}: unfinished (no {cell_file})")
            continue
        try:
            cell = read_json(path)
            validate_summary(cell, path, cell_only=True)
        except DataFormatError as exc:
            out.left_out.append(f"{cell_dir.name}: unreadable ({exc})")
            continue
        reason = incompatibility(cell, identity, evaluation, seed)
        if reason is None and CellResult(cell).ok and not results_complete(cell_dir, frame_ids):
            reason = f"result files in {cell_dir / 'data'} are incomplete"
        if reason is None:
            out.included.append(cell)
        else:
            out.left_out.append(f"{cell_dir.name}: {reason}")
    return out


__all__ = ["EarlierCells", "earlier_cells", "incompatibility"]
