"""``robustbench3d data synth``: generate the embedded procedural dataset in the KITTI layout.

Imports only the standard library at module level (numpy, embreex, ... load inside ``run``).
"""

from __future__ import annotations

import argparse

from robustbench3d.synth import DEFAULT_FRAMES, DEFAULT_SEED, DEFAULT_VAL_FRACTION

#: ``--val-fraction``: a share of the frames (0: every frame in train.txt, 1: every frame in val.txt).
VAL_FRACTION_RANGE = (0.0, 1.0)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from robustbench3d.ranges import FRAMES_RANGE, PROCESSES_RANGE, SEED_RANGE, default_processes

    parser.add_argument("--out", metavar="DIR",
                        help="output root (default: <cache>/datasets/synth, see ROBUSTBENCH3D_CACHE)")
    parser.add_argument("--frames", type=int, default=DEFAULT_FRAMES, metavar="N",
                        help=f"number of frames 000000..N-1, {FRAMES_RANGE[0]}..{FRAMES_RANGE[1]} "
                             f"(default {DEFAULT_FRAMES})")
    parser.add_argument("--seed", type=int, default=DEFAULT_SEED, metavar="S",
                        help=f"dataset seed, {SEED_RANGE[0]}..{SEED_RANGE[1]}; frame i depends only on (S, i) "
                             f"(default {DEFAULT_SEED})")
    parser.add_argument("--val-fraction", type=float, default=DEFAULT_VAL_FRACTION, metavar="F",
                        help=f"share of frames listed in ImageSets/val.txt, 0..1 (default {DEFAULT_VAL_FRACTION}; "
                             "the rest go to train.txt)")
    parser.add_argument("--workers", type=int, default=default_processes(), metavar="W",
                        help=f"parallel worker processes, {PROCESSES_RANGE[0]}..{PROCESSES_RANGE[1]} "
                             "(default: number of CPUs)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")


def check_numbers(args: argparse.Namespace) -> None:
    """Every numeric option in its range, before any work (one line naming the option and the range)."""
    from robustbench3d.ranges import FRAMES_RANGE, PROCESSES_RANGE, SEED_RANGE, check_range

    check_range("--frames", args.frames, *FRAMES_RANGE, "frames; KITTI frame ids have six digits")
    check_range("--seed", args.seed, *SEED_RANGE, "dataset seed")
    check_range("--val-fraction", args.val_fraction, *VAL_FRACTION_RANGE, "share of frames in val.txt",
                integer=False)
    check_range("--workers", args.workers, *PROCESSES_RANGE, "worker processes")


def run(args: argparse.Namespace) -> int:
    from robustbench3d.fileio import check_output_dir
    from robustbench3d.paths import dataset_dir
    from robustbench3d.synth.writer import generate_dataset

    out = check_output_dir(args.out if args.out else dataset_dir("synth"), "--out")
    check_numbers(args)
    report = generate_dataset(out, args.frames, args.seed, args.val_fraction, args.workers,
                              progress=not args.no_progress)
    rate = report.generated / report.seconds if report.generated and report.seconds > 0 else 0.0
    print(f"{report.root}: {report.frames} frames ({report.generated} generated, {report.skipped} already present"
          f"{f', {rate:.2f} frames/s' if rate else ''}); train {report.train}, val {report.val}")
    return 0
