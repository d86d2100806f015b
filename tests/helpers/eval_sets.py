"""The synthetic evaluation sets (``tests/fixtures/eval/generate.py``) as :class:`Labels`, frame by frame."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from eval_fixture_generator import load_generator

from robustbench3d.kitti import Labels
from robustbench3d.kitti.labels import parse_labels


def set_labels(spec: Any) -> tuple[list[Labels], list[Labels]]:
    """The ground truth and detections of the generated set ``spec`` (a generator ``SetSpec``), one
    :class:`Labels` a frame (a frame without a result file: no detections)."""
    ids, gt, dt = load_generator().make_set(spec)
    gts = [parse_labels("\n".join(gt[i]), Path(f"{i}.txt"), scored=False) for i in ids]
    dts = [parse_labels("\n".join(dt[i]), Path(f"{i}.txt"), scored=True) if i in dt else Labels.empty(True)
           for i in ids]
    return gts, dts
