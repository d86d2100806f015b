"""One tradeoff run: dataset, sweeps, cells measured, points scored, files written."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from robustbench3d.datasets import dataset_identity, load_ground_truth, resolve_dataset
from robustbench3d.errors import RobustBenchError
from robustbench3d.metrics import HEADLINE
from robustbench3d.provenance import host_provenance, library_versions, utc_now
from robustbench3d.tradeoff.analysis import Scorer, score
from robustbench3d.tradeoff.measure import CellMeasure, CellPlan, Context, measure_cell, plan_cell, warm_caches
from robustbench3d.tradeoff.outdir import check_cells
from robustbench3d.tradeoff.output import write_all
from robustbench3d.tradeoff.sweeps import CLEAN, SWEEP_NAMES, Setting, Sweep, VictimDefaults, build_sweeps, cells_of


@dataclass(frozen=True)
class TradeoffConfig:
    """What ``robustbench3d tradeoff`` was asked (see its ``--help``)."""

    victim: str = "fpointnet-v1-lite"
    attack: str = "adv-object"
    proposals: str = "detector"
    frames: int = 50
    data: Path | None = None
    split: str = "val"
    sweeps: tuple[str, ...] = SWEEP_NAMES
    metric: str = "bev"
    threads: int = 1
    resamples: int = 1000
    tolerance: float = 1.0
    seed: int = 0
    batch_size: int = 4

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["data"] = None if self.data is None else str(self.data)
        d["sweeps"] = list(self.sweeps)
        return d


def victim_defaults(cfg: TradeoffConfig) -> VictimDefaults:
    """The victim's own points per frustum, 2D input size and precision knob (it is created once to see)."""
    import inspect

    from robustbench3d.runner.records import victim_kwargs
    from robustbench3d.victims import VICTIMS, create_victim

    params = inspect.signature(VICTIMS.get(cfg.victim).factory).parameters
    victim = create_victim(cfg.victim, **victim_kwargs(cfg.victim, {}, cfg.seed))
    fidelity = victim.fidelity() if callable(getattr(victim, "fidelity", None)) else {}  # FPointNetCascade's
    size = fidelity.get("input_size")
    return VictimDefaults(num_points=fidelity.get("num_points") if "num_points" in params else None,
                          input_size=tuple(size) if size is not None and "input_size" in params else None,
                          precision="precision" in params)


def run_tradeoff(cfg: TradeoffConfig, out: Path, log: Callable[[str], None] = print, force: bool = False,
                 say: Callable[[str], None] | None = None) -> list[Path]:
    """Measure every cell the sweeps need (reusing finished ones of the same fingerprint in ``out/cells``;
    others are refused before any is measured unless ``force``, :mod:`robustbench3d.tradeoff.outdir`), score,
    write the files. ``say`` gets the lines on kept and replaced cells (default ``log``)."""
    from robustbench3d.victims import VICTIMS

    if cfg.attack == CLEAN:
        raise RobustBenchError("--attack: give an attack to score against the clean control 'none'")
    VICTIMS.entry(cfg.victim)  # unknown names fail before any work
    from robustbench3d.attacks import ATTACKS

    ATTACKS.entry(cfg.attack)
    dataset = resolve_dataset(cfg.data, cfg.split, lazy=True, max_frames=cfg.frames, log=log)
    gt = load_ground_truth(dataset, cfg.frames)
    identity = dataset_identity(dataset, gt)
    sweeps = build_sweeps(cfg.victim, cfg.sweeps, frames=len(gt.frame_ids), defaults=victim_defaults(cfg))
    default = Setting(cfg.victim)
    specs = cells_of(sweeps, default, cfg.attack)
    ctx = Context(kitti=dataset.kitti(), gt=gt, dataset=identity, proposals=cfg.proposals, seed=cfg.seed,
                  batch_size=cfg.batch_size, threads=cfg.threads, out=out)
    plans: list[CellPlan | None] = [plan_cell(spec, ctx) for spec in specs]
    check_cells([p for p in plans if p is not None], out, force, say or log)
    started = utc_now()
    warm_caches(specs, ctx, log)
    measures: dict[str, CellMeasure] = {}
    for i, spec in enumerate(specs):
        plan, plans[i] = plans[i], None  # its attack (and the caches it fills) is released after the cell
        log(f"tradeoff: cell {i + 1}/{len(specs)}: {spec.key}")
        measures[spec.key] = measure_cell(spec, ctx, log, plan)
    key = (HEADLINE.cls, cfg.metric, HEADLINE.recall, HEADLINE.difficulty)
    rows = score(sweeps, measures, cfg.attack, Scorer(gt.labels, cfg.resamples, cfg.seed, key), default)
    host = host_provenance()
    doc = {
        "measured_at": started, "config": cfg.as_dict(), "ap": list(key), "dataset": identity,
        "machine": host["platform"], "provenance": {**host, "libraries": library_versions()},
        "sweeps": {s.name: s.notes for s in sweeps},
        "cells": {k: {**{f: v for f, v in m.record.items() if f != "config"}, "reused": m.reused,
                      "wall_s_total": sum(m.wall_s), "cpu_s_total": sum(m.cpu_s)} for k, m in measures.items()},
        "points": rows,
        "reused_cells": sum(m.reused for m in measures.values()),
    }
    if any(isinstance(s, Sweep) for s in sweeps) and doc["reused_cells"]:
        log(f"tradeoff: {doc['reused_cells']} cell(s) reused from an earlier run in {out} (their timings too)")
    return write_all(out, doc)
