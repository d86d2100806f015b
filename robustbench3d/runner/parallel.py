"""The grid's cells computed in frame shards on an executor (``run --executor local|ray``).

:func:`run_cells` is the parallel counterpart of the grid's one-cell-at-a-time loop: finished cells
are reused by fingerprint exactly as there; every other cell is cut into shards
(:mod:`robustbench3d.runner.shards`) and the shards of *all* cells go to the executor at once, so
cells and the frames within a cell spread over the workers. A cell is assembled when its last shard
returns: its result files are settled (one per frame, the workers' texts), parsed back and evaluated
once over all its frames, ``data.partial/`` becomes ``data/`` and ``cell.json`` is written, the same
record as the one-process path but for timings and the ``executor`` provenance entry.

A cell whose earlier run was interrupted keeps the shards it finished (their records in
``shards.partial/`` match the cell's fingerprint and files): only the missing shards run again.

The cell's ``cpu_seconds`` add up its shards' worker CPU time and the assembly; ``seconds`` runs from
its first shard's start to its assembly; ``peak_rss_mb`` is the largest worker's peak during one of
its shards.
"""

from __future__ import annotations

import pickle
import shutil
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from robustbench3d.attacks import ATTACKS
from robustbench3d.attacks.base import Attack
from robustbench3d.errors import DataFormatError
from robustbench3d.kitti.labels import parse_labels
from robustbench3d.provenance import utc_now
from robustbench3d.results import SCHEMA_VERSION, write_validated
from robustbench3d.runner.cell import (
    PARTIAL,
    SHARD_MARKS,
    CellFailure,
    evaluate_cell,
    promote,
    remove_results,
    victim_failure,
)
from robustbench3d.runner.config import CellKey, fingerprint
from robustbench3d.runner.executors import Executor
from robustbench3d.runner.outcome import (
    CELL_FILE,
    CellOutcome,
    RunContext,
    Verdict,
    cell_provenance,
    describe_outcome,
    failure_verdict,
    reusable_cell,
)
from robustbench3d.runner.shards import CellJob, Shard, ShardResult, finished_shard, settle_files, shard_ranges
from robustbench3d.victims import VICTIMS
from robustbench3d.victims.spec import Capabilities


@dataclass
class _Cell:
    """A cell whose shards are out."""

    position: int
    key: CellKey
    want: str
    cfg: dict[str, Any]
    started: str
    shards: list[Shard]
    results: dict[int, ShardResult] = field(default_factory=dict)


def run_cells(run: RunContext, cells: Sequence[CellKey], cfgs: Sequence[dict[str, Any]],
              attacks: dict[str, Attack], cells_dir: Path, executor: Executor) -> list[CellOutcome]:
    """Reuse, skip or compute every cell of ``cells`` (grid order, ``cfgs`` their configurations) on
    ``executor``; returns the outcomes in grid order. Raises :class:`DataFormatError` on bad input."""
    from tqdm import tqdm

    outcomes: dict[int, CellOutcome] = {}
    waiting: dict[str, _Cell] = {}
    attack_bytes: dict[str, bytes] = {}
    todo: list[Shard] = []
    frame_ids = run.inputs.gt.frame_ids
    pairs = list(zip(frame_ids, run.inputs.gt.labels, strict=True))

    def done(position: int, outcome: CellOutcome) -> None:
        outcomes[position] = outcome
        run.log(f"[{position + 1}/{len(cells)}] {outcome.key}: {describe_outcome(outcome)}")

    for position, (key, cfg) in enumerate(zip(cells, cfgs, strict=True)):
        cell_dir = cells_dir / key.dirname
        want = fingerprint(cfg)
        old = reusable_cell(cell_dir, run.log, want, frame_ids)
        if old is not None:
            done(position, CellOutcome(key, old, reused=True))
            continue
        (cell_dir / CELL_FILE).unlink(missing_ok=True)  # from here on, no stale "finished" marker
        started, t0, cpu0 = utc_now(), time.perf_counter(), time.process_time()
        verdict, spec = _before_shards(run, key, cfg)
        if verdict is not None:
            remove_results(cell_dir)
            cell = _record(run, key, want, cfg, verdict, started, t0, cpu0, cell_dir, {})
            done(position, CellOutcome(key, cell, reused=False))
            continue
        if key.attack not in attack_bytes:
            attack_bytes[key.attack] = pickle.dumps(attacks[key.attack])
        job = CellJob(key=key, cell_dir=str(cell_dir), fingerprint=want, victim_spec=spec,
                      victim_kwargs=dict(cfg["victim"]["kwargs"]), attack=attack_bytes[key.attack],
                      kitti=run.inputs.kitti, seed=run.inputs.seed, batch_size=run.inputs.batch_size)
        shards = [Shard(job, i, start, tuple(pairs[start:stop]))
                  for i, (start, stop) in enumerate(shard_ranges(len(pairs), job.batch_size, executor.shard_frames))]
        pending = _Cell(position, key, want, cfg, started, shards)
        for shard in shards:
            reused = finished_shard(shard)
            if reused is not None:
                pending.results[shard.index] = reused
            else:
                todo.append(shard)
        if len(pending.results) == len(shards):  # every shard finished before an interruption
            done(position, _assemble(run, pending, executor))
        else:
            waiting[key.dirname] = pending

    if todo:
        bar = tqdm(total=sum(len(s.frames) for s in todo), unit="frame", file=sys.stderr,
                   disable=not run.inputs.progress, desc=f"{len(waiting)} cell(s), {len(todo)} shards",
                   dynamic_ncols=True, leave=False)
        try:
            for result in executor.run(todo):
                bar.update(len(result.frame_ids))
                pending = waiting.get(result.cell)
                if pending is None or result.index in pending.results:  # a shard that ran twice counts once
                    continue
                if result.status == "bad_input" and result.bad_input is not None:
                    path, problem, line, fld = result.bad_input
                    raise DataFormatError(path, problem, line, fld)
                pending.results[result.index] = result
                run.log.debug(f"shard {result.index + 1}/{len(pending.shards)} of {result.cell}: "
                              f"{len(result.frame_ids)} frame(s), {result.status}, on {result.host}:{result.pid}")
                if len(pending.results) == len(pending.shards):
                    del waiting[result.cell]
                    done(pending.position, _assemble(run, pending, executor))
        finally:
            bar.close()
    if waiting:  # an executor that lost shards without saying so
        raise RuntimeError(f"executor {executor.kind}: no result for some shards of {', '.join(sorted(waiting))}")
    return [outcomes[i] for i in range(len(cells))]


def _before_shards(run: RunContext, key: CellKey, cfg: dict[str, Any]) -> tuple[Verdict | None, Any]:
    """A verdict known before any shard runs (the attack needs what the victim lacks; the victim's
    registry entry cannot be loaded), else (None, the victim's registry entry)."""
    caps = cfg["victim"]["capabilities"]
    if caps is not None:
        unmet = ATTACKS.get(key.attack).requirements.unmet(Capabilities(**caps))
        if unmet is not None:
            return Verdict("skipped", f"attack {key.attack!r} {unmet}"), None
    try:
        return None, VICTIMS.get(key.victim)
    except Exception as exc:
        return failure_verdict(victim_failure(key.victim, exc), run.log), None


def _assemble(run: RunContext, cell: _Cell, executor: Executor) -> CellOutcome:
    """The cell from its shards' results: settle, parse and evaluate the result files, record it."""
    cell_dir = Path(cell.shards[0].job.cell_dir)
    results = [cell.results[i] for i in range(len(cell.shards))]
    computed = [r for r in results if not r.reused]
    first = min((r.started for r in computed), default=None)
    t0 = time.perf_counter() - (time.time() - first if first is not None else 0.0)
    cpu0 = time.process_time() - sum(r.cpu_seconds for r in computed)
    errors = [r for r in results if r.status == "error"]
    skips = [r for r in results if r.status == "skipped"]
    if errors:
        if errors[0].unexpected and errors[0].traceback is not None:
            run.log.warning(errors[0].traceback.rstrip())
        verdict = Verdict("error", errors[0].reason, traceback=errors[0].traceback)
    elif skips:
        verdict = Verdict("skipped", skips[0].reason)
    else:
        ids = [fid for r in results for fid in r.frame_ids]
        texts = [text for r in results for text in r.texts]
        if ids != run.inputs.gt.frame_ids or len(texts) != len(ids):
            raise RuntimeError(f"{cell.key}: the shards returned frames {ids[:3]}... for {len(ids)} frames, "
                               f"{len(texts)} result texts; expected the {len(run.inputs.gt.frame_ids)} split frames")
        try:
            settle_files(cell_dir, ids, texts)
            partial = cell_dir / PARTIAL
            detections = [parse_labels(text, partial / f"{fid}.txt", scored=True) for fid, text in zip(ids, texts,
                                                                                                      strict=True)]
            verdict = Verdict("ok", metrics=evaluate_cell(run.inputs, detections))
            promote(cell_dir)
            shutil.rmtree(cell_dir / SHARD_MARKS, ignore_errors=True)
        except (CellFailure, DataFormatError) as exc:
            verdict = failure_verdict(CellFailure(f"{cell.key}: {exc}"), run.log)
    if verdict.status != "ok":
        remove_results(cell_dir)
    peaks = [r.peak_rss_mb for r in computed if r.peak_rss_mb is not None]
    extra: dict[str, Any] = {
        "executor": {**executor.describe(), "shards": len(results), "shards_reused": len(results) - len(computed),
                     "workers": sorted({f"{r.host}:{r.pid}" for r in computed})},
        "peak_rss_mb": max(peaks) if peaks else None,
    }
    determinism = next((r.determinism for r in computed if r.determinism), None)
    record = _record(run, cell.key, cell.want, cell.cfg, verdict, cell.started, t0, cpu0, cell_dir, extra,
                     determinism)
    probe = results[0].victim_probe if verdict.status == "ok" else None  # the first shard's check
    return CellOutcome(cell.key, record, reused=False, probe=probe)


def _record(run: RunContext, key: CellKey, want: str, cfg: dict[str, Any], verdict: Verdict, started: str,
            t0: float, cpu0: float, cell_dir: Path, extra: dict[str, Any],
            determinism: dict[str, Any] | None = None) -> dict[str, Any]:
    """Write and return the cell's ``cell.json`` (the grid's record; ``extra`` added to its provenance,
    the workers' ``determinism`` flags over the parent's)."""
    provenance = cell_provenance(run, want, cfg, verdict, started, t0, cpu0, rss_reset=False)
    provenance.update(extra)
    if determinism:
        provenance["determinism"] = {**provenance["determinism"], **determinism}
    cell = {"schema_version": SCHEMA_VERSION, "victim": key.victim, "attack": key.attack, "proposals": key.proposals,
            "status": verdict.status, "reason": verdict.reason, "dataset": run.identity, "metrics": verdict.metrics,
            "provenance": provenance}
    cell_dir.mkdir(parents=True, exist_ok=True)
    return write_validated(cell_dir / CELL_FILE, cell, cell_only=True)


__all__ = ["run_cells"]
