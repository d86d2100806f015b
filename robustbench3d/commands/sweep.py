"""``robustbench3d sweep``: the dose–response sweep — one universal object per family (icosphere level x radius),
each trained by ``attack train``'s recipe to its own plateau, all scored with the clean control and the benign
sphere of each radius on the same frames in one benchmark run (:mod:`robustbench3d.sweep`).

    robustbench3d sweep --victim NAME --mode adv-texture --levels 2,4 --radii 0.2,0.4,0.6 --out DIR [--full]

Writes ``DIR/objects/`` (the objects with their sidecars, curves, checkpoints and training cost), ``DIR/run/`` (the
benchmark run), ``DIR/sweep.json``, ``.csv``, ``.md`` and ``.png``, and prints the table and, per victim, the
smallest object swept that takes at least half of moderate BEV AP. Resumable at every stage; numeric options have
ranges checked before any work.

Standard library only at module level.
"""

from __future__ import annotations

import argparse
import sys

#: The training options a sweep passes to ``attack train`` (None: the shipped recipe's value), with their
#: TrainConfig field; their ranges are TrainConfig's (attacks.train_config.INT_RANGES / FLOAT_RANGES).
TRAIN_OPTIONS = {"steps": "steps", "batch_cars": "batch_cars", "eval_every": "eval_every",
                 "eval_frames": "eval_frames", "plateau_window": "plateau_window", "plateau_tol": "plateau_tol",
                 "lidar_boxes": "lidar_boxes", "lidar_loss": "lidar_loss", "image_loss": "image_loss",
                 "lr_shape": "lr_shape", "lr_color": "lr_color"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from robustbench3d.ranges import PROCESSES_RANGE, RESAMPLES_RANGE, SEED_RANGE, default_processes

    parser.add_argument("--victim", required=True, metavar="NAME", help="registered white-box victim")
    parser.add_argument("--mode", required=True, choices=("adv-shape", "adv-texture", "adv-object"),
                        help="what each object optimises (as `attack train`)")
    parser.add_argument("--levels", default="2", metavar="L,L",
                        help="icosphere levels (colour freedom): 2, 3, 4 = 162, 642, 2562 vertex colours (default 2)")
    parser.add_argument("--radii", default="0.4", metavar="R,R",
                        help="object radii in metres, 0.2..0.6 in whole centimetres; the bounds scale with the "
                             "radius (default 0.4); the seed's point l2-r0.40 is always swept")
    parser.add_argument("--out", required=True, metavar="DIR",
                        help="sweep directory: new, empty, or a sweep of the same configuration (resumed)")
    parser.add_argument("--data", metavar="DIR", help="KITTI-layout dataset (default: the embedded one)")
    parser.add_argument("--split", default="val", help="split the objects are scored on (default val)")
    parser.add_argument("--train-split", default="train", help="split the objects are trained on (default train)")
    frames = parser.add_mutually_exclusive_group()
    frames.add_argument("--max-frames", type=int, metavar="N",
                        help="score on the first N frames of --split, 1..1000000 (default: as `run`, 25 of the "
                             "embedded val split)")
    frames.add_argument("--full", action="store_true", help="score on the whole --split")
    parser.add_argument("--train-max-frames", type=int, metavar="N",
                        help="train on the first N frames of --train-split, 1..1000000 (default: all)")
    parser.add_argument("--proposals", default="detector,gt", metavar="SRC,SRC",
                        help="2D proposal sources the objects are scored with (default detector,gt: both LiDAR "
                             "protocols)")
    parser.add_argument("--seed", type=int, default=0, metavar="S",
                        help=f"training, attack and bootstrap seed, {SEED_RANGE[0]}..{SEED_RANGE[1]} (default 0)")
    parser.add_argument("--bootstrap", type=int, default=1000, metavar="R",
                        help=f"bootstrap resamples of the intervals, {RESAMPLES_RANGE[0]}..{RESAMPLES_RANGE[1]} "
                             "(default 1000)")
    group = parser.add_argument_group("training (default: the shipped object's recipe of --mode, with the held-out "
                                      "curve and plateau stop; ranges as `attack train`)")
    group.add_argument("--steps", type=int, metavar="N", help="step budget of each object")
    group.add_argument("--batch-cars", type=int, metavar="B", help="cars per step")
    group.add_argument("--eval-every", type=int, metavar="K", help="held-out evaluation every K steps")
    group.add_argument("--eval-frames", type=int, metavar="N", help="held-out frames (default 20)")
    group.add_argument("--plateau-window", type=int, metavar="W", help="plateau stop window (steps)")
    group.add_argument("--plateau-tol", type=float, metavar="T", help="plateau stop relative improvement")
    group.add_argument("--lidar-boxes", choices=("gt", "detector", "gt-object", "gt-append"),
                       help="2D boxes of the LiDAR loss's frustums")
    group.add_argument("--lidar-loss", choices=("seed", "box", "seed+box"), help="LiDAR loss terms")
    group.add_argument("--image-loss", choices=("mean", "sum"), help="image loss per car")
    group.add_argument("--lr-shape", type=float, help="Adam step of the shape")
    group.add_argument("--lr-color", type=float, help="Adam step of the colour logits")
    parser.add_argument("--executor", choices=("local", "ray"), default="local",
                        help="where trainings and frame shards run: local worker processes or a Ray cluster "
                             "(default local)")
    parser.add_argument("--workers", type=int, default=default_processes(), metavar="W",
                        help=f"points trained at a time and scoring processes, {PROCESSES_RANGE[0]}.."
                             f"{PROCESSES_RANGE[1]} (default: CPUs; 1: everything in this process)")
    parser.add_argument("--address", metavar="ADDR", help="a running Ray cluster to join (--executor ray)")
    parser.add_argument("--force", action="store_true",
                        help="retrain objects and replace cells and files of another configuration (each named)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars and per-point lines")


def check_options(args: argparse.Namespace) -> None:
    """Every option in its range before any work (one line naming the option and the range)."""
    from robustbench3d.attacks.spec import check_max_frames
    from robustbench3d.errors import RobustBenchError
    from robustbench3d.ranges import PROCESSES_RANGE, SEED_RANGE, check_bootstrap, check_range
    from robustbench3d.victims.spec import PROPOSAL_SOURCES, describe_sources

    check_max_frames(args.max_frames)
    check_max_frames(args.train_max_frames, "--train-max-frames")
    check_range("--seed", args.seed, *SEED_RANGE, "training, attack and bootstrap seed")
    check_bootstrap(args.bootstrap)
    check_range("--workers", args.workers, *PROCESSES_RANGE, "worker processes")
    if args.address is not None and args.executor != "ray":
        raise RobustBenchError("--address joins a Ray cluster: give it with --executor ray")
    sources = proposals(args.proposals)
    bad = [s for s in sources if s not in PROPOSAL_SOURCES]
    if bad:
        raise RobustBenchError(f"--proposals: unknown source {bad[0]!r}; choose from {describe_sources()}")


def proposals(text: str) -> tuple[str, ...]:
    from robustbench3d.errors import RobustBenchError

    items = tuple(t.strip() for t in text.split(","))
    if not text.strip() or any(not t for t in items) or len(set(items)) != len(items):
        raise RobustBenchError(f"--proposals {text!r}: expected distinct sources separated by commas, e.g. detector,gt")
    return items


def config_from_args(args: argparse.Namespace) -> object:
    """The :class:`~robustbench3d.sweep.run.SweepConfig` of parsed arguments; the training overrides are checked
    here by building each point's TrainConfig (its one-line range errors name the field and option)."""
    from robustbench3d.errors import RobustBenchError
    from robustbench3d.runner.config import default_max_frames
    from robustbench3d.sweep.grid import parse_levels, parse_radii, points
    from robustbench3d.sweep.run import SweepConfig
    from robustbench3d.sweep.train import train_config

    check_options(args)
    cfg = SweepConfig(victim=args.victim, mode=args.mode, levels=parse_levels(args.levels),
                      radii=parse_radii(args.radii), data=args.data, split=args.split,
                      max_frames=default_max_frames(args.max_frames, args.full, args.data, args.split),
                      train_split=args.train_split, train_max_frames=args.train_max_frames,
                      proposals=proposals(args.proposals), seed=args.seed, bootstrap=args.bootstrap,
                      train={field: getattr(args, opt) for opt, field in TRAIN_OPTIONS.items()} | {"seed": args.seed})
    for p in points(cfg.mode, cfg.levels, cfg.radii):
        try:
            train_config(p, cfg.train)
        except (TypeError, ValueError) as exc:
            raise RobustBenchError(f"training settings: {exc}") from None
    return cfg


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from robustbench3d.fileio import check_output_dir, remove_created_dir
    from robustbench3d.sweep.run import Execution, run_sweep

    out = check_output_dir(args.out, "--out")
    cfg = config_from_args(args)
    ex = Execution(executor=args.executor, workers=args.workers, address=args.address,
                   progress=not args.no_progress, force=args.force)

    def log(line: str) -> None:
        if not args.no_progress:
            print(line, file=sys.stderr, flush=True)

    def say(line: str) -> None:  # what was kept or replaced: printed with --no-progress too
        print(line, file=sys.stderr, flush=True)

    created = not Path(out).exists()
    try:
        paths, doc = run_sweep(cfg, ex, Path(out), log, say)  # type: ignore[arg-type]
    except BaseException:
        if created:
            remove_created_dir(out)
        raise
    print((Path(out) / "sweep.md").read_text(encoding="utf-8"))
    for sentence in doc["sentences"].values():
        print(sentence)
    print("sweep: wrote " + ", ".join(str(p) for p in paths))
    return 0
