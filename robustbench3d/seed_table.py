"""The run's results in the layout of the seed paper's Table 1 (Car BEV AP @ IoU 0.7, easy / moderate / hard).

The seed paper's Table 1 has four rows: clean, LiDAR-only attack, image-only attack and both. They map to
the registered attacks as :data:`SEED_ROWS` says: ``none`` (clean), the controls ``benign-sphere`` and
``random-shape`` (no counterpart in the paper), ``adv-shape`` (LiDAR-only, scored with ground-truth 2D
boxes: proposals ``gt``), ``adv-texture`` (image-only) and ``adv-object`` (both), the last two with the
victim's own 2D detector (proposals ``detector``). Clean and control rows appear for every proposal
source. Per victim, one row per ``ok`` summary cell of that map:

* BEV AP R40 and R11 (easy moderate hard, percent);
* the clean reference: BEV AP R40 of the ``none`` cell with the same proposals, as the cell's
  ``attack_effect`` records it (:mod:`robustbench3d.runner.effect`);
* the relative drop at moderate, (clean - attacked) / clean in percent, R40 and R11;
* the attack success rate (percent);
* the seed paper's row and numbers, and its relative drop at moderate against its clean row.

Rows appear only for cells the summary has; a victim without attacked cells of the map gets one line
naming the attacks that would fill its table instead. Standard library only.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from robustbench3d.eval.rules import DIFFICULTIES
from robustbench3d.fileio import atomic_write_text
from robustbench3d.results import CellResult
from robustbench3d.texttable import format_table

#: File name of the markdown table next to ``summary.json``.
SEED_TABLE_FILE = "seed_table.md"
CLASS, METRIC = "Car", "bev"


@dataclass(frozen=True)
class PaperRow:
    """One row of the seed paper's Table 1: its label and Car BEV AP @ 0.7 (easy, moderate, hard; percent)."""

    label: str
    bev: tuple[float, float, float]


@dataclass(frozen=True)
class SeedRow:
    """A row of the layout: the summary cell (attack, proposals) it shows and the paper row beside it."""

    name: str
    attack: str
    proposals: str
    paper: PaperRow | None


PAPER_CLEAN = PaperRow("clean", (85.7, 83.6, 76.2))
PAPER_LIDAR = PaperRow("LiDAR-only", (37.4, 37.8, 39.1))
PAPER_IMAGE = PaperRow("image-only", (51.9, 36.0, 31.5))
PAPER_BOTH = PaperRow("LiDAR+image", (27.5, 22.7, 19.2))

#: The layout's rows in order. The paper has one clean row; it stands beside both clean rows.
SEED_ROWS: tuple[SeedRow, ...] = (
    SeedRow("clean", "none", "detector", PAPER_CLEAN),
    SeedRow("clean", "none", "gt", PAPER_CLEAN),
    SeedRow("benign-sphere", "benign-sphere", "detector", None),
    SeedRow("benign-sphere", "benign-sphere", "gt", None),
    SeedRow("random-shape", "random-shape", "detector", None),
    SeedRow("random-shape", "random-shape", "gt", None),
    SeedRow("adv-shape", "adv-shape", "gt", PAPER_LIDAR),
    SeedRow("adv-texture", "adv-texture", "detector", PAPER_IMAGE),
    SeedRow("adv-object", "adv-object", "detector", PAPER_BOTH),
)
CLEAN_ATTACK = "none"

HEADER: tuple[str, ...] = (
    "row", "proposals", "BEV R40 (E M H)", "BEV R11 (E M H)", "clean R40 (E M H)", "rel. drop M % (R40 R11)",
    "ASR %", "seed paper", "paper BEV (E M H)", "paper rel. drop M %",
)
_ALIGN = "llrrrrrlrr"
_NONE = "-"


def paper_relative_drop(row: PaperRow) -> float:
    """The paper row's relative drop at moderate against the paper's clean row (a fraction)."""
    return (PAPER_CLEAN.bev[1] - row.bev[1]) / PAPER_CLEAN.bev[1]


def interval(cell: CellResult, cls: str, metric: str, recall: str, difficulty: str, drop: bool = False
             ) -> list[float] | None:
    """The bootstrap 95 % interval of a cell's AP (``metrics_ci``) or, with ``drop``, of its paired drop
    (``attack_effect.drop_ci``); None where the summary has none."""
    table = (cell.effect or {}).get("drop_ci") if drop else cell.cell.get("metrics_ci")
    try:
        return None if table is None else table[cls][metric][recall][difficulty]
    except KeyError:
        return None


def with_interval(text: str, ci: list[float] | None) -> str:
    """``text [lo, hi]`` (one decimal), or ``text`` without an interval."""
    return text if ci is None else f"{text} [{ci[0]:.1f}, {ci[1]:.1f}]"


def _aps(get: Callable[[str], float | None], fmt: str,
         ci: Callable[[str], list[float] | None] | None = None) -> str:
    """E M H values of ``get(difficulty)`` (each followed by ``[lo, hi]`` where ``ci`` gives one); ``-`` if
    any is missing."""
    values = []
    for d in DIFFICULTIES:
        try:
            value = get(d)
        except LookupError:
            return _NONE
        if value is None:
            return _NONE
        values.append(with_interval(format(value, fmt), ci(d) if ci is not None else None))
    return " ".join(values)


def _percent(value: float | None) -> str:
    return _NONE if value is None else f"{100 * value:.1f}"


def _relative(cell: CellResult) -> str:
    parts = []
    for recall in ("R40", "R11"):
        try:
            parts.append(_percent(cell.drop(CLASS, METRIC, recall, "moderate", relative=True)))
        except LookupError:
            return _NONE
    return " ".join(parts)


def _row(spec: SeedRow, cell: CellResult) -> list[str]:
    """The layout's strings for one ``ok`` cell."""
    attacked = cell.effect is not None
    paper = spec.paper
    return [
        spec.name, spec.proposals,
        _aps(lambda d: cell.ap(CLASS, METRIC, "R40", d), "6.2f", lambda d: interval(cell, CLASS, METRIC, "R40", d)),
        _aps(lambda d: cell.ap(CLASS, METRIC, "R11", d), "6.2f", lambda d: interval(cell, CLASS, METRIC, "R11", d)),
        _aps(lambda d: cell.clean_ap(CLASS, METRIC, "R40", d), "6.2f") if attacked else _NONE,
        _relative(cell) if attacked else _NONE,
        _percent(cell.attack_success_rate) if attacked else _NONE,
        paper.label if paper else _NONE,
        " ".join(f"{v:.1f}" for v in paper.bev) if paper else _NONE,
        _percent(paper_relative_drop(paper)) if paper and spec.attack != CLEAN_ATTACK else _NONE,
    ]


@dataclass
class VictimSection:
    """One victim's part of the layout: its rows (strings, :data:`HEADER` order) and notes."""

    victim: str
    frames: int
    rows: list[list[str]] = field(default_factory=list)
    #: ``"attack / proposals: status: reason"`` for cells of the map that are not ``ok``.
    no_ap: list[str] = field(default_factory=list)
    #: Rows of the map the summary has no cell for.
    absent: list[SeedRow] = field(default_factory=list)

    @property
    def has_attacked(self) -> bool:
        """Whether the summary has any attacked cell of the map for this victim (``ok`` or not)."""
        return any(spec.attack != CLEAN_ATTACK and spec not in self.absent for spec in SEED_ROWS)


def sections(cells: Sequence[dict[str, Any]]) -> list[VictimSection]:
    """One :class:`VictimSection` per victim of ``cells`` (summary cells), in order of first appearance."""
    by_victim: dict[str, dict[tuple[str, str], CellResult]] = {}
    for cell in map(CellResult, cells):
        by_victim.setdefault(cell.victim, {}).setdefault((cell.attack, cell.proposals), cell)
    out = []
    for victim, have in by_victim.items():
        section = VictimSection(victim, next(iter(have.values())).frames)
        for spec in SEED_ROWS:
            cell = have.get((spec.attack, spec.proposals))
            if cell is None:
                section.absent.append(spec)
            elif cell.status == "ok":
                section.rows.append(_row(spec, cell))
            else:
                section.no_ap.append(f"{spec.attack} / {spec.proposals}: {cell.status}: {cell.reason}")
        out.append(section)
    return out


def _iou(cells: Sequence[dict[str, Any]]) -> float:
    for cell in map(CellResult, cells):
        result = cell.result
        if result is not None and METRIC in result.metrics(CLASS):
            with contextlib.suppress(KeyError):
                return result.iou(CLASS, METRIC)
    return 0.7


TITLE = "Seed paper Table 1 layout"


def _subtitle(cells: Sequence[dict[str, Any]]) -> str:
    return f"{CLASS} BEV AP in % at IoU {_iou(cells):.2f}, easy / moderate / hard"


LEGEND = ("clean R40 = the 'none' cell with the same proposals; rel. drop = (clean - attacked) / clean at "
          "moderate; ASR = Cars matched clean and missed attacked (moderate, BEV IoU 0.7); seed paper = its "
          "Table 1 (one clean row, beside both proposal sources), its rel. drop against its clean row")


def _fill_hint(absent: Sequence[SeedRow]) -> str:
    """``adv-shape (--proposals gt), ...`` for the absent attacked rows."""
    names: dict[str, list[str]] = {}
    for spec in absent:
        if spec.attack != CLEAN_ATTACK:
            names.setdefault(spec.attack, []).append(spec.proposals)
    return ", ".join(f"{a} (--proposals {','.join(p)})" for a, p in names.items())


def _no_layout(secs: Sequence[VictimSection]) -> str | None:
    """The sentence that replaces the layout when no victim has an attacked cell of the map, else None."""
    if any(s.has_attacked for s in secs):
        return None
    return f"no attacked cell of it in this run; these attacks fill it: {_fill_hint(SEED_ROWS)}"


def _notes(section: VictimSection) -> list[str]:
    notes = [f"no AP: {line}" for line in section.no_ap]
    if not section.has_attacked:
        notes.append(f"no attacked cell of the layout; these attacks fill it: {_fill_hint(section.absent)}")
    elif missing := [f"{s.attack} / {s.proposals}" for s in section.absent if s.attack != CLEAN_ATTACK]:
        notes.append(f"not in this run: {', '.join(missing)}")
    return notes


def _legend(cells: Sequence[dict[str, Any]]) -> str:
    """The legend, plus what ``[lo, hi]`` means when some cell carries bootstrap intervals."""
    meta = next((c["metrics_ci"]["meta"] for c in cells if c.get("metrics_ci")), None)
    if meta is None:
        return LEGEND
    return (f"{LEGEND}; [lo, hi] = {100 * meta['level']:.0f} % bootstrap interval over frames "
            f"({meta['resamples']} resamples)")


def seed_table_text(cells: Sequence[dict[str, Any]]) -> str:
    """The layout as plain text (:func:`robustbench3d.texttable.format_table`), one section per victim."""
    secs = sections(cells)
    if (empty := _no_layout(secs)) is not None:
        return f"{TITLE}: {empty}"
    lines = [f"{TITLE}: {_subtitle(cells)}", _legend(cells)]
    for section in secs:
        lines.append(f"victim {section.victim}, {section.frames} frames")
        if section.rows:
            lines.append(format_table(HEADER, section.rows, align=_ALIGN))
        lines += _notes(section)
    return "\n".join(lines)


def _md_cell(text: str) -> str:
    """Whitespace runs collapsed (the text table's padding), pipes escaped."""
    return " ".join(text.split()).replace("|", "\\|")


def _md_table(rows: Sequence[Sequence[str]]) -> list[str]:
    rule = ["---:" if a == "r" else "---" for a in _ALIGN]
    return ["| " + " | ".join(map(_md_cell, r)) + " |" for r in (HEADER, rule, *rows)]


def seed_table_markdown(cells: Sequence[dict[str, Any]]) -> str:
    """The layout as markdown: a title, the legend, then per victim a heading, a pipe table and its notes."""
    secs = sections(cells)
    lines = [f"# {TITLE}", ""]
    if (empty := _no_layout(secs)) is not None:
        return "\n".join([*lines, empty[0].upper() + empty[1:] + ".", ""])
    lines += [f"{_subtitle(cells)}; {_legend(cells)}.", ""]
    for section in secs:
        lines += [f"## {section.victim}", "", f"{section.frames} frames.", ""]
        if section.rows:
            lines += [*_md_table(section.rows), ""]
        if notes := _notes(section):
            lines += [*(f"- {_md_cell(n)}" for n in notes), ""]
    return "\n".join(lines)


def write_seed_table(path: str | Path, cells: Sequence[dict[str, Any]]) -> str:
    """Write :func:`seed_table_markdown` of ``cells`` to ``path`` atomically; returns the text."""
    text = seed_table_markdown(cells)
    atomic_write_text(path, text)
    return text


__all__ = [
    "CLEAN_ATTACK", "HEADER", "LEGEND", "PAPER_BOTH", "PAPER_CLEAN", "PAPER_IMAGE", "PAPER_LIDAR", "SEED_ROWS",
    "SEED_TABLE_FILE", "TITLE", "PaperRow", "SeedRow", "VictimSection", "paper_relative_drop", "sections",
    "seed_table_markdown", "seed_table_text", "write_seed_table",
]
