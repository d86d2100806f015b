"""Reading a GT label directory and a result directory into :class:`ObjectTable` s, fast.

Frame set: the ids of the split file if one is given, else every ``*.txt`` in the GT directory
(sorted). Every frame of the set must have a GT label file. A frame without a result file has no
detections. Result files of frames outside the set are ignored and counted (the caller reports
them). A result directory laid out like the devkit's (``<dir>/data/*.txt``) is accepted too.

Parsing takes a vectorised fast path; whenever anything in it looks wrong (column count,
unknown type, non-number, non-finite value, non-integer occlusion, a ground-truth value no
object has...) every file is re-read with :func:`robustbench3d.kitti.read_labels`, which raises
the precise ``file:line: field`` error, so both paths accept exactly the same files.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from robustbench3d.errors import DataFormatError
from robustbench3d.eval.table import TYPE_CODE, ObjectTable
from robustbench3d.kitti.labels import Labels, impossible_rows, read_labels
from robustbench3d.kitti.splits import read_split


@dataclass(frozen=True)
class LoadedDirs:
    """Ground truth and detections of one frame set, plus bookkeeping for the report."""

    frame_ids: list[str]
    gt: ObjectTable
    dt: ObjectTable
    pred_dir: Path
    frames_without_results: int
    ignored_result_files: list[str]


def _txt_stems(directory: Path) -> set[str]:
    with os.scandir(directory) as it:
        return {e.name[:-4] for e in it if e.name.endswith(".txt") and e.is_file()}


def _require_dir(path: Path, what: str) -> None:
    if not path.exists():
        raise DataFormatError(path, f"{what} directory not found")
    if not path.is_dir():
        raise DataFormatError(path, f"{what} path is not a directory")


def frame_ids(gt_dir: Path, split: Path | None = None) -> list[str]:
    """Frame ids to evaluate: the split's (checked against ``gt_dir``) or all GT label files."""
    _require_dir(gt_dir, "ground-truth label")
    available = _txt_stems(gt_dir)
    if split is None:
        if not available:
            raise DataFormatError(gt_dir, "no label files (*.txt) in the ground-truth directory")
        return sorted(available)
    if not split.is_file():
        raise DataFormatError(split, "split file not found")
    ids = read_split(split)
    if not ids:
        raise DataFormatError(split, "split file lists no frames")
    for i in ids:
        if i not in available:
            raise DataFormatError(gt_dir / f"{i}.txt", f"ground-truth label file not found (frame listed in {split})")
    return ids


def _slow_table(paths: list[Path | None], scored: bool) -> ObjectTable:
    """The data layer's strict reader, file by file (raises the precise error on bad input)."""
    per_frame = [Labels.empty(with_score=scored) if p is None else read_labels(p, scored=scored) for p in paths]
    return ObjectTable.from_labels(per_frame, scored)


def read_table(paths: list[Path | None], scored: bool) -> ObjectTable:
    """Objects of one file per frame (None: a frame with no objects) as an :class:`ObjectTable`.

    Args:
        paths: per frame, the label/result file or None.
        scored: True for 16-column results, False for 15-column ground truth.
    """
    ncol = 16 if scored else 15
    types: list[str] = []
    numbers: list[str] = []
    rows_per_frame = np.zeros(len(paths), dtype=np.int64)
    for fi, path in enumerate(paths):
        if path is None:
            continue
        try:
            with open(os.fspath(path), "rb") as f:
                text = f.read().decode("utf-8")
        except (UnicodeDecodeError, OSError):
            return _slow_table(paths, scored)
        toks = text.split()
        lines = text.split("\n")
        n = len(lines) - lines.count("")
        # Whitespace-only lines, or a line with a wrong column count, send everything to the slow path.
        if len(toks) != n * ncol:
            return _slow_table(paths, scored)
        types.extend(toks[0::ncol])
        del toks[0::ncol]
        numbers.extend(toks)
        rows_per_frame[fi] = n
    codes = np.array([TYPE_CODE.get(t, -1) for t in types], dtype=np.int64)
    try:  # float() is the data layer's own number parser
        numeric = np.fromiter(map(float, numbers), dtype=np.float64, count=len(numbers)).reshape(-1, ncol - 1)
    except ValueError:
        return _slow_table(paths, scored)
    occ = numeric[:, 1]
    if ((codes < 0).any() or not np.isfinite(numeric).all()
            or (occ != np.trunc(occ)).any() or (occ < -1).any() or (occ > 3).any()
            or (not scored and impossible_rows(numeric).any())):
        return _slow_table(paths, scored)
    frame = np.repeat(np.arange(len(paths), dtype=np.int64), rows_per_frame)
    return ObjectTable.from_columns(frame, codes, numeric, len(paths), scored)


def load_dirs(gt_dir: str | Path, pred_dir: str | Path, split: str | Path | None = None) -> LoadedDirs:
    """Read the frame set's GT labels and results (see the module doc for the rules)."""
    gt_dir, pred_dir = Path(gt_dir), Path(pred_dir)
    ids = frame_ids(gt_dir, None if split is None else Path(split))
    _require_dir(pred_dir, "result")
    results = _txt_stems(pred_dir)
    if not results and (pred_dir / "data").is_dir():
        pred_dir = pred_dir / "data"
        results = _txt_stems(pred_dir)
    gt = read_table([gt_dir / f"{i}.txt" for i in ids], scored=False)
    dt_paths: list[Path | None] = [pred_dir / f"{i}.txt" if i in results else None for i in ids]
    dt = read_table(dt_paths, scored=True)
    wanted = set(ids)
    return LoadedDirs(
        frame_ids=ids, gt=gt, dt=dt, pred_dir=pred_dir,
        frames_without_results=sum(p is None for p in dt_paths),
        ignored_result_files=sorted(results - wanted),
    )
