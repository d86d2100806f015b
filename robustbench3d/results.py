"""Benchmark result files: the summary JSON Schema, validation, and the long-format table.

``summary.json`` is a JSON list of cells (one per victim x attack x proposal source)::

    {"schema_version": 1, "victim": str, "attack": str, "proposals": "detector" | "gt",
     "status": "ok" | "skipped" | "error", "reason": str | null,
     "dataset": {...identity...}, "metrics": <evaluator JSON> | null, "provenance": {...}}

validated against ``robustbench3d/schemas/summary.schema.json`` (shipped with the package).
The long-format CSV has one row per AP number of every ``ok`` cell (columns :data:`CSV_COLUMNS`: the AP's,
then each attack metric's, :mod:`robustbench3d.metrics`); it is the single source later leaderboards are built
from. :class:`CellResult` is the typed read access to one cell that every reader of summaries goes through.
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import Any, NamedTuple

from robustbench3d.errors import DataFormatError
from robustbench3d.eval.rules import DIFFICULTIES, RECALL_SAMPLES
from robustbench3d.fileio import atomic_write_text, read_data_text
from robustbench3d.metrics import (
    ATTACK_METRICS,
    HEADLINE,
    SUCCESS_CLASS,
    SUCCESS_DIFFICULTY,
    SUCCESS_METRIC,
    attack_metric,
    csv_columns,
    drop_tables,  # re-exported, as are success_rate and SUCCESS_*: attack train's held-out curve reads them here
    success_rate,
)

SCHEMA_VERSION = 1
SCHEMA_RESOURCE = "summary.schema.json"
#: The columns of an AP value, then of each attack metric (:func:`robustbench3d.metrics.csv_columns`).
AP_COLUMNS: tuple[str, ...] = (
    "victim", "attack", "proposals", "class", "metric", "iou", "recall_points", "difficulty", "ap",
)
CSV_COLUMNS: tuple[str, ...] = (*AP_COLUMNS, *csv_columns())
#: Recall sampling name -> number of recall points (``R40`` -> 40, ``R11`` -> 11), in report order.
RECALL_POINTS: dict[str, int] = {name: len(idx) for name, idx in RECALL_SAMPLES.items()}


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


def _first_path(obj: Any, match: Callable[[Any], bool],
                parts: tuple[Any, ...] = ()) -> tuple[tuple[Any, ...], Any] | None:
    """(JSON path parts, value) of the first value in ``obj`` (itself, then lists and dicts walked in order)
    that ``match``es, or None."""
    if match(obj):
        return parts, obj
    items = obj.items() if isinstance(obj, dict) else enumerate(obj) if isinstance(obj, list) else ()
    for key, value in items:
        found = _first_path(value, match, (*parts, key))
        if found is not None:
            return found
    return None


def non_finite_path(obj: Any, parts: tuple[Any, ...] = ()) -> tuple[tuple[Any, ...], float] | None:
    """(JSON path parts, value) of the first NaN or infinite float in ``obj`` (lists and dicts walked in
    order), or None. JSON has no such numbers, and JSON Schema cannot refuse them: ``NaN`` compares
    false with every bound, so ``{"minimum": 0, "maximum": 100}`` lets a NaN AP through."""
    return _first_path(obj, lambda v: isinstance(v, float) and not math.isfinite(v), parts)


def validate_summary(summary: Any, source: str | Path = "summary.json", cell_only: bool = False) -> None:
    """Raise :class:`DataFormatError` naming ``source`` and the JSON path of the most relevant
    violation unless ``summary`` (a list of cells, or one cell with ``cell_only``) is valid.

    Every number must be finite (a NaN or infinite value is refused first, naming its path)."""
    from jsonschema.exceptions import best_match

    bad = non_finite_path(summary)
    if bad is not None:
        raise DataFormatError(source, f"{bad[1]!r} is not a finite number (JSON has no NaN or Infinity)",
                              field=_json_path(bad[0]))
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


class _NonFiniteToken:
    """Stands in for a ``NaN`` / ``Infinity`` / ``-Infinity`` token while a file is parsed, so that
    :func:`read_json` can name the field that holds it."""

    def __init__(self, token: str):
        self.token = token


def read_json(path: str | Path) -> Any:
    """Parse a JSON file; :class:`DataFormatError` naming it on a missing or unreadable file (a
    directory, no permission), bad JSON (the message gives line and column), or a ``NaN`` /
    ``Infinity`` token (not JSON, though Python's parser accepts it; the error names the field)."""
    path = Path(path)
    text = read_data_text(path)
    tokens: list[str] = []

    def refuse(token: str) -> _NonFiniteToken:
        tokens.append(token)
        return _NonFiniteToken(token)

    try:
        data = json.loads(text, parse_constant=refuse)
    except json.JSONDecodeError as exc:
        raise DataFormatError(path, f"not valid JSON ({exc})") from None
    if tokens:
        found = _first_path(data, lambda v: isinstance(v, _NonFiniteToken))
        field = _json_path(found[0]) if found is not None else None
        raise DataFormatError(path, f"{tokens[0]} is not JSON (numbers must be finite)", field=field)
    return data


def read_summary(path: str | Path) -> list[dict[str, Any]]:
    """Read and validate a ``summary.json``."""
    data = read_json(path)
    validate_summary(data, path)
    return data


class APValue(NamedTuple):
    """One AP number of an evaluation (percent) and where it sits."""

    cls: str
    metric: str
    recall: str
    difficulty: str
    ap: float


@dataclass(frozen=True)
class APResult:
    """Typed read access to the evaluator's JSON (:func:`robustbench3d.eval.evaluate`'s result)."""

    data: Mapping[str, Any]

    @property
    def classes(self) -> tuple[str, ...]:
        """Evaluated classes, in the evaluator's order."""
        return tuple(self.data["meta"]["classes"])

    @property
    def meta(self) -> Mapping[str, Any]:
        """The evaluation's record of itself (evaluator, version, frames, classes, metrics, min_overlap, ...)."""
        return self.data["meta"]

    @property
    def evaluated_metrics(self) -> tuple[str, ...]:
        """The metrics the evaluation was asked for (``meta.metrics``), in the evaluator's order."""
        return tuple(self.data["meta"]["metrics"])

    def metrics(self, cls: str) -> tuple[str, ...]:
        """Metrics with AP values for ``cls`` (none if the class was skipped), in result order."""
        return tuple(self.data.get(cls, {}))

    def iou(self, cls: str, metric: str) -> float:
        """Minimum overlap of ``metric`` for ``cls``."""
        return self.data["meta"]["min_overlap"][cls][metric]

    def min_overlap(self, cls: str) -> Mapping[str, float]:
        """Minimum overlap per metric for ``cls`` (empty if the evaluation records none)."""
        return self.data["meta"].get("min_overlap", {}).get(cls, {})

    def ap(self, cls: str, metric: str, recall: str, difficulty: str) -> float:
        """AP in percent; :class:`LookupError` naming what is missing if there is no such value."""
        checks = (("recall sampling", recall, tuple(RECALL_POINTS)), ("difficulty", difficulty, DIFFICULTIES))
        for what, value, known in checks:
            if value not in known:
                raise LookupError(f"unknown {what} {value!r}; expected one of {', '.join(known)}")
        if metric not in self.metrics(cls):
            have = ", ".join(f"{c}/{m}" for c in self.classes for m in self.metrics(c)) or "none"
            raise LookupError(f"no AP for class {cls!r} metric {metric!r} (evaluated: {have})")
        return self.data[cls][metric][recall][difficulty]

    def values(self) -> Iterator[APValue]:
        """Every AP value: by class, metric, recall sampling (R40 before R11), then difficulty."""
        for cls in self.classes:
            for metric in self.metrics(cls):
                for recall in RECALL_POINTS:
                    for diff in DIFFICULTIES:
                        yield APValue(cls, metric, recall, diff, self.data[cls][metric][recall][diff])


@dataclass(frozen=True)
class CellResult:
    """Typed read access to one summary cell (see the module docstring): its identity, dataset, provenance,
    evaluation (:class:`APResult`), intervals and attack metrics (:mod:`robustbench3d.metrics`). AP positions
    default to :data:`robustbench3d.metrics.HEADLINE`."""

    cell: Mapping[str, Any]

    @property
    def victim(self) -> str:
        return self.cell["victim"]

    @property
    def attack(self) -> str:
        return self.cell["attack"]

    @property
    def proposals(self) -> str:
        return self.cell["proposals"]

    @property
    def id(self) -> tuple[str, str, str]:
        """(victim, attack, proposals): what names the cell in a summary."""
        return (self.victim, self.attack, self.proposals)

    @property
    def name(self) -> str:
        """``victim+attack+proposals``, the cell's directory name (registry names hold no ``+``)."""
        return "+".join(self.id)

    @property
    def status(self) -> str:
        return self.cell["status"]

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def reason(self) -> str | None:
        return self.cell["reason"]

    @property
    def dataset(self) -> Mapping[str, Any]:
        """The dataset identity record (split, frames, split_frames, sha256, embedded, root, ...)."""
        return self.cell["dataset"]

    @property
    def frames(self) -> int:
        return self.dataset["frames"]

    @property
    def provenance(self) -> Mapping[str, Any]:
        return self.cell["provenance"]

    @property
    def config(self) -> Mapping[str, Any]:
        """Everything the result depends on (``provenance.config``; its sha256 is :attr:`fingerprint`)."""
        return self.provenance["config"]

    @property
    def fingerprint(self) -> str:
        return self.provenance["fingerprint"]

    @property
    def seed(self) -> int:
        """The run seed (``provenance.seed``)."""
        return self.provenance["seed"]

    @property
    def flags(self) -> list[Mapping[str, str]]:
        """The sanity flags (:mod:`robustbench3d.runner.flags`); empty when none were recorded."""
        return list(self.cell.get("flags") or [])

    @property
    def result(self) -> APResult | None:
        """The cell's evaluation, or None unless it is ``ok``."""
        return APResult(self.cell["metrics"]) if self.ok else None

    def ap(self, cls: str = HEADLINE.cls, metric: str = HEADLINE.metric, recall: str = HEADLINE.recall,
           difficulty: str = HEADLINE.difficulty) -> float:
        """AP in percent of an ``ok`` cell (:class:`LookupError` for another status or a missing value)."""
        result = self.result
        if result is None:
            raise LookupError(f"cell {self.victim} / {self.attack} / {self.proposals} is {self.status}: no AP")
        return result.ap(cls, metric, recall, difficulty)

    def interval(self, cls: str = HEADLINE.cls, metric: str = HEADLINE.metric, recall: str = HEADLINE.recall,
                 difficulty: str = HEADLINE.difficulty, table: str = "metrics_ci") -> Any:
        """The recorded bootstrap interval (``[lo, hi]``) of an AP (``table`` ``metrics_ci``, the cell's) or of an
        ``interval`` attack metric (``table`` its name, e.g. ``drop_ci``, in the attack effect); None where the
        summary has none."""
        in_effect = table in ATTACK_METRICS and ATTACK_METRICS[table].kind == "interval"
        tree = (self.effect or {}).get(table) if in_effect else self.cell.get(table)
        for key in (cls, metric, recall, difficulty):
            if not isinstance(tree, Mapping) or key not in tree:
                return None
            tree = tree[key]
        return tree

    @property
    def interval_meta(self) -> Mapping[str, Any] | None:
        """How the cell's AP intervals were drawn (``metrics_ci.meta``: level, resamples, seed, ...), or None."""
        ci = self.cell.get("metrics_ci")
        return ci["meta"] if ci else None

    @property
    def effect(self) -> Mapping[str, Any] | None:
        """The comparison with the clean cell (``attack_effect``, :mod:`robustbench3d.runner.effect`), or
        None (the clean cell itself, a cell that is not ``ok``, or no ``ok`` clean cell)."""
        return self.cell.get("attack_effect")

    @property
    def clean_cell(self) -> str | None:
        """The directory name of the clean cell the attack effect was computed against, or None."""
        effect = self.effect
        return None if effect is None else effect.get("clean_cell")

    def effect_value(self, name: str, cls: str = HEADLINE.cls, metric: str = HEADLINE.metric,
                     recall: str = HEADLINE.recall, difficulty: str = HEADLINE.difficulty) -> Any:
        """The attack metric ``name`` (:data:`robustbench3d.metrics.ATTACK_METRICS`): an ``ap`` metric's value at
        the AP position, a ``cell`` metric's number (the position is ignored). :class:`LookupError` for an
        unknown or ``interval`` metric (see :meth:`interval`), without a clean-cell comparison, or for a position
        the comparison lacks."""
        m = attack_metric(name)
        effect = self.effect
        if effect is None:
            raise LookupError(f"cell {self.victim} / {self.attack} / {self.proposals} has no clean-cell comparison")
        try:
            if m.kind == "cell":
                return effect[name][m.value_key]
            if m.kind == "ap":
                return effect[name][cls][metric][recall][difficulty]
        except KeyError:
            raise LookupError(f"no {name} for class {cls!r} metric {metric!r} {recall} {difficulty}") from None
        raise LookupError(f"attack metric {name!r} is an interval: read it with CellResult.interval")

    def clean_ap(self, cls: str = HEADLINE.cls, metric: str = HEADLINE.metric, recall: str = HEADLINE.recall,
                 difficulty: str = HEADLINE.difficulty) -> float:
        """AP in percent of the clean cell this attacked cell is compared with (:class:`LookupError` if none)."""
        value = self.effect_value("clean", cls, metric, recall, difficulty)
        assert value is not None
        return value

    def drop(self, cls: str = HEADLINE.cls, metric: str = HEADLINE.metric, recall: str = HEADLINE.recall,
             difficulty: str = HEADLINE.difficulty, relative: bool = False) -> float | None:
        """Clean AP - attacked AP in percentage points, or with ``relative`` that drop / clean AP (a
        fraction; None where the clean AP is 0). :class:`LookupError` without a clean-cell comparison."""
        return self.effect_value("relative_drop" if relative else "drop", cls, metric, recall, difficulty)

    @property
    def attack_success_rate(self) -> float | None:
        """Share of the target-class objects matched clean that the attacked cell misses (see
        ``attack_effect.success``); None without a comparison or when the clean cell matches none."""
        return None if self.effect is None else self.effect_value("success")


def _metric_columns(cell: CellResult, v: APValue) -> dict[str, Any]:
    """The attack metrics' CSV values of one AP value of ``cell`` (all None unless every one is found)."""
    columns = {m.column: None for m in ATTACK_METRICS.values() if m.column is not None}
    if cell.effect is None:
        return columns
    where = (v.cls, v.metric, v.recall, v.difficulty)
    try:
        return {m.column: cell.effect_value(m.name, *where) for m in ATTACK_METRICS.values() if m.column is not None}
    except LookupError:
        return columns


def long_rows(cells: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per AP value of every ``ok`` cell, in cell order, then class, metric, recall
    sampling (R40 before R11) and difficulty. ``iou`` is the metric's minimum overlap,
    ``recall_points`` 40 or 11, ``ap`` in percent. Attacked cells compared with a clean cell also fill
    each attack metric's column (:mod:`robustbench3d.metrics`: ``clean_ap``, ``ap_drop`` in percentage points,
    ``relative_drop`` and the cell's ``attack_success_rate``, repeated on each of its rows, as fractions); these
    are empty otherwise, as is a relative drop from a clean AP of 0."""
    rows = []
    for cell in map(CellResult, cells):
        result = cell.result
        if result is None:
            continue
        for v in result.values():
            row = {"victim": cell.victim, "attack": cell.attack, "proposals": cell.proposals, "class": v.cls,
                   "metric": v.metric, "iou": result.iou(v.cls, v.metric),
                   "recall_points": RECALL_POINTS[v.recall], "difficulty": v.difficulty, "ap": v.ap,
                   **_metric_columns(cell, v)}
            rows.append(row)
    return rows


def long_csv_text(rows: Sequence[dict[str, Any]]) -> str:
    """CSV text of :func:`long_rows` (floats written in their shortest exact form; the columns are
    :data:`CSV_COLUMNS`, read from the attack metrics' table when called)."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=(*AP_COLUMNS, *csv_columns()), lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: repr(v) if isinstance(v, float) else "" if v is None else v for k, v in row.items()})
    return buf.getvalue()


def write_long_csv(path: str | Path, cells: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Write the long-format CSV of ``cells`` atomically; returns its rows."""
    rows = long_rows(cells)
    atomic_write_text(path, long_csv_text(rows))
    return rows


__all__ = [
    "AP_COLUMNS", "CSV_COLUMNS", "RECALL_POINTS", "SCHEMA_VERSION", "SUCCESS_CLASS", "SUCCESS_DIFFICULTY",
    "SUCCESS_METRIC", "APResult", "APValue", "CellResult", "drop_tables", "dumps", "load_schema", "long_csv_text",
    "long_rows", "read_json", "read_summary", "schema_errors", "success_rate", "validate_summary", "write_long_csv",
    "write_validated",
]
