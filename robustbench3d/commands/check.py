"""``robustbench3d check``: the AP / AP-drop regression gate of a run against a recorded baseline
(the baseline format and the rules: :mod:`robustbench3d.gate`).

    robustbench3d check RUN_DIR --write-baseline FILE [--force]
    robustbench3d check RUN_DIR --baseline FILE [--tol-ap X] [--tol-drop Y] [--json PATH] [--junit PATH] [--force]

``--write-baseline``, ``--json`` and ``--junit`` write new files; an existing one is replaced only with
``--force`` (the command says so), never when it is a file being read. Tolerances are percentage points
in :data:`~robustbench3d.gate.TOL_RANGE`. ``--json`` writes :func:`~robustbench3d.gate.report_record`,
``--junit`` :func:`~robustbench3d.gate.junit_xml`. Exit 1 on a move past tolerance, 2 on a malformed file.

Standard library only.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence
from pathlib import Path

from robustbench3d.errors import RobustBenchError
from robustbench3d.gate import (
    DEFAULT_TOL_AP,
    DEFAULT_TOL_DROP,
    TOL_RANGE,
    GateReport,
    baseline_from_run,
    compare,
    format_report,
    junit_xml,
    read_baseline,
    read_run,
    report_record,
    summary_path,
    write_record,
)
from robustbench3d.results import dumps


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
    parser.add_argument("--json", metavar="PATH", help="with --baseline: also write the verdict and every compared "
                                                       "value as JSON (a new file unless --force)")
    parser.add_argument("--junit", metavar="PATH", help="with --baseline: also write JUnit XML, one testcase per "
                                                        "cell and metric (a new file unless --force)")
    parser.add_argument("--force", action="store_true", help="let --write-baseline, --json or --junit replace an "
                                                             "existing file")
    lo, hi = TOL_RANGE
    parser.add_argument("--tol-ap", type=_tolerance, default=DEFAULT_TOL_AP, metavar="X",
                        help=f"tolerance of every AP, percentage points in [{lo:g}, {hi:g}] (default {DEFAULT_TOL_AP})")
    parser.add_argument("--tol-drop", type=_tolerance, default=DEFAULT_TOL_DROP, metavar="Y",
                        help=f"tolerance of every moderate AP drop, percentage points in [{lo:g}, {hi:g}] "
                             f"(default {DEFAULT_TOL_DROP})")
    parser.add_argument("--allow-improvements", action="store_true",
                        help="do not fail on a higher AP or a smaller drop past tolerance (they are still listed)")


def _same_file(a: Path, b: Path) -> bool:
    return a.resolve() == b.resolve()


def _baseline_output(run_dir: str, out: str, force: bool) -> Path:
    """``--write-baseline FILE`` checked before any work: writable, new unless ``force``, and not the
    summary being read (which ``--force`` would otherwise replace)."""
    from robustbench3d.fileio import check_output_file

    path = check_output_file(out, "--write-baseline", force=force)
    summary = summary_path(run_dir)
    if path.exists() and summary.exists() and _same_file(path, summary):
        raise RobustBenchError(f"--write-baseline {path}: is the run's summary being read; choose another file "
                               "(nothing was written)")
    return path


def _report_outputs(args: argparse.Namespace) -> list[tuple[str, Path]]:
    """``--json`` / ``--junit`` checked before any work: writable, new unless ``--force``, and none of the
    files read nor each other."""
    from robustbench3d.fileio import check_output_file

    taken = [(Path(args.baseline), "the baseline being read"), (summary_path(args.run_dir), "the run's summary")]
    outputs = []
    for flag, value in (("--json", args.json), ("--junit", args.junit)):
        if value is None:
            continue
        path = check_output_file(value, flag, force=args.force)
        for other, what in taken:
            if _same_file(path, other):
                raise RobustBenchError(f"{flag} {path}: is {what}; choose another file (nothing was written)")
        taken.append((path, f"the {flag} file"))
        outputs.append((flag, path))
    return outputs


def _write_baseline_command(args: argparse.Namespace) -> int:
    from robustbench3d.fileio import replacing_note

    for flag, value in (("--json", args.json), ("--junit", args.junit)):
        if value is not None:
            raise RobustBenchError(f"{flag}: applies to --baseline only (--write-baseline compares nothing)")
    out = _baseline_output(args.run_dir, args.write_baseline, args.force)
    record = baseline_from_run(args.run_dir)  # before the note: a refused run replaces nothing
    note = replacing_note(out)
    if note:
        print(note)
    write_record(record, out)
    print(f"baseline: {out} ({len(record['cells'])} cells of {record['source']['summary']})")
    return 0


def _write_outputs(outputs: Sequence[tuple[str, Path]], report: GateReport, run_path: Path,
                   baseline_path: Path) -> None:
    from robustbench3d.fileio import atomic_write_text, replacing_note

    for flag, path in outputs:
        if flag == "--json":
            text, what = dumps(report_record(report, run_path, baseline_path)), "JSON"
        else:
            text, what = junit_xml(report, run_path, baseline_path), "JUnit XML"
        note = replacing_note(path)
        if note:
            print(note)
        atomic_write_text(path, text)
        print(f"wrote {path} ({what})")


def run(args: argparse.Namespace) -> int:
    if args.write_baseline is not None:
        return _write_baseline_command(args)
    outputs = _report_outputs(args)
    if args.force and not outputs:
        raise RobustBenchError("--force: applies to --write-baseline only, or to the --json/--junit files of "
                               "--baseline (this check writes no file)")
    baseline_path = Path(args.baseline)
    baseline = read_baseline(baseline_path)
    run_path, cells = read_run(args.run_dir)
    report = compare(baseline, cells, run_path, args.tol_ap, args.tol_drop, args.allow_improvements)
    print(format_report(report, run_path, baseline_path), file=sys.stdout)
    _write_outputs(outputs, report, run_path, baseline_path)
    return 0 if report.ok else 1
