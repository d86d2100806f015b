"""``robustbench3d victims train-yolo``: train the 2D detector (mini-YOLO by default) on a KITTI-layout
dataset. Writes OUT/last.pt (resumable), OUT/model.pt and OUT/log.jsonl."""

from __future__ import annotations

import argparse
import sys

from robustbench3d.victims.train_common import add_common_arguments, loop_options


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_common_arguments(parser, epochs=100, batch_size=16)
    parser.add_argument("--layout", choices=("mini", "mini3", "tiny", "v3"), default="mini", help="network layout")
    parser.add_argument("--loss", choices=("iou", "v3"), default="iou",
                        help="iou: multi-prior assignment, GIoU, IoU objectness (default); v3: the 2019 loss")
    parser.add_argument("--lr-schedule", choices=("step", "cosine"), default="step",
                        help="step: x0.1 at 80%% and 90%% of the epochs; cosine: down to lr/100")
    parser.add_argument("--precision", choices=("fp32", "bf16"), default="fp32",
                        help="bf16: bfloat16 autocast for the network (about 2x faster on AVX512-BF16 CPUs)")
    parser.add_argument("--scale-jitter", type=float, default=0.0, metavar="J",
                        help="zoom training images by U(1-J, 1+J) with a random shift (default 0: off)")
    parser.add_argument("--val-limit", type=int, default=None, help="validate on at most this many val images")
    parser.add_argument("--anchors", choices=("kmeans", "config"), default="kmeans",
                        help="k-means anchors on the training boxes, or the layout's defaults")
    parser.add_argument("--no-flip", action="store_true", help="disable horizontal-flip augmentation")
    parser.add_argument("--input-size", type=_size, default=None, metavar="WxH",
                        help="network input size in px, multiples of the largest stride (default: the layout's)")
    parser.add_argument("--init", default=None, metavar="MODEL",
                        help="start from this trained model.pt or cascade weights file (its weights and "
                        "anchors, scaled to the input size; its layout may be a prefix of --layout)")


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"input size must be WxH in pixels, got {text!r}") from None
    if w <= 0 or h <= 0:
        raise argparse.ArgumentTypeError(f"input size must be positive, got {text!r}")
    return w, h


def run(args: argparse.Namespace) -> int:
    from robustbench3d.fileio import check_output_dir
    from robustbench3d.victims.yolo.training import YoloTrainConfig, train

    check_output_dir(args.out, "--out")
    cfg = YoloTrainConfig(layout=args.layout, loss=args.loss, lr_schedule=args.lr_schedule, precision=args.precision,
                          scale_jitter=args.scale_jitter, val_limit=args.val_limit, anchors=args.anchors,
                          flip=not args.no_flip, input_size=args.input_size, init=args.init,
                          train_split=args.train_split, val_split=args.val_split,
                          **({"lr": args.lr} if args.lr is not None else {}))
    state = train(args.data, args.out, cfg, loop_options(args), resume=args.resume)
    done = "finished" if state["finished"] else f"stopped after step {state['step']} (resume with --resume)"
    print(f"train yolo: {done}; outputs in {args.out}", file=sys.stderr)
    return 0
