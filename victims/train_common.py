"""Arguments shared by ``robustbench3d victims train-yolo|train-fpointnet`` (standard library only)."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_common_arguments(parser: argparse.ArgumentParser, epochs: int, batch_size: int) -> None:
    parser.add_argument("--data", type=Path, required=True, help="dataset root in the KITTI layout")
    parser.add_argument("--out", type=Path, required=True, help="output directory (checkpoints, model.pt, log)")
    parser.add_argument("--epochs", type=int, default=epochs, help=f"number of epochs (default {epochs})")
    parser.add_argument("--batch-size", type=int, default=batch_size, help=f"batch size (default {batch_size})")
    parser.add_argument("--seed", type=int, default=0, help="seed of every random choice (default 0)")
    parser.add_argument("--resume", action="store_true", help="continue from OUT/last.pt if present")
    parser.add_argument("--lr", type=float, default=None, help="base learning rate (default per model)")
    parser.add_argument("--train-split", default="train", help="ImageSets list used for training")
    parser.add_argument("--val-split", default="val", help="ImageSets list used for validation")
    parser.add_argument("--checkpoint-every", type=int, default=0, metavar="STEPS",
                        help="also checkpoint every STEPS optimizer steps (default: epoch ends only)")
    parser.add_argument("--max-steps", type=int, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def loop_options(args: argparse.Namespace):  # -> LoopOptions (imported lazily)
    from robustbench3d.victims.training import LoopOptions

    if args.threads is not None:
        import torch

        torch.set_num_threads(args.threads)
    return LoopOptions(epochs=args.epochs, batch_size=args.batch_size, seed=args.seed,
                       checkpoint_every=args.checkpoint_every, max_steps=args.max_steps,
                       progress=not args.no_progress)
