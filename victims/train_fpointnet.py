"""``robustbench3d train fpointnet``: train Frustum-PointNet v1 on GT-box frustums of a
KITTI-layout dataset. Writes OUT/last.pt (resumable), OUT/model.pt and OUT/log.jsonl."""

from __future__ import annotations

import argparse
import sys

from robustbench3d.victims.train_common import add_common_arguments, loop_options


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_common_arguments(parser, epochs=150, batch_size=32)
    parser.add_argument("--model", choices=("full", "lite"), default="full", help="network config (§1.6)")
    parser.add_argument("--types", default="Car", help="comma-separated KITTI types to train on (default Car)")
    parser.add_argument("--augment-x", type=int, default=5, help="perturbed copies per train box (default 5)")
    parser.add_argument("--shift", choices=("faithful", "intended", "off"), default="faithful",
                        help="random-shift augmentation: the original code's, the intended Gaussian, or none")
    parser.add_argument("--single-size-residual", action="store_true",
                        help="fix the corner-loss quirk that adds the size residual twice")
    parser.add_argument("--lr-schedule", choices=("step", "cosine"), default="step",
                        help="step: x0.7 every 20 epochs (the PyTorch port); cosine: to 1e-5 over the run")
    parser.add_argument("--bn-decay-step", type=int, default=800_000, metavar="SAMPLES",
                        help="halve the BatchNorm momentum every SAMPLES training samples (default 800000, "
                             "the original; scale it down with the run length)")
    parser.add_argument("--no-flip", action="store_true", help="disable the random flip")
    parser.add_argument("--val-limit", type=int, default=None, help="evaluate on at most this many val frustums")


def run(args: argparse.Namespace) -> int:
    from robustbench3d.fileio import check_output_dir
    from robustbench3d.victims.fpointnet.training import FPointNetTrainConfig, train

    check_output_dir(args.out, "--out")
    cfg = FPointNetTrainConfig(model=args.model, types=tuple(t for t in args.types.split(",") if t),
                               augment_x=args.augment_x, lr_schedule=args.lr_schedule, bn_decay_step=args.bn_decay_step,
                               flip=not args.no_flip, shift=args.shift,
                               double_size_residual=not args.single_size_residual,
                               train_split=args.train_split, val_split=args.val_split,
                               **({"lr": args.lr} if args.lr is not None else {}))
    state = train(args.data, args.out, cfg, loop_options(args), resume=args.resume, val_limit=args.val_limit)
    done = "finished" if state["finished"] else f"stopped after step {state['step']} (resume with --resume)"
    print(f"train fpointnet: {done}; outputs in {args.out}", file=sys.stderr)
    return 0
