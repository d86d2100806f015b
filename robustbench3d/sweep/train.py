"""One universal object per sweep point, trained by ``attack train``'s
:func:`~robustbench3d.attacks.train_run.train_universal` with the same settings but the family.

Settings: those the shipped object of the mode was trained with (``attacks/objects/manifest.json``,
``training.config``), so the seed's point ``l2-r0.40`` is the shipped recipe; an object shipped without the
held-out curve (``eval_every`` 0) gets the curve and plateau stop (:data:`CURVE_DEFAULTS`), since each point must
be trained to its own plateau; options (``--steps``, ``--eval-every``, ...) override; the family's ``level`` and
``radius`` are the point's.

Reuse and resume (decided for every point before any training, :func:`plan_point`): an object file whose
sidecar records this configuration (every field but ``checkpoint_every``), victim (weights sha256) and training
data is kept; one that differs only in when training stops (``steps``, the plateau settings) and whose checkpoint
is beside it is continued (``train_universal``'s ``--resume``), as is a checkpoint without an object file (an
interrupted training; ``train_universal`` refuses a checkpoint of another training). Any other object file is
refused unless ``--force`` (then retrained, its files replaced, one line each).

Each training is a job (:class:`TrainJob`, :func:`train_point`) that also appends its session's wall and CPU
seconds to ``NAME.cost.json`` beside the object (every session, finished or interrupted).
"""

from __future__ import annotations

import dataclasses
import json
import os
import platform
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from robustbench3d.errors import RobustBenchError
from robustbench3d.sweep.grid import Point

#: The held-out curve of a point whose shipped recipe has none: an evaluation every 25 steps (``attack train``'s
#: default) on the last 20 frames of the training split (as the shipped frustum-protocol objects, whose curves
#: were the first; 5 frames make a noisy plateau), the plateau stop's defaults.
CURVE_DEFAULTS = {"eval_every": 25, "eval_frames": 20, "plateau_window": 60, "plateau_tol": 0.004}
#: Config fields that do not change the object (only how often a checkpoint is written).
IGNORED = ("checkpoint_every",)
COST_SUFFIX = ".cost.json"


def shipped_config(mode: str) -> dict[str, Any]:
    """The training config of the shipped object named ``mode`` (empty when none ships)."""
    from robustbench3d.attacks.shipped import read_manifest

    for entry in read_manifest()["objects"]:
        if entry.get("name") == mode:
            return dict((entry.get("training") or {}).get("config") or {})
    return {}


def train_config(point: Point, overrides: Mapping[str, Any]) -> Any:
    """The :class:`~robustbench3d.attacks.train_config.TrainConfig` of ``point`` (module doc); ``overrides``:
    field -> value, None meaning "not given". Bad values raise the config's one-line error."""
    from robustbench3d.attacks.train_config import TrainConfig

    fields = {f.name for f in dataclasses.fields(TrainConfig)}
    base = {k: v for k, v in shipped_config(point.mode).items() if k in fields}
    if not base.get("eval_every"):
        base.update(CURVE_DEFAULTS)
    base.update({k: v for k, v in overrides.items() if v is not None})
    base.update(mode=point.mode, level=point.level, radius=point.radius)
    base["eot"] = tuple(base.get("eot") or ())
    return TrainConfig(**base)


def config_record(config: Any) -> dict[str, Any]:
    """A config as a sidecar records it (``made_by.config``), JSON-normalised."""
    return json.loads(json.dumps({**dataclasses.asdict(config), "eot": list(config.eot)}))


def _comparable(config: Mapping[str, Any]) -> dict[str, Any]:
    from robustbench3d.attacks.train_config import RECORD_DEFAULTS

    d = {**RECORD_DEFAULTS, **json.loads(json.dumps(dict(config)))}
    for name in IGNORED:
        d.pop(name, None)
    return d


@dataclass(frozen=True)
class Wanted:
    """What a point's object must have been made with: config, victim record, training data record."""

    config: dict[str, Any]
    victim: dict[str, Any]
    data: dict[str, Any]


@dataclass(frozen=True)
class Plan:
    """What happens to a point: ``reuse``, ``resume`` or ``train`` (``force``: replacing files), and the line
    to print (None: nothing to say)."""

    action: str
    force: bool = False
    note: str | None = None


def _differences(made_by: Mapping[str, Any], wanted: Wanted) -> list[str]:
    """The fields (``config.steps``, ``victim``, ``training_data``) in which a sidecar differs from ``wanted``."""
    have, want = _comparable(made_by.get("config") or {}), _comparable(wanted.config)
    diff = [f"config.{k}" for k in sorted(set(have) | set(want)) if have.get(k) != want.get(k)]
    norm = json.loads(json.dumps({"victim": wanted.victim, "training_data": wanted.data}))
    diff += [k for k in ("victim", "training_data") if made_by.get(k) != norm[k]]
    return diff


def plan_point(point: Point, out: Path, wanted: Wanted, force: bool) -> Plan:
    """Reuse, resume, train or refuse the point's object (module doc); refusals raise before any training."""
    from robustbench3d.attacks.objectfile import read_object_file, sidecar_path
    from robustbench3d.attacks.train_config import RESUMABLE
    from robustbench3d.attacks.train_run import checkpoint_path

    ply = out / point.file
    ckpt = checkpoint_path(ply)
    if not ply.exists() and not sidecar_path(ply).exists():
        if ckpt.is_file():
            return Plan("resume", force, f"sweep: {point.name}: continuing the interrupted training {ckpt.name}")
        return Plan("train", force)
    try:
        made_by = read_object_file(ply).made_by
        diff = _differences(made_by, wanted)
    except RobustBenchError as exc:
        made_by, diff = {}, [f"unreadable ({exc})"]
    if not diff:
        return Plan("reuse", note=f"sweep: {point.name}: keeping {ply} (same configuration, victim and data)")
    if ckpt.is_file() and all(d.removeprefix("config.") in RESUMABLE for d in diff):
        return Plan("resume", force, f"sweep: {point.name}: continuing its training ({', '.join(diff)} changed)")
    if not force:
        raise RobustBenchError(f"--out: {ply} exists and was made with another configuration ({', '.join(diff)} "
                               "differ); pass --force to retrain it, or choose another --out (nothing was trained)")
    return Plan("train", True, f"sweep: {point.name}: replacing {ply} (--force): {', '.join(diff)} differ")


@dataclass(frozen=True)
class TrainJob:
    """Everything a worker needs to train one point (picklable)."""

    name: str
    out: str
    config: dict[str, Any]
    victim: str
    victim_info: dict[str, Any]
    data: str | None
    split: str
    max_frames: int | None
    resume: bool
    force: bool
    warm_workers: int = 1
    progress: bool = False


def cost_path(ply: str | Path) -> Path:
    """``NAME.cost.json`` beside the object file ``NAME.ply``."""
    ply = Path(ply)
    return ply.with_name(ply.stem + COST_SUFFIX)


def read_cost(ply: str | Path) -> list[dict[str, Any]]:
    """The training sessions recorded beside ``ply`` (empty when none was)."""
    path = cost_path(ply)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (FileNotFoundError, ValueError):
        return []
    return list(doc.get("sessions") or []) if isinstance(doc, dict) else []


def _record_session(ply: Path, session: dict[str, Any]) -> None:
    from robustbench3d.fileio import atomic_write_text

    sessions = [*read_cost(ply), session]
    atomic_write_text(cost_path(ply), json.dumps({"sessions": sessions}, indent=1) + "\n")


def train_point(job: TrainJob, log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Train (or continue) the job's object and return ``{"name", "made_by"}``; the session's cost is appended to
    ``NAME.cost.json`` whether it finished or not. Runs in a worker process (one intra-op thread) or in the
    caller's."""
    from robustbench3d.attacks import train_run
    from robustbench3d.attacks.train_config import TrainConfig
    from robustbench3d.provenance import utc_now
    from robustbench3d.runner.shards import worker_setup
    from robustbench3d.victims import create_victim

    worker_setup()
    say = log or (lambda line: None)
    started, t0, c0 = utc_now(), time.perf_counter(), time.process_time()
    finished = False
    try:
        config = TrainConfig(**{**job.config, "eot": tuple(job.config.get("eot") or ())})
        victim = create_victim(job.victim)
        train = train_run.training_split(job.data, job.split, job.max_frames, progress=False)
        made_by = train_run.train_universal(
            victim, job.victim_info, train.dataset.kitti(), train.gt.frame_ids, train.gt.labels, config, job.out,
            data_identity=train.identity, resume=job.resume,
            force=job.force, progress=job.progress, log=lambda line: say(f"sweep: {job.name}: {line}"),
            workers=job.warm_workers)
        finished = True
    finally:
        _record_session(Path(job.out), {"started": started, "wall_s": round(time.perf_counter() - t0, 3),
                                        "cpu_s": round(time.process_time() - c0, 3), "finished": finished,
                                        "host": platform.node(), "pid": os.getpid(),
                                        "cpu_count": os.cpu_count()})
    return {"name": job.name, "made_by": made_by}


__all__ = ["CURVE_DEFAULTS", "Plan", "TrainJob", "Wanted", "config_record", "cost_path", "plan_point", "read_cost",
           "shipped_config", "train_config", "train_point"]
