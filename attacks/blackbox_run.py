"""The loop of ``attack train --optimizer cma``: generations of the black-box optimiser
(:mod:`~robustbench3d.attacks.blackbox`) until the query budget, with the white-box loop's held-out curve,
plateau stop, checkpoints and output files (:mod:`~robustbench3d.attacks.train_run`).

**One generation** (a "step" of the curve and of ``--eval-every``, ``--checkpoint-every`` and
``--plateau-window``): the strategy proposes ``population`` candidates, each is scored on the generation's
frames (``frames_per_candidate`` queries), and the strategy is told the fitness values. The current object is
the strategy's mean (the candidates are single noisy draws around it).

**The held-out curve** is the white-box one (:mod:`~robustbench3d.attacks.train_curve`: the last frames of the
split, never drawn), with the black-box fitness as its loss: at an evaluation the mean's object attacks the
held-out frames exactly as a benchmark cell does (``attack_rng(seed, frame)``, default settings), one
``detect`` per frame gives both the AP effect and the held-out loss (the mean car score of the module doc of
:mod:`~robustbench3d.attacks.blackbox` over the held-out cars, plus the Laplacian term in the shape modes). The
object file is the state of lowest held-out loss; the plateau stop is the white-box rule in generations. The
curve's queries (the clean held-out frames once, then one per held-out frame per evaluation) are counted apart
from the budget, which pays for the optimisation only.

**Files**: ``OBJ.ply`` and its sidecar (the white-box sidecar's fields, with ``made_by.optimizer`` and
``made_by.queries``; ``made_by.config`` holds the settings that apply to this optimiser and its name), the curve
files, and the checkpoint ``OBJ.cma.json`` (plain JSON: the fitness values of every generation, the curve rows,
the best state's parameters, counters; :mod:`~robustbench3d.attacks.blackbox` says how a resumed run rebuilds
the strategy from them). The written-once rule of :mod:`~robustbench3d.attacks.train_run` holds with this
checkpoint in the place of ``OBJ.train.pt``; the query budget, the checkpoint interval and the plateau settings
may change on ``--resume`` (a larger budget continues the run). A resumed run ends with the bytes of an
uninterrupted one.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from robustbench3d.attacks.base import target_cars
from robustbench3d.attacks.blackbox import (
    BlackBoxSettings,
    ParamSpace,
    QueryObjective,
    car_scores,
    cma_version,
    make_strategy,
    mean_digest,
    shape_penalty,
)
from robustbench3d.attacks.train_config import RESUMABLE, TrainConfig, TrainingError, training_cars
from robustbench3d.attacks.train_curve import (
    HeldOut,
    best_of,
    eval_proposals,
    make_row,
    plateau,
    split_held_out,
    write_curve,
)
from robustbench3d.attacks.train_run import (
    check_outputs,
    check_resumed,
    curve_record,
    held_out_line,
    parametrisation_record,
    progress_bar,
)
from robustbench3d.kitti.dataset import KittiDataset
from robustbench3d.kitti.labels import Labels

CHECKPOINT_FORMAT = "robustbench3d.attack_train_cma_checkpoint/1"
TOOL = "robustbench3d attack train"
#: The config fields (:class:`~robustbench3d.attacks.train_config.TrainConfig`) that the black-box optimiser
#: uses; the others (steps, batch_cars, the Adam steps, the image and box loss settings) are the white-box
#: loss's and are not recorded.
CONFIG_FIELDS = ("mode", "seed", "lambda_lap", "eot", "occlusion", "lidar_boxes", "supersample", "checkpoint_every",
                 "eval_every", "eval_frames", "plateau_window", "plateau_tol", "level", "radius")


def cma_checkpoint_path(out: str | Path) -> Path:
    """The black-box run's checkpoint beside object file ``out``: ``NAME.cma.json``."""
    out = Path(out)
    return out.with_name(out.stem + ".cma.json")


def cma_config(config: TrainConfig, settings: BlackBoxSettings, dimension: int) -> dict[str, Any]:
    """The sidecar's ``made_by.config``: the fields of :data:`CONFIG_FIELDS` as :meth:`TrainConfig.record` writes
    them (the family's only when not the default), the optimiser's name, population and frames per candidate."""
    rec = config.record()
    return {**{k: rec[k] for k in CONFIG_FIELDS if k in rec}, "optimizer": "cma",
            "population": settings.popsize(dimension), "frames_per_candidate": settings.frames_per_candidate}


class _HeldOut(HeldOut):
    """:class:`~robustbench3d.attacks.train_curve.HeldOut` that counts its queries and keeps the detections of
    its last attacked evaluation (the held-out loss reads them: one ``detect`` per frame for both)."""

    def __init__(self, *args: Any) -> None:
        super().__init__(*args)
        self.queries = 0
        self.last: list[Labels] | None = None

    def _detect(self, frame: Any, gt: Labels, record: Any) -> Labels:
        self.queries += 1
        return super()._detect(frame, gt, record)

    def attacked(self, obj: Any) -> list[Labels]:
        self.last = super().attacked(obj)
        return self.last

    def loss(self) -> float:
        """Mean car score of the held-out cars in the last attacked evaluation (no Laplacian term)."""
        assert self.last is not None
        scores = [car_scores(det, target_cars(gt)) for det, gt in zip(self.last, self.labels, strict=True)]
        return float(np.concatenate(scores).mean())


class _State:
    """What the checkpoint holds (module doc)."""

    def __init__(self) -> None:
        self.fitness: list[list[float]] = []
        self.history: list[dict[str, float]] = []
        self.rows: list[dict[str, Any]] = []
        self.best: dict[str, Any] | None = None
        self.queries = 0
        self.eval_queries = 0
        self.eval_s = 0.0
        self.elapsed_s = 0.0

    @property
    def generation(self) -> int:
        return len(self.fitness)

    def to_json(self, identity: dict[str, Any], es: Any) -> str:
        return json.dumps({"format": CHECKPOINT_FORMAT, "identity": identity, "generation": self.generation,
                           "queries": self.queries, "eval_queries": self.eval_queries, "fitness": self.fitness,
                           "history": self.history, "rows": self.rows, "best": self.best, "eval_s": self.eval_s,
                           "elapsed_s": self.elapsed_s,
                           "check": {"mean_sha256": mean_digest(es.mean), "sigma": float(es.sigma)}}) + "\n"


def _read_checkpoint(path: Path, identity: dict[str, Any]) -> dict[str, Any]:
    """The checkpoint's JSON, refused (one line naming the file and field) if it is not one of this training."""
    from robustbench3d.errors import DataFormatError

    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DataFormatError(path, f"not a readable black-box checkpoint ({type(exc).__name__})") from None
    if not isinstance(data, dict) or data.get("format") != CHECKPOINT_FORMAT:
        raise DataFormatError(path, f"expected {CHECKPOINT_FORMAT!r}", field="format")
    have = data.get("identity")
    if have != identity:
        have = have if isinstance(have, dict) else {}
        diff = sorted(k for k in set(have) | set(identity) if k not in ("config", "optimizer")
                      and have.get(k) != identity.get(k))
        for part in ("config", "optimizer"):
            hc = have.get(part) if isinstance(have.get(part), dict) else {}
            wc = identity[part]
            diff += sorted(f"{part}.{k}" for k in set(hc) | set(wc) if hc.get(k) != wc.get(k))
        raise TrainingError(f"{path}: field 'identity': the checkpoint belongs to another training "
                            f"({', '.join(diff)} differ); use another --out or drop --resume")
    fitness = data.get("fitness")
    if not isinstance(fitness, list) or not all(isinstance(f, list) and all(isinstance(v, float) for v in f)
                                                for f in fitness):
        raise DataFormatError(path, "expected a list of lists of numbers", field="fitness")
    return data


def _replay(es: Any, data: dict[str, Any], path: Path) -> None:
    """Rebuild the strategy's state: ask/tell with the recorded fitness values, then check the mean and step
    size against the checkpoint's (module doc of :mod:`~robustbench3d.attacks.blackbox`)."""
    for values in data["fitness"]:
        candidates = es.ask()
        if len(candidates) != len(values):
            raise TrainingError(f"{path}: field 'fitness': a generation of {len(values)} values for a population "
                                f"of {len(candidates)}; use another --out or drop --resume")
        es.tell(candidates, values)
    check = data.get("check") or {}
    if check.get("mean_sha256") != mean_digest(es.mean) or check.get("sigma") != float(es.sigma):
        raise TrainingError(f"{path}: field 'check': replaying the recorded generations with cma {cma_version()} "
                            "does not give the strategy the checkpoint recorded (another cma version?); use "
                            "another --out or drop --resume")


class BlackBoxRun:
    """The generations, evaluations and checkpoints of one run (module doc)."""

    def __init__(self, objective: QueryObjective, space: ParamSpace, settings: BlackBoxSettings,
                 heldout: _HeldOut | None, config: TrainConfig, out: Path, identity: dict[str, Any],
                 say: Callable[[str], None]) -> None:
        self.objective, self.space, self.settings, self.heldout = objective, space, settings, heldout
        self.config, self.out, self.identity, self.say = config, out, identity, say
        self.popsize = settings.popsize(space.dimension)
        self.per_generation = settings.generation_queries(space.dimension)
        self.es = make_strategy(space, self.popsize, config.seed)
        self.state = _State()
        self.ckpt = cma_checkpoint_path(out)
        self.stop: str | None = None
        self.title = f"{config.name} (cma) against {identity['victim'].get('name', '?')}"

    def resume(self, data: dict[str, Any]) -> None:
        """Continue the checkpoint ``data`` (already checked by :func:`_read_checkpoint`)."""
        _replay(self.es, data, self.ckpt)
        s = self.state
        s.fitness, s.history, s.rows, s.best = data["fitness"], data["history"], data["rows"], data["best"]
        s.queries, s.eval_queries = int(data["queries"]), int(data["eval_queries"])
        s.eval_s, s.elapsed_s = float(data["eval_s"]), float(data["elapsed_s"])
        self.objective.queries = s.queries
        if self.heldout is not None:
            self.heldout.queries = s.eval_queries

    def generations(self) -> int:
        """The generations the budget pays for in all."""
        return self.settings.query_budget // self.per_generation

    def frames_to_come(self) -> list[str]:
        """The training frames the remaining generations draw, in order of first use (every frame once)."""
        seen: dict[int, None] = {}
        for g in range(self.state.generation, self.generations()):
            seen.update(dict.fromkeys(self.objective.frames(g, self.settings.frames_per_candidate)))
            if len(seen) == len(self.objective.usable):
                break
        return [self.objective.frame_ids[i] for i in seen]

    def current_object(self) -> Any:
        return self.space.object_at(self.es.mean)

    def _generation(self) -> None:
        """Ask, score every candidate on the generation's frames, tell."""
        g = self.state.generation
        frames = self.objective.frames(g, self.settings.frames_per_candidate)
        candidates = self.es.ask()
        values = [self.objective.fitness(self.space.object_at(x), g, frames) for x in candidates]
        self.es.tell(candidates, values)
        s = self.state
        s.fitness.append([float(v) for v in values])
        s.queries += self.per_generation
        assert s.queries == self.objective.queries, (s.queries, self.objective.queries)
        s.history.append({"fitness_mean": float(np.mean(values)), "fitness_best": float(np.min(values)),
                          "fitness_median": float(np.median(values)), "sigma": float(self.es.sigma),
                          "queries": s.queries})

    def train(self, progress: bool, on_generation: Callable[[BlackBoxRun], None] | None) -> None:
        s, config = self.state, self.config
        if self.heldout is not None:
            if s.generation == 0 and not s.rows:
                self._evaluate_regular()
            if s.rows and s.rows[-1]["step"] == s.generation:  # a resumed run that stopped here stops again
                self.stop = plateau(s.rows, config.plateau_window, config.plateau_tol)
        bar = progress_bar(self.generations() * self.per_generation, s.queries, progress, f"{config.name} (cma)",
                           "query")
        try:
            while self.stop is None and s.queries + self.per_generation <= self.settings.query_budget:
                t0 = time.perf_counter()
                self._generation()
                s.elapsed_s += time.perf_counter() - t0
                h = s.history[-1]
                bar.set_postfix_str(f"fitness mean {h['fitness_mean']:.4g} best {h['fitness_best']:.4g} "
                                    f"sigma {h['sigma']:.3g}")
                bar.update(self.per_generation)
                if self.heldout is not None and s.generation % config.eval_every == 0:
                    self._evaluate_regular()
                    self.stop = plateau(s.rows, config.plateau_window, config.plateau_tol)
                last = s.queries + self.per_generation > self.settings.query_budget
                if s.generation % config.checkpoint_every == 0 or last or self.stop:
                    self.save_checkpoint()
                if on_generation is not None:
                    on_generation(self)
        finally:
            bar.close()
        if self.stop is not None:
            self.say(self.stop)

    def save_checkpoint(self) -> None:
        from robustbench3d.fileio import atomic_write_text

        atomic_write_text(self.ckpt, self.state.to_json(self.identity, self.es))
        if self.heldout is not None:
            write_curve(self.out, self.state.rows, self.title)

    def _train_loss(self, step: int) -> float | None:
        """Mean fitness of the candidates of the generations since the previous regular evaluation."""
        rows = self.state.rows
        since = rows[-1]["step"] if rows else step
        hist = self.state.history[since:step]
        return float(np.mean([h["fitness_mean"] for h in hist])) if hist else None

    def _evaluate(self, step: int) -> dict[str, Any]:
        """The curve row of the strategy's mean at generation ``step``."""
        assert self.heldout is not None
        t0 = time.perf_counter()
        obj = self.current_object()
        effect = self.heldout.effect(obj)
        losses: dict[str, float] = {"total": self.heldout.loss() + shape_penalty(obj, self.config)}
        if self.config.kind.shape:
            from robustbench3d.attacks.object import laplacian_smoothness

            losses["laplacian"] = laplacian_smoothness(obj.vertices())
        row = make_row(step, self._train_loss(step), losses, effect, self.state.rows)
        took = time.perf_counter() - t0
        self.state.eval_s += took
        self.state.eval_queries = self.heldout.queries
        rel = "n/a" if row["relative_drop"] is None else f"{row['relative_drop']:.1%}"
        asr = "n/a" if row["asr"] is None else f"{row['asr']:.1%}"
        self.say(f"generation {step} ({self.state.queries} queries): held-out loss {row['heldout_loss']:.4g}"
                 f"{' (best)' if row['best'] else ''}, relative drop {rel}, ASR {asr} ({took:.1f} s)")
        return row

    def _evaluate_regular(self) -> None:
        row = self._evaluate(self.state.generation)
        self.state.rows.append(row)
        if row["best"]:
            self.state.best = {"step": row["step"], "x": [float(v) for v in self.es.mean]}

    def finish(self) -> tuple[Any, int, list[dict[str, Any]]]:
        """(the object to write, the generation of its state, every curve row), as the white-box loop's."""
        s = self.state
        if self.heldout is None:
            return self.current_object(), s.generation, []
        rows = list(s.rows)
        if not rows or rows[-1]["step"] != s.generation:
            rows.append(self._evaluate(s.generation))
        write_curve(self.out, rows, self.title)
        best = best_of(rows)
        assert best is not None
        if best["step"] == s.generation:
            return self.current_object(), s.generation, rows
        assert s.best is not None and s.best["step"] == best["step"]
        return self.space.object_at(np.asarray(s.best["x"], dtype=np.float64)), best["step"], rows


def _identity(config: TrainConfig, settings: BlackBoxSettings, dimension: int, victim_info: dict[str, Any],
              data_identity: dict[str, Any]) -> dict[str, Any]:
    """What a resumed run must share with the checkpoint: the config but its resumable fields, the optimiser's
    settings but the budget, the victim and the data."""
    conf = cma_config(config, settings, dimension)
    for name in RESUMABLE:
        conf.pop(name, None)
    if config.eval_every == 0:
        conf["eval_frames"] = 0
    return json.loads(json.dumps({"config": conf, "optimizer": settings.identity(dimension, cma_version()),
                                  "victim": victim_info, "data": data_identity}))


def query_proposals(config: TrainConfig, victim: Any) -> str:
    """The proposal mode of every query and of the held-out curve: the white-box curve's
    (:func:`~robustbench3d.attacks.train_curve.eval_proposals`: the victim's own 2D detector in the modes with a
    texture, else ``--lidar-boxes``), except that a victim which finds its own objects (it lists ``"detector"``
    in ``supported_proposals`` but not ``"gt"``, e.g. ``pointpillars``) gets ``"detector"`` for the default
    ``--lidar-boxes gt``, as the white-box trainer scores such a victim. Decided by ``supported_proposals``, not
    by the white-box oracles: a black-box victim that takes proposals (an ONNX cascade) keeps ``--lidar-boxes``.
    Any other mode the victim does not list is refused by :func:`check_victim`."""
    source = eval_proposals(config)
    listed = tuple(getattr(victim, "supported_proposals", ()))
    if source == "gt" and "gt" not in listed and "detector" in listed:
        return "detector"
    return source


def check_victim(victim: Any, name: str, source: str) -> None:
    """Refuse a victim that is not a Detector or does not take the queries' proposals."""
    from robustbench3d.victims.base import Detector

    if not isinstance(victim, Detector):
        raise TrainingError(f"victim {name!r} cannot be attacked: it does not implement Detector (detect, "
                            "supported_proposals)")
    if source not in victim.supported_proposals:
        hint = " (pass --lidar-boxes with one of those)" if source != "detector" else ""
        raise TrainingError(f"victim {name!r} does not take the proposals {source!r} the queries need (it takes "
                            f"{', '.join(victim.supported_proposals)}){hint}")


def train_blackbox(victim: Any, victim_info: dict[str, Any], kitti: KittiDataset, frame_ids: list[str],
                   labels: list[Labels], config: TrainConfig, settings: BlackBoxSettings, out: str | Path, *,
                   data_identity: dict[str, Any] | None = None, resume: bool = False, force: bool = False,
                   progress: bool = True, on_generation: Callable[[BlackBoxRun], None] | None = None,
                   log: Callable[[str], None] | None = None, workers: int = 1) -> dict[str, Any]:
    """Optimise the object with the black-box optimiser (module doc) on ``frame_ids`` but the held-out ones,
    write it to ``out`` and return its sidecar's ``made_by``. Arguments as
    :func:`~robustbench3d.attacks.train_run.train_universal`'s; ``settings``: the optimiser's;
    ``on_generation`` is called after every generation (tests use it to interrupt a run)."""
    from robustbench3d.attacks.objectfile import save_object

    out = Path(out)
    say = log if log is not None else (lambda line: None)
    data_identity = data_identity or {}
    name = str(victim_info.get("name", type(victim).__name__))
    source = query_proposals(config, victim)
    check_victim(victim, name, source)
    space = ParamSpace(config)
    train_ids, train_labels, held_ids, held_labels = split_held_out(frame_ids, labels,
                                                                    config.held_out(len(frame_ids)))
    heldout = _HeldOut(victim, kitti, held_ids, held_labels, source, config.seed) if held_ids else None
    held_line = held_out_line(config, heldout, len(frame_ids))
    if heldout is not None and heldout.cars == 0:
        heldout = None
    ckpt = cma_checkpoint_path(out)
    notes = check_outputs(out, force=force, resume=resume, curve=heldout is not None, ckpt=ckpt)
    objective = QueryObjective(victim, kitti, train_ids, train_labels, config, source)
    _check_budget(objective, settings, space, kitti, len(train_ids))
    identity = _identity(config, settings, space.dimension, victim_info, data_identity)
    run = BlackBoxRun(objective, space, settings, heldout, config, out, identity, say)
    if resume and ckpt.is_file():
        data = _read_checkpoint(ckpt, identity)
        run.resume(data)
        notes += check_resumed(out, {"config": cma_config(config, settings, space.dimension), "victim": victim_info,
                                     "training_data": data_identity}, force,
                               run.state.rows if heldout is not None else None, run.state.generation, ckpt=ckpt)
    for line in notes:
        say(line)
    say(held_line)
    say(f"cma: {space.dimension} parameters, population {run.popsize} x {settings.frames_per_candidate} frame(s) = "
        f"{run.per_generation} queries per generation, {run.generations()} generation(s) in the budget of "
        f"{settings.query_budget} queries" + _remainder(settings, run.per_generation))
    _warm(run, workers=workers, progress=progress, log=say)
    run.train(progress, on_generation)
    obj, object_step, rows = run.finish()
    made_by = _made_by(out, run, victim_info, data_identity, rows, object_step, len(training_cars(train_labels)))
    save_object(out, obj, made_by)
    return made_by


def _remainder(settings: BlackBoxSettings, per_generation: int) -> str:
    left = settings.query_budget % per_generation
    return f" ({left} left unused: less than one generation)" if left else ""


def _check_budget(objective: QueryObjective, settings: BlackBoxSettings, space: ParamSpace, kitti: KittiDataset,
                  frames: int) -> None:
    """Refuse training data without target cars, more frames per candidate than frames with cars, and a budget
    below one generation (before any query)."""
    if not objective.usable:
        raise TrainingError(f"the training data ({frames} frame(s) of split {kitti.split!r} under {kitti.root}) has "
                            "no target cars (label type Car): nothing to attack")
    if settings.frames_per_candidate > len(objective.usable):
        raise TrainingError(f"--frames-per-candidate {settings.frames_per_candidate}: the training frames have "
                            f"only {len(objective.usable)} frame(s) with target cars")
    per = settings.generation_queries(space.dimension)
    if settings.query_budget < per:
        raise TrainingError(f"--query-budget {settings.query_budget}: one generation takes {per} queries "
                            f"(population {settings.popsize(space.dimension)} x --frames-per-candidate "
                            f"{settings.frames_per_candidate})")


def _warm(run: BlackBoxRun, *, workers: int, progress: bool, log: Callable[[str], None]) -> None:
    """Compute the exact-occlusion scene depths the remaining generations and the held-out evaluations read
    (as :func:`~robustbench3d.attacks.train_run.warm_depths` does for the white-box loop)."""
    from robustbench3d.attacks.depth_cache import attack_depth_jobs, synth_key, warm_scene_depths

    kitti = run.objective.kitti
    key = synth_key(kitti.root)
    if key is None:
        return
    obj = run.current_object()
    jobs = attack_depth_jobs(run.objective.attack(obj), kitti, run.frames_to_come())
    if run.heldout is not None:
        jobs += run.heldout.depth_jobs(obj)
    if jobs:
        warm_scene_depths(Path(kitti.root).resolve(), key, jobs, workers=workers, progress=progress, log=log)


def _made_by(out: Path, run: BlackBoxRun, victim_info: dict[str, Any], data_identity: dict[str, Any],
             rows: list[dict[str, Any]], object_step: int, cars: int) -> dict[str, Any]:
    """The sidecar's ``made_by`` of the finished run (the white-box fields, module doc)."""
    from robustbench3d import __version__
    from robustbench3d.victims.spec import PROTOCOL_LABELS

    s, config, settings = run.state, run.config, run.settings
    if run.stop is not None:
        stopped = {"reason": "plateau", "step": s.generation, "line": run.stop}
    else:
        stopped = {"reason": "query budget", "step": s.generation,
                   "line": f"reached --query-budget {settings.query_budget} ({s.queries} queries used)"}
    curve = None if run.heldout is None else curve_record(out, config, run.heldout, rows, object_step, s.eval_s)
    hist = s.history
    weights = {"car_score": 1.0, **({"laplacian": config.lambda_lap} if config.kind.shape else {})}
    return {
        "attack": config.mode, "tool": TOOL, "package_version": __version__,
        "victim": victim_info, "training_data": data_identity,
        "config": cma_config(config, settings, run.space.dimension),
        "seed": config.seed, "steps": s.generation, "cars": cars,
        "object_step": object_step, "stopped": stopped, "curve": curve,
        "parametrisation": parametrisation_record(config, object="the CMA-ES mean"),
        "lidar_proposals": PROTOCOL_LABELS.get(run.objective.source) if config.kind.lidar else None,
        "optimizer": settings.record(run.space.dimension, cma_version()),
        "queries": {"proposals": run.objective.source, "budget": settings.query_budget, "used": s.queries,
                    "per_generation": run.per_generation, "held_out": s.eval_queries,
                    "rule": "one detect of one attacked frame"},
        "losses": {"weights": weights, "first_step": hist[0] if hist else None,
                   "last_step": hist[-1] if hist else None, "mean_last_10": _mean_history(hist[-10:])},
        "drop_estimate": None, "wall_time_s": round(s.elapsed_s, 3),
    }


def _mean_history(hist: list[dict[str, float]]) -> dict[str, float] | None:
    if not hist:
        return None
    return {k: float(np.mean([h[k] for h in hist])) for k in hist[0] if k != "queries"}
