"""``robustbench3d check``: the AP / AP-drop regression gate of a run against a recorded baseline.

    robustbench3d check RUN_DIR --write-baseline FILE [--force]
    robustbench3d check RUN_DIR --baseline FILE [--tol-ap X] [--tol-drop Y]

``--write-baseline`` writes a new FILE; an existing one is replaced only with ``--force`` (the command
says so), never when it is the summary being read. Tolerances are percentage points in
:data:`TOL_RANGE`.

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
status changed, or the dataset or protocol differs. Unreadable or malformed files exit 2
(:class:`~robustbench3d.errors.DataFormatError`, naming the file and field; a directory given as a
file, bad JSON with its line, a NaN or Infinity anywhere); a passing check exits 0.

Standard library only.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from robustbench3d.errors import DataFormatError, RobustBenchError
from robustbench3d.results import dumps, read_json, validate_summary
from robustbench3d.texttable import format_table

FORMAT = "robustbench3d.baseline"
VERSION = 1
CLASS, RECALL = "Car", "R40"
GATE_METRICS: tuple[str, ...] = ("bev", "3d")
DIFFICULTIES: tuple[str, ...] = ("easy", "moderate", "hard")
#: Dataset identity keys compared between the baseline and the run (``root`` is informational).
DATASET_KEYS: tuple[str, ...] = ("split", "frames", "split_frames", "sha256", "embedded")
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
    return (cell["victim"], cell["attack"], cell["proposals"])


def _name(cid: CellId) -> str:
    return "+".join(cid)


def _dataset(cell: Mapping[str, Any]) -> dict[str, Any]:
    return {k: cell["dataset"].get(k) for k in (*DATASET_KEYS, "root")}


def _protocol(cell: Mapping[str, Any]) -> dict[str, Any]:
    prov = cell["provenance"]
    overlap = (cell["metrics"] or {}).get("meta", {}).get("min_overlap", {}).get(CLASS, {})
    return {"class": CLASS, "recall": RECALL, "metrics": list(GATE_METRICS),
            "min_overlap": {m: overlap.get(m) for m in GATE_METRICS},
            "evaluation": prov["config"].get("evaluation"), "seed": prov["seed"]}


def _values(cell: Mapping[str, Any], path: Path, index: int) -> tuple[dict | None, dict | None]:
    """(AP table, moderate-drop table) of a summary cell (None where it has none)."""
    if cell["status"] != "ok":
        return None, None
    where = f"$[{index}].metrics.{CLASS}"
    table = cell["metrics"].get(CLASS)
    if table is None:
        raise DataFormatError(path, f"cell {_name(_cell_id(cell))} has no {CLASS} AP", field=where)
    ap: dict[str, dict[str, float]] = {}
    for m in GATE_METRICS:
        if m not in table:
            raise DataFormatError(path, f"cell {_name(_cell_id(cell))} has no {CLASS} {m} AP", field=f"{where}.{m}")
        ap[m] = {d: float(table[m][RECALL][d]) for d in DIFFICULTIES}
    effect = cell.get("attack_effect")
    drop = None
    if effect is not None:
        drop = {m: effect["drop"].get(CLASS, {}).get(m, {}).get(RECALL, {}).get("moderate") for m in GATE_METRICS}
    return ap, drop


def _object_sha(cell: Mapping[str, Any]) -> str | None:
    obj = cell["provenance"]["config"]["attack"].get("object") or {}
    inner = obj.get("object") if isinstance(obj, dict) else None
    return inner.get("ply_sha256") if isinstance(inner, dict) else None


def _common(cells: Sequence[Mapping[str, Any]], what: str, fn: Any, path: Path) -> dict[str, Any]:
    """``fn(cell)`` of the ok cells (or all cells), refusing a summary whose cells disagree."""
    ok = [c for c in cells if c["status"] == "ok"] or list(cells)
    first = fn(ok[0])
    for c in ok[1:]:
        if fn(c) != first:
            raise DataFormatError(path, f"cells {_name(_cell_id(ok[0]))} and {_name(_cell_id(c))} have different "
                                        f"{what}; a baseline covers one {what}")
    return first


def baseline_from_run(run: str | Path) -> dict[str, Any]:
    """The baseline record of a run (module doc). Refuses a run with ``error`` cells."""
    path, cells = read_run(run)
    failed = [_name(_cell_id(c)) for c in cells if c["status"] == "error"]
    if failed:
        raise RobustBenchError(f"{path}: cell(s) {', '.join(failed)} failed; a baseline records finished cells only")
    out_cells = []
    for i, cell in enumerate(cells):
        ap, drop = _values(cell, path, i)
        out_cells.append({"victim": cell["victim"], "attack": cell["attack"], "proposals": cell["proposals"],
                          "status": cell["status"], "ap": ap, "drop_moderate": drop,
                          "victim_weights_sha256": cell["provenance"]["config"]["victim"].get("weights_sha256"),
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
    _write_record(record, out)
    return record


def _write_record(record: dict[str, Any], out: str | Path) -> None:
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
    for key in ("class", "recall", "metrics", "min_overlap", "evaluation", "seed"):
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
class Move:
    """One value of one cell that moved past its tolerance."""

    cell: str
    metric: str
    baseline: float | None
    now: float | None
    tolerance: float
    verdict: str  # "regression" | "improvement" | "appeared" | "vanished"

    @property
    def delta(self) -> float | None:
        return None if self.baseline is None or self.now is None else self.now - self.baseline


@dataclass
class GateReport:
    """The outcome of :func:`compare`: moved values, structural problems and what was compared."""

    moves: list[Move] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    compared_cells: int = 0
    compared_values: int = 0
    allow_improvements: bool = False

    @property
    def failing_moves(self) -> list[Move]:
        return [m for m in self.moves if not (self.allow_improvements and m.verdict == "improvement")]

    @property
    def ok(self) -> bool:
        return not self.problems and not self.failing_moves


def _judge(cell: str, metric: str, base: float | None, now: float | None, tol: float,
           higher_is_better: bool) -> tuple[Move | None, bool]:
    """(the move, whether a value was compared) of one value."""
    if base is None and now is None:
        return None, False
    if base is None or now is None:
        return Move(cell, metric, base, now, tol, "appeared" if base is None else "vanished"), True
    delta = now - base
    if abs(delta) <= tol:
        return None, True
    better = delta > 0 if higher_is_better else delta < 0
    return Move(cell, metric, base, now, tol, "improvement" if better else "regression"), True


def _differences(base: Mapping[str, Any], now: Mapping[str, Any], keys: Sequence[str]) -> list[str]:
    return [f"{k} {base.get(k)!r} (run: {now.get(k)!r})" if k not in ("sha256", "evaluation") else f"{k} differs"
            for k in keys if base.get(k) != now.get(k)]


def compare(baseline: Mapping[str, Any], cells: Sequence[Mapping[str, Any]], run_path: Path,
            tol_ap: float = DEFAULT_TOL_AP, tol_drop: float = DEFAULT_TOL_DROP,
            allow_improvements: bool = False) -> GateReport:
    """Compare a run's summary cells with a baseline (module doc)."""
    report = GateReport(allow_improvements=allow_improvements)
    ds = _common(cells, "dataset", _dataset, run_path)
    diff = _differences(baseline["dataset"], ds, DATASET_KEYS)
    if diff:
        report.problems.append("another dataset: " + "; ".join(diff))
    proto = _common(cells, "evaluation protocol", _protocol, run_path)
    diff = _differences(baseline["protocol"], proto, ("class", "recall", "metrics", "min_overlap", "evaluation",
                                                        "seed"))
    if diff:
        report.problems.append("another evaluation protocol: " + "; ".join(diff))
    if baseline["dataset"].get("root") != ds.get("root"):
        report.notes.append(f"dataset root {ds.get('root')} (baseline: {baseline['dataset'].get('root')}); "
                            "same split, frames and labels")
    run_cells = {_cell_id(c): (i, c) for i, c in enumerate(cells)}
    base_ids = set()
    for bcell in baseline["cells"]:
        cid = (bcell["victim"], bcell["attack"], bcell["proposals"])
        base_ids.add(cid)
        name = _name(cid)
        if cid not in run_cells:
            report.problems.append(f"cell {name} is in the baseline but not in the run")
            continue
        i, cell = run_cells[cid]
        if cell["status"] != bcell["status"]:
            reason = f": {cell['reason']}" if cell.get("reason") else ""
            report.problems.append(f"cell {name} is {cell['status']} (baseline: {bcell['status']}){reason}")
            continue
        report.compared_cells += 1
        ap, drop = _values(cell, run_path, i)
        for m in GATE_METRICS if ap is not None else ():
            for d in DIFFICULTIES:
                move, counted = _judge(name, f"{_label(m)} AP {d}", bcell["ap"][m][d], ap[m][d], tol_ap, True)
                report.compared_values += counted
                if move:
                    report.moves.append(move)
        bdrop = bcell["drop_moderate"] or {}
        for m in GATE_METRICS:
            move, counted = _judge(name, f"{_label(m)} drop moderate", bdrop.get(m), (drop or {}).get(m), tol_drop,
                                   False)
            report.compared_values += counted
            if move:
                report.moves.append(move)
        moved = any(mv.cell == name for mv in report.moves)
        if moved and bcell.get("victim_weights_sha256") != cell["provenance"]["config"]["victim"].get("weights_sha256"):
            report.notes.append(f"{name}: the victim's weights changed since the baseline")
        if moved and bcell.get("attack_object_sha256") != _object_sha(cell):
            report.notes.append(f"{name}: the attack's object changed since the baseline")
    for cid in run_cells:
        if cid not in base_ids:
            report.problems.append(f"cell {_name(cid)} is in the run but not in the baseline")
    return report


def _label(metric: str) -> str:
    return {"bev": "BEV", "3d": "3D"}[metric]


def _fmt(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def format_report(report: GateReport, run_path: Path, baseline_path: Path) -> str:
    """The per-cell diff table and the verdict, as printed by ``check``."""
    lines = []
    if report.moves:
        rows = [[m.cell, m.metric, _fmt(m.baseline), _fmt(m.now),
                 "-" if m.delta is None else f"{m.delta:+.2f}", f"{m.tolerance:.2f}",
                 m.verdict + (" (allowed)" if m not in report.failing_moves else "")] for m in report.moves]
        lines.append("values that moved past their tolerance (AP in %, R40, Car; drop in percentage points):")
        lines.append(format_table(["cell", "metric", "baseline", "now", "delta", "tolerance", "verdict"], rows,
                                  align="llrrrrl"))
    lines += [f"problem: {p}" for p in report.problems]
    lines += [f"note: {n}" for n in report.notes]
    head = (f"{run_path} against {baseline_path}: {report.compared_cells} cell(s), {report.compared_values} "
            "value(s) compared")
    if report.ok:
        allowed = len(report.moves)
        lines.append(f"check passed: {head}, none moved past its tolerance"
                     + (f" except {allowed} allowed improvement(s)" if allowed else ""))
    else:
        regressions = sum(m.verdict in ("regression", "vanished") for m in report.failing_moves)
        improvements = sum(m.verdict in ("improvement", "appeared") for m in report.failing_moves)
        lines.append(f"check FAILED: {head}; {regressions} regression(s), {improvements} improvement(s) past "
                     f"tolerance, {len(report.problems)} problem(s)")
        if improvements:
            lines.append("an improvement past tolerance fails too (the baseline is stale): accept the new numbers "
                         f"with --write-baseline {baseline_path} --force, or pass --allow-improvements")
    return "\n".join(lines)


# ---- command ---------------------------------------------------------------------------------------

def _tolerance(text: str) -> float:
    """A tolerance in percentage points, within :data:`TOL_RANGE` (argparse names the option)."""
    lo, hi = TOL_RANGE
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of percentage points in [{lo:g}, {hi:g}], "
                                         f"got {text!r}") from None
    if not math.isfinite(value) or not lo <= value <= hi:
        raise argparse.ArgumentTypeError(f"expected a number of percentage points in [{lo:g}, {hi:g}], got {text!r}")
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run_dir", metavar="RUN_DIR", help="a run's output directory (its summary.json), or a "
                                                           "summary.json")
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("--baseline", metavar="FILE", help="compare the run with this baseline; exit 1 on a move")
    group.add_argument("--write-baseline", metavar="FILE", help="record the run's numbers as a baseline (a new file "
                                                                "unless --force)")
    parser.add_argument("--force", action="store_true", help="let --write-baseline replace an existing FILE")
    lo, hi = TOL_RANGE
    parser.add_argument("--tol-ap", type=_tolerance, default=DEFAULT_TOL_AP, metavar="X",
                        help=f"tolerance of every AP, percentage points in [{lo:g}, {hi:g}] (default {DEFAULT_TOL_AP})")
    parser.add_argument("--tol-drop", type=_tolerance, default=DEFAULT_TOL_DROP, metavar="Y",
                        help=f"tolerance of every moderate AP drop, percentage points in [{lo:g}, {hi:g}] "
                             f"(default {DEFAULT_TOL_DROP})")
    parser.add_argument("--allow-improvements", action="store_true",
                        help="do not fail on a higher AP or a smaller drop past tolerance (they are still listed)")


def _baseline_output(run_dir: str, out: str, force: bool) -> Path:
    """``--write-baseline FILE`` checked before any work: writable, new unless ``force``, and not the
    summary being read (which ``--force`` would otherwise replace)."""
    from robustbench3d.fileio import check_output_file

    path = check_output_file(out, "--write-baseline", force=force)
    summary = summary_path(run_dir)
    if path.exists() and summary.exists() and path.resolve() == summary.resolve():
        raise RobustBenchError(f"--write-baseline {path}: is the run's summary being read; choose another file "
                               "(nothing was written)")
    return path


def run(args: argparse.Namespace) -> int:
    if args.write_baseline is not None:
        from robustbench3d.fileio import replacing_note

        out = _baseline_output(args.run_dir, args.write_baseline, args.force)
        record = baseline_from_run(args.run_dir)  # before the note: a refused run replaces nothing
        note = replacing_note(out)
        if note:
            print(note)
        _write_record(record, out)
        print(f"baseline: {out} ({len(record['cells'])} cells of {record['source']['summary']})")
        return 0
    if args.force:
        raise RobustBenchError("--force: applies to --write-baseline only (check --baseline writes no file)")
    baseline_path = Path(args.baseline)
    baseline = read_baseline(baseline_path)
    run_path, cells = read_run(args.run_dir)
    report = compare(baseline, cells, run_path, args.tol_ap, args.tol_drop, args.allow_improvements)
    print(format_report(report, run_path, baseline_path), file=sys.stdout)
    return 0 if report.ok else 1


__all__ = ["FORMAT", "VERSION", "GateReport", "Move", "baseline_from_run", "compare", "format_report",
           "read_baseline", "read_run", "validate_baseline", "write_baseline"]
