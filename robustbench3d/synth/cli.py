"""``robustbench3d data synth``: generate the embedded procedural dataset in the KITTI layout.

Imports only the standard library at module level (numpy, embreex, ... load inside ``run``).
"""

from __future__ import annotations

import argparse
import os

from robustbench3d.synth import DEFAULT_FRAMES, DEFAULT_SEED, DEFAULT_VAL_FRACTION


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", metavar="DIR",
                        help="output root (default: <cache>/datasets/synth, see ROBUSTBENCH3D_CACHE)")
    parser.add_argument("--frames", type=int, default=DEFAULT_FRAMES, metavar="N",
                        help=f"number of frames 000000..N-1 (default {DEFAULT_FRAMES})")
    parser.add_argument("--seed", type=int, default=DEFAULT_SEED, metavar="S",
                        help=f"dataset seed; frame i depends only on (S, i) (default {DEFAULT_SEED})")
    parser.add_argument("--val-fraction", type=float, default=DEFAULT_VAL_FRACTION, metavar="F",
                        help=f"share of frames listed in ImageSets/val.txt (default {DEFAULT_VAL_FRACTION}; "
                             "the rest go to train.txt)")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1, metavar="W",
                        help="parallel worker processes (default: number of CPUs)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")


def run(args: argparse.Namespace) -> int:
    from robustbench3d.fileio import check_output_dir
    from robustbench3d.paths import dataset_dir
    from robustbench3d.synth.writer import generate_dataset

    out = check_output_dir(args.out if args.out else dataset_dir("synth"), "--out")
    report = generate_dataset(out, args.frames, args.seed, args.val_fraction, args.workers,
                              progress=not args.no_progress)
    rate = report.generated / report.seconds if report.generated and report.seconds > 0 else 0.0
    print(f"{report.root}: {report.frames} frames ({report.generated} generated, {report.skipped} already present"
          f"{f', {rate:.2f} frames/s' if rate else ''}); train {report.train}, val {report.val}")
    return 0
