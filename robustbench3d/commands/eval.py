"""``robustbench3d eval``: score KITTI result files against ground-truth labels.

Standard library only at module level (numpy is imported inside :func:`run`).
"""

from __future__ import annotations

import argparse

from robustbench3d.eval.rules import CLASSES, METRICS


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--gt", required=True, metavar="DIR", help="ground-truth label directory (label_2)")
    parser.add_argument("--pred", required=True, metavar="DIR",
                        help="result directory (16-column files; a frame without a file has no detections)")
    parser.add_argument("--split", metavar="FILE", help="frame ids to evaluate (default: every GT label file)")
    parser.add_argument("--classes", metavar="LIST",
                        help=f"comma-separated subset of {','.join(CLASSES)} "
                             "(default: every class with a detection, as the devkit; Car if none)")
    parser.add_argument("--metrics", metavar="LIST", default=",".join(METRICS),
                        help=f"comma-separated subset of {','.join(METRICS)} (default: all)")
    parser.add_argument("--json", metavar="PATH", help="also write the result as JSON (atomically)")


def _split_list(text: str | None) -> list[str] | None:
    return None if text is None else [t.strip() for t in text.split(",") if t.strip()]


def run(args: argparse.Namespace) -> int:
    from robustbench3d.errors import RobustBenchError
    from robustbench3d.eval.rules import normalise_names
    from robustbench3d.fileio import check_output_file

    if args.json:
        check_output_file(args.json, "--json")
    classes = _split_list(args.classes)
    try:
        if classes is not None:
            classes = list(normalise_names(classes, CLASSES, "class"))
        metrics = list(normalise_names(_split_list(args.metrics) or [], METRICS, "metric"))
    except ValueError as exc:
        raise RobustBenchError(str(exc)) from None

    from robustbench3d.eval.kitti_eval import evaluate_dirs
    from robustbench3d.eval.report import ap_table, write_json

    result = evaluate_dirs(args.gt, args.pred, args.split, classes=classes, metrics=metrics)
    print(ap_table(result))
    if args.json:
        write_json(args.json, result)
    return 0
