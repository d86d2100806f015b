"""Human-readable AP table and JSON output of an evaluation result."""

from __future__ import annotations

import json
from pathlib import Path

from robustbench3d.eval.rules import DIFFICULTIES, RECALL_SAMPLES
from robustbench3d.texttable import format_table

_METRIC_LABEL = {"2d": "2D AP", "aos": "AOS", "bev": "BEV AP", "3d": "3D AP"}


def row_label(cls: str, metric: str, threshold: float, recall: str) -> str:
    """E.g. ``"Car BEV AP@0.70 R40"``."""
    return f"{cls} {_METRIC_LABEL[metric]}@{threshold:.2f} {recall}"


def ap_table(result: dict) -> str:
    """Metric x difficulty table (AP in percent), R40 and R11 rows labelled, then notes."""
    meta = result["meta"]
    rows = []
    for cls in meta["classes"]:
        for metric, by_recall in result.get(cls, {}).items():
            thr = meta["min_overlap"][cls][metric]
            for recall in RECALL_SAMPLES:
                aps = by_recall[recall]
                rows.append([row_label(cls, metric, thr, recall), *(f"{aps[d]:.2f}" for d in DIFFICULTIES)])
    head = f"KITTI AP in % ({meta['evaluator']} {meta['version']}, devkit semantics), {meta['frames']} frames"
    lines = [head, format_table(["", *DIFFICULTIES], rows, align="l" + "r" * len(DIFFICULTIES), rule=False)]
    for s in meta.get("skipped", []):
        lines.append(f"skipped: {s['class']} {s['metric']}: {s['reason']}")
    lines += [f"note: {n}" for n in meta.get("notes", [])]
    return "\n".join(lines)


def write_json(path: str | Path, result: dict) -> None:
    """Write the result as indented JSON, atomically."""
    from robustbench3d.fileio import atomic_write_text

    atomic_write_text(path, json.dumps(result, indent=2) + "\n")
