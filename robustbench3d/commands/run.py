"""``robustbench3d run``: every victim x attack x proposal-source cell on one dataset split.

A run file (TOML, :mod:`robustbench3d.runner.runfile`) holds a run's configuration with the keys of its
provenance (``RunConfig.as_dict()``, each cell's ``provenance.run``): ``run --print-config`` writes it,
``run --config FILE`` runs it, ``run --config-from RUN_DIR`` takes it from a finished run. Options given on
the command line override the file's values (``--victim-arg``/``--attack-arg`` key by key). TOML has no
null: a missing ``data`` is the embedded dataset, ``max_frames = "all"`` every frame of the split (a missing
``max_frames``: the command line's default); relative paths are taken from the current directory, as on
the command line.

Standard library only at module level (numpy and the registries load inside :func:`run`).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Mapping
from typing import Any

from robustbench3d.errors import RobustBenchError
from robustbench3d.logs import add_verbosity_arguments, cli_logging, verbosity
from robustbench3d.ranges import (
    BATCH_RANGE,
    FRAMES_RANGE,
    PROCESSES_RANGE,
    RESAMPLES_RANGE,
    SEED_RANGE,
    check_bootstrap,
    check_range,
    default_processes,
)
from robustbench3d.registry import parse_factory_args


def _names(text: str) -> list[str]:
    return [t.strip() for t in text.split(",") if t.strip()]


def frames_line(max_frames: int | None, requested: int | None, full: bool, data: str | None, split: str,
                source: str = "--max-frames") -> str:
    """The line ``run`` prints first: which frames of which split it evaluates (``max_frames``: the run's,
    from :func:`~robustbench3d.runner.config.default_max_frames`; ``requested``: the ``--max-frames``
    given, or the run file's ``max_frames``, named by ``source``), and how to get all."""
    if data is not None:
        where = f"split {split} of {data}"
        return (f"frames: the first {max_frames} of {where} ({source})" if max_frames is not None
                else f"frames: every frame of {where}")
    from robustbench3d.datasets import EMBEDDED, embedded_split

    ids = embedded_split(EMBEDDED, split)
    if ids is None:  # not a split of the embedded dataset: resolving it names the problem
        return f"frames: split {split} of the embedded dataset"
    where = f"the embedded {split} split"
    if max_frames is None or max_frames >= len(ids):
        return f"frames: all {len(ids)} frames of {where}{' (--full)' if full else ''}"
    how = source if requested is not None else "the quick default, runner.config.DEFAULT_VAL_FRAMES"
    return (f"frames: the first {max_frames} of the {len(ids)} frames of {where}, {ids[0]}..{ids[max_frames - 1]} "
            f"({how}); --full runs all {len(ids)}")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    # options that are run-file keys default to None: given ones override the file (runfile.DEFAULTS fills the rest)
    frames, seeds, batch, procs, resamples = FRAMES_RANGE, SEED_RANGE, BATCH_RANGE, PROCESSES_RANGE, RESAMPLES_RANGE
    parser.add_argument("--victims", metavar="NAME[,NAME...]",
                        help="registered victims, or ONNX victim directories (registered under their directory name); "
                             "required unless the run file names them")
    parser.add_argument("--attacks", metavar="NAME[,NAME...]",
                        help="registered attacks, or object files NAME.ply (registered under NAME) "
                             "(default: none, the clean control)")
    from robustbench3d.victims.spec import describe_sources

    parser.add_argument("--proposals", metavar="SRC[,SRC...]",
                        help="2D proposal sources (frustum protocols), any of: "
                             + describe_sources()
                             + ". A victim that does not support a source gets a skipped cell (default: detector)")
    parser.add_argument("--out", metavar="DIR",
                        help="output directory (cell files, summary.json, results.csv, seed_table.md); "
                             "an interrupted run resumes: finished cells of the same configuration are kept; "
                             "required unless the run file gives it")
    parser.add_argument("--force", action="store_true",
                        help="replace finished cells in --out that were computed with another configuration "
                             "(without it the run refuses them up front; each replaced cell is named)")
    parser.add_argument("--data", metavar="DIR",
                        help="KITTI-layout dataset root (default: the embedded procedural dataset in the cache, "
                             "generated if missing)")
    parser.add_argument("--split", help="split name, ImageSets/<split>.txt (default: val)")
    parser.add_argument("--max-frames", type=int, metavar="N",
                        help=f"evaluate only the first N frames of the split, {frames[0]}..{frames[1]} (default on "
                             "the embedded val split: the first DEFAULT_VAL_FRAMES, see --full; elsewhere: all)")
    parser.add_argument("--full", action="store_true",
                        help="evaluate the whole split (the embedded val split's default is a first-N slice)")
    parser.add_argument("--seed", type=int, metavar="S",
                        help=f"run seed, {seeds[0]}..{seeds[1]}: attack randomness per frame, and seed= of victims "
                             "that take one (default 0)")
    parser.add_argument("--batch-size", type=int, metavar="B",
                        help=f"frames per detect call, {batch[0]}..{batch[1]} (default 4)")
    parser.add_argument("--victim-arg", action="append", metavar="NAME:KEY=VALUE",
                        help="keyword argument of a victim's factory, e.g. fpointnet-v1:weights=cascade.pt "
                             "(repeatable; VALUE is JSON or a string)")
    parser.add_argument("--attack-arg", action="append", metavar="NAME:KEY=VALUE",
                        help="keyword argument of an attack's factory (repeatable)")
    parser.add_argument("--workers", type=int, default=default_processes(), metavar="W",
                        help=f"processes generating the embedded dataset if it is missing, {procs[0]}..{procs[1]} "
                             "(default: CPUs)")
    parser.add_argument("--executor", choices=("local", "ray"), default="local",
                        help="where frame shards of the cells run: local worker processes, or a Ray cluster "
                             "(docs/executors.md; default: local)")
    parser.add_argument("--jobs", type=int, default=default_processes(), metavar="J",
                        help=f"worker processes (local; 1: everything in this process) or CPUs of the local Ray "
                             f"cluster started without --address, {procs[0]}..{procs[1]} (default: CPUs)")
    parser.add_argument("--address", metavar="ADDR",
                        help="a running Ray cluster to join (--executor ray): HOST:PORT (the head's GCS port, "
                             "e.g. 6379), ray://HOST:PORT (Ray Client), auto (the cluster `ray start` recorded on "
                             "this machine) or local (start one, as without --address); checked up front")
    parser.add_argument("--bootstrap", type=int, metavar="R",
                        help="bootstrap resamples of the frames for the 95 %% confidence interval of every AP and "
                             f"(paired) AP drop, {resamples[0]}..{resamples[1]}; 0: none (default 1000)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars on stderr")
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--config", metavar="FILE",
                        help="run file (TOML, the keys of the run's provenance; see --print-config); options given "
                             "with it override its values (--victim-arg/--attack-arg key by key)")
    source.add_argument("--config-from", metavar="RUN_DIR",
                        help="take the run file from a finished run's summary.json (the configuration whose grid "
                             "covers all its cells), e.g. with --print-config or another --out")
    parser.add_argument("--print-config", action="store_true",
                        help="print the run's configuration as a run file (TOML) on stdout and exit without running")
    add_verbosity_arguments(parser)


def check_numbers(args: argparse.Namespace) -> None:
    """Every numeric option of ``run`` given in its range (:data:`FRAMES_RANGE` ...), before any work."""
    if args.max_frames is not None:
        check_range("--max-frames", args.max_frames, *FRAMES_RANGE, "frames")
    if args.seed is not None:
        check_range("--seed", args.seed, *SEED_RANGE, "run seed")
    if args.batch_size is not None:
        check_range("--batch-size", args.batch_size, *BATCH_RANGE, "frames per detect call")
    check_range("--workers", args.workers, *PROCESSES_RANGE, "dataset generation processes")
    check_range("--jobs", args.jobs, *PROCESSES_RANGE, "worker processes")
    if args.bootstrap is not None:
        check_bootstrap(args.bootstrap)


def _cli_settings(args: argparse.Namespace) -> dict[str, Any]:
    """The run-file keys the command line gives (unresolved references, as typed)."""
    given: dict[str, Any] = {}
    for key in ("victims", "attacks", "proposals"):
        if getattr(args, key) is not None:
            given[key] = _names(getattr(args, key))
    for key in ("out", "data", "split", "seed", "batch_size", "bootstrap"):
        if getattr(args, key) is not None:
            given[key] = getattr(args, key)
    given["victim_args"] = parse_factory_args(args.victim_arg, "--victim-arg")
    given["attack_args"] = parse_factory_args(args.attack_arg, "--attack-arg")
    return given


def run_settings(args: argparse.Namespace) -> tuple[dict[str, Any], str]:
    """The run's settings (the keys of :data:`~robustbench3d.runner.runfile.RUN_KEYS`, ``max_frames`` resolved;
    victims and attacks as typed: names or paths) from :data:`~robustbench3d.runner.runfile.DEFAULTS`, the run
    file and the command line, in rising precedence;
    and what set ``max_frames`` (for :func:`frames_line`)."""
    from robustbench3d.runner.config import default_max_frames
    from robustbench3d.runner.runfile import (
        ALL_FRAMES,
        ARG_TABLES,
        DEFAULTS,
        RUN_KEYS,
        config_from_run,
        load_run_file,
        merge_args,
    )

    if args.config is not None:
        file, origin = load_run_file(args.config), f"max_frames in {args.config}"
    elif args.config_from is not None:
        file, origin = config_from_run(args.config_from), f"max_frames of {args.config_from}"
    else:
        file, origin = {}, "--max-frames"
    cli = _cli_settings(args)
    settings = {**DEFAULTS, **{k: v for k, v in file.items() if k != "max_frames"},
                **{k: v for k, v in cli.items() if k not in ARG_TABLES}}
    for key in ARG_TABLES:
        settings[key] = merge_args(file.get(key, {}), cli[key])
    if args.max_frames is not None or args.full or "max_frames" not in file:
        settings["max_frames"] = default_max_frames(args.max_frames, args.full, settings["data"], settings["split"])
        origin = "--max-frames"
    else:
        settings["max_frames"] = None if file["max_frames"] == ALL_FRAMES else file["max_frames"]
    for key, option in (("victims", "--victims"), ("out", "--out")):
        if key not in settings:
            raise RobustBenchError(f"{option} is required (or {key} in the --config run file)")
    return {key: settings[key] for key in RUN_KEYS}, origin


def _check_run_names(victims: list[str], attacks: list[str]) -> None:
    """Unknown victim or attack names, refused before ``--print-config`` prints (as the run refuses them)."""
    from robustbench3d.attacks import ATTACKS
    from robustbench3d.victims import VICTIMS

    for name in victims:
        VICTIMS.entry(name)
    for name in attacks:
        ATTACKS.entry(name)


def run_config(settings: Mapping[str, Any], args: argparse.Namespace) -> Any:
    """The :class:`~robustbench3d.runner.RunConfig` of ``settings`` (object files and ONNX directories
    registered under their names) with the command line's execution options."""
    from robustbench3d.attacks import ATTACKS
    from robustbench3d.runner import RunConfig
    from robustbench3d.victims import VICTIMS

    victims, _ = VICTIMS.resolve_all(list(settings["victims"]), {})
    _, victim_args = VICTIMS.resolve_all([], settings["victim_args"])
    attacks, _ = ATTACKS.resolve_all(list(settings["attacks"]), {})
    _, attack_args = ATTACKS.resolve_all([], settings["attack_args"])
    return RunConfig(
        victims=tuple(victims), attacks=tuple(attacks), proposals=tuple(settings["proposals"]), out=settings["out"],
        data=settings["data"], split=settings["split"], max_frames=settings["max_frames"], seed=settings["seed"],
        batch_size=settings["batch_size"], victim_args=victim_args, attack_args=attack_args,
        classes=tuple(settings["classes"]), workers=args.workers,
        progress=not (args.no_progress or args.quiet), bootstrap=settings["bootstrap"], force=args.force,
    )


# --- the command ----------------------------------------------------------------------------------------

def run(args: argparse.Namespace) -> int:
    with cli_logging(verbosity(args)):
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    import logging

    from robustbench3d.fileio import check_output_dir, remove_created_dir
    from robustbench3d.runner import run_benchmark
    from robustbench3d.runner.executors import make_executor
    from robustbench3d.runner.runfile import run_file_text

    log = logging.getLogger("robustbench3d.run")
    check_numbers(args)
    settings, origin = run_settings(args)
    config = run_config(settings, args)
    if args.print_config:
        _check_run_names(list(config.victims), list(config.attacks))
        sys.stdout.write(run_file_text(settings))
        return 0
    out = check_output_dir(config.out, "--out")
    created = not out.exists()
    executor = make_executor(args.executor, args.jobs, args.address)  # a Ray address is checked here
    requested = config.max_frames if args.max_frames is not None or origin != "--max-frames" else None
    log.info(frames_line(config.max_frames, requested, args.full, settings["data"], config.split, origin))
    log.debug(f"run configuration: {json.dumps(config.as_dict(), sort_keys=True)}")
    if executor is None:  # one intra-op thread, as in every worker process: the same result files
        from robustbench3d.runner.shards import worker_setup

        worker_setup()
    try:
        if executor is None:
            report = run_benchmark(config)
        else:
            with executor:
                report = run_benchmark(config, executor=executor)
    except BaseException:
        if created:  # a run that failed before writing any result leaves no directory behind
            remove_created_dir(out)
        raise
    _print_results(report)
    if report.failed:
        log.error(f"robustbench3d: {len(report.failed)} of {len(report.outcomes)} cells failed")
        return 1
    return 0


def _print_results(report: Any, write: Callable[[str], None] = print) -> None:
    """The run's tables and result paths on stdout: on a terminal folded to its width (``rich``,
    :func:`~robustbench3d.runner.table.fold_table`), else (a file, a pipe, CI) the plain text tables."""
    from functools import partial

    from robustbench3d.runner.table import fold_table, summary_table, terminal_width
    from robustbench3d.seed_table import SEED_TABLE_FILE, seed_table_text

    width = terminal_width() if sys.stdout.isatty() else None
    if width is not None:  # the prose lines wrapped too (at spaces: paths are never split)
        write = partial(_fitted, write=write, width=width)
    write(summary_table(report.summary, width=width))
    write(f"results: {report.out / 'summary.json'}, {report.out / 'results.csv'}")
    if report.earlier or report.left_out:
        write(f"{len(report.earlier)} of these cells come from earlier runs into {report.out}; "
              f"{len(report.left_out)} cell(s) there are left out (not comparable with this run, listed above)")
    write("")
    if width is None:
        write(seed_table_text(report.summary))
    else:
        write(seed_table_text(report.summary, table=partial(fold_table, width=width, key=2)))
    write(f"seed table: {report.out / SEED_TABLE_FILE}")


def _fitted(text: str, write: Callable[[str], None], width: int) -> None:
    from robustbench3d.runner.table import fit_lines

    write(fit_lines(text, width))
