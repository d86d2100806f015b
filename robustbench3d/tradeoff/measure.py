"""Timing and scoring the cells of a tradeoff run, all in this process, on the same frames.

Each :class:`~robustbench3d.tradeoff.sweeps.CellSpec` is measured once per run (settings that share a
cell share its measurement): the victim is created and the attack prepared untimed, then every batch of
frames is attacked, (decimated,) detected and written as KITTI result files, timed per batch in wall
and CPU seconds (:func:`time.perf_counter`, :func:`time.process_time`) with ``threads`` torch threads (the
time spent emulating a sparser scan, :class:`DecimatedScan`, left out: a real sparser sensor does not pay it).
The dataset-level caches the attacked cells read (the clean scans' beam patterns, the scene depth of
each camera sampling) are filled before any cell is timed (:func:`warm_caches`), so every cell is
timed in the same steady state whatever its place in the run. Results go to ``OUT/cells/<id>/``
(``data/`` and ``cell.json``, written last, with the configuration its fingerprint hashes): a rerun with
the same fingerprint reuses a finished cell, timings included (``reused`` says so), so an interrupted run
resumes; a finished cell of another fingerprint is replaced only under ``--force``
(:mod:`robustbench3d.tradeoff.outdir`, checked before any cell is measured).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from robustbench3d import __version__
from robustbench3d.attacks import create_attack
from robustbench3d.attacks.base import Attack, target_cars
from robustbench3d.attacks.record import ObjectRecord
from robustbench3d.datasets import GroundTruth
from robustbench3d.fileio import atomic_write_text
from robustbench3d.kitti.dataset import Frame, KittiDataset
from robustbench3d.kitti.labels import Labels
from robustbench3d.provenance import utc_now
from robustbench3d.runner.cell import (
    PARTIAL,
    attack_rng,
    detect_frames,
    prepare_attack,
    promote,
    remove_results,
    results_complete,
)
from robustbench3d.runner.config import fingerprint
from robustbench3d.runner.effect import read_results
from robustbench3d.runner.records import victim_kwargs, victim_record
from robustbench3d.tradeoff.sweeps import CLEAN, CellSpec
from robustbench3d.victims import create_victim

CELL_FILE = "cell.json"


class DecimatedScan(Attack):
    """``inner``'s attacked frame with every ``k``-th azimuth column of each laser kept
    (:func:`robustbench3d.sensors.scan_density.decimate_azimuth`): a sensor of k x coarser horizontal
    resolution seeing the same scene and object (its record's object returns renumbered in the sparser scan)."""

    def __init__(self, inner: Attack, k: int):
        self.inner, self.k = inner, int(k)
        #: Wall and CPU seconds spent decimating since the last :meth:`take_spent` (the harness's cost of
        #: emulating the sparser sensor, which a real one does not pay; left out of the cell's time).
        self._spent = [0.0, 0.0]

    def take_spent(self) -> tuple[float, float]:
        """(wall, CPU) seconds spent decimating since the last call."""
        out = (self._spent[0], self._spent[1])
        self._spent = [0.0, 0.0]
        return out

    def bind_dataset(self, kitti: KittiDataset) -> None:
        self.inner.bind_dataset(kitti)

    def prepare(self, victim: Any) -> None:
        self.inner.prepare(victim)

    def apply(self, frame: Frame, targets: Labels, rng: np.random.Generator) -> Frame:
        out = self.inner.apply(frame, targets, rng)
        return dataclasses.replace(out, scan=self._decimated(out.scan)[0])

    def apply_recorded(self, frame: Frame, targets: Labels, rng: np.random.Generator) -> tuple[Frame, ObjectRecord]:
        """``inner``'s attacked frame and record, decimated: each car's object returns renumbered to the rows they
        keep in the sparser scan (those dropped with their column leave it)."""
        out, record = self.inner.apply_recorded(frame, targets, rng)
        scan, keep = self._decimated(out.scan)
        if keep is None:
            return dataclasses.replace(out, scan=scan), record
        row = np.cumsum(keep) - 1  # the new row of each kept old row
        returns = tuple(row[r[keep[r]]] for r in record.returns)
        return dataclasses.replace(out, scan=scan), ObjectRecord(record.boxes, returns, record.target_index)

    def _decimated(self, scan: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """(the rows of ``scan`` :func:`~robustbench3d.sensors.scan_density.decimate_azimuth` keeps, the (N,) mask
        of them, None when every row is kept: k = 1), the time spent counted in :meth:`take_spent`."""
        from robustbench3d.sensors.scan_density import decimate_azimuth, point_columns

        w, c = time.perf_counter(), time.process_time()
        keep = None
        if self.k == 1:
            out = decimate_azimuth(scan, self.k)
        else:
            _, column, _ = point_columns(scan)
            keep = (column >= 0) & (column % self.k == 0)
            out = np.asarray(scan)[keep]
        self._spent[0] += time.perf_counter() - w
        self._spent[1] += time.process_time() - c
        return out, keep

    def describe(self) -> dict[str, Any]:
        return {**self.inner.describe(), "scan_decimation": self.k}


@dataclass(frozen=True)
class Context:
    """What every cell of a tradeoff run shares."""

    kitti: KittiDataset
    gt: GroundTruth
    dataset: dict[str, Any]
    proposals: str
    seed: int
    batch_size: int
    threads: int
    out: Path


@dataclass
class CellMeasure:
    """A measured cell: detections per frame and the time of each batch."""

    spec: CellSpec
    detections: list[Labels]
    batch_frames: list[int]
    wall_s: list[float]
    cpu_s: list[float]
    reused: bool
    record: dict[str, Any]

    def time_of(self, frames: int, clock: str = "wall") -> float:
        """Seconds the first ``frames`` frames took (whole batches; a partial batch pro rata)."""
        times = self.wall_s if clock == "wall" else self.cpu_s
        total, left = 0.0, frames
        for n, t in zip(self.batch_frames, times, strict=True):
            take = min(n, left)
            total += t * take / n
            left -= take
            if left <= 0:
                break
        return total


def make_attack(spec: CellSpec, kitti: KittiDataset) -> Attack:
    """The cell's attack, bound to the dataset (wrapped in :class:`DecimatedScan` when decimating)."""
    attack = create_attack(spec.attack, **dict(spec.attack_args))
    attack.bind_dataset(kitti)
    return attack if spec.decimation == 1 else DecimatedScan(attack, spec.decimation)


def cell_config(spec: CellSpec, ctx: Context, victim: dict[str, Any], attack: dict[str, Any]) -> dict[str, Any]:
    """Everything a cell's detections and timings depend on (its sha256 is the cell's fingerprint)."""
    return {"package_version": __version__, "cell": json.loads(spec.key), "victim": victim, "attack": attack,
            "dataset": {k: ctx.dataset[k] for k in ("root", "split", "frames", "sha256", "embedded")},
            "proposals": ctx.proposals, "seed": ctx.seed, "batch_size": ctx.batch_size, "threads": ctx.threads}


def cell_dir(ctx: Context, spec: CellSpec) -> Path:
    """``OUT/cells/<victim>+<attack>+<12 hex of the spec>``."""
    return ctx.out / "cells" / f"{spec.victim}+{spec.attack}+{hashlib.sha256(spec.key.encode()).hexdigest()[:12]}"


@dataclass(frozen=True)
class CellPlan:
    """A cell about to be measured or reused: its victim arguments and record, its attack (made once, the
    instance measured), the configuration and fingerprint, and its directory."""

    spec: CellSpec
    kwargs: dict[str, Any]
    victim: dict[str, Any]
    attack: Attack
    attack_record: dict[str, Any]
    config: dict[str, Any]
    fingerprint: str
    where: Path
    ids: list[str]  # the frames the cell covers


def plan_cell(spec: CellSpec, ctx: Context) -> CellPlan:
    """The :class:`CellPlan` of ``spec`` in ``ctx`` (creates no victim)."""
    kwargs = victim_kwargs(spec.victim, dict(spec.victim_args), ctx.seed)
    vrec = victim_record(spec.victim, kwargs)
    attack = make_attack(spec, ctx.kitti)
    arec = {"name": spec.attack, "params": dict(spec.attack_args), "object": attack.describe()}
    cfg = cell_config(spec, ctx, vrec, arec)
    return CellPlan(spec, kwargs, vrec, attack, arec, cfg, fingerprint(cfg), cell_dir(ctx, spec),
                    list(ctx.gt.frame_ids[:spec.frames]))


def finished_record(where: Path) -> dict[str, Any] | None:
    """The ``cell.json`` of a finished cell directory (a JSON object with a fingerprint), else None."""
    try:
        rec = json.loads((where / CELL_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return rec if isinstance(rec, dict) and isinstance(rec.get("fingerprint"), str) else None


def measure_cell(spec: CellSpec, ctx: Context, log: Callable[[str], None] = print,
                 plan: CellPlan | None = None) -> CellMeasure:
    """Run (or reuse) one cell (``plan``: its :func:`plan_cell`, made here when not given); see the module
    docstring."""
    import torch

    plan = plan if plan is not None else plan_cell(spec, ctx)
    kwargs, vrec, attack, arec, fp, where = (plan.kwargs, plan.victim, plan.attack, plan.attack_record,
                                             plan.fingerprint, plan.where)
    ids = plan.ids
    done = where / CELL_FILE
    rec = finished_record(where)
    if rec is not None and rec["fingerprint"] == fp and results_complete(where, ids):
        log(f"tradeoff: reusing {where.name} (measured {rec['measured_at']})")
        return CellMeasure(spec, read_results(where / "data", ids), rec["batch_frames"], rec["wall_s"],
                           rec["cpu_s"], True, rec)
    done.unlink(missing_ok=True)
    remove_results(where)
    (where / PARTIAL).mkdir(parents=True)
    torch.set_num_threads(ctx.threads)
    victim = create_victim(spec.victim, **kwargs)
    prepare_attack(attack, spec.attack, victim)
    frames: list[int] = []
    wall: list[float] = []
    cpu: list[float] = []
    clock = [time.perf_counter(), time.process_time()]

    def batch_done(n: int) -> None:
        w, c = time.perf_counter(), time.process_time()
        spent = attack.take_spent() if isinstance(attack, DecimatedScan) else (0.0, 0.0)
        frames.append(n)
        wall.append(w - clock[0] - spent[0])
        cpu.append(c - clock[1] - spent[1])
        clock[0], clock[1] = time.perf_counter(), time.process_time()

    found = detect_frames(victim, spec.victim, attack, spec.attack, ctx.proposals, ctx.kitti, ctx.seed,
                          ctx.batch_size, list(zip(ids, ctx.gt.labels[:len(ids)], strict=True)), where / PARTIAL,
                          batch_done)
    promote(where)
    rec = {"fingerprint": fp, "config": plan.config, "spec": json.loads(spec.key), "victim": vrec, "attack": arec,
           "measured_at": utc_now(), "threads": ctx.threads,
           "batch_frames": frames, "wall_s": wall, "cpu_s": cpu}
    atomic_write_text(done, json.dumps(rec, indent=1, default=str) + "\n")
    log(f"tradeoff: {where.name}: {sum(wall):.1f} s wall, {sum(cpu):.1f} s CPU for {len(ids)} frames")
    return CellMeasure(spec, [parsed for _, parsed in found], frames, wall, cpu, False, rec)


def warm_caches(specs: Sequence[CellSpec], ctx: Context, log: Callable[[str], None] = print) -> None:
    """Fill the caches attacked cells read (scan beam patterns; scene depth per camera sampling) for every
    frame, so that no timed cell pays for them (module docstring)."""
    seen: set[str] = set()
    attacks: list[Attack] = []
    for spec in specs:
        if spec.attack == CLEAN:
            continue
        attack = create_attack(spec.attack, **dict(spec.attack_args))
        attack.bind_dataset(ctx.kitti)
        depth_key = json.dumps({"supersample": getattr(attack, "supersample", None),
                                "occlusion": getattr(attack, "occlusion", None)}, sort_keys=True)
        if depth_key not in seen:
            seen.add(depth_key)
            attacks.append(attack)
    if not attacks:
        return
    log(f"tradeoff: warming the scan-pattern and scene-depth caches ({len(attacks)} camera sampling(s))")
    for fid, gt in zip(ctx.gt.frame_ids, ctx.gt.labels, strict=True):
        frame = ctx.kitti.lazy_frame(fid, gt)
        targets = target_cars(gt)
        if len(targets) == 0:
            continue
        attacks[0].apply(frame, targets, attack_rng(ctx.seed, fid))  # the clean scan's beam pattern
        for attack in attacks:
            scene_depth = getattr(attack, "scene_depth", None)
            if scene_depth is not None:
                scene_depth(frame, targets)
