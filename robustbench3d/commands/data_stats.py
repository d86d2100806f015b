"""``robustbench3d data stats``: LiDAR and label statistics of KITTI-layout datasets, side by side
(:mod:`robustbench3d.dataset_stats`: what is measured and why).
"""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("roots", nargs="+", metavar="DIR", help="KITTI-layout dataset roots (first = reference)")
    parser.add_argument("--frames", type=int, default=50, help="frames per dataset (default 50; 0 = all)")
    parser.add_argument("--json", metavar="PATH", help="also write the statistics as JSON")


def run(args: argparse.Namespace) -> int:
    import json

    from robustbench3d.dataset_stats import dataset_statistics, format_comparison
    from robustbench3d.fileio import check_output_file

    if args.json:
        check_output_file(args.json, "--json")
    stats = [dataset_statistics(r, args.frames or None) for r in args.roots]
    print(format_comparison(stats))
    if args.json:
        from robustbench3d.fileio import atomic_write_text

        atomic_write_text(args.json, json.dumps(stats, indent=2) + "\n")
    return 0
