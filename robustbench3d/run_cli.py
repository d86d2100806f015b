"""``robustbench3d run``: every victim x attack x proposal-source cell on one dataset split.

Standard library only at module level (numpy and the registries load inside :func:`run`).
"""

from __future__ import annotations

import argparse
import json
import os
from typing import Any


def _names(text: str) -> list[str]:
    return [t.strip() for t in text.split(",") if t.strip()]


def parse_factory_args(items: list[str] | None, option: str) -> dict[str, dict[str, Any]]:
    """``["NAME:KEY=VALUE", ...]`` -> ``{NAME: {KEY: VALUE}}``; VALUE is parsed as JSON when it is
    valid JSON (numbers, true/false, null, lists), else kept as a string (paths)."""
    from robustbench3d.errors import RobustBenchError

    out: dict[str, dict[str, Any]] = {}
    for item in items or []:
        name, sep, assignment = item.partition(":")
        key, eq, raw = assignment.partition("=")
        if not sep or not eq or not name.strip() or not key.strip():
            raise RobustBenchError(f"{option} {item!r}: expected NAME:KEY=VALUE (e.g. fpointnet-v1:weights=cascade.pt)")
        try:
            value: Any = json.loads(raw)
        except json.JSONDecodeError:
            value = raw
        out.setdefault(name.strip(), {})[key.strip()] = value
    return out


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--victims", required=True, metavar="NAME[,NAME...]",
                        help="registered victims, or ONNX victim directories (registered under their directory name)")
    parser.add_argument("--attacks", default="none", metavar="NAME[,NAME...]",
                        help="registered attacks, or object files NAME.ply (registered under NAME) "
                             "(default: none, the clean control)")
    parser.add_argument("--proposals", default="detector", metavar="SRC[,SRC...]",
                        help="2D proposal sources: detector (the victim's own) and/or gt (ground-truth boxes); "
                             "a victim that does not support a source gets a skipped cell (default: detector)")
    parser.add_argument("--out", required=True, metavar="DIR",
                        help="output directory (cell files, summary.json, results.csv, seed_table.md); "
                             "an interrupted run resumes")
    parser.add_argument("--data", metavar="DIR",
                        help="KITTI-layout dataset root (default: the embedded procedural dataset in the cache, "
                             "generated if missing)")
    parser.add_argument("--split", default="val", help="split name, ImageSets/<split>.txt (default: val)")
    parser.add_argument("--max-frames", type=int, metavar="N", help="evaluate only the first N frames of the split")
    parser.add_argument("--seed", type=int, default=0, metavar="S",
                        help="run seed: attack randomness per frame, and seed= of victims that take one (default 0)")
    parser.add_argument("--batch-size", type=int, default=4, metavar="B", help="frames per detect call (default 4)")
    parser.add_argument("--victim-arg", action="append", metavar="NAME:KEY=VALUE",
                        help="keyword argument of a victim's factory, e.g. fpointnet-v1:weights=cascade.pt "
                             "(repeatable; VALUE is JSON or a string)")
    parser.add_argument("--attack-arg", action="append", metavar="NAME:KEY=VALUE",
                        help="keyword argument of an attack's factory (repeatable)")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1, metavar="W",
                        help="processes generating the embedded dataset if it is missing (default: CPUs)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars on stderr")


def run(args: argparse.Namespace) -> int:
    import sys

    from robustbench3d.attacks.controls import resolve_attack_references
    from robustbench3d.fileio import check_output_dir, remove_created_dir
    from robustbench3d.runner import RunConfig, run_benchmark, summary_table
    from robustbench3d.seed_table import SEED_TABLE_FILE, seed_table_text
    from robustbench3d.victims import resolve_victim_references

    out = check_output_dir(args.out, "--out")
    created = not out.exists()

    victims, victim_args = resolve_victim_references(_names(args.victims),
                                                     parse_factory_args(args.victim_arg, "--victim-arg"))
    attacks, attack_args = resolve_attack_references(_names(args.attacks),
                                                     parse_factory_args(args.attack_arg, "--attack-arg"))
    config = RunConfig(
        victims=tuple(victims), attacks=tuple(attacks),
        proposals=tuple(_names(args.proposals)), out=args.out, data=args.data, split=args.split,
        max_frames=args.max_frames, seed=args.seed, batch_size=args.batch_size,
        victim_args=victim_args,
        attack_args=attack_args,
        workers=args.workers, progress=not args.no_progress,
    )
    try:
        report = run_benchmark(config)
    except BaseException:
        if created:  # a run that failed before writing any result leaves no directory behind
            remove_created_dir(out)
        raise
    print(summary_table(report.summary))
    print(f"results: {report.out / 'summary.json'}, {report.out / 'results.csv'}")
    if report.earlier or report.left_out:
        print(f"{len(report.earlier)} of these cells come from earlier runs into {report.out}; "
              f"{len(report.left_out)} cell(s) there are left out (not comparable with this run, listed above)")
    print()
    print(seed_table_text(report.summary))
    print(f"seed table: {report.out / SEED_TABLE_FILE}")
    if report.failed:
        print(f"robustbench3d: {len(report.failed)} of {len(report.outcomes)} cells failed", file=sys.stderr)
        return 1
    return 0
