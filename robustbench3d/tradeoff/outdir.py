"""The written-once rule for ``tradeoff --out DIR``.

``DIR`` is new or empty, or a tradeoff directory: it holds ``tradeoff.json`` or tradeoff cells
(``cells/<victim>+<attack>+<12 hex>/``, an interrupted run). A tradeoff directory of the same
configuration is resumed: its finished cells of the same fingerprint are reused (one line says how many),
the four tradeoff files rewritten. Refused before any work unless ``--force``:

* any other non-empty directory, e.g. a ``robustbench3d run`` directory (``summary.json``, run cells in
  ``cells/``), whose cells the tradeoff's would mix with;
* a tradeoff directory whose ``tradeoff.json`` records another configuration (any option but
  ``--no-progress``/``--force``: the files would be replaced);
* a finished cell whose fingerprint differs from the one this run computes for it (another ``--frames``,
  seed, batch size, threads, dataset or version: the cell would be replaced), checked once the dataset is
  read, before any cell is measured.

Under ``--force`` each replacement is named in one line.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from robustbench3d.errors import DataFormatError, RobustBenchError
from robustbench3d.tradeoff.measure import CellPlan, finished_record
from robustbench3d.tradeoff.output import JSON_FILE, read_doc

#: A tradeoff cell's directory name (:func:`~robustbench3d.tradeoff.measure.cell_dir`); a run's cells end in
#: their proposal source instead.
TRADEOFF_CELL = re.compile(r".+\+.+\+[0-9a-f]{12}")
#: How a tradeoff cell's configuration entries are named in messages (dotted paths).
CELL_LABELS = {"dataset.frames": "frames (--frames)", "threads": "--threads", "batch_size": "--batch-size",
               "seed": "--seed", "proposals": "--proposals"}
#: Files ``robustbench3d run`` writes at the top of its ``--out``.
RUN_FILES = ("summary.json", "results.csv", "seed_table.md")


def _foreign(out: Path) -> str | None:
    """Why the non-empty ``out`` is not a tradeoff directory, or None if it is one."""
    run_file = next((name for name in RUN_FILES if (out / name).exists()), None)
    if run_file is not None:
        return f"is a `robustbench3d run` directory ({run_file}); the tradeoff's cells would mix with its cells"
    cells = out / "cells"
    entries = sorted(p.name for p in cells.iterdir()) if cells.is_dir() else []
    other = next((name for name in entries if not TRADEOFF_CELL.fullmatch(name)), None)
    if other is not None:
        return f"holds cells/{other}, not a tradeoff cell (a `robustbench3d run` directory?)"
    if (cells.exists() or cells.is_symlink()) and not cells.is_dir():
        return "holds a cells entry that is not a directory"
    if not (out / JSON_FILE).exists() and not entries:
        return f"is not empty and not a tradeoff directory (no {JSON_FILE}, no tradeoff cells)"
    return None


def _normal(config: dict[str, Any]) -> dict[str, Any]:
    """A recorded or current configuration with ``data`` as an absolute path."""
    out = dict(config)
    if out.get("data") is not None:
        out["data"] = str(Path(out["data"]).resolve())
    return out


def config_changes(old: dict[str, Any], new: dict[str, Any]) -> str | None:
    """``"--frames 50 vs 3; ..."`` for the options whose recorded value differs, or None."""
    a, b = _normal(old), _normal(new)
    diff = [k for k in dict.fromkeys([*a, *b]) if a.get(k) != b.get(k)]
    return "; ".join(f"--{k.replace('_', '-')} {a.get(k)!r} vs {b.get(k)!r}" for k in diff) or None


def check_out_dir(out: Path, config: dict[str, Any], force: bool, say: Callable[[str], None]) -> None:
    """Check an existing ``--out`` (module doc) before any work; ``config`` is this run's
    (:meth:`~robustbench3d.tradeoff.run.TradeoffConfig.as_dict`). Raises :class:`RobustBenchError`."""
    if not out.is_dir() or not any(out.iterdir()):
        return
    hint = "choose another --out, or pass --force to write into it (nothing was written)"
    why = _foreign(out)
    if why is not None:
        if not force:
            raise RobustBenchError(f"--out {out}: {why}; {hint}")
        say(f"tradeoff: writing into {out}, which {why.removeprefix('is ')} (--force)")
        return
    if not (out / JSON_FILE).is_file():
        return  # an interrupted tradeoff: its cells are checked one by one (check_cells)
    try:
        changes = config_changes(read_doc(out)["config"], config)
    except (DataFormatError, TypeError, AttributeError) as exc:
        changes = f"its {JSON_FILE} cannot be read ({exc})"
    if changes is None:
        return
    if not force:
        raise RobustBenchError(f"--out {out}: holds a tradeoff of another configuration (on disk vs this run: "
                               f"{changes}); pass --force to replace it, or choose another --out (nothing was written)")
    say(f"tradeoff: replacing the tradeoff of another configuration in {out} (--force): {changes}")


def check_cells(plans: Sequence[CellPlan], out: Path, force: bool, say: Callable[[str], None]) -> None:
    """Before any cell is measured: refuse finished cells whose fingerprint differs (unless ``force``, then
    name each one replaced) and say how many finished cells of the same fingerprint are kept."""
    from robustbench3d.runner.cell import results_complete
    from robustbench3d.runner.config import config_differences, refuse_changed_cells

    kept, changed = 0, []
    for plan in plans:
        rec = finished_record(plan.where)
        if rec is None:
            continue
        if rec["fingerprint"] == plan.fingerprint:
            kept += results_complete(plan.where, plan.ids)
        else:
            old = rec.get("config")
            why = (config_differences(old, plan.config, labels=CELL_LABELS) if isinstance(old, dict)
                   else "fingerprint differs (its cell.json records no configuration)")
            changed.append((plan.where.name, why))
    if not force:
        refuse_changed_cells(out, changed, cell="tradeoff cell", done="measured")
    for name, why in changed:
        say(f"tradeoff: replacing finished cell {name} (--force): on disk vs this run: {why}")
    if kept:
        say(f"tradeoff: keeping {kept} finished cell(s) already in {out} (same fingerprint: reused with their "
            "timings)")


__all__ = ["TRADEOFF_CELL", "check_cells", "check_out_dir", "config_changes"]
