"""``robustbench3d victims train-fpointnet``: train Frustum-PointNet v1 on GT-box frustums of a
KITTI-layout dataset. Writes OUT/last.pt (resumable), OUT/model.pt and OUT/log.jsonl."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

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
    parser.add_argument("--val-limit", type=int, default=None,
                        help="evaluate on at most this many val frustums (0: no validation, the val split is not read)")
    parser.add_argument("--precision", choices=("fp32", "bf16"), default="fp32",
                        help="bf16: bfloat16 autocast for the network (float32 weights, optimizer and loss)")
    parser.add_argument("--layout", choices=("rows", "conv"), default="rows",
                        help="per-point layers as Linear on (B*N, C) rows (default, faster) or as 1x1 Conv1d; "
                             "same model, same state dict")
    parser.add_argument("--device", default="cpu", help="torch device to train on: cpu (default) or cuda")
    parser.add_argument("--cache", type=Path, metavar="FILE",
                        help="train frustum cache: read the train set from FILE, writing it from --data first if "
                             "absent (compact, quantized to 1 mm; lets a machine without the dataset train)")


def resolve_device(name: str) -> str:
    """A torch device name checked to be usable here (RobustBenchError otherwise)."""
    import torch

    from robustbench3d.errors import RobustBenchError

    try:
        dev = torch.device(name)
    except RuntimeError as exc:
        raise RobustBenchError(f"--device {name!r}: {exc}") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise RobustBenchError(f"--device {name!r}: torch sees no CUDA device here")
    if dev.type not in ("cpu", "cuda"):
        raise RobustBenchError(f"--device {name!r}: expected cpu or cuda")
    return str(dev)


def resource_record(device: str, wall_s: float, state: dict) -> dict:
    """Wall time, steps, device and peak memory of a training run (written to OUT/timing.json)."""
    import platform
    import resource

    import torch

    rec = {"device": device, "wall_seconds": wall_s, "steps": state["step"], "finished": state["finished"],
           "threads": torch.get_num_threads(), "cpu": platform.processor() or platform.machine(),
           "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
           "train_seconds": state.get("seconds", {}).get("train", 0.0),
           "val_seconds": state.get("seconds", {}).get("val", 0.0)}
    if device.startswith("cuda"):
        rec["gpu"] = torch.cuda.get_device_name(torch.device(device))
        rec["peak_gpu_mib"] = torch.cuda.max_memory_allocated(torch.device(device)) / 2**20
    return rec


def run(args: argparse.Namespace) -> int:
    import json
    import time

    from robustbench3d.errors import RobustBenchError
    from robustbench3d.fileio import atomic_write_text, check_output_dir
    from robustbench3d.victims.fpointnet.training import FPointNetTrainConfig, train

    check_output_dir(args.out, "--out")
    device = resolve_device(args.device)
    if args.val_limit is not None and args.val_limit < 0:
        raise RobustBenchError(f"--val-limit {args.val_limit}: expected >= 0")
    t0 = time.perf_counter()
    cfg = FPointNetTrainConfig(model=args.model, precision=args.precision, layout=args.layout,
                               types=tuple(t for t in args.types.split(",") if t),
                               augment_x=args.augment_x, lr_schedule=args.lr_schedule, bn_decay_step=args.bn_decay_step,
                               flip=not args.no_flip, shift=args.shift,
                               double_size_residual=not args.single_size_residual,
                               train_split=args.train_split, val_split=args.val_split,
                               **({"lr": args.lr} if args.lr is not None else {}))
    state = train(args.data, args.out, cfg, loop_options(args), resume=args.resume, val_limit=args.val_limit,
                  cache=args.cache, device=device)
    atomic_write_text(args.out / "timing.json", json.dumps(resource_record(device, time.perf_counter() - t0, state),
                                                           indent=1, sort_keys=True) + "\n")
    done = "finished" if state["finished"] else f"stopped after step {state['step']} (resume with --resume)"
    print(f"train fpointnet: {done}; outputs in {args.out}", file=sys.stderr)
    return 0
