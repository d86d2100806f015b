"""``robustbench3d victims train-pointpillars``: train the PointPillars-style LiDAR Car detector on a
KITTI-layout dataset. Writes OUT/last.pt (resumable), OUT/model.pt, OUT/log.jsonl and OUT/timing.json; an
OUT holding an earlier run's files is refused unless --resume (which continues it from OUT/last.pt)."""

from __future__ import annotations

import argparse
import sys

from robustbench3d.victims.train_common import add_common_arguments, loop_options

#: --val-limit: 0 (no validation) .. the whole KITTI val split; more frames only cost time.
VAL_LIMIT_RANGE = (0, 10_000)
#: --pillar-size (m): below 0.16 the grid outgrows one CPU; above 0.64 a car is under 3 x 7 pillars.
PILLAR_SIZE_RANGE = (0.16, 0.64)
#: --lr: Adam(W) learning rates outside this are divergent or frozen for this network.
LR_RANGE = (1e-6, 1e-1)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_common_arguments(parser, epochs=16, batch_size=4)
    parser.add_argument("--val-limit", type=int, default=100,
                        help="validate (Car BEV AP R40) on the first N val frames after each epoch "
                             "(0: no validation, the val split is not read; "
                             f"{VAL_LIMIT_RANGE[0]}..{VAL_LIMIT_RANGE[1]}; default 100)")
    parser.add_argument("--precision", choices=("fp32", "bf16"), default="fp32",
                        help="bf16: bfloat16 autocast for the network (float32 weights, optimizer and loss)")
    parser.add_argument("--pillar-size", type=float, default=0.32,
                        help=f"pillar side in m ({PILLAR_SIZE_RANGE[0]}..{PILLAR_SIZE_RANGE[1]}; default 0.32)")


def _check(args: argparse.Namespace) -> None:
    from robustbench3d.errors import RobustBenchError

    checks = [("--val-limit", args.val_limit, VAL_LIMIT_RANGE), ("--pillar-size", args.pillar_size, PILLAR_SIZE_RANGE),
              ("--epochs", args.epochs, (1, 10_000)), ("--batch-size", args.batch_size, (2, 256))]
    if args.lr is not None:
        checks.append(("--lr", args.lr, LR_RANGE))
    if args.threads is not None:
        checks.append(("--threads", args.threads, (1, 1024)))
    for flag, value, (lo, hi) in checks:
        if not lo <= value <= hi:
            raise RobustBenchError(f"{flag} {value}: expected {lo}..{hi}")


def run(args: argparse.Namespace) -> int:
    import json
    import platform
    import resource
    import time
    from dataclasses import replace

    import torch

    from robustbench3d.fileio import atomic_write_text, check_output_dir
    from robustbench3d.victims.pointpillars.model import PointPillarsConfig
    from robustbench3d.victims.pointpillars.training import PointPillarsTrainConfig, train

    _check(args)
    check_output_dir(args.out, "--out")
    if not args.resume:
        from robustbench3d.errors import RobustBenchError

        taken = [n for n in ("last.pt", "model.pt", "log.jsonl") if (args.out / n).exists()]
        if taken:
            raise RobustBenchError(f"--out {args.out}: holds {', '.join(taken)} of an earlier run; pass --resume to "
                                   "continue it, or use another --out (nothing was written)")
    t0 = time.perf_counter()
    base = PointPillarsConfig()
    cfg = replace(base, grid=replace(base.grid, pillar_size=args.pillar_size))
    tcfg = PointPillarsTrainConfig(precision=args.precision, train_split=args.train_split, val_split=args.val_split,
                                   **({"lr": args.lr} if args.lr is not None else {}))
    state = train(args.data, args.out, cfg, tcfg, loop_options(args), resume=args.resume, val_limit=args.val_limit)
    record = {"wall_seconds": time.perf_counter() - t0, "steps": state["step"], "finished": state["finished"],
              "threads": torch.get_num_threads(), "cpu": platform.processor() or platform.machine(),
              "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
              "train_seconds": state.get("seconds", {}).get("train", 0.0),
              "val_seconds": state.get("seconds", {}).get("val", 0.0)}
    atomic_write_text(args.out / "timing.json", json.dumps(record, indent=1, sort_keys=True) + "\n")
    done = "finished" if state["finished"] else f"stopped after step {state['step']} (resume with --resume)"
    print(f"train pointpillars: {done}; outputs in {args.out}", file=sys.stderr)
    return 0
