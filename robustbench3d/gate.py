"""The AP / AP-drop regression gate of a run against a recorded baseline (``robustbench3d check``; the pytest
plugin's ``robustbench3d_gate`` fixture).

    robustbench3d check RUN_DIR --write-baseline FILE [--force]
    robustbench3d check RUN_DIR --baseline FILE [--tol-ap X] [--tol-drop Y] [--json PATH] [--junit PATH] [--force]

``--write-baseline``, ``--json`` and ``--junit`` write new files; an existing one is replaced only with
``--force`` (the command says so), never when it is a file being read. Tolerances are percentage points
in :data:`TOL_RANGE`. ``--json`` writes :func:`report_record`, ``--junit`` :func:`junit_xml`.

A **baseline** (:data:`FORMAT`, version :data:`VERSION`) is a small JSON file::

    {"format": "robustbench3d.baseline", "version": 1, "created": ISO time,
     "source": {"summary": path, "summary_sha256": hex, "package_version": str},
     "dataset": {split, frames, split_frames, sha256, embedded, root},
     "protocol": {"class": "Car", "recall": "R40", "metrics": ["bev", "3d"], "min_overlap": {"bev", "3d"},
                  "evaluation": <the cells' evaluation record>, "seed": int},
     "cells": [{"victim", "attack", "proposals", "status",
                "ap": {"bev": {"easy", "moderate", "hard"}, "3d": {...}} | null,
                "drop_moderate": {"bev": x, "3d": y} | null,
                "victim_weights_sha256": hex | null, "attack_object_sha256": hex | null}, ...]}

AP is Car AP in percent (R40); ``drop_moderate`` is the attacked cell's moderate AP drop against its
clean cell (``attack_effect``, percentage points; null for the clean cell and for a cell without a
comparison). The dataset is identified by split, frame counts, the labels' sha256 and the generator
parameters (``root`` is recorded but not compared: the same dataset sits at another path on CI).

``check`` compares every AP and every AP drop of every baseline cell with the run's summary and
**fails (exit 1) on any move past its tolerance**, in either direction: a lower AP or a larger drop is
a *regression*; a higher AP or a smaller drop is an *improvement*, which fails too (the baseline is
stale: record the new numbers with ``--write-baseline FILE --force``) unless ``--allow-improvements``. It also
fails when a baseline cell is missing from the run, the run has a cell the baseline lacks, a cell's
status changed, or the dataset or protocol differs; a differing dataset or protocol is reported alone
(:func:`format_mismatch`: the fields that differ), since every per-cell difference follows from it.
Unreadable or malformed files exit 2 (:class:`~robustbench3d.errors.DataFormatError`, naming the file
and field; a directory given as a file, bad JSON with its line, a NaN or Infinity anywhere); a passing
check exits 0.

Standard library only.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from robustbench3d.errors import DataFormatError, RobustBenchError
from robustbench3d.eval.rules import DIFFICULTIES
from robustbench3d.metrics import HEADLINE, attack_metric
from robustbench3d.results import CellResult, dumps, read_json, validate_summary
from robustbench3d.texttable import format_table

FORMAT = "robustbench3d.baseline"
VERSION = 1
#: The gated AP: the headline's class and recall sampling, every difficulty of :data:`GATE_METRICS`.
CLASS, RECALL = HEADLINE.cls, HEADLINE.recall
GATE_METRICS: tuple[str, ...] = ("bev", "3d")
#: The gated attack metric (:data:`robustbench3d.metrics.ATTACK_METRICS`), at the headline difficulty; the
#: baseline format (``drop_moderate``) and ``--tol-drop`` are its, so gating another one is a format change.
GATED_EFFECT = attack_metric("drop")
GATED_DIFFICULTY = HEADLINE.difficulty
#: Dataset identity keys compared between the baseline and the run (``root`` is informational).
DATASET_KEYS: tuple[str, ...] = ("split", "frames", "split_frames", "sha256", "embedded")
#: Evaluation protocol keys compared between the baseline and the run.
PROTOCOL_KEYS: tuple[str, ...] = ("class", "recall", "metrics", "min_overlap", "evaluation", "seed")
#: Default tolerances, percentage points.
DEFAULT_TOL_AP = 1.0
DEFAULT_TOL_DROP = 1.0
#: Range of ``--tol-ap`` and ``--tol-drop``, percentage points. AP lies in [0, 100] and a drop in
#: [-100, 100], so a tolerance above 100 never fails anything: a typo such as ``--tol-ap 1e3`` would
#: silently switch the gate off. 0 demands the exact numbers (a rerun of the same code, weights and
#: seed reproduces them).
TOL_RANGE = (0.0, 100.0)
SUMMARY_FILE = "summary.json"
CellId = tuple[str, str, str]


# ---- reading a run ---------------------------------------------------------------------------------

def summary_path(run: str | Path) -> Path:
    """``RUN_DIR/summary.json`` (or ``run`` itself when it names a file)."""
    run = Path(run)
    return run if run.suffix == ".json" and not run.is_dir() else run / SUMMARY_FILE


def read_run(run: str | Path) -> tuple[Path, list[dict[str, Any]]]:
    """The run's validated summary cells (:class:`DataFormatError` naming the file otherwise)."""
    path = summary_path(run)
    if path.parent.exists() and not path.parent.is_dir():
        raise DataFormatError(path.parent, "is a file; expected a run directory or its summary.json")
    if not path.parent.is_dir():
        raise DataFormatError(path.parent, "run directory not found")
    cells = read_json(path)
    validate_summary(cells, path)
    if not cells:
        raise DataFormatError(path, "the summary lists no cell")
    seen: set[CellId] = set()
    for i, cell in enumerate(cells):
        cid = _cell_id(cell)
        if cid in seen:
            raise DataFormatError(path, f"cell {_name(cid)} is listed twice", field=f"$[{i}]")
        seen.add(cid)
    return path, cells


def _cell_id(cell: Mapping[str, Any]) -> CellId:
    return CellResult(cell).id


def _name(cid: CellId) -> str:
    return "+".join(cid)


def _dataset(cell: Mapping[str, Any]) -> dict[str, Any]:
    dataset = CellResult(cell).dataset
    return {k: dataset.get(k) for k in (*DATASET_KEYS, "root")}


def _protocol(cell: Mapping[str, Any]) -> dict[str, Any]:
    r = CellResult(cell)
    overlap = r.result.min_overlap(CLASS) if r.result is not None else {}
    return {"class": CLASS, "recall": RECALL, "metrics": list(GATE_METRICS),
            "min_overlap": {m: overlap.get(m) for m in GATE_METRICS},
            "evaluation": r.config.get("evaluation"), "seed": r.seed}


def _gated_effect(cell: CellResult, m: str) -> float | None:
    """The gated attack metric of ``cell`` at metric ``m`` (None where its comparison has no value there)."""
    try:
        return cell.effect_value(GATED_EFFECT.name, CLASS, m, RECALL, GATED_DIFFICULTY)
    except LookupError:
        return None


def _values(cell: Mapping[str, Any], path: Path, index: int) -> tuple[dict | None, dict | None]:
    """(AP table, moderate-drop table) of a summary cell (None where it has none)."""
    r = CellResult(cell)
    result = r.result
    if result is None:
        return None, None
    where = f"$[{index}].metrics.{CLASS}"
    have = result.metrics(CLASS)
    if not have:
        raise DataFormatError(path, f"cell {r.name} has no {CLASS} AP", field=where)
    ap: dict[str, dict[str, float]] = {}
    for m in GATE_METRICS:
        if m not in have:
            raise DataFormatError(path, f"cell {r.name} has no {CLASS} {m} AP", field=f"{where}.{m}")
        ap[m] = {d: float(result.ap(CLASS, m, RECALL, d)) for d in DIFFICULTIES}
    drop = None if r.effect is None else {m: _gated_effect(r, m) for m in GATE_METRICS}
    return ap, drop


def _object_sha(cell: Mapping[str, Any]) -> str | None:
    obj = CellResult(cell).config["attack"].get("object") or {}
    inner = obj.get("object") if isinstance(obj, dict) else None
    return inner.get("ply_sha256") if isinstance(inner, dict) else None


def _common(cells: Sequence[Mapping[str, Any]], what: str, fn: Any, path: Path) -> dict[str, Any]:
    """``fn(cell)`` of the ok cells (or all cells), refusing a summary whose cells disagree."""
    ok = [c for c in cells if CellResult(c).ok] or list(cells)
    first = fn(ok[0])
    for c in ok[1:]:
        if fn(c) != first:
            raise DataFormatError(path, f"cells {_name(_cell_id(ok[0]))} and {_name(_cell_id(c))} have different "
                                        f"{what}; a baseline covers one {what}")
    return first


def baseline_from_run(run: str | Path) -> dict[str, Any]:
    """The baseline record of a run (module doc). Refuses a run with ``error`` cells."""
    path, cells = read_run(run)
    failed = [CellResult(c).name for c in cells if CellResult(c).status == "error"]
    if failed:
        raise RobustBenchError(f"{path}: cell(s) {', '.join(failed)} failed; a baseline records finished cells only")
    out_cells = []
    for i, cell in enumerate(cells):
        ap, drop = _values(cell, path, i)
        r = CellResult(cell)
        out_cells.append({"victim": r.victim, "attack": r.attack, "proposals": r.proposals,
                          "status": r.status, "ap": ap, "drop_moderate": drop,
                          "victim_weights_sha256": r.config["victim"].get("weights_sha256"),
                          "attack_object_sha256": _object_sha(cell)})
    from robustbench3d import __version__
    from robustbench3d.provenance import utc_now

    return {"format": FORMAT, "version": VERSION, "created": utc_now(),
            "source": {"summary": str(path.resolve()), "summary_sha256": hashlib.sha256(path.read_bytes()).hexdigest(),
                       "package_version": __version__},
            "dataset": _common(cells, "dataset", _dataset, path),
            "protocol": _common(cells, "evaluation protocol", _protocol, path),
            "cells": out_cells}


def write_baseline(run: str | Path, out: str | Path) -> dict[str, Any]:
    """Write the baseline of ``run`` to ``out`` (atomically, validated by reading it back); returns it.
    ``out`` is replaced if it exists (the ``check`` command refuses that without ``--force``)."""
    record = baseline_from_run(run)
    write_record(record, out)
    return record


def write_record(record: dict[str, Any], out: str | Path) -> None:
    """Serialise ``record``, validate what will land on disk, then write it atomically."""
    from robustbench3d.fileio import atomic_write_text

    text = dumps(record)
    validate_baseline(json.loads(text), out)
    atomic_write_text(out, text)


# ---- reading a baseline ----------------------------------------------------------------------------

def _need(obj: Any, key: str, kind: type | tuple[type, ...], path: Path, where: str) -> Any:
    if not isinstance(obj, dict) or key not in obj:
        raise DataFormatError(path, "missing", field=f"{where}.{key}")
    value = obj[key]
    if isinstance(value, bool) or not isinstance(value, kind):
        names = " or ".join(k.__name__ for k in (kind if isinstance(kind, tuple) else (kind,)))
        raise DataFormatError(path, f"expected {names}, got {type(value).__name__}", field=f"{where}.{key}")
    return value


def _number(value: Any, path: Path, where: str, nullable: bool = False) -> None:
    if value is None and nullable:
        return
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise DataFormatError(path, f"expected a finite number{' or null' if nullable else ''}, got {value!r}",
                              field=where)


def validate_baseline(data: Any, path: str | Path) -> None:
    """Raise :class:`DataFormatError` naming ``path`` and the field unless ``data`` is a baseline."""
    path = Path(path)
    if not isinstance(data, dict):
        raise DataFormatError(path, f"expected a JSON object, got {type(data).__name__}", field="$")
    if data.get("format") != FORMAT:
        raise DataFormatError(path, f"expected {FORMAT!r}, got {data.get('format')!r} (write one with "
                                    "`robustbench3d check RUN_DIR --write-baseline FILE`)", field="$.format")
    if data.get("version") != VERSION:
        raise DataFormatError(path, f"unsupported version {data.get('version')!r} (this robustbench3d reads "
                                    f"{VERSION})", field="$.version")
    dataset = _need(data, "dataset", dict, path, "$")
    for key in DATASET_KEYS:
        if key not in dataset:
            raise DataFormatError(path, "missing", field=f"$.dataset.{key}")
    protocol = _need(data, "protocol", dict, path, "$")
    for key in PROTOCOL_KEYS:
        if key not in protocol:
            raise DataFormatError(path, "missing", field=f"$.protocol.{key}")
    cells = _need(data, "cells", list, path, "$")
    seen: set[CellId] = set()
    for i, cell in enumerate(cells):
        where = f"$.cells[{i}]"
        cid = tuple(_need(cell, k, str, path, where) for k in ("victim", "attack", "proposals"))
        if cid in seen:
            raise DataFormatError(path, f"cell {_name(cid)} is listed twice", field=where)  # type: ignore[arg-type]
        seen.add(cid)  # type: ignore[arg-type]
        status = _need(cell, "status", str, path, where)
        if status not in ("ok", "skipped"):
            raise DataFormatError(path, f"expected 'ok' or 'skipped', got {status!r}", field=f"{where}.status")
        ap = _need(cell, "ap", (dict, type(None)), path, where)
        if (ap is None) != (status != "ok"):
            raise DataFormatError(path, "an ok cell has AP values and only an ok cell", field=f"{where}.ap")
        for m in GATE_METRICS if ap is not None else ():
            for d in DIFFICULTIES:
                _number(_need(ap, m, dict, path, f"{where}.ap").get(d), path, f"{where}.ap.{m}.{d}")
        drop = _need(cell, "drop_moderate", (dict, type(None)), path, where)
        for m in GATE_METRICS if drop is not None else ():
            _number(drop.get(m), path, f"{where}.drop_moderate.{m}", nullable=True)


def read_baseline(path: str | Path) -> dict[str, Any]:
    """Read and validate a baseline file."""
    data = read_json(path)
    validate_baseline(data, path)
    return data


# ---- comparing -------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Comparison:
    """One compared value of one cell: a Car AP (percent, R40) or a moderate AP drop (percentage points)
    of the baseline and the run, with its verdict."""

    cell: str
    quantity: str  # "ap" | "drop"
    metric: str  # "bev" | "3d"
    difficulty: str
    baseline: float | None
    now: float | None
    tolerance: float
    verdict: str  # "within" | "regression" | "improvement" | "appeared" | "vanished"

    @property
    def delta(self) -> float | None:
        return None if self.baseline is None or self.now is None else self.now - self.baseline

    @property
    def moved(self) -> bool:
        """Past its tolerance (or present on one side only)."""
        return self.verdict != "within"

    @property
    def label(self) -> str:
        """``BEV AP moderate`` / ``3D drop moderate``."""
        return f"{_label(self.metric)} {'AP' if self.quantity == 'ap' else 'drop'} {self.difficulty}"


#: Earlier name of :class:`Comparison` (a value that moved).
Move = Comparison


@dataclass(frozen=True)
class CellCheck:
    """A cell of the baseline (``status``: its baseline status) or one only the run has (``status`` None),
    with the problem that kept its values from being compared."""

    cell: CellId
    status: str | None
    problem: str | None = None

    @property
    def name(self) -> str:
        return _name(self.cell)


@dataclass(frozen=True)
class Mismatch:
    """A dataset or protocol field (dotted path into a nested record) that differs from the baseline."""

    section: str  # "dataset" | "protocol"
    field: str
    baseline: Any
    run: Any

    def text(self) -> str:
        return f"{self.section} {self.field}: baseline {_show(self.baseline)}, run {_show(self.run)}"


@dataclass
class GateReport:
    """The outcome of :func:`compare`: every compared value, every cell, and the dataset/protocol fields
    that differ (when any does, no cell is compared: every per-cell difference would follow from it)."""

    values: list[Comparison] = field(default_factory=list)
    cells: list[CellCheck] = field(default_factory=list)
    mismatches: list[Mismatch] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    tol_ap: float = DEFAULT_TOL_AP
    tol_drop: float = DEFAULT_TOL_DROP
    allow_improvements: bool = False

    @property
    def moves(self) -> list[Comparison]:
        """The values past their tolerance."""
        return [v for v in self.values if v.moved]

    def allowed(self, value: Comparison) -> bool:
        """An improvement that ``--allow-improvements`` lets pass."""
        return self.allow_improvements and value.verdict == "improvement"

    def failing(self, value: Comparison) -> bool:
        return value.moved and not self.allowed(value)

    @property
    def failing_moves(self) -> list[Comparison]:
        return [v for v in self.values if self.failing(v)]

    @property
    def problems(self) -> list[str]:
        """Cells missing from the run or the baseline, or whose status changed."""
        return [c.problem for c in self.cells if c.problem]

    @property
    def comparable(self) -> bool:
        return not self.mismatches

    @property
    def compared_cells(self) -> int:
        return sum(c.status is not None and c.problem is None for c in self.cells)

    @property
    def compared_values(self) -> int:
        return len(self.values)

    @property
    def ok(self) -> bool:
        return self.comparable and not self.problems and not self.failing_moves


def _judge(cell: str, quantity: str, metric: str, difficulty: str, base: float | None, now: float | None,
           tol: float, higher_is_better: bool) -> Comparison | None:
    """The comparison of one value (None when neither side has it)."""
    if base is None and now is None:
        return None
    if base is None or now is None:
        verdict = "appeared" if base is None else "vanished"
    elif abs(now - base) <= tol:
        verdict = "within"
    else:
        verdict = "improvement" if (now > base) == higher_is_better else "regression"
    return Comparison(cell, quantity, metric, difficulty, base, now, tol, verdict)


_MISSING = object()


def _field_diffs(section: str, base: Mapping[str, Any], now: Mapping[str, Any], keys: Sequence[str],
                 prefix: str = "") -> list[Mismatch]:
    """The fields of ``keys`` that differ, descending into records both sides hold (``embedded.seed``)."""
    out = []
    for key in keys:
        b, n = base.get(key, _MISSING), now.get(key, _MISSING)
        if b == n:
            continue
        if isinstance(b, dict) and isinstance(n, dict):
            out += _field_diffs(section, b, n, sorted(set(b) | set(n)), f"{prefix}{key}.")
        else:
            out.append(Mismatch(section, prefix + key, None if b is _MISSING else b, None if n is _MISSING else n))
    return out


def _show(value: Any) -> str:
    """A field value for the terminal: JSON, a sha256 cut to 16 hex digits."""
    if isinstance(value, str) and len(value) == 64 and all(ch in "0123456789abcdef" for ch in value):
        return value[:16] + "..."
    return json.dumps(value, sort_keys=True, default=str)


def compare(baseline: Mapping[str, Any], cells: Sequence[Mapping[str, Any]], run_path: Path,
            tol_ap: float = DEFAULT_TOL_AP, tol_drop: float = DEFAULT_TOL_DROP,
            allow_improvements: bool = False) -> GateReport:
    """Compare a run's summary cells with a baseline (module doc). A run over another dataset or
    protocol is reported by its differing fields alone: its cells are not compared."""
    report = GateReport(tol_ap=tol_ap, tol_drop=tol_drop, allow_improvements=allow_improvements)
    ds = _common(cells, "dataset", _dataset, run_path)
    proto = _common(cells, "evaluation protocol", _protocol, run_path)
    report.mismatches = (_field_diffs("dataset", baseline["dataset"], ds, DATASET_KEYS)
                         + _field_diffs("protocol", baseline["protocol"], proto, PROTOCOL_KEYS))
    if baseline["dataset"].get("root") != ds.get("root"):
        same = "" if report.mismatches else "; same split, frames and labels"
        report.notes.append(f"dataset root {ds.get('root')} (baseline: {baseline['dataset'].get('root')}); "
                            f"recorded, not compared{same}")
    if report.comparable:
        _compare_cells(report, baseline["cells"], cells, run_path)
    return report


def _cell_problem(bcell: Mapping[str, Any], found: tuple[int, Mapping[str, Any]] | None, name: str) -> str | None:
    if found is None:
        return f"cell {name} is in the baseline but not in the run"
    cell = CellResult(found[1])
    if cell.status != bcell["status"]:
        reason = f": {cell.reason}" if cell.reason else ""
        return f"cell {name} is {cell.status} (baseline: {bcell['status']}){reason}"
    return None


def _compare_cells(report: GateReport, base_cells: Sequence[Mapping[str, Any]],
                   cells: Sequence[Mapping[str, Any]], run_path: Path) -> None:
    """Add every baseline cell, its compared values, and the cells only the run has, to ``report``."""
    run_cells = {_cell_id(c): (i, c) for i, c in enumerate(cells)}
    for bcell in base_cells:
        cid: CellId = (bcell["victim"], bcell["attack"], bcell["proposals"])
        problem = _cell_problem(bcell, run_cells.get(cid), _name(cid))
        report.cells.append(CellCheck(cid, bcell["status"], problem))
        if problem is None:
            i, cell = run_cells[cid]
            _compare_values(report, _name(cid), bcell, *_values(cell, run_path, i))
            _explain(report, _name(cid), bcell, cell)
    base_ids = {c.cell for c in report.cells}
    report.cells += [CellCheck(cid, None, f"cell {_name(cid)} is in the run but not in the baseline")
                     for cid in run_cells if cid not in base_ids]


def _compare_values(report: GateReport, name: str, bcell: Mapping[str, Any], ap: dict | None,
                    drop: dict | None) -> None:
    found = []
    for m in GATE_METRICS if ap is not None else ():
        found += [_judge(name, "ap", m, d, bcell["ap"][m][d], ap[m][d], report.tol_ap, True) for d in DIFFICULTIES]
    bdrop = bcell["drop_moderate"] or {}
    found += [_judge(name, GATED_EFFECT.name, m, GATED_DIFFICULTY, bdrop.get(m), (drop or {}).get(m),
                     report.tol_drop, not GATED_EFFECT.higher_is_stronger) for m in GATE_METRICS]
    report.values += [v for v in found if v is not None]


def _explain(report: GateReport, name: str, bcell: Mapping[str, Any], cell: Mapping[str, Any]) -> None:
    """Notes on what changed under a cell whose values moved (its victim's weights, its attack's object)."""
    if not any(v.cell == name for v in report.moves):
        return
    if bcell.get("victim_weights_sha256") != CellResult(cell).config["victim"].get("weights_sha256"):
        report.notes.append(f"{name}: the victim's weights changed since the baseline")
    if bcell.get("attack_object_sha256") != _object_sha(cell):
        report.notes.append(f"{name}: the attack's object changed since the baseline")


def _label(metric: str) -> str:
    return {"bev": "BEV", "3d": "3D"}[metric]


def _fmt(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def _delta(value: Comparison) -> str:
    return "-" if value.delta is None else f"{value.delta:+.2f}"


def _verdict(report: GateReport, value: Comparison) -> str:
    return value.verdict + (" (allowed)" if report.allowed(value) else "")


def reason(value: Comparison) -> str:
    """One line naming the cell, the value and its numbers: ``CELL BEV AP moderate: baseline 64.00, now
    62.50, delta -1.50, tolerance 1.00: regression``."""
    return (f"{value.cell} {value.label}: baseline {_fmt(value.baseline)}, now {_fmt(value.now)}, delta "
            f"{_delta(value)}, tolerance {value.tolerance:.2f}: {value.verdict}")


def _counts(report: GateReport) -> dict[str, int]:
    failing = report.failing_moves
    return {"regressions": sum(m.verdict in ("regression", "vanished") for m in failing),
            "improvements": sum(m.verdict in ("improvement", "appeared") for m in failing),
            "allowed_improvements": sum(report.allowed(m) for m in report.moves),
            "problems": len(report.problems), "mismatches": len(report.mismatches)}


def _mismatch_kinds(report: GateReport) -> str:
    kinds = {"dataset": "another dataset", "protocol": "another evaluation protocol"}
    return " and ".join(dict.fromkeys(kinds[m.section] for m in report.mismatches))


def format_mismatch(report: GateReport, run_path: Path, baseline_path: Path) -> str:
    """The one block ``check`` prints for a run over another dataset or protocol: the differing fields."""
    lines = [f"check FAILED: {run_path} is not comparable with {baseline_path}: {_mismatch_kinds(report)}"]
    lines += [f"  {m.text()}" for m in report.mismatches]
    lines += [f"  note: {n}" for n in report.notes]
    lines.append("no cell was compared (every per-cell difference would follow from this): run on the baseline's "
                 "dataset and protocol (--data, --split, --max-frames, --seed), or record this run as the "
                 f"baseline with --write-baseline {baseline_path} --force")
    return "\n".join(lines)


def format_report(report: GateReport, run_path: Path, baseline_path: Path) -> str:
    """The per-cell diff table and the verdict, as printed by ``check`` (:func:`format_mismatch` alone
    for a run over another dataset or protocol)."""
    if not report.comparable:
        return format_mismatch(report, run_path, baseline_path)
    lines = []
    if report.moves:
        rows = [[m.cell, m.label, _fmt(m.baseline), _fmt(m.now), _delta(m), f"{m.tolerance:.2f}",
                 _verdict(report, m)] for m in report.moves]
        lines.append("values that moved past their tolerance (AP in %, R40, Car; drop in percentage points):")
        lines.append(format_table(["cell", "metric", "baseline", "now", "delta", "tolerance", "verdict"], rows,
                                  align="llrrrrl"))
    lines += [f"problem: {p}" for p in report.problems]
    lines += [f"note: {n}" for n in report.notes]
    head = (f"{run_path} against {baseline_path}: {report.compared_cells} cell(s), {report.compared_values} "
            "value(s) compared")
    counts = _counts(report)
    if report.ok:
        allowed = counts["allowed_improvements"]
        lines.append(f"check passed: {head}, none moved past its tolerance"
                     + (f" except {allowed} allowed improvement(s)" if allowed else ""))
    else:
        lines.append(f"check FAILED: {head}; {counts['regressions']} regression(s), {counts['improvements']} "
                     f"improvement(s) past tolerance, {counts['problems']} problem(s)")
        if counts["improvements"]:
            lines.append("an improvement past tolerance fails too (the baseline is stale): accept the new numbers "
                         f"with --write-baseline {baseline_path} --force, or pass --allow-improvements")
    return "\n".join(lines)


# ---- machine-readable results: --json, --junit ------------------------------------------------------

REPORT_FORMAT = "robustbench3d.check"
REPORT_VERSION = 1
JUNIT_SUITE = "robustbench3d check"


def _reasons(report: GateReport) -> list[str]:
    """Why the check failed, one line each (empty when it passed)."""
    if not report.comparable:
        return [f"{_mismatch_kinds(report)}: " + "; ".join(m.text() for m in report.mismatches)]
    return [*report.problems, *(reason(v) for v in report.failing_moves)]


def _value_record(report: GateReport, value: Comparison) -> dict[str, Any]:
    return {"quantity": value.quantity, "metric": value.metric, "difficulty": value.difficulty,
            "baseline": value.baseline, "current": value.now, "difference": value.delta,
            "tolerance": value.tolerance, "pass": not report.failing(value), "verdict": value.verdict}


def _cell_record(report: GateReport, cell: CellCheck) -> dict[str, Any]:
    values = [v for v in report.values if v.cell == cell.name]
    reasons = [cell.problem] if cell.problem else [reason(v) for v in values if report.failing(v)]
    return {"cell": cell.name, "victim": cell.cell[0], "attack": cell.cell[1], "proposals": cell.cell[2],
            "baseline_status": cell.status, "pass": not reasons, "problem": cell.problem,
            "values": [_value_record(report, v) for v in values], "reasons": reasons}


def report_record(report: GateReport, run_path: Path, baseline_path: Path) -> dict[str, Any]:
    """The ``--json`` record: the verdict, the tolerances, the dataset/protocol mismatch (if any: no cell
    is listed), and per cell every compared value (baseline, current, difference, tolerance, pass) and
    the reasons it failed. AP in percent (Car, R40); drops in percentage points."""
    return {"format": REPORT_FORMAT, "version": REPORT_VERSION,
            "verdict": "passed" if report.ok else "failed", "exit_status": 0 if report.ok else 1,
            "run": str(run_path), "baseline": str(baseline_path),
            "units": {"ap": f"percent ({CLASS}, {RECALL})", "drop": "percentage points (moderate AP drop)"},
            "tolerances": {"ap": report.tol_ap, "drop": report.tol_drop},
            "allow_improvements": report.allow_improvements, "comparable": report.comparable,
            "mismatch": [{"section": m.section, "field": m.field, "baseline": m.baseline, "run": m.run}
                         for m in report.mismatches],
            "counts": {"cells": report.compared_cells, "values": report.compared_values, **_counts(report)},
            "cells": [_cell_record(report, c) for c in report.cells],
            "notes": list(report.notes), "reasons": _reasons(report)}


@dataclass(frozen=True)
class _Case:
    classname: str
    name: str
    failure: tuple[str, str, str] | None  # (type, message, text)
    out: str = ""


def _failure(kind: str, lines: Sequence[str]) -> tuple[str, str, str] | None:
    return (kind, "; ".join(lines), "\n".join(lines)) if lines else None


def _dataset_case(report: GateReport) -> _Case:
    lines = [m.text() for m in report.mismatches]
    failure = _failure("mismatch", lines)
    if failure:
        failure = ("mismatch", f"{_mismatch_kinds(report)}: {failure[1]}; no cell was compared", failure[2])
    return _Case(JUNIT_SUITE, "dataset and evaluation protocol", failure, "\n".join(report.notes))


def _cell_cases(report: GateReport, cell: CellCheck) -> list[_Case]:
    """One testcase per metric (BEV, 3D: its AP easy/moderate/hard and moderate drop) of an ok baseline
    cell, one ``status`` testcase for a skipped one, one ``in baseline`` testcase for a cell only the run has."""
    if cell.status is None:
        return [_Case(cell.name, "in baseline", _failure("problem", [cell.problem or ""]))]
    if cell.status != "ok":
        return [_Case(cell.name, "status", _failure("problem", [cell.problem] if cell.problem else []),
                      f"{cell.status} in the baseline" + ("" if cell.problem else " and the run"))]
    cases = []
    for m in GATE_METRICS:
        values = [v for v in report.values if v.cell == cell.name and v.metric == m]
        failing = [v for v in values if report.failing(v)]
        kind = "problem" if cell.problem else (failing[0].verdict if failing else "")
        lines = [cell.problem] if cell.problem else [reason(v) for v in failing]
        out = "\n".join(reason(v) + (" (allowed)" if report.allowed(v) else "") for v in values)
        cases.append(_Case(cell.name, f"{_label(m)} AP and drop", _failure(kind, lines), out))
    return cases


def junit_xml(report: GateReport, run_path: Path, baseline_path: Path) -> str:
    """The ``--junit`` document: one testsuite; a ``dataset and evaluation protocol`` testcase, then (when
    that passes) one testcase per baseline cell and metric; a failure's message names the cell, the
    metric and the numbers."""
    import xml.etree.ElementTree as ET

    cases = [_dataset_case(report)]
    if report.comparable:
        cases += [case for cell in report.cells for case in _cell_cases(report, cell)]
    counts = {"tests": str(len(cases)), "failures": str(sum(c.failure is not None for c in cases)),
              "errors": "0", "skipped": "0"}
    root = ET.Element("testsuites", name=JUNIT_SUITE, **counts)
    suite = ET.SubElement(root, "testsuite", name=JUNIT_SUITE, **counts)
    props = ET.SubElement(suite, "properties")
    for key, value in (("run", run_path), ("baseline", baseline_path), ("tol_ap", report.tol_ap),
                       ("tol_drop", report.tol_drop), ("allow_improvements", report.allow_improvements),
                       ("verdict", "passed" if report.ok else "failed")):
        ET.SubElement(props, "property", name=key, value=str(value))
    for case in cases:
        node = ET.SubElement(suite, "testcase", classname=case.classname, name=case.name)
        if case.failure:
            kind, message, text = case.failure
            ET.SubElement(node, "failure", type=kind, message=message).text = text
        if case.out:
            ET.SubElement(node, "system-out").text = case.out
    ET.indent(root)
    return ET.tostring(root, encoding="unicode", xml_declaration=True) + "\n"


# ---- command ---------------------------------------------------------------------------------------


__all__ = ["FORMAT", "REPORT_FORMAT", "VERSION", "CellCheck", "Comparison", "GateReport", "Mismatch", "Move",
           "baseline_from_run", "compare", "format_mismatch", "format_report", "junit_xml", "read_baseline",
           "read_run", "reason", "report_record", "validate_baseline", "write_baseline", "write_record"]
