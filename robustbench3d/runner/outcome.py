"""How a cell of the grid ends and how it is recorded: the types and records shared by the one-process
loop (:mod:`robustbench3d.runner.grid`) and the executor path (:mod:`robustbench3d.runner.parallel`).

* :class:`RunContext`: what every cell of a run shares; :class:`Verdict`: how one cell ended;
  :class:`CellOutcome`: the cell's summary record; :class:`RunReport`: what a run did.
* :data:`CELL_FILE`, :func:`finished_cell`, :func:`reusable_cell`: a finished cell on disk and the rule that
  reuses it (module doc of :mod:`~robustbench3d.runner.grid`).
* :func:`failure_verdict`, :func:`cell_provenance`, :func:`describe_outcome`: a failed cell's verdict, a
  computed cell's ``provenance`` record and the one-line description a run prints per cell.

This module imports no other runner module but :mod:`~robustbench3d.runner.cell` and
:mod:`~robustbench3d.runner.config`, so every runner module may import it (no import cycle).
"""

from __future__ import annotations

import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from robustbench3d.errors import DataFormatError, RobustBenchError
from robustbench3d.logs import LineLog, warn
from robustbench3d.provenance import determinism_flags, library_versions, peak_rss_mb, utc_now
from robustbench3d.results import CellResult, read_json, validate_summary
from robustbench3d.runner.cell import ATTACK_STREAM, CellFailure, CellInputs, results_complete
from robustbench3d.runner.config import CellKey, RunConfig

#: A cell's summary record, in its directory: the cell is finished when it exists (written atomically, last).
CELL_FILE = "cell.json"


@dataclass(frozen=True)
class RunContext:
    """What every cell of a run shares."""

    config: RunConfig
    inputs: CellInputs
    identity: dict[str, Any]
    host: dict[str, Any]
    log: LineLog


@dataclass(frozen=True)
class Verdict:
    """How a cell ended: status, reason (skipped, error), metrics (ok) and traceback (error)."""

    status: str
    reason: str | None = None
    metrics: dict[str, Any] | None = None
    traceback: str | None = None


@dataclass
class CellOutcome:
    """A cell of the finished run: its summary record and whether it was reused from disk."""

    key: CellKey
    cell: dict[str, Any]
    reused: bool
    #: The victim's determinism verdict (:func:`robustbench3d.runner.flags.determinism`) from the process
    #: that computed the cell with that victim (a shard worker; this one, after the cells, with no executor);
    #: None: not checked (reused, not ok).
    probe: list[dict[str, str]] | None = None


@dataclass
class RunReport:
    """What :func:`~robustbench3d.runner.grid.run_benchmark` did."""

    out: Path
    dataset: dict[str, Any]
    outcomes: list[CellOutcome] = field(default_factory=list)
    #: Finished, comparable cells of earlier runs in ``out`` (in the summary after this run's).
    earlier: list[dict[str, Any]] = field(default_factory=list)
    #: ``"<cell dir>: <reason>"`` for each cell directory of ``out`` the summary leaves out.
    left_out: list[str] = field(default_factory=list)

    @property
    def cells(self) -> list[dict[str, Any]]:
        """This run's cells, grid order."""
        return [o.cell for o in self.outcomes]

    @property
    def summary(self) -> list[dict[str, Any]]:
        """The cells of ``summary.json``: this run's, then :attr:`earlier`."""
        return self.cells + self.earlier

    @property
    def failed(self) -> list[CellOutcome]:
        return [o for o in self.outcomes if CellResult(o.cell).status == "error"]


def finished_cell(cell_dir: Path, print_fn: Callable[[str], None] | None = None) -> dict | None:
    """The cell's ``cell.json`` if it is there and schema-valid, else None: the cell is recomputed (an invalid
    one is said through ``print_fn`` if given, as :func:`reusable_cell` does)."""
    path = cell_dir / CELL_FILE
    if not path.is_file():
        return None
    try:
        cell = read_json(path)
        validate_summary(cell, path, cell_only=True)
    except DataFormatError as exc:
        if print_fn is not None:
            print_fn(f"  recomputing: {exc}")
        return None
    return cell


def reusable_cell(cell_dir: Path, print_fn: Callable[[str], None], want: str, frame_ids: list[str]) -> dict | None:
    """The finished cell of ``cell_dir`` if a run with fingerprint ``want`` reuses it (same fingerprint, not an
    error, all its result files there), else None (why it is recomputed is said through ``print_fn``)."""
    cell = finished_cell(cell_dir, print_fn)
    result = None if cell is None else CellResult(cell)
    if result is None or result.fingerprint != want or result.status == "error":
        return None
    if result.ok and not results_complete(cell_dir, frame_ids):
        print_fn(f"  recomputing: result files in {cell_dir / 'data'} are incomplete")
        return None
    return cell


def describe_outcome(outcome: CellOutcome) -> str:
    """The cell's status as the run's line for it says it (``ok (1.2 s)``, ``reused``, ``error: ...``)."""
    cell = CellResult(outcome.cell)
    if cell.ok:
        return "reused" if outcome.reused else f"ok ({cell.provenance['seconds']:.1f} s)"
    return f"{cell.status}{' (reused)' if outcome.reused else ''}: {cell.reason}"


def failure_verdict(exc: CellFailure, log: Callable[[str], None]) -> Verdict:
    """The error verdict of a failed cell, with the traceback of its cause (logged if unexpected)."""
    cause = exc.__cause__ or exc
    tb = "".join(traceback.format_exception(type(cause), cause, cause.__traceback__))
    if not isinstance(cause, RobustBenchError):  # an unexpected exception: show where it came from
        warn(log, tb.rstrip())
    return Verdict("error", str(exc), traceback=tb)


def cell_provenance(run: RunContext, want: str, cfg: dict[str, Any], verdict: Verdict, started: str,
                    t0: float, cpu0: float, rss_reset: bool) -> dict[str, Any]:
    """The ``provenance`` record of a cell computed now: fingerprint ``want`` of configuration ``cfg``, the run,
    host and versions, ``started`` (UTC) and the wall and CPU seconds since ``t0`` (``time.perf_counter``) and
    ``cpu0`` (``time.process_time``); the peak RSS since its reset only if ``rss_reset``."""
    caps = cfg["victim"]["capabilities"]
    provenance = {
        "fingerprint": want, "config": cfg, "run": run.config.as_dict(), **run.host, "versions": library_versions(),
        "seed": run.config.seed,
        "determinism": {**determinism_flags(), "victim_deterministic": None if caps is None else caps["deterministic"],
                        "attack_rng": f"numpy.random.default_rng([seed, int(frame_id), {ATTACK_STREAM:#x}])"},
        "started": started, "finished": utc_now(), "seconds": round(time.perf_counter() - t0, 3),
        "cpu_seconds": round(time.process_time() - cpu0, 3),
        "peak_rss_mb": round(peak, 1) if rss_reset and (peak := peak_rss_mb()) is not None else None,
    }
    if verdict.traceback is not None:
        provenance["traceback"] = verdict.traceback
    return provenance


__all__ = ["CELL_FILE", "CellOutcome", "RunContext", "RunReport", "Verdict", "cell_provenance", "describe_outcome",
           "failure_verdict", "finished_cell", "reusable_cell"]
