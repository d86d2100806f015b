"""``robustbench3d run``: every victim x attack x proposal-source cell on one dataset split.

Standard library only at module level (numpy and the registries load inside :func:`run`).
"""

from __future__ import annotations

import argparse
import json
from typing import Any

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


def _names(text: str) -> list[str]:
    return [t.strip() for t in text.split(",") if t.strip()]


def parse_factory_args(items: list[str] | None, option: str) -> dict[str, dict[str, Any]]:
    """``["NAME:KEY=VALUE", ...]`` -> ``{NAME: {KEY: VALUE}}``; VALUE is parsed as JSON when it is
    valid JSON (numbers, true/false, null, lists), else kept as a string (paths)."""
    from robustbench3d.errors import RobustBenchError

    out: dict[str, dict[str, Any]] = {}
    for item in items or []:
        name, sep, assignment = item.partition(":")
        key, eq, raw = assignment.partition("=")
        if not sep or not eq or not name.strip() or not key.strip():
            raise RobustBenchError(f"{option} {item!r}: expected NAME:KEY=VALUE (e.g. fpointnet-v1:weights=cascade.pt)")
        try:
            value: Any = json.loads(raw)
        except json.JSONDecodeError:
            value = raw
        out.setdefault(name.strip(), {})[key.strip()] = value
    return out


def frames_line(max_frames: int | None, requested: int | None, full: bool, data: str | None, split: str) -> str:
    """The line ``run`` prints first: which frames of which split it evaluates (``max_frames``: the run's,
    from :func:`~robustbench3d.runner.config.default_max_frames`; ``requested``: the ``--max-frames``
    given), and how to get all."""
    if data is not None:
        where = f"split {split} of {data}"
        return (f"frames: the first {max_frames} of {where} (--max-frames)" if max_frames is not None
                else f"frames: every frame of {where}")
    from robustbench3d.datasets import EMBEDDED, embedded_split

    ids = embedded_split(EMBEDDED, split)
    if ids is None:  # not a split of the embedded dataset: resolving it names the problem
        return f"frames: split {split} of the embedded dataset"
    where = f"the embedded {split} split"
    if max_frames is None or max_frames >= len(ids):
        return f"frames: all {len(ids)} frames of {where}{' (--full)' if full else ''}"
    how = "--max-frames" if requested is not None else "the quick default, runner.config.DEFAULT_VAL_FRAMES"
    return (f"frames: the first {max_frames} of the {len(ids)} frames of {where}, {ids[0]}..{ids[max_frames - 1]} "
            f"({how}); --full runs all {len(ids)}")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    frames, seeds, batch, procs, resamples = FRAMES_RANGE, SEED_RANGE, BATCH_RANGE, PROCESSES_RANGE, RESAMPLES_RANGE
    parser.add_argument("--victims", required=True, metavar="NAME[,NAME...]",
                        help="registered victims, or ONNX victim directories (registered under their directory name)")
    parser.add_argument("--attacks", default="none", metavar="NAME[,NAME...]",
                        help="registered attacks, or object files NAME.ply (registered under NAME) "
                             "(default: none, the clean control)")
    parser.add_argument("--proposals", default="detector", metavar="SRC[,SRC...]",
                        help="2D proposal sources: detector (the victim's own) and/or gt (ground-truth boxes); "
                             "a victim that does not support a source gets a skipped cell (default: detector)")
    parser.add_argument("--out", required=True, metavar="DIR",
                        help="output directory (cell files, summary.json, results.csv, seed_table.md); "
                             "an interrupted run resumes: finished cells of the same configuration are kept")
    parser.add_argument("--force", action="store_true",
                        help="replace finished cells in --out that were computed with another configuration "
                             "(without it the run refuses them up front; each replaced cell is named)")
    parser.add_argument("--data", metavar="DIR",
                        help="KITTI-layout dataset root (default: the embedded procedural dataset in the cache, "
                             "generated if missing)")
    parser.add_argument("--split", default="val", help="split name, ImageSets/<split>.txt (default: val)")
    parser.add_argument("--max-frames", type=int, metavar="N",
                        help=f"evaluate only the first N frames of the split, {frames[0]}..{frames[1]} (default on "
                             "the embedded val split: the first DEFAULT_VAL_FRAMES, see --full; elsewhere: all)")
    parser.add_argument("--full", action="store_true",
                        help="evaluate the whole split (the embedded val split's default is a first-N slice)")
    parser.add_argument("--seed", type=int, default=0, metavar="S",
                        help=f"run seed, {seeds[0]}..{seeds[1]}: attack randomness per frame, and seed= of victims "
                             "that take one (default 0)")
    parser.add_argument("--batch-size", type=int, default=4, metavar="B",
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
    parser.add_argument("--bootstrap", type=int, default=1000, metavar="R",
                        help="bootstrap resamples of the frames for the 95 %% confidence interval of every AP and "
                             f"(paired) AP drop, {resamples[0]}..{resamples[1]}; 0: none (default 1000)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars on stderr")


def check_numbers(args: argparse.Namespace) -> None:
    """Every numeric option of ``run`` in its range (:data:`FRAMES_RANGE` ...), before any work."""
    if args.max_frames is not None:
        check_range("--max-frames", args.max_frames, *FRAMES_RANGE, "frames")
    check_range("--seed", args.seed, *SEED_RANGE, "run seed")
    check_range("--batch-size", args.batch_size, *BATCH_RANGE, "frames per detect call")
    check_range("--workers", args.workers, *PROCESSES_RANGE, "dataset generation processes")
    check_range("--jobs", args.jobs, *PROCESSES_RANGE, "worker processes")
    check_bootstrap(args.bootstrap)


def run(args: argparse.Namespace) -> int:
    import sys

    from robustbench3d.attacks.controls import resolve_attack_references
    from robustbench3d.fileio import check_output_dir, remove_created_dir
    from robustbench3d.runner import RunConfig, run_benchmark, summary_table
    from robustbench3d.runner.config import default_max_frames
    from robustbench3d.runner.executors import make_executor
    from robustbench3d.seed_table import SEED_TABLE_FILE, seed_table_text
    from robustbench3d.victims import resolve_victim_references

    out = check_output_dir(args.out, "--out")
    check_numbers(args)
    created = not out.exists()

    victims, victim_args = resolve_victim_references(_names(args.victims),
                                                     parse_factory_args(args.victim_arg, "--victim-arg"))
    attacks, attack_args = resolve_attack_references(_names(args.attacks),
                                                     parse_factory_args(args.attack_arg, "--attack-arg"))
    max_frames = default_max_frames(args.max_frames, args.full, args.data, args.split)
    config = RunConfig(
        victims=tuple(victims), attacks=tuple(attacks),
        proposals=tuple(_names(args.proposals)), out=args.out, data=args.data, split=args.split,
        max_frames=max_frames, seed=args.seed, batch_size=args.batch_size,
        victim_args=victim_args,
        attack_args=attack_args,
        workers=args.workers, progress=not args.no_progress, bootstrap=args.bootstrap, force=args.force,
    )
    executor = make_executor(args.executor, args.jobs, args.address)  # a Ray address is checked here
    print(frames_line(max_frames, args.max_frames, args.full, args.data, args.split), file=sys.stderr, flush=True)
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
    print(summary_table(report.summary))
    print(f"results: {report.out / 'summary.json'}, {report.out / 'results.csv'}")
    if report.earlier or report.left_out:
        print(f"{len(report.earlier)} of these cells come from earlier runs into {report.out}; "
              f"{len(report.left_out)} cell(s) there are left out (not comparable with this run, listed above)")
    print()
    print(seed_table_text(report.summary))
    print(f"seed table: {report.out / SEED_TABLE_FILE}")
    if report.failed:
        print(f"robustbench3d: {len(report.failed)} of {len(report.outcomes)} cells failed", file=sys.stderr)
        return 1
    return 0
