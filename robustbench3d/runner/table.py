"""The run's printed table: one row per cell, Car BEV and 3D AP (R40 and R11) per difficulty."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

#: (metric, recall sampling) column groups of the table.
COLUMNS: tuple[tuple[str, str], ...] = (("bev", "R40"), ("bev", "R11"), ("3d", "R40"), ("3d", "R11"))
_LABEL = {"bev": "BEV", "3d": "3D"}
_DIFFS = ("easy", "moderate", "hard")


def _group(metrics: dict[str, Any] | None, cls: str, metric: str, recall: str) -> str:
    if metrics is None or metric not in metrics.get(cls, {}):
        return "-"
    aps = metrics[cls][metric][recall]
    return " ".join(f"{aps[d]:6.2f}" for d in _DIFFS)


def format_table(cells: Sequence[dict[str, Any]], cls: str = "Car") -> str:
    """Plain-text table of summary cells, then one line per skipped or failed cell."""
    iou = next((c["metrics"]["meta"]["min_overlap"][cls]["bev"] for c in cells
                if c["status"] == "ok" and cls in c["metrics"]["meta"]["min_overlap"]), 0.7)
    head = ["victim", "attack", "proposals", "status"] + [f"{_LABEL[m]} {r} (E M H)" for m, r in COLUMNS]
    rows = [[c["victim"], c["attack"], c["proposals"], c["status"]]
            + [_group(c["metrics"], cls, m, r) for m, r in COLUMNS] for c in cells]
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(head)]

    def line(values: Sequence[str]) -> str:
        return "  ".join(v.ljust(w) for v, w in zip(values, widths, strict=True)).rstrip()

    frames = next((c["dataset"]["frames"] for c in cells), 0)
    lines = [f"{cls} AP in % at IoU {iou:.2f}, easy / moderate / hard, {frames} frames",
             line(head), line(["-" * w for w in widths]), *(line(r) for r in rows)]
    for c in cells:
        if c["status"] != "ok":
            lines.append(f"{c['status']}: {c['victim']} / {c['attack']} / {c['proposals']}: {c['reason']}")
    return "\n".join(lines)
