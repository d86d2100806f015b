"""``robustbench3d report RUN_DIR [RUN_DIR ...] --out DIR``: a leaderboard a person reads (the files and their
content: :mod:`robustbench3d.report.build`).

``DIR`` must be new, empty or an earlier report's: a report there is replaced (one line says so), any other
non-empty directory is refused unless ``--force`` (:mod:`robustbench3d.report.outdir`). Options, ``DIR`` and
the input files are checked before any work; nothing is written until every figure is made.

Standard library only at module level.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from robustbench3d.report.build import SCENES_RANGE


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("runs", nargs="*", metavar="RUN_DIR", help="output directories of `robustbench3d run`")
    parser.add_argument("--tradeoff", action="append", default=[], metavar="DIR",
                        help="output directory of `robustbench3d tradeoff`: its Pareto table and figure become a "
                             "section (repeatable)")
    parser.add_argument("--sweep", action="append", default=[], metavar="DIR",
                        help="output directory of `robustbench3d sweep`: its dose-response figure and table become a "
                             "section (repeatable)")
    parser.add_argument("--out", required=True, metavar="DIR", help="directory to write the report into")
    parser.add_argument("--strict", action="store_true",
                        help="refuse runs that are not comparable instead of separating them into sections")
    parser.add_argument("--scenes", type=int, default=3, metavar="N",
                        help="scene figures per section: the N attacked cells with the largest relative drop, one "
                             f"per attack, each on its worst frame ({SCENES_RANGE[0]}..{SCENES_RANGE[1]}; default 3; "
                             "0: none)")
    parser.add_argument("--force", action="store_true",
                        help="write into a non-empty --out directory that holds no earlier report, replacing the "
                             "files of the same names (each named in one line); an earlier report is replaced "
                             "without it")
    parser.add_argument("--title", default="robustbench3d leaderboard", help="page title")


def run(args: argparse.Namespace) -> int:
    from robustbench3d.errors import RobustBenchError
    from robustbench3d.report.build import HTML_FILE, MD_FILE, build, check_scenes, contents
    from robustbench3d.report.outdir import check_out_dir, plan_writes, write_report
    from robustbench3d.report.sweep_view import SweepView
    from robustbench3d.report.tradeoff_view import TradeoffView

    check_scenes(args.scenes)
    if not args.runs and not args.tradeoff and not args.sweep:
        raise RobustBenchError("give at least one RUN_DIR, --tradeoff DIR or --sweep DIR")
    out = check_out_dir(args.out, args.force)
    trades = [TradeoffView.read(p) for p in args.tradeoff]  # bad files fail before any work
    sweeps = [SweepView.read(p) for p in args.sweep]
    views, notes = build(args.runs, args.scenes, args.strict) if args.runs else ([], [])
    runs = [str(Path(r)) for r in [*args.runs, *args.tradeoff, *args.sweep]]
    files = contents(views, trades, runs, args.title, notes, sweeps)
    for line in plan_writes(out, list(files)):
        print(f"report: {line}")
    write_report(out, files)
    for note in notes:
        print(f"report: {note}")
    print(f"report: {out.path / HTML_FILE}, {out.path / MD_FILE} ({len(views)} section(s))")
    return 0
