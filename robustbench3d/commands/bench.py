"""``robustbench3d bench``: speed and memory benchmarks that print a table (:data:`robustbench3d.bench.BENCHMARKS`).

Targets are checked here, in benchmarks, never as wall-clock asserts in unit tests.
"""

from __future__ import annotations

import argparse
import importlib
import json
import time

from robustbench3d.bench import BENCHMARKS, dict_table


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("names", nargs="*", metavar="NAME",
                        help=f"benchmarks to run (default: all of {', '.join(BENCHMARKS)})")
    parser.add_argument("--quick", action="store_true", help="smaller inputs, for a smoke run")
    parser.add_argument("--json", metavar="PATH", help="also write the rows as JSON")


def run(args: argparse.Namespace) -> int:
    from robustbench3d.errors import RobustBenchError
    from robustbench3d.fileio import check_output_file

    if args.json:
        check_output_file(args.json, "--json")
    names = args.names or list(BENCHMARKS)
    unknown = [n for n in names if n not in BENCHMARKS]
    if unknown:
        raise RobustBenchError(f"unknown benchmark {unknown[0]!r}; available: {', '.join(BENCHMARKS)}")
    all_rows: list[dict] = []
    for name in names:
        module, func = BENCHMARKS[name].split(":")
        t0 = time.perf_counter()
        rows = getattr(importlib.import_module(module), func)(quick=args.quick)
        print(f"== {name} ({time.perf_counter() - t0:.1f} s)")
        print(dict_table(rows))
        all_rows.extend({"benchmark": name, **r} for r in rows)
    if args.json:
        from robustbench3d.fileio import atomic_write_text

        atomic_write_text(args.json, json.dumps(all_rows, indent=2) + "\n")
    return 0
