"""``robustbench3d train yolo``: train the 2D detector (mini-YOLO by default) on a KITTI-layout
dataset. Writes OUT/last.pt (resumable), OUT/model.pt and OUT/log.jsonl."""

from __future__ import annotations

import argparse
import sys

from robustbench3d.victims.train_common import add_common_arguments, loop_options


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_common_arguments(parser, epochs=100, batch_size=16)
    parser.add_argument("--layout", choices=("mini", "tiny", "v3"), default="mini", help="network layout")
    parser.add_argument("--anchors", choices=("kmeans", "config"), default="kmeans",
                        help="k-means anchors on the training boxes, or the layout's defaults")
    parser.add_argument("--no-flip", action="store_true", help="disable horizontal-flip augmentation")


def run(args: argparse.Namespace) -> int:
    from robustbench3d.victims.yolo.training import YoloTrainConfig, train

    cfg = YoloTrainConfig(layout=args.layout, anchors=args.anchors, flip=not args.no_flip,
                          train_split=args.train_split, val_split=args.val_split,
                          **({"lr": args.lr} if args.lr is not None else {}))
    state = train(args.data, args.out, cfg, loop_options(args), resume=args.resume)
    done = "finished" if state["finished"] else f"stopped after step {state['step']} (resume with --resume)"
    print(f"train yolo: {done}; outputs in {args.out}", file=sys.stderr)
    return 0
