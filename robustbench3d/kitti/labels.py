"""KITTI object labels and detection results (``label_2/*.txt``, result ``data/*.txt``).

One object per line, space separated: type, truncated, occluded, alpha, bbox (left, top, right,
bottom; image-2 pixels), dimensions (height, width, length; m), location (x, y, z of the box's
bottom centre in the rectified camera-0 frame; m), rotation_y (rad, about rect y), and in result
files a 16th column, score. Blank lines and trailing white space are tolerated; anything else
that deviates raises :class:`~robustbench3d.errors.DataFormatError` naming file, line and field.

Ground-truth rows (15 columns) must also describe a possible object (:func:`impossible_rows`):
truncated in 0..1 (or -1, unknown), bbox right >= left and bottom >= top, and dimensions >= 0,
or exactly -1 -1 -1, KITTI's "no 3D box" placeholder (DontCare rows). Result rows (16 columns)
are a detector's output and are not held to this: a bad prediction is scored, not refused.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from robustbench3d.errors import DataFormatError
from robustbench3d.fileio import atomic_write_text, read_data_text

KITTI_TYPES: tuple[str, ...] = (
    "Car", "Van", "Truck", "Pedestrian", "Person_sitting", "Cyclist", "Tram", "Misc", "DontCare",
)
FIELDS: tuple[str, ...] = (
    "type", "truncated", "occluded", "alpha", "bbox_left", "bbox_top", "bbox_right", "bbox_bottom",
    "height", "width", "length", "x", "y", "z", "rotation_y", "score",
)
#: Decimals of the geometry columns of written result files (the KITTI devkit's ``%.2f``); scores
#: are written exactly. Results are evaluated on the parsed files, so in-memory and file scores agree.
RESULT_PRECISION = 2


def type_mask(types: np.ndarray | Iterable[str], wanted: Iterable[str]) -> np.ndarray:
    """(N,) bool: which of N KITTI type names (e.g. :attr:`Labels.type`) are one of ``wanted``."""
    return np.isin(np.asarray(types, dtype=str), np.asarray(list(wanted), dtype=str))


@dataclass(frozen=True, eq=False)
class Labels:
    """A frame's objects, column-wise (N objects).

    Attributes:
        type: (N,) str, one of :data:`KITTI_TYPES`.
        truncated: (N,) float64, fraction of the object outside the image (-1 when unknown).
        occluded: (N,) int64, 0 visible, 1 partly, 2 largely occluded, 3 unknown (-1 in results).
        alpha: (N,) float64, observation angle in rad, [-pi, pi].
        bbox: (N, 4) float64, left, top, right, bottom in image-2 pixels.
        dimensions: (N, 3) float64, height, width, length in m.
        location: (N, 3) float64, bottom centre in the rectified camera frame, m.
        rotation_y: (N,) float64, yaw about rect y in rad; 0 faces rect +x.
        score: (N,) float64 detection confidence, or None for ground truth.
    """

    type: np.ndarray
    truncated: np.ndarray
    occluded: np.ndarray
    alpha: np.ndarray
    bbox: np.ndarray
    dimensions: np.ndarray
    location: np.ndarray
    rotation_y: np.ndarray
    score: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = len(self.type)
        shapes = {
            "truncated": (n,), "occluded": (n,), "alpha": (n,), "bbox": (n, 4),
            "dimensions": (n, 3), "location": (n, 3), "rotation_y": (n,),
        }
        if self.score is not None:
            shapes["score"] = (n,)
        for name, shape in shapes.items():
            if getattr(self, name).shape != shape:
                raise ValueError(f"Labels.{name} has shape {getattr(self, name).shape}, expected {shape}")

    def __len__(self) -> int:
        return len(self.type)

    @property
    def has_score(self) -> bool:
        return self.score is not None

    @classmethod
    def empty(cls, with_score: bool = False) -> Labels:
        return cls(
            type=np.empty(0, dtype=object), truncated=np.empty(0), occluded=np.empty(0, dtype=np.int64),
            alpha=np.empty(0), bbox=np.empty((0, 4)), dimensions=np.empty((0, 3)),
            location=np.empty((0, 3)), rotation_y=np.empty(0), score=np.empty(0) if with_score else None,
        )

    def select(self, index: np.ndarray | slice) -> Labels:
        """Objects picked by a boolean mask, an index array or a slice."""
        return Labels(
            type=self.type[index], truncated=self.truncated[index], occluded=self.occluded[index],
            alpha=self.alpha[index], bbox=self.bbox[index], dimensions=self.dimensions[index],
            location=self.location[index], rotation_y=self.rotation_y[index],
            score=None if self.score is None else self.score[index],
        )

    def of_types(self, types: Iterable[str]) -> Labels:
        """The objects whose type is one of ``types``, in order (:func:`type_mask`)."""
        return self.select(type_mask(self.type, types))

    @classmethod
    def concatenate(cls, parts: list[Labels]) -> Labels:
        if not parts:
            return cls.empty()
        scored = {p.has_score for p in parts}
        if len(scored) != 1:
            raise ValueError("cannot concatenate scored and unscored Labels")

        def cat(name: str) -> np.ndarray:
            return np.concatenate([getattr(p, name) for p in parts])

        return cls(
            type=cat("type"), truncated=cat("truncated"), occluded=cat("occluded"), alpha=cat("alpha"),
            bbox=cat("bbox"), dimensions=cat("dimensions"), location=cat("location"),
            rotation_y=cat("rotation_y"), score=cat("score") if parts[0].has_score else None,
        )

    def to_text(self, precision: int = RESULT_PRECISION) -> str:
        """Label-file text, one line per object, the KITTI devkit's ``%.2f`` style by default.

        Scores (result files) are written exactly (shortest round-trip repr), so ranking and ties survive.
        """
        lines = []
        p = precision
        for i in range(len(self)):
            line = f"{self.type[i]} {self.truncated[i]:.{p}f} {int(self.occluded[i])} {self.alpha[i]:.{p}f}"
            nums = (*self.bbox[i], *self.dimensions[i], *self.location[i], self.rotation_y[i])
            line += " " + " ".join(f"{v:.{p}f}" for v in nums)
            if self.score is not None:
                line += f" {float(self.score[i])!r}"
            lines.append(line)
        return "".join(line + "\n" for line in lines)


def _parse_float(token: str, path: Path, lineno: int, field: str) -> float:
    try:
        value = float(token)
    except ValueError:
        raise DataFormatError(path, f"expected a number, got {token!r}", lineno, field) from None
    if not math.isfinite(value):
        raise DataFormatError(path, f"expected a finite number, got {token!r}", lineno, field)
    return value


def _value_checks(numeric: np.ndarray) -> list[tuple[str, np.ndarray, str]]:
    """(field, (N,) True where a row breaks the rule, rule) of the ground-truth value rules over
    the numeric columns (truncated first, as in :func:`parse_labels`)."""
    t, bbox, dims = numeric[:, 0], numeric[:, 3:7], numeric[:, 7:10]
    placeholder = (dims == -1).all(axis=1)
    return [
        ("truncated", ~(((t >= 0) & (t <= 1)) | (t == -1)), "expected a fraction in 0..1 (or -1 for unknown)"),
        ("bbox", (bbox[:, 2] < bbox[:, 0]) | (bbox[:, 3] < bbox[:, 1]),
         "expected left <= right and top <= bottom"),
        ("dimensions", (dims < 0).any(axis=1) & ~placeholder,
         "height, width, length must be >= 0 (or -1 -1 -1 for no 3D box)"),
    ]


def impossible_rows(numeric: np.ndarray) -> np.ndarray:
    """(N,) True where a ground-truth row's numeric columns (as parsed, type excluded) describe
    no possible object (the rules of the module doc)."""
    bad = np.zeros(len(numeric), dtype=bool)
    for _, mask, _ in _value_checks(numeric):
        bad |= mask
    return bad


def _check_values(numeric: np.ndarray, rows: list[list[str]], linenos: list[int], path: Path) -> None:
    """Raise for the first ground-truth row (then first field) that breaks a value rule."""
    first = None
    for field, mask, rule in _value_checks(numeric):
        hit = np.flatnonzero(mask)
        if len(hit) and (first is None or hit[0] < first[0]):
            first = (int(hit[0]), field, rule)
    if first is None:
        return
    r, field, rule = first
    cols = {"truncated": slice(1, 2), "bbox": slice(4, 8), "dimensions": slice(8, 11)}[field]
    raise DataFormatError(path, f"{rule}, got {' '.join(rows[r][cols])}", linenos[r], field)


def parse_labels(text: str, path: str | Path = "<string>", scored: bool | None = None) -> Labels:
    """Parse label text.

    Args:
        text: file contents.
        path: file name used in error messages.
        scored: True requires 16 columns (results), False requires 15 (ground truth), None
            accepts either but the whole file must agree.
    """
    path = Path(path)
    rows: list[list[str]] = []
    linenos: list[int] = []
    for lineno, raw in enumerate(text.split("\n"), start=1):
        line = raw.strip()
        if not line:
            continue
        rows.append(line.split())
        linenos.append(lineno)
    expected = None if scored is None else (16 if scored else 15)
    for toks, lineno in zip(rows, linenos, strict=True):
        if expected is None:
            if len(toks) not in (15, 16):
                raise DataFormatError(path, f"expected 15 or 16 columns, got {len(toks)}", lineno)
            expected = len(toks)
        elif len(toks) != expected:
            why = "" if scored is not None or lineno == linenos[0] else " like the lines above"
            raise DataFormatError(path, f"expected {expected} columns{why}, got {len(toks)}", lineno)
    n = len(rows)
    has_score = expected == 16
    types = np.empty(n, dtype=object)
    numeric = np.empty((n, 15 if has_score else 14), dtype=np.float64)
    for r, (toks, lineno) in enumerate(zip(rows, linenos, strict=True)):
        if toks[0] not in KITTI_TYPES:
            raise DataFormatError(
                path, f"unknown object type {toks[0]!r}; expected one of {', '.join(KITTI_TYPES)}", lineno, "type"
            )
        types[r] = toks[0]
        for c, tok in enumerate(toks[1:]):
            numeric[r, c] = _parse_float(tok, path, lineno, FIELDS[c + 1])
        occ = numeric[r, 1]
        if occ != int(occ) or not -1 <= occ <= 3:
            raise DataFormatError(path, f"expected an integer in -1..3, got {toks[2]!r}", lineno, "occluded")
    if not has_score:
        _check_values(numeric, rows, linenos, path)
    return Labels(
        type=types,
        truncated=numeric[:, 0].copy(),
        occluded=numeric[:, 1].astype(np.int64),
        alpha=numeric[:, 2].copy(),
        bbox=numeric[:, 3:7].copy(),
        dimensions=numeric[:, 7:10].copy(),
        location=numeric[:, 10:13].copy(),
        rotation_y=numeric[:, 13].copy(),
        score=numeric[:, 14].copy() if has_score else None,
    )


def read_labels(path: str | Path, scored: bool | None = None) -> Labels:
    """Read a KITTI label or result file (see :func:`parse_labels`)."""
    path = Path(path)
    return parse_labels(read_data_text(path), path, scored)


def write_labels(path: str | Path, labels: Labels, precision: int = 2) -> None:
    """Write a label/result file atomically (an empty file for zero objects)."""
    atomic_write_text(path, labels.to_text(precision))
