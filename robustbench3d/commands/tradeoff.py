"""``robustbench3d tradeoff``: the harness's speed/accuracy trade, measured on one machine in one run.

Standard library only at module level (numpy, torch and the registries load inside :func:`run`).
"""

from __future__ import annotations

import argparse
import os
import sys

#: ``--tolerance``: AP points, and AP is a percentage (0..100), so any larger tolerance accepts every point.
TOLERANCE_RANGE = (0.0, 100.0)


def threads_range() -> tuple[int, int]:
    """``--threads``: 1 to this machine's CPUs; more torch threads than cores oversubscribe them and the
    timings measure the contention, not the setting."""
    return 1, os.cpu_count() or 1


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from robustbench3d.ranges import BATCH_RANGE, FRAMES_RANGE, RESAMPLES_RANGE, SEED_RANGE
    from robustbench3d.tradeoff.sweeps import SWEEP_NAMES
    from robustbench3d.victims.spec import PROPOSAL_SOURCES, describe_sources

    parser.add_argument("--out", required=True, metavar="DIR",
                        help="output directory (tradeoff.json/.csv/.md/.png; cells/ for resuming): new, empty, or "
                             "a tradeoff of the same configuration (resumed); see --force")
    parser.add_argument("--force", action="store_true",
                        help="write into an --out that is not a tradeoff directory, or replace a tradeoff (and "
                             "cells) of another configuration there; each replacement is named")
    parser.add_argument("--victim", default="fpointnet-v1-lite", help="registered victim (default fpointnet-v1-lite)")
    parser.add_argument("--attack", default="adv-object", help="registered attack scored with the clean control "
                                                                "(default adv-object)")
    parser.add_argument("--proposals", default="detector", choices=PROPOSAL_SOURCES,
                        help=f"2D proposal source, one of {describe_sources()} (default detector)")
    parser.add_argument("--frames", type=int, default=50, metavar="N",
                        help=f"evaluate the first N frames of the split, {FRAMES_RANGE[0]}..{FRAMES_RANGE[1]} "
                             "(default 50)")
    parser.add_argument("--data", default=None, metavar="DIR", help="KITTI-layout dataset (default: embedded)")
    parser.add_argument("--split", default="val", help="split (default val)")
    parser.add_argument("--sweeps", default=",".join(SWEEP_NAMES), metavar="A,B",
                        help=f"sweeps to run (default all: {','.join(SWEEP_NAMES)})")
    parser.add_argument("--metric", default="bev", choices=("bev", "3d"), help="AP scored (moderate, R40)")
    parser.add_argument("--threads", type=int, default=1,
                        help=f"torch threads while timing, 1..CPUs ({threads_range()[1]} here; default 1)")
    parser.add_argument("--resamples", type=int, default=1000,
                        help=f"bootstrap resamples, {RESAMPLES_RANGE[0]}..{RESAMPLES_RANGE[1]} (default 1000)")
    parser.add_argument("--tolerance", type=float, default=1.0, metavar="AP",
                        help="|ΔAP| of the 'fastest within tolerance' table, "
                             f"{TOLERANCE_RANGE[0]:g}..{TOLERANCE_RANGE[1]:g} (default 1.0 point)")
    parser.add_argument("--seed", type=int, default=0,
                        help=f"attack and bootstrap seed, {SEED_RANGE[0]}..{SEED_RANGE[1]} (default 0)")
    parser.add_argument("--batch-size", type=int, default=4,
                        help=f"frames per detect call, {BATCH_RANGE[0]}..{BATCH_RANGE[1]} (default 4)")
    parser.add_argument("--no-progress", action="store_true", help="no per-cell lines on stderr")


def check_numbers(args: argparse.Namespace) -> None:
    """Every numeric option in its range, before any work (one line naming the option and the range)."""
    from robustbench3d.ranges import BATCH_RANGE, FRAMES_RANGE, RESAMPLES_RANGE, SEED_RANGE, check_range

    check_range("--frames", args.frames, *FRAMES_RANGE, "frames")
    check_range("--threads", args.threads, *threads_range(), "torch threads, at most this machine's CPUs")
    check_range("--resamples", args.resamples, *RESAMPLES_RANGE, "bootstrap resamples")
    check_range("--tolerance", args.tolerance, *TOLERANCE_RANGE, "AP points", integer=False)
    check_range("--seed", args.seed, *SEED_RANGE, "attack and bootstrap seed")
    check_range("--batch-size", args.batch_size, *BATCH_RANGE, "frames per detect call")


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from robustbench3d.fileio import check_output_dir, remove_created_dir
    from robustbench3d.tradeoff.outdir import check_out_dir
    from robustbench3d.tradeoff.run import TradeoffConfig, run_tradeoff

    out = check_output_dir(args.out, "--out")
    check_numbers(args)

    def log(line: str) -> None:
        if not args.no_progress:
            print(line, file=sys.stderr, flush=True)

    def say(line: str) -> None:  # what was kept or replaced: printed with --no-progress too
        print(line, file=sys.stderr, flush=True)

    cfg = TradeoffConfig(victim=args.victim, attack=args.attack, proposals=args.proposals, frames=args.frames,
                         data=None if args.data is None else Path(args.data), split=args.split,
                         sweeps=tuple(s.strip() for s in args.sweeps.split(",") if s.strip()), metric=args.metric,
                         threads=args.threads, resamples=args.resamples, tolerance=args.tolerance, seed=args.seed,
                         batch_size=args.batch_size)
    check_out_dir(out, cfg.as_dict(), args.force, say)
    created = not out.exists()
    try:
        paths = run_tradeoff(cfg, out, log, force=args.force, say=say)
    except BaseException:
        if created:  # a run that failed before measuring any cell leaves no directory behind
            remove_created_dir(out)
        raise
    print((out / "tradeoff.md").read_text(encoding="utf-8"))
    print("tradeoff: wrote " + ", ".join(str(p) for p in paths))
    return 0
