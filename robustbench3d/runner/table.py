"""The run's printed table: one row per cell, Car BEV and 3D AP (R40 and R11) per difficulty.

Two renderings of the same numbers: plain text (:func:`robustbench3d.texttable.format_table`, one line per
cell, as wide as it needs: for files, pipes and CI logs, stable for tools and tests), and for a terminal a
table folded to its width by ``rich`` (:func:`fold_table`: easy / moderate / hard on three lines of a cell;
column groups that do not fit beside the first columns move to a block below, which repeats them). Cell
text wraps only at spaces, so no number is ever cut.
"""

from __future__ import annotations

import contextlib
import shutil
import textwrap
from collections.abc import Sequence
from typing import Any

from robustbench3d.eval.rules import DIFFICULTIES, MIN_OVERLAP
from robustbench3d.metrics import HEADLINE
from robustbench3d.results import CellResult
from robustbench3d.seed_table import with_interval
from robustbench3d.texttable import format_table

#: (metric, recall sampling) column groups of the table.
COLUMNS: tuple[tuple[str, str], ...] = (("bev", "R40"), ("bev", "R11"), ("3d", "R40"), ("3d", "R11"))
_LABEL = {"bev": "BEV", "3d": "3D"}


def _value(cell: CellResult, cls: str, metric: str, recall: str, difficulty: str) -> str:
    """AP, followed for an attacked cell by its change against the clean cell, e.g. ``71.20(-8.15)``; each
    with its bootstrap interval where the cell has one, e.g. ``71.20 [69.8, 72.6](-8.15 [-9.9, -6.4])``."""
    where = (cls, metric, recall, difficulty)
    text = with_interval(f"{cell.ap(*where):6.2f}", cell.interval(*where))
    if cell.effect is not None:
        with contextlib.suppress(LookupError):
            drop_ci = cell.interval(*where, table="drop_ci")
            change = None if drop_ci is None else [-drop_ci[1], -drop_ci[0]]
            text += f"({with_interval(f'{-cell.drop(cls, metric, recall, difficulty):+.2f}', change)})"
    return text


def _group(cell: CellResult, cls: str, metric: str, recall: str, sep: str = " ") -> str:
    """The E M H values of a column group, joined by ``sep``; ``-`` without them."""
    result = cell.result
    if result is None or metric not in result.metrics(cls):
        return "-"
    return sep.join(_value(cell, cls, metric, recall, d) for d in DIFFICULTIES)


def _asr(cell: CellResult) -> str:
    rate = cell.attack_success_rate
    return "-" if rate is None else f"{100 * rate:.1f}"


def summary_table(cells: Sequence[dict[str, Any]], cls: str = HEADLINE.cls, width: int | None = None) -> str:
    """Plain-text table of summary cells, then one line per skipped or failed cell; with ``width``
    (characters, e.g. :func:`terminal_width`) folded to it (:func:`fold_table`; prose lines wrapped)."""
    results = [CellResult(c) for c in cells]
    iou = next((r.result.iou(cls, "bev") for r in results
                if r.result is not None and "bev" in r.result.metrics(cls)), MIN_OVERLAP["bev"][HEADLINE.cls])
    attacked = any(r.effect is not None for r in results)
    frames = next((r.frames for r in results), 0)
    title = f"{cls} AP in % at IoU {iou:.2f}, easy / moderate / hard, {frames} frames"
    if attacked:
        title += ("; attacked cells: (AP change against the clean cell 'none'), ASR = Cars matched clean "
                  "and missed attacked (moderate, BEV IoU 0.7)")
    ci_meta = next((r.interval_meta for r in results if r.interval_meta is not None), None)
    if ci_meta is not None:
        title += (f"; [lo, hi] = {100 * ci_meta['level']:.0f} % bootstrap interval over frames "
                  f"({ci_meta['resamples']} resamples; AP changes: paired, the same frames for both cells)")
    groups = [f"{_LABEL[m]} {r} (E M H)" for m, r in COLUMNS]
    asr = ["ASR %"] if attacked else []
    if width is None:
        head = ["victim", "attack", "proposals", "status", *groups, *asr]
        rows = [[r.victim, r.attack, r.proposals, r.status] + [_group(r, cls, m, rec) for m, rec in COLUMNS]
                + ([_asr(r)] if attacked else []) for r in results]
        table = format_table(head, rows)
    else:  # one line per difficulty; the cell's names on as many lines
        head = ["victim / attack / proposals", "status", *groups, *asr]
        rows = [[f"{r.victim}\n{r.attack}\n{r.proposals}", r.status]
                + [_group(r, cls, m, rec, "\n") for m, rec in COLUMNS] + ([_asr(r)] if attacked else [])
                for r in results]
        table = fold_table(head, rows, width=width, key=2)
    lines = [title, table]
    lines += [f"{r.status}: {r.victim} / {r.attack} / {r.proposals}: {r.reason}" for r in results if r.status != "ok"]
    text = "\n".join(lines)
    return text if width is None else fit_lines(text, width)


#: Narrowest width :func:`fold_table` lays out for (characters): below it a terminal reported nonsense.
MIN_WIDTH = 40


def terminal_width() -> int:
    """The terminal's width in characters (``COLUMNS`` first, then the terminal of stdout; 80 if neither
    says), at least :data:`MIN_WIDTH`."""
    return max(MIN_WIDTH, shutil.get_terminal_size().columns)


def fit_lines(text: str, width: int) -> str:
    """Every line of ``text`` wider than ``width`` wrapped at its spaces (words are never split)."""
    out: list[str] = []
    for line in text.splitlines():
        out.extend([line] if len(line) <= width else
                   textwrap.wrap(line, width, break_long_words=False, break_on_hyphens=False))
    return "\n".join(out)


def _rich_table(header: Sequence[str], rows: Sequence[Sequence[str]], align: str, columns: Sequence[int]) -> Any:
    from rich import box
    from rich.table import Table

    table = Table(box=box.SIMPLE_HEAD, show_edge=False, pad_edge=False, padding=(0, 1))
    for i in columns:
        table.add_column(header[i], justify="right" if align[i] == "r" else "left", overflow="fold")
    for row in rows:
        table.add_row(*(row[i] for i in columns))
    return table


def fold_table(header: Sequence[str], rows: Sequence[Sequence[str]], *, width: int, key: int = 1,
               align: str | None = None) -> str:
    """The table folded to ``width`` characters with ``rich``: as one table when it fits, else in blocks of
    consecutive columns, each beginning with the ``key`` first columns, each as wide as fits (a single
    column wider than the rest of the width wraps its text at spaces). Cells may hold several lines.

    Args:
        header, rows: titles and cells (strings), as for :func:`robustbench3d.texttable.format_table`.
        width: characters per line (at least :data:`MIN_WIDTH` are used).
        key: leading columns repeated in every block (the row's names).
        align: one letter per column, ``l`` or ``r`` (default: all left).
    """
    from rich.console import Console
    from rich.measure import Measurement

    width = max(MIN_WIDTH, width)
    align = align if align is not None else "l" * len(header)
    console = Console(width=width, color_system=None, force_terminal=False, highlight=False, legacy_windows=False)

    unbounded = console.options.update(max_width=10**6)  # Measurement.get caps at max_width

    def natural(columns: Sequence[int]) -> int:
        return Measurement.get(console, unbounded, _rich_table(header, rows, align, columns)).maximum

    blocks: list[list[int]] = []
    for i in range(key, len(header)):
        if blocks and natural([*range(key), *blocks[-1], i]) <= width:
            blocks[-1].append(i)
        else:
            blocks.append([i])
    texts = []
    for block in blocks or [[]]:
        with console.capture() as capture:
            console.print(_rich_table(header, rows, align, [*range(key), *block]))
        texts.append("\n".join(line.rstrip() for line in capture.get().rstrip("\n").splitlines()))
    return "\n\n".join(texts)
