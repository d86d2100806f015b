"""``robustbench3d tradeoff``: the harness's speed/accuracy trade, measured on one machine in one run.

Standard library only at module level (numpy, torch and the registries load inside :func:`run`).
"""

from __future__ import annotations

import argparse
import sys


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from robustbench3d.tradeoff.sweeps import SWEEP_NAMES

    parser.add_argument("--out", required=True, metavar="DIR",
                        help="output directory (tradeoff.json/.csv/.md/.png; cells/ for resuming)")
    parser.add_argument("--victim", default="fpointnet-v1-lite", help="registered victim (default fpointnet-v1-lite)")
    parser.add_argument("--attack", default="adv-object", help="registered attack scored with the clean control "
                                                                "(default adv-object)")
    parser.add_argument("--proposals", default="detector", choices=("detector", "gt"),
                        help="2D proposal source (default detector)")
    parser.add_argument("--frames", type=int, default=50, metavar="N",
                        help="evaluate the first N frames of the split (default 50)")
    parser.add_argument("--data", default=None, metavar="DIR", help="KITTI-layout dataset (default: embedded)")
    parser.add_argument("--split", default="val", help="split (default val)")
    parser.add_argument("--sweeps", default=",".join(SWEEP_NAMES), metavar="A,B",
                        help=f"sweeps to run (default all: {','.join(SWEEP_NAMES)})")
    parser.add_argument("--metric", default="bev", choices=("bev", "3d"), help="AP scored (moderate, R40)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads while timing (default 1)")
    parser.add_argument("--resamples", type=int, default=1000, help="bootstrap resamples (default 1000)")
    parser.add_argument("--tolerance", type=float, default=1.0, metavar="AP",
                        help="|ΔAP| of the 'fastest within tolerance' table (default 1.0 point)")
    parser.add_argument("--seed", type=int, default=0, help="attack and bootstrap seed (default 0)")
    parser.add_argument("--batch-size", type=int, default=4, help="frames per detect call (default 4)")
    parser.add_argument("--no-progress", action="store_true", help="no per-cell lines on stderr")


def run(args: argparse.Namespace) -> int:
    from robustbench3d.errors import RobustBenchError

    for name, value, low in (("--frames", args.frames, 1), ("--threads", args.threads, 1),
                             ("--resamples", args.resamples, 1), ("--batch-size", args.batch_size, 1),
                             ("--seed", args.seed, 0)):
        if value < low:
            raise RobustBenchError(f"{name} must be at least {low}, got {value}")
    if not args.tolerance >= 0:
        raise RobustBenchError(f"--tolerance must be >= 0, got {args.tolerance}")
    from pathlib import Path

    from robustbench3d.fileio import check_output_dir
    from robustbench3d.tradeoff.run import TradeoffConfig, run_tradeoff

    def log(line: str) -> None:
        if not args.no_progress:
            print(line, file=sys.stderr, flush=True)

    cfg = TradeoffConfig(victim=args.victim, attack=args.attack, proposals=args.proposals, frames=args.frames,
                         data=None if args.data is None else Path(args.data), split=args.split,
                         sweeps=tuple(s.strip() for s in args.sweeps.split(",") if s.strip()), metric=args.metric,
                         threads=args.threads, resamples=args.resamples, tolerance=args.tolerance, seed=args.seed,
                         batch_size=args.batch_size)
    out = check_output_dir(args.out, "--out")
    paths = run_tradeoff(cfg, out, log)
    print((out / "tradeoff.md").read_text(encoding="utf-8"))
    print("tradeoff: wrote " + ", ".join(str(p) for p in paths))
    return 0
