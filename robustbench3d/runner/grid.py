"""The victims x attacks x proposal sources grid: resume, skip, run, record, summarise.

Output layout::

    OUT/cells/<victim>+<attack>+<proposals>/cell.json     one summary cell (schema-valid)
    OUT/cells/<victim>+<attack>+<proposals>/data/*.txt    KITTI result files, one per frame
    OUT/summary.json                                      list of cells: this run's (grid order), then
                                                          earlier runs' comparable ones (directory order)
    OUT/results.csv                                       long format, one row per AP value

A cell is finished when its ``cell.json`` exists (written atomically, last). A rerun reuses a
finished ``ok`` or ``skipped`` cell whose configuration fingerprint is unchanged (and whose result
files are all there) and says how many it kept; ``error`` cells are always retried. A finished ``ok`` or
``skipped`` cell of the grid whose fingerprint differs (another ``--max-frames``, object file, victim
argument...) is never replaced silently: the run refuses before computing anything, naming the cell and
what differs, unless ``RunConfig.force`` (``--force``), which replaces it with one line per cell.
A victim that cannot be created (e.g. missing weights) or fails makes error cells; the run goes on.
A run with attacked cells also runs (or reuses) the clean control ``none`` of each victim x proposal
source, and every attacked cell records its AP drop and attack success rate against it
(``attack_effect``, :mod:`robustbench3d.runner.effect`).
Each attack is created once per run: the instance whose ``describe()`` enters the fingerprints is
the one every cell prepares and applies.

The summary and the CSV cover every finished cell of ``OUT`` run on the same dataset, evaluation
and seed (:mod:`robustbench3d.runner.collect`), so runs of different victims or attacks into one
directory add up; finished cells that are not comparable are left out and listed. An attacked cell
is compared only with a clean cell of the same configuration but for the attack (victim and its
arguments, proposals, dataset and frames, seed, batch size, evaluation, versions); else its
``attack_effect`` is null and the run says why.

The cell's outcome, the run's report and the cell records this loop shares with the executor path
(:mod:`robustbench3d.runner.parallel`) are in :mod:`robustbench3d.runner.outcome`.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from robustbench3d.attacks import ATTACKS, create_attack
from robustbench3d.attacks.base import Attack
from robustbench3d.datasets import dataset_identity, load_ground_truth, resolve_dataset
from robustbench3d.errors import DataFormatError, RobustBenchError
from robustbench3d.logs import line_log, warn
from robustbench3d.provenance import host_provenance, reset_peak_rss, utc_now
from robustbench3d.results import SCHEMA_VERSION, CellResult, write_long_csv, write_validated
from robustbench3d.runner.cell import (
    CellFailure,
    CellInputs,
    remove_results,
    results_complete,
    run_cell,
    victim_failure,
)
from robustbench3d.runner.collect import earlier_cells
from robustbench3d.runner.config import CellKey, RunConfig, config_differences, fingerprint, grid, refuse_changed_cells
from robustbench3d.runner.effect import CLEAN_ATTACK, attach_effects, with_clean_cells
from robustbench3d.runner.executors import Executor
from robustbench3d.runner.flags import determinism, record_flags
from robustbench3d.runner.outcome import (
    CELL_FILE,
    CellOutcome,
    RunContext,
    RunReport,
    Verdict,
    cell_provenance,
    describe_outcome,
    failure_verdict,
    finished_cell,
    reusable_cell,
)
from robustbench3d.runner.parallel import run_cells
from robustbench3d.runner.records import (
    attack_record,
    cell_config,
    evaluation_record,
    victim_kwargs,
    victim_record,
)
from robustbench3d.seed_table import SEED_TABLE_FILE, write_seed_table
from robustbench3d.victims import VICTIMS, create_victim
from robustbench3d.victims.spec import Capabilities

SUMMARY_FILE = "summary.json"
CSV_FILE = "results.csv"


@contextlib.contextmanager
def _exclusive(out: Path) -> Iterator[None]:
    """Hold an advisory lock on ``out/.lock`` (released when the process dies, so no stale locks)."""
    try:
        import fcntl
    except ImportError:  # not POSIX: no protection against concurrent runs
        yield
        return
    with open(out / ".lock", "w") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise RobustBenchError(f"{out}: another robustbench3d run is writing there") from None
        yield


class _VictimSlot:
    """A victim created on first need (never if all its cells are reused or skipped)."""

    def __init__(self, name: str, kwargs: dict[str, Any]):
        self.name, self.kwargs = name, kwargs
        self._victim: Any = None
        self._error: CellFailure | None = None
        self._probes: dict[str, list[dict[str, str]]] = {}

    def get(self) -> Any:
        if self._victim is None and self._error is None:
            try:
                self._victim = create_victim(self.name, **self.kwargs)
            except DataFormatError:
                raise  # a bad file the user pointed at (e.g. weights=): bad input, the command exits 2
            except Exception as exc:
                self._error = victim_failure(self.name, exc)
        if self._error is not None:
            raise self._error
        return self._victim

    def probe(self, proposals: str, inputs: CellInputs) -> list[dict[str, str]]:
        """The created victim's determinism verdict on the split's first frame, once per proposal source."""
        if proposals not in self._probes:
            self._probes[proposals] = determinism(self.get(), proposals, inputs.kitti, inputs.gt.frame_ids[0],
                                                  inputs.gt.labels[0])
        return [dict(f) for f in self._probes[proposals]]


def _check_names(config: RunConfig) -> None:
    """Unknown victim or attack names fail the whole run up front (with did-you-mean)."""
    for name in config.victims:
        VICTIMS.entry(name)
    for name in config.attacks:
        ATTACKS.entry(name)


def _check_finished(out: Path, cells: list[CellKey], cfgs: list[dict[str, Any]], force: bool,
                    frame_ids: list[str], log: Callable[[str], None]) -> None:
    """The written-once rule for the grid's cells, before any is computed (module doc): refuse a finished
    ``ok`` or ``skipped`` cell whose fingerprint differs from this run's unless ``force`` (then name each one
    replaced); say how many unchanged finished cells are kept."""
    kept, changed = 0, []
    for key, cfg in zip(cells, cfgs, strict=True):
        cell_dir = out / "cells" / key.dirname
        found = finished_cell(cell_dir)
        old = None if found is None else CellResult(found)
        if old is None or old.status == "error":  # nothing finished there, or an error cell: always retried
            continue
        if old.fingerprint != fingerprint(cfg):
            why = config_differences(old.config, cfg)
            dependents = _compared_with(out / "cells", key.dirname, {k.dirname for k in cells})
            if dependents:
                why += (f"; {len(dependents)} attacked cell(s) of earlier runs are compared with it and lose their "
                        f"clean reference when it is replaced: {', '.join(dependents)}")
            changed.append((key.dirname, why))
        elif old.status == "skipped" or results_complete(cell_dir, frame_ids):
            kept += 1
    if not force:
        refuse_changed_cells(out, changed)
    for name, why in changed:
        warn(log, f"replacing finished cell {name} (--force): on disk vs this run: {why}")
    if kept:
        log(f"keeping {kept} finished cell(s) already in {out} (same configuration fingerprint: not recomputed)")


def _compared_with(cells_dir: Path, clean: str, grid_cells: set[str]) -> list[str]:
    """Cells of ``cells_dir`` outside the grid whose recorded ``attack_effect`` is against cell ``clean``."""
    out = []
    for cell_dir in sorted(p for p in cells_dir.iterdir() if p.is_dir() and p.name not in grid_cells):
        cell = finished_cell(cell_dir)
        if cell is not None and CellResult(cell).clean_cell == clean:
            out.append(cell_dir.name)
    return out


def run_benchmark(config: RunConfig, print_fn: Callable[[str], None] | None = None,
                  executor: Executor | None = None) -> RunReport:
    """Run (or resume) every cell of ``config``; write cell files, ``summary.json`` and the CSV.

    Args:
        config: what to run.
        print_fn: receives the run's lines (one per cell, what was kept or replaced, warnings); default: the
            ``robustbench3d.runner`` logger (:mod:`robustbench3d.logs`; stderr when logging is not set up).
            Detail lines (fingerprints, shards) go only to the logger, at DEBUG.
        executor: where frame shards of the cells run (:mod:`robustbench3d.runner.executors`; the
            caller closes it); None: every cell in this process, one after another.
    Raises:
        RobustBenchError: unknown names, bad arguments, an unusable dataset (before any cell runs).
    """
    log = line_log(__name__, print_fn)
    _check_names(config)
    if with_clean_cells(config) is not config:
        config = with_clean_cells(config)
        log(f"adding the clean control {CLEAN_ATTACK!r}: attacked cells are compared with it (run or reused)")
    attacks = {name: _create_attack(name, config) for name in config.attacks}  # one instance per run
    attack_records = {name: attack_record(name, dict(config.attack_args.get(name, {})), attack)
                      for name, attack in attacks.items()}
    out = config.out
    out.mkdir(parents=True, exist_ok=True)
    with _exclusive(out):
        dataset = resolve_dataset(config.data, config.split, workers=config.workers, progress=config.progress,
                                  lazy=True, max_frames=config.max_frames, log=log)  # only the frames evaluated
        gt = load_ground_truth(dataset, config.max_frames)
        identity = dataset_identity(dataset, gt)
        log(f"dataset {identity['root']} split {identity['split']}: {identity['frames']} of "
            f"{identity['split_frames']} frames (labels sha256 {identity['sha256'][:12]})")
        inputs = CellInputs(kitti=dataset.kitti(), gt=gt, seed=config.seed, batch_size=config.batch_size,
                            classes=config.classes, progress=config.progress, bootstrap=config.bootstrap)
        for attack in attacks.values():  # e.g. exact occlusion on a generated dataset
            attack.bind_dataset(inputs.kitti)
        evaluation = evaluation_record(config.classes)
        run = RunContext(config, inputs, identity, host_provenance(), log)
        report = RunReport(out=out, dataset=identity)
        slots: dict[str, _VictimSlot] = {}
        records: dict[str, dict[str, Any]] = {}
        for name in config.victims:
            kwargs = victim_kwargs(name, config.victim_args.get(name, {}), config.seed)
            slots[name], records[name] = _VictimSlot(name, kwargs), victim_record(name, kwargs)
        cells = grid(config)
        cfgs = [cell_config(key, records[key.victim], attack_records[key.attack], identity, config.seed,
                            config.batch_size, evaluation) for key in cells]
        _check_finished(out, cells, cfgs, config.force, gt.frame_ids, log)
        for stale in (SUMMARY_FILE, CSV_FILE, SEED_TABLE_FILE):  # derived files: rewritten at the end, never stale
            (out / stale).unlink(missing_ok=True)
        if executor is not None:  # frame shards of every cell on the executor's workers
            report.outcomes.extend(run_cells(run, cells, cfgs, attacks, out / "cells", executor))
        else:
            for i, (key, cfg) in enumerate(zip(cells, cfgs, strict=True), start=1):
                outcome = _run_one(run, key, cfg, slots[key.victim], attacks[key.attack],
                                   out / "cells" / key.dirname)
                log(f"[{i}/{len(cells)}] {key}: {describe_outcome(outcome)}")
                report.outcomes.append(outcome)
            for outcome in report.outcomes:  # determinism checks, on the victims the computed cells used
                if not outcome.reused and CellResult(outcome.cell).ok:
                    outcome.probe = slots[outcome.key.victim].probe(outcome.key.proposals, inputs)
        found = earlier_cells(out / "cells", {key.dirname for key in cells}, identity, evaluation, config.seed,
                              gt.frame_ids, CELL_FILE)
        report.earlier, report.left_out = found.included, found.left_out
        if report.earlier:
            log(f"the summary also lists {len(report.earlier)} finished cell(s) of earlier runs in {out}")
        for line in report.left_out:
            log.warning(f"left out of the summary: {line}")
        _record_effects(report, out / "cells", inputs, log)
        record_flags(report, out / "cells", attacks, log, CELL_FILE)
        summary = write_validated(out / SUMMARY_FILE, report.summary)
        write_long_csv(out / CSV_FILE, summary)
        write_seed_table(out / SEED_TABLE_FILE, summary)
    return report


def _record_effects(report: RunReport, cells_dir: Path, inputs: CellInputs,
                    log: Callable[[str], None] | None = None) -> None:
    """Compare every attacked cell of the summary with its clean cell (:mod:`.effect`); rewrite the
    ``cell.json`` of each cell whose comparison changed (atomically, the cell stays finished)."""
    cells = report.summary
    for i in attach_effects(cells, cells_dir, inputs.gt.labels, inputs.gt.frame_ids, inputs.bootstrap, inputs.seed,
                            log):
        cell = cells[i]
        write_validated(cells_dir / CellKey(*CellResult(cell).id).dirname / CELL_FILE, cell, cell_only=True)


def _create_attack(name: str, config: RunConfig) -> Attack:
    """The run's one instance of attack ``name``: described in every cell's fingerprint and applied."""
    return create_attack(name, **dict(config.attack_args.get(name, {})))


def _skip_reason(key: CellKey, capabilities: dict[str, Any] | None, slot: _VictimSlot) -> str | None:
    """Why the cell is skipped (attack needs what the victim lacks, unsupported proposal source), or None.

    Creates the victim only when the attack's requirements are met (raises :class:`CellFailure` if
    it cannot be created)."""
    if capabilities is not None:
        unmet = ATTACKS.get(key.attack).requirements.unmet(Capabilities(**capabilities))
        if unmet is not None:
            return f"attack {key.attack!r} {unmet}"
    supported = tuple(slot.get().supported_proposals)
    if key.proposals not in supported:
        return f"victim {key.victim!r} supports proposals {', '.join(supported)} only (not {key.proposals!r})"
    return None


def _execute(run: RunContext, key: CellKey, capabilities: dict[str, Any] | None, slot: _VictimSlot,
             attack: Attack, cell_dir: Path) -> Verdict:
    """Skip, run or fail the cell; a cell that is not ``ok`` keeps no result files."""
    try:
        skip = _skip_reason(key, capabilities, slot)
        verdict = (Verdict("skipped", skip) if skip is not None else
                   Verdict("ok", metrics=run_cell(slot.get(), key.victim, attack, key.attack, key.proposals,
                                                   run.inputs, cell_dir)))
    except CellFailure as exc:
        verdict = failure_verdict(exc, run.log)
    if verdict.status != "ok":
        remove_results(cell_dir)
    return verdict


def _run_one(run: RunContext, key: CellKey, cfg: dict[str, Any], slot: _VictimSlot, attack: Attack,
             cell_dir: Path) -> CellOutcome:
    """Reuse the finished cell if its fingerprint is unchanged, else compute and record it."""
    want = fingerprint(cfg)
    run.log.debug(f"{key}: fingerprint {want[:12]}, directory {cell_dir}")
    old = reusable_cell(cell_dir, run.log, want, run.inputs.gt.frame_ids)
    if old is not None:
        return CellOutcome(key, old, reused=True)
    (cell_dir / CELL_FILE).unlink(missing_ok=True)  # from here on, no stale "finished" marker
    started, t0, cpu0, rss_reset = utc_now(), time.perf_counter(), time.process_time(), reset_peak_rss()
    verdict = _execute(run, key, cfg["victim"]["capabilities"], slot, attack, cell_dir)
    cell = {"schema_version": SCHEMA_VERSION, "victim": key.victim, "attack": key.attack, "proposals": key.proposals,
            "status": verdict.status, "reason": verdict.reason, "dataset": run.identity, "metrics": verdict.metrics,
            "provenance": cell_provenance(run, want, cfg, verdict, started, t0, cpu0, rss_reset)}
    cell_dir.mkdir(parents=True, exist_ok=True)
    return CellOutcome(key, write_validated(cell_dir / CELL_FILE, cell, cell_only=True), reused=False)


__all__ = ["CELL_FILE", "CSV_FILE", "SUMMARY_FILE", "CellOutcome", "RunReport", "run_benchmark"]
