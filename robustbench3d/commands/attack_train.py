"""``robustbench3d attack train``: optimise a universal roof object against a white-box victim.

    robustbench3d attack train adv-shape|adv-texture|adv-object --victim V --out OBJ.ply
        [--level 2|3|4] [--radius R]
        [--data DIR] [--split train] [--steps N] [--batch-cars B] [--seed S] [--eot jitter,range-noise,dropout]
        [--eval-every K] [--eval-frames N] [--plateau-window W] [--plateau-tol T] [--resume] [--force]
        [--workers W] [--optimizer adam|cma [--query-budget N] [--population P] [--frames-per-candidate F]]

``--optimizer cma`` trains through the victim's ``detect`` alone (any registered victim, gradients or not): CMA-ES
over the same parameters, the query budget in frame queries (:mod:`robustbench3d.attacks.blackbox`,
:mod:`robustbench3d.attacks.blackbox_run`; the extra ``blackbox`` installs it); the default ``adam`` is the
white-box trainer described next.

Writes the object file ``OBJ.ply`` and its sidecar (losses and weights, victim, training data, config,
seed, steps, wall time, the held-out curve's summary and why training stopped; the object's family, ``--level``
and ``--radius``, in its template record); ``OBJ.train.pt`` beside it is
the checkpoint ``--resume`` continues from. Every ``K`` steps the object is evaluated on the last ``N`` frames
of the split, which are never trained on: ``OBJ.curve.csv`` and ``OBJ.curve.png`` hold the training and
held-out losses, the held-out relative drop and ASR; ``OBJ.ply`` is the state of lowest held-out loss, and
training stops once that loss improved by less than ``T`` (relative) over ``W`` steps
(:mod:`robustbench3d.attacks.train_curve`). See :mod:`robustbench3d.attacks.train` for the optimisation.
None of the files is replaced without ``--force``, except by ``--resume`` continuing the training that wrote
them (:mod:`robustbench3d.attacks.train_run`). Before the first step, ``--workers`` processes compute the
exact-occlusion scene depths the run will read that are not cached yet (:func:`robustbench3d.attacks.train_run.
warm_depths`). Numeric options have ranges
(:data:`robustbench3d.attacks.train_config.INT_RANGES`, ``FLOAT_RANGES``), checked before any work.

Standard library only at module level.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from collections.abc import Callable

    from robustbench3d.attacks.train_config import TrainConfig

MODE_NAMES = ("adv-shape", "adv-texture", "adv-object")
OPTIMIZERS = ("adam", "cma")
#: The black-box options (``--optimizer cma`` only).
CMA_OPTIONS = ("query_budget", "population", "frames_per_candidate")
EOT_NAMES = ("jitter", "range-noise", "dropout")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("mode", choices=MODE_NAMES,
                        help="adv-shape: LiDAR loss, shape only (grey); adv-texture: image loss, colours only "
                             "(undeformed sphere); adv-object: both")
    parser.add_argument("--victim", required=True, metavar="NAME", help="registered white-box victim")
    parser.add_argument("--victim-arg", action="append", metavar="KEY=VALUE",
                        help="keyword argument of the victim's factory (repeatable; VALUE is JSON or a string)")
    parser.add_argument("--data", metavar="DIR",
                        help="KITTI-layout dataset root (default: the embedded dataset, generated if missing)")
    parser.add_argument("--split", default="train", help="training split, ImageSets/<split>.txt (default: train)")
    parser.add_argument("--max-frames", type=int, metavar="N",
                        help="only the first N frames of the split (1 to 1000000)")
    parser.add_argument("--out", required=True, metavar="OBJ.ply", help="the object file to write")
    parser.add_argument("--level", type=int, default=2, metavar="L",
                        help="object family: icosphere level 2, 3 or 4 (162, 642 or 2562 vertices, each with its own "
                             "colour; default 2)")
    parser.add_argument("--radius", type=float, default=0.40, metavar="R",
                        help="object family: sphere radius in m, 0.2 to 0.6 in whole centimetres (it stays within a "
                             "car roof; the box constraint is +-R; default 0.40)")
    parser.add_argument("--steps", type=int, default=300, metavar="N", help="optimisation steps (default 300)")
    parser.add_argument("--batch-cars", type=int, default=8, metavar="B", help="cars per step (default 8)")
    parser.add_argument("--seed", type=int, default=0, metavar="S", help="seed of the batches and EOT (default 0)")
    parser.add_argument("--lr-shape", type=float, default=5e-3, help="Adam step of the shape (default 5e-3)")
    parser.add_argument("--lr-color", type=float, default=1e-2, help="Adam step of the colour logits (default 1e-2)")
    parser.add_argument("--lambda-lap", type=float, default=0.01, help="Laplacian weight (default 0.01)")
    parser.add_argument("--lambda-img", type=float, default=1.0, help="image-loss weight in adv-object (default 1)")
    parser.add_argument("--no-class-prob", action="store_true",
                        help="image loss on the objectness alone (default: objectness x class probability)")
    parser.add_argument("--eot", default="", metavar="NAME[,NAME]",
                        help=f"expectation over transformation: {', '.join(EOT_NAMES)} or all (default: none)")
    parser.add_argument("--occlusion", choices=("scan", "none"), default="scan",
                        help="camera occlusion of the object by the scene, as in the benchmark (default scan)")
    parser.add_argument("--lidar-boxes", choices=("gt", "detector", "gt-object", "gt-append"), default="gt",
                        help="2D boxes of the LiDAR loss's frustums: the cars' ground-truth boxes (gt: the object "
                             "outside "
                             "the frustum), the victim's own detections on the attacked image, or a frustum protocol "
                             "that holds the object: gt-object (GT box united with the object's box), gt-append (the "
                             "car's object returns added to its GT-box frustum) (default gt)")
    parser.add_argument("--lidar-loss", choices=("seed", "box", "seed+box"), default="seed",
                        help="LiDAR loss terms: the seed paper's segmentation term, the regressed box's BEV IoU "
                             "with the ground truth, or both (default seed)")
    parser.add_argument("--lambda-box", type=float, default=1.0, help="weight of the box term (default 1)")
    parser.add_argument("--image-loss", choices=("mean", "sum"), default="mean",
                        help="image loss per car: the mean over its 2D candidates, or the sum over those of IoU "
                             ">= 0.5 with it (default mean)")
    parser.add_argument("--checkpoint-every", type=int, default=25, metavar="K", help="steps per checkpoint (25)")
    parser.add_argument("--eval-every", type=int, default=25, metavar="K",
                        help="evaluate on the held-out frames every K steps (0 to 1000000; default 25; 0: no "
                             "evaluation, no curve, every frame trains)")
    parser.add_argument("--eval-frames", type=int, default=5, metavar="N",
                        help="hold out the last N frames of the split, never trained on, for the curve (1 to "
                             "10000, at most a fifth of the split; default 5)")
    parser.add_argument("--plateau-window", type=int, default=60, metavar="W",
                        help="stop when the best held-out loss fell by less than --plateau-tol over the last W "
                             "steps (1 to 1000000; default 60)")
    parser.add_argument("--plateau-tol", type=float, default=0.004, metavar="T",
                        help="relative improvement of the plateau stop (0 to 1; default 0.004; 0: never stop)")
    parser.add_argument("--resume", action="store_true",
                        help="continue from the checkpoint OBJ.train.pt if it exists (its configuration must match; "
                             "--steps may grow), replacing OBJ.ply and OBJ.json if that training wrote them")
    parser.add_argument("--force", action="store_true",
                        help="replace an existing OBJ.ply, its sidecar and (without --resume) its checkpoint; "
                             "without it they are refused")
    parser.add_argument("--workers", type=int, default=None, metavar="W",
                        help="worker processes computing, before the first step, the exact-occlusion scene depths "
                             "the run will read that are not cached yet (1 to 1024; default: the CPUs)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    parser.add_argument("--optimizer", choices=OPTIMIZERS, default="adam",
                        help="adam: the white-box trainer through the victim's gradients (default); cma: black-box "
                             "CMA-ES through its detect alone, for any victim (needs the extra 'blackbox'; a step is "
                             "then a generation; --steps, --batch-cars, --lr-*, --lambda-img, --lambda-box, "
                             "--lidar-loss, --image-loss and --no-class-prob do not apply)")
    parser.add_argument("--query-budget", type=int, default=None, metavar="N",
                        help="--optimizer cma: frame queries (one detect of one attacked frame) the optimisation "
                             "may spend, 1 to 100000000; required with cma")
    parser.add_argument("--population", type=int, default=None, metavar="P",
                        help="--optimizer cma: candidates per generation, 4 to 4096 (default 4 + 3 ln n for n "
                             "parameters: 22 for the default family's texture or shape)")
    parser.add_argument("--frames-per-candidate", type=int, default=None, metavar="F",
                        help="--optimizer cma: training frames each candidate is scored on per generation, the "
                             "same for every candidate, 1 to 1024 (default 2)")


def _victim_kwargs(items: list[str] | None) -> dict[str, Any]:
    from robustbench3d.registry import parse_factory_args

    return parse_factory_args([f"victim:{i}" for i in items or []], "--victim-arg").get("victim", {})


def _eot(text: str) -> tuple[str, ...]:
    from robustbench3d.errors import RobustBenchError

    names = [t.strip() for t in text.split(",") if t.strip()]
    if names == ["all"]:
        return EOT_NAMES
    bad = [n for n in names if n not in EOT_NAMES]
    if bad:
        raise RobustBenchError(f"--eot {text}: unknown {', '.join(bad)} (choose from {', '.join(EOT_NAMES)} or all)")
    return tuple(names)


def config_from_args(args: argparse.Namespace) -> TrainConfig:
    """The training configuration of parsed ``attack train`` arguments (:func:`add_arguments`)."""
    from robustbench3d.attacks.train_config import TrainConfig

    return TrainConfig(mode=args.mode, steps=args.steps, batch_cars=args.batch_cars, seed=args.seed,
                       lr_shape=args.lr_shape, lr_color=args.lr_color, lambda_lap=args.lambda_lap,
                       lambda_img=args.lambda_img, use_class=not args.no_class_prob, eot=_eot(args.eot),
                       occlusion=args.occlusion, lidar_boxes=args.lidar_boxes, lidar_loss=args.lidar_loss,
                       lambda_box=args.lambda_box, image_loss=args.image_loss,
                       checkpoint_every=args.checkpoint_every, eval_every=args.eval_every,
                       eval_frames=args.eval_frames, plateau_window=args.plateau_window,
                       plateau_tol=args.plateau_tol, level=args.level, radius=args.radius)


def blackbox_settings(args: argparse.Namespace) -> Any:
    """The :class:`~robustbench3d.attacks.blackbox.BlackBoxSettings` of ``--optimizer cma`` (ranges checked, the
    ``cma`` package present), None for adam; the black-box options without cma are refused (one line)."""
    from robustbench3d.errors import RobustBenchError

    given = [f"--{name.replace('_', '-')}" for name in CMA_OPTIONS if getattr(args, name, None) is not None]
    if args.optimizer != "cma":
        if given:
            raise RobustBenchError(f"{', '.join(given)}: only with --optimizer cma")
        return None
    from robustbench3d.attacks.blackbox import BlackBoxSettings, import_cma

    if args.query_budget is None:
        raise RobustBenchError("--optimizer cma: --query-budget N is required (frame queries, 1 to 100000000)")
    frames = {} if args.frames_per_candidate is None else {"frames_per_candidate": args.frames_per_candidate}
    settings = BlackBoxSettings(args.query_budget, args.population, **frames)
    import_cma()
    return settings


def _prepare(args: argparse.Namespace, config: TrainConfig, check: Callable[[Any], None],
             ckpt: Path | None = None) -> tuple[Path, int, Any, dict[str, Any], Any]:
    """What both optimisers start from, every refusal before the data is read: the output path (checked; again,
    with its notes, in the run loop; ``ckpt``: the black-box checkpoint), the worker count, the victim (``check``
    refuses it), its record and the training split (:class:`~robustbench3d.attacks.train_run.TrainingSplit`)."""
    from robustbench3d.attacks.spec import check_max_frames
    from robustbench3d.attacks.train_run import check_outputs, training_split, victim_record
    from robustbench3d.errors import RobustBenchError
    from robustbench3d.ranges import PROCESSES_RANGE, check_range, default_processes
    from robustbench3d.victims import create_victim

    check_max_frames(args.max_frames)
    workers = default_processes() if args.workers is None else args.workers
    check_range("--workers", workers, *PROCESSES_RANGE, "worker processes")
    out = Path(args.out)
    check_outputs(out, force=args.force, resume=args.resume, curve=config.eval_every > 0, ckpt=ckpt)
    kwargs = _victim_kwargs(args.victim_arg)
    try:
        victim = create_victim(args.victim, **kwargs)
    except TypeError as exc:
        raise RobustBenchError(f"--victim {args.victim}: {exc}") from None
    check(victim)
    train = training_split(args.data, args.split, args.max_frames, progress=not args.no_progress)
    return out, workers, victim, victim_record(args.victim, kwargs), train


def run(args: argparse.Namespace) -> int:
    from robustbench3d.attacks.train_config import check_oracles
    from robustbench3d.attacks.train_run import train_universal

    config = config_from_args(args)
    blackbox = blackbox_settings(args)
    if blackbox is not None:
        return _run_blackbox(args, config, blackbox)
    out, workers, victim, record, train = _prepare(args, config, lambda victim: check_oracles(
        victim, config.mode, args.victim, config.lidar_boxes, config.lidar_loss))
    made_by = train_universal(victim, record, train.dataset.kitti(), train.gt.frame_ids,
                              train.gt.labels, config, out, data_identity=train.identity,
                              resume=args.resume, force=args.force, progress=not args.no_progress, log=print,
                              workers=workers)
    last = made_by["losses"]["last_step"] or {}
    drop = made_by["drop_estimate"]
    print(f"{out}: {config.name} after {made_by['steps']} steps on {made_by['cars']} cars "
          f"({made_by['wall_time_s']:.1f} s); last step: "
          + ", ".join(f"{k} {v:.4g}" for k, v in last.items() if k in ("lidar", "image", "laplacian", "total"))
          + (f"; running drop estimate {drop:.0%}" if drop is not None else ""))
    _print_curve(out, made_by)
    return 0


def _print_curve(out: Path, made_by: dict[str, Any], step: str = "step") -> None:
    """The line on the held-out curve's best state (none without a curve)."""
    curve = made_by["curve"]
    if curve is not None:
        best = curve["best"]
        rel = "n/a" if best["relative_drop"] is None else f"{best['relative_drop']:.1%}"
        asr = "n/a" if best["asr"] is None else f"{best['asr']:.1%}"
        print(f"{out}: the state of {step} {curve['best_step']} (lowest held-out loss {best['heldout_loss']:.4g}; "
              f"held-out relative drop {rel}, ASR {asr}); stopped at {step} {made_by['stopped']['step']} "
              f"({made_by['stopped']['reason']}); curve in {curve['files']['csv']} and {curve['files']['png']}")


def _run_blackbox(args: argparse.Namespace, config: TrainConfig, settings: Any) -> int:
    """``--optimizer cma``: :func:`robustbench3d.attacks.blackbox_run.train_blackbox`, refusals first."""
    from robustbench3d.attacks.blackbox_run import check_victim, cma_checkpoint_path, query_proposals, train_blackbox

    out, workers, victim, record, train = _prepare(  # the victim is checked again in train_blackbox
        args, config, lambda victim: check_victim(victim, args.victim, query_proposals(config, victim)),
        ckpt=cma_checkpoint_path(args.out))
    made_by = train_blackbox(victim, record, train.dataset.kitti(), train.gt.frame_ids,
                             train.gt.labels, config, settings, out, data_identity=train.identity,
                             resume=args.resume, force=args.force, progress=not args.no_progress, log=print,
                             workers=workers)
    last = made_by["losses"]["last_step"] or {}
    q = made_by["queries"]
    print(f"{out}: {config.name} (cma) after {made_by['steps']} generations, {q['used']} of {q['budget']} queries "
          f"on {made_by['cars']} cars ({made_by['wall_time_s']:.1f} s; {q['held_out']} held-out queries)"
          + (f"; last generation: fitness mean {last['fitness_mean']:.4g}, best {last['fitness_best']:.4g}, "
             f"sigma {last['sigma']:.3g}" if last else ""))
    _print_curve(out, made_by, "generation")
    return 0
