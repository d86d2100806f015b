"""One sweep: plan every point, train the objects that are missing, score everything in one benchmark run, write
the files.

``DIR`` (``--out``) is new, empty or a sweep directory (``sweep.json``, ``objects/``, ``run/``): a sweep there is
resumed. Its ``sweep.json`` records the configuration; another one (any option but the grid ``--levels``/``--radii``
and how it executes) is refused before any work unless ``--force``. Objects are reused, resumed or refused as
:mod:`~robustbench3d.sweep.train` says; the run in ``DIR/run`` resumes as ``robustbench3d run`` does (its finished
cells of the same fingerprint are kept), except that the cells of an object this invocation (re)trained are removed
first (their object changed; one line each). ``sweep.json``, ``.csv``, ``.md`` and ``.png`` are derived files,
rewritten at the end of every invocation.
"""

from __future__ import annotations

import inspect
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from robustbench3d.errors import DataFormatError, RobustBenchError
from robustbench3d.sweep.grid import Point, benign_name, points, radii_of
from robustbench3d.sweep.output import JSON_FILE, read_doc, write_all

FORMAT = "robustbench3d.sweep/1"
#: What a sweep directory holds at its top level (anything else makes ``--out`` someone else's directory).
SWEEP_ENTRIES = ("sweep.json", "sweep.csv", "sweep.md", "sweep.png", "objects", "run")
#: Config keys that may change between invocations on the same ``--out`` (the grid grows or shrinks).
GRID_KEYS = ("levels", "radii")


@dataclass(frozen=True)
class SweepConfig:
    """What ``robustbench3d sweep`` was asked (its ``--help``); ``train``: TrainConfig overrides (None: the
    shipped recipe's value)."""

    victim: str
    mode: str
    levels: tuple[int, ...]
    radii: tuple[float, ...]
    data: str | None = None
    split: str = "val"
    max_frames: int | None = None
    train_split: str = "train"
    train_max_frames: int | None = None
    proposals: tuple[str, ...] = ("detector", "gt")
    seed: int = 0
    bootstrap: int = 1000
    train: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return {"victim": self.victim, "mode": self.mode, "levels": list(self.levels), "radii": list(self.radii),
                "data": None if self.data is None else str(Path(self.data).resolve()), "split": self.split,
                "max_frames": self.max_frames, "train_split": self.train_split,
                "train_max_frames": self.train_max_frames, "proposals": list(self.proposals), "seed": self.seed,
                "bootstrap": self.bootstrap, "train": {k: v for k, v in sorted(self.train.items()) if v is not None}}


@dataclass(frozen=True)
class Execution:
    """How the sweep runs (not recorded as configuration): executor kind, workers, Ray address, progress."""

    executor: str = "local"
    workers: int = 1
    address: str | None = None
    progress: bool = False
    force: bool = False


def _settled(config: dict[str, Any]) -> dict[str, Any]:
    """A sweep configuration without the training settings a resumed training may change (when it stops:
    :data:`~robustbench3d.attacks.train_config.RESUMABLE`)."""
    from robustbench3d.attacks.train_config import RESUMABLE

    return {**config, "train": {k: v for k, v in dict(config.get("train") or {}).items() if k not in RESUMABLE}}


def check_out_dir(out: Path, config: dict[str, Any], force: bool, say: Callable[[str], None]) -> None:
    """``--out``'s written-once rule (module doc), before any work."""
    if not out.is_dir() or not any(out.iterdir()):
        return
    foreign = sorted(p.name for p in out.iterdir() if p.name not in SWEEP_ENTRIES and not p.name.startswith("."))
    if foreign:
        if not force:
            raise RobustBenchError(f"--out {out}: not a sweep directory (holds {foreign[0]}); choose another --out, "
                                   "or pass --force to write into it (nothing was written)")
        say(f"sweep: writing into {out}, which is not a sweep directory (--force)")
        return
    if not (out / JSON_FILE).is_file():
        return  # an interrupted sweep: objects and cells are checked one by one
    try:
        old = _settled(read_doc(out)["config"])
        config = _settled(config)
        diff = [k for k in dict.fromkeys([*old, *config]) if k not in GRID_KEYS and old.get(k) != config.get(k)]
    except (DataFormatError, TypeError, AttributeError) as exc:
        diff = [f"its {JSON_FILE} cannot be read ({exc})"]
    if not diff:
        return
    what = "; ".join(f"{k}: {old.get(k)!r} vs {config.get(k)!r}" if isinstance(old, dict) and k in config else k
                     for k in diff)
    if not force:
        raise RobustBenchError(f"--out {out}: holds a sweep of another configuration (on disk vs this run: {what}); "
                               "pass --force to replace it, or choose another --out (nothing was written)")
    say(f"sweep: replacing the sweep of another configuration in {out} (--force): {what}")


class BenignFactory:
    """The registry factory of the benign sphere of one radius (``benign-sphere`` with ``radius``), registered
    under :func:`~robustbench3d.sweep.grid.benign_name`; its identity names the radius, so registering it again
    is a no-op."""

    def __init__(self, radius: float) -> None:
        from robustbench3d.attacks.roof import settings_parameters

        self.radius = radius
        self.__module__ = __name__
        self.__qualname__ = f"BenignFactory[r{radius:.2f}]"
        self.__signature__ = inspect.Signature(settings_parameters())

    def __call__(self, **settings: Any) -> Any:
        from robustbench3d.attacks import ATTACKS

        return ATTACKS.get("benign-sphere").create(radius=self.radius, **settings)


def register_benign(radius: float) -> str:
    """The attack name of the benign sphere of ``radius`` (registered for this process when not the seed's)."""
    from robustbench3d.attacks import ATTACKS
    from robustbench3d.attacks.spec import AttackSpec

    name = benign_name(radius)
    if name == "benign-sphere":
        return name
    return ATTACKS.register_reference(
        name, AttackSpec(factory=BenignFactory(radius),
                         summary=f"control: the undeformed grey sphere, r {radius:.2f} m"),
        origin="robustbench3d sweep", taken=f"attack name {name!r} is taken by another attack")


def train_all(cfg: SweepConfig, ex: Execution, out: Path, pts: list[Point], victim: dict[str, Any],
              data: dict[str, Any], log: Callable[[str], None], say: Callable[[str], None]) -> set[str]:
    """Plan every point (refusals before any training), train those not reused; the names (re)trained."""
    from robustbench3d.sweep.jobs import run_jobs
    from robustbench3d.sweep.train import TrainJob, Wanted, config_record, plan_point, train_config

    jobs = []
    for p in pts:
        conf = train_config(p, cfg.train)
        plan = plan_point(p, out, Wanted(config_record(conf), victim, data), ex.force)
        if plan.note:
            say(plan.note)
        if plan.action != "reuse":
            jobs.append(TrainJob(p.name, str(out / p.file), config_record(conf), cfg.victim, victim, cfg.data,
                                 cfg.train_split, cfg.train_max_frames, resume=plan.action == "resume",
                                 force=plan.force, warm_workers=1, progress=ex.progress and ex.workers == 1))
    if not jobs:
        return set()
    (out / "objects").mkdir(parents=True, exist_ok=True)
    log(f"sweep: training {len(jobs)} object(s) ({', '.join(j.name for j in jobs)}) on {ex.executor} workers "
        f"(up to {ex.workers} at a time)")
    done = set()
    for result in run_jobs(jobs, ex.executor, ex.workers, ex.address, log):
        made_by = result["made_by"]
        stopped = made_by.get("stopped") or {}
        log(f"sweep: {result['name']}: trained, {made_by['steps']} steps ({stopped.get('reason', '?')})")
        done.add(result["name"])
    return done


def _object_attack(ply: Path) -> str:
    """The attack name of the object file ``ply`` (its stem). A name this process registered earlier for another
    object file of the same stem (an earlier sweep in another directory, in the same Python session) is released
    first: object-file references are per-process registrations."""
    from robustbench3d.attacks import ATTACKS
    from robustbench3d.attacks.zoo import ORIGIN_OBJECT_FILE, ObjectFileFactory

    name = ply.stem
    if name in ATTACKS and ATTACKS.entry(name).origin == ORIGIN_OBJECT_FILE:
        factory = getattr(ATTACKS.get(name), "factory", None)
        if isinstance(factory, ObjectFileFactory) and factory.path != ply.resolve():
            ATTACKS.unregister(name)
    return ATTACKS.resolve(str(ply))


def score_all(cfg: SweepConfig, ex: Execution, out: Path, pts: list[Point], retrained: set[str],
              log: Callable[[str], None], say: Callable[[str], None]) -> Any:
    """One benchmark run in ``out/run``: every point's object, the clean control, each radius's benign sphere."""
    from robustbench3d.runner import RunConfig, run_benchmark
    from robustbench3d.runner.executors import make_executor

    objects = [_object_attack(out / p.file) for p in pts]
    benign = [register_benign(r) for r in radii_of(pts)]
    for name in sorted(retrained):
        for proposals in cfg.proposals:
            cell = out / "run" / "cells" / f"{cfg.victim}+{name}+{proposals}"
            if cell.exists():
                say(f"sweep: removing the cell {cell.name} of the object this sweep retrained")
                shutil.rmtree(cell)
    config = RunConfig(victims=(cfg.victim,), attacks=("none", *benign, *objects), proposals=cfg.proposals,
                       out=out / "run", data=None if cfg.data is None else Path(cfg.data), split=cfg.split,
                       max_frames=cfg.max_frames, seed=cfg.seed, bootstrap=cfg.bootstrap, progress=ex.progress,
                       force=ex.force)
    executor = make_executor(ex.executor, ex.workers, ex.address)
    if executor is None:
        from robustbench3d.runner.shards import worker_setup

        worker_setup()
        return run_benchmark(config, print_fn=log)
    with executor:
        return run_benchmark(config, print_fn=log, executor=executor)


def _point_record(p: Point, out: Path) -> dict[str, Any]:
    from robustbench3d.attacks.objectfile import read_object_file
    from robustbench3d.sweep.train import read_cost

    loaded = read_object_file(out / p.file)
    m = loaded.made_by
    stopped = m.get("stopped") or {}
    curve = m.get("curve") or {}
    sessions = read_cost(out / p.file)
    return {"name": p.name, "mode": p.mode, "level": p.level, "radius": p.radius, "vertex_colours": p.vertex_colours,
            "faces": p.family.n_faces, "seed_point": p.seed_point,
            "object": {"path": p.file, "sha256": loaded.sha256},
            "training": {"steps": m.get("steps"), "object_step": m.get("object_step"),
                         "stopped": stopped.get("reason"), "stop_line": stopped.get("line"),
                         "cars": m.get("cars"), "config": m.get("config"),
                         "heldout_best": curve.get("best"), "curve": (curve.get("files") or {})},
            "cost": {"train_wall_s": round(sum(s["wall_s"] for s in sessions), 3) if sessions else None,
                     "train_cpu_s": round(sum(s["cpu_s"] for s in sessions), 3) if sessions else None,
                     "train_steps_wall_s": m.get("wall_time_s"), "sessions": sessions}}


def run_sweep(cfg: SweepConfig, ex: Execution, out: Path, log: Callable[[str], None] = print,
              say: Callable[[str], None] | None = None) -> tuple[list[Path], dict[str, Any]]:
    """Train, score and write (module doc); the files written and the sweep document."""
    from robustbench3d.attacks.train_run import training_split, victim_record
    from robustbench3d.datasets import load_ground_truth, resolve_dataset
    from robustbench3d.provenance import host_provenance, library_versions, utc_now
    from robustbench3d.results import CellResult, read_summary
    from robustbench3d.sweep.analysis import Scorer, scores, smallest_sentence
    from robustbench3d.victims import VICTIMS

    say = say or log
    VICTIMS.entry(cfg.victim)  # an unknown name fails before any work
    pts = points(cfg.mode, cfg.levels, cfg.radii)
    check_out_dir(out, cfg.as_dict(), ex.force, say)
    started = utc_now()
    victim = victim_record(cfg.victim)
    data = training_split(cfg.data, cfg.train_split, cfg.train_max_frames, progress=ex.progress, lazy=True,
                          log=log).identity
    retrained = train_all(cfg, ex, out, pts, victim, data, log, say)
    report = score_all(cfg, ex, out, pts, retrained, log, say)
    summary = read_summary(out / "run" / "summary.json")
    dataset = resolve_dataset(cfg.data, cfg.split, lazy=True, max_frames=cfg.max_frames, log=log)
    gt = load_ground_truth(dataset, cfg.max_frames)
    records = [_point_record(p, out) for p in pts]
    attacks = {p.name: {"kind": "object", "name": p.name, "level": p.level, "radius": p.radius,
                        "vertex_colours": p.vertex_colours, "seed_point": p.seed_point} for p in pts}
    for r in radii_of(pts):
        attacks[benign_name(r)] = {"kind": "benign", "name": benign_name(r), "level": None, "radius": r,
                                   "vertex_colours": None, "seed_point": False}
    mine = [c for c in summary if CellResult(c).victim == cfg.victim and CellResult(c).proposals in cfg.proposals]
    rows = scores(mine, attacks, Scorer(out / "run", gt.labels, gt.frame_ids, cfg.bootstrap, cfg.seed))
    for rec in records:  # scoring cost of each point: its cells' wall and CPU seconds
        cells = [r for r in rows if r["attack"] == rec["name"]]
        rec["cost"]["score_wall_s"] = round(sum(r["seconds"] or 0 for r in cells), 3) if cells else None
        rec["cost"]["score_cpu_s"] = round(sum(r["cpu_seconds"] or 0 for r in cells), 3) if cells else None
    seed = next(p for p in pts if p.seed_point)
    doc: dict[str, Any] = {
        "format": FORMAT, "config": cfg.as_dict(), "dataset": report.dataset,
        "training_data": data, "victim": victim,
        "seed_point": {"name": seed.name, "level": seed.level, "radius": seed.radius},
        "points": records, "controls": [a for a in attacks.values() if a["kind"] == "benign"], "scores": rows,
        "run": {"dir": "run", "summary": "run/summary.json"},
    }
    doc["sentences"] = {v: smallest_sentence(doc, v) for v in dict.fromkeys(r["victim"] for r in rows
                                                                              if r["kind"] == "object")}
    doc["provenance"] = {"started": started, "finished": utc_now(), "host": host_provenance(),
                         "libraries": library_versions(),
                         "execution": {"executor": ex.executor, "workers": ex.workers, "address": ex.address}}
    return write_all(out, doc), doc


__all__ = ["FORMAT", "BenignFactory", "Execution", "SweepConfig", "check_out_dir", "register_benign", "run_sweep"]
