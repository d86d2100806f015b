"""Benchmark result files: the summary JSON Schema, validation, and the long-format table.

``summary.json`` is a JSON list of cells (one per victim x attack x proposal source)::

    {"schema_version": 1, "victim": str, "attack": str, "proposals": "detector" | "gt",
     "status": "ok" | "skipped" | "error", "reason": str | null,
     "dataset": {...identity...}, "metrics": <evaluator JSON> | null, "provenance": {...}}

validated against ``robustbench3d/schemas/summary.schema.json`` (shipped with the package).
The long-format CSV has one row per AP number of every ``ok`` cell (columns :data:`CSV_COLUMNS`);
it is the single source later leaderboards are built from.
"""

from __future__ import annotations

import csv
import io
import json
from collections.abc import Iterable, Sequence
from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import Any

from robustbench3d.errors import DataFormatError
from robustbench3d.fileio import atomic_write_text

SCHEMA_VERSION = 1
SCHEMA_RESOURCE = "summary.schema.json"
CSV_COLUMNS: tuple[str, ...] = (
    "victim", "attack", "proposals", "class", "metric", "iou", "recall_points", "difficulty", "ap",
)
_DIFFICULTIES = ("easy", "moderate", "hard")
_RECALLS = {"R40": 40, "R11": 11}


@lru_cache(maxsize=1)
def load_schema() -> dict[str, Any]:
    """The summary JSON Schema (draft 2020-12) shipped in ``robustbench3d/schemas``."""
    text = resources.files("robustbench3d").joinpath("schemas", SCHEMA_RESOURCE).read_text(encoding="utf-8")
    return json.loads(text)


def _json_path(parts: Iterable[Any]) -> str:
    out = "$"
    for p in parts:
        out += f"[{p}]" if isinstance(p, int) else f".{p}"
    return out


def _validator(cell_only: bool) -> Any:
    import jsonschema

    schema = load_schema()
    if cell_only:
        schema = {"$schema": schema["$schema"], "$defs": schema["$defs"], "$ref": "#/$defs/cell"}
    return jsonschema.Draft202012Validator(schema)


def schema_errors(summary: Any, cell_only: bool = False) -> list[str]:
    """Every schema violation as ``"<JSON path>: <problem>"`` (empty if valid)."""
    errors = sorted(_validator(cell_only).iter_errors(summary), key=lambda e: list(map(str, e.absolute_path)))
    return [f"{_json_path(e.absolute_path)}: {e.message}" for e in errors]


def validate_summary(summary: Any, source: str | Path = "summary.json", cell_only: bool = False) -> None:
    """Raise :class:`DataFormatError` naming ``source`` and the JSON path of the most relevant
    violation unless ``summary`` (a list of cells, or one cell with ``cell_only``) is valid."""
    from jsonschema.exceptions import best_match

    error = best_match(_validator(cell_only).iter_errors(summary))
    if error is not None:
        raise DataFormatError(source, error.message, field=_json_path(error.absolute_path))


def _to_builtin(obj: Any) -> Any:
    """``json.dumps`` fallback for numpy scalars and arrays and for paths."""
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def dumps(obj: Any) -> str:
    """Indented JSON text; NaN/inf are refused (they are not JSON)."""
    return json.dumps(obj, indent=2, allow_nan=False, default=_to_builtin) + "\n"


def write_validated(path: str | Path, obj: Any, cell_only: bool = False) -> Any:
    """Serialise, re-read and validate (so what is checked is exactly what lands on disk), then
    write atomically. Returns the re-read object (plain JSON types)."""
    text = dumps(obj)
    data = json.loads(text)
    validate_summary(data, path, cell_only=cell_only)
    atomic_write_text(path, text)
    return data


def read_json(path: str | Path) -> Any:
    """Parse a JSON file; :class:`DataFormatError` naming it on a missing file or bad JSON."""
    path = Path(path)
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise DataFormatError(path, "file not found") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataFormatError(path, f"not valid JSON ({exc})") from None


def read_summary(path: str | Path) -> list[dict[str, Any]]:
    """Read and validate a ``summary.json``."""
    data = read_json(path)
    validate_summary(data, path)
    return data


def long_rows(cells: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per AP value of every ``ok`` cell, in cell order, then class, metric, recall
    sampling (R40 before R11) and difficulty. ``iou`` is the metric's minimum overlap,
    ``recall_points`` 40 or 11, ``ap`` in percent."""
    rows = []
    for cell in cells:
        if cell["status"] != "ok":
            continue
        metrics = cell["metrics"]
        overlap = metrics["meta"]["min_overlap"]
        for cls in metrics["meta"]["classes"]:
            for metric, by_recall in metrics.get(cls, {}).items():
                for recall, points in _RECALLS.items():
                    for diff in _DIFFICULTIES:
                        rows.append({"victim": cell["victim"], "attack": cell["attack"],
                                     "proposals": cell["proposals"], "class": cls, "metric": metric,
                                     "iou": overlap[cls][metric], "recall_points": points, "difficulty": diff,
                                     "ap": by_recall[recall][diff]})
    return rows


def long_csv_text(rows: Sequence[dict[str, Any]]) -> str:
    """CSV text of :func:`long_rows` (floats written in their shortest exact form)."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=CSV_COLUMNS, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: repr(v) if isinstance(v, float) else v for k, v in row.items()})
    return buf.getvalue()


def write_long_csv(path: str | Path, cells: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Write the long-format CSV of ``cells`` atomically; returns its rows."""
    rows = long_rows(cells)
    atomic_write_text(path, long_csv_text(rows))
    return rows


__all__ = [
    "CSV_COLUMNS", "SCHEMA_VERSION", "dumps", "load_schema", "long_csv_text", "long_rows", "read_json",
    "read_summary", "schema_errors", "validate_summary", "write_long_csv", "write_validated",
]
