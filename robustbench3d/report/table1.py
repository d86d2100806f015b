"""The seed paper's Table 1 beside a section's measured rows: the report's Table 1 block.

Its rows are :func:`robustbench3d.seed_table.victim_layout`'s, the map ``seed_table.md`` uses. Per row of the
paper (clean, LiDAR-only, image-only, LiDAR+image) the block shows the paper's Car BEV AP @ IoU 0.7 (easy,
moderate, hard), then each victim's cells of that row: a clean row per proposal source; a LiDAR-only row per
LiDAR protocol (``gt``: GT 2D boxes with the object outside the frustum; each further proposal source, such
as ``gt-object``, adds one: :func:`robustbench3d.seed_table.layout_rows`); image-only and LiDAR+image with
the victim's own 2D detector. Each measured row has its BEV AP (R40 and R11) with the bootstrap interval the
run recorded, its clean reference at moderate, its relative drop at moderate and its attack success rate;
the paper's relative drop is against its clean row. Rows of the paper the section has no cell for, and the
section's cells that are no row of the paper (controls, other attacks or protocols), are named in notes.

Standard library only.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from robustbench3d.metrics import HEADLINE
from robustbench3d.report.data import Section
from robustbench3d.results import CellResult
from robustbench3d.seed_table import (
    PAPER_BOTH,
    PAPER_CLEAN,
    PAPER_IMAGE,
    PAPER_LIDAR,
    MeasuredRow,
    PaperRow,
    SeedRow,
    interval_meta,
    layout_rows,
    paper_relative_drop,
    proposal_label,
    victim_layout,
)

#: The paper's rows, in its order.
PAPER_ROWS: tuple[PaperRow, ...] = (PAPER_CLEAN, PAPER_LIDAR, PAPER_IMAGE, PAPER_BOTH)
#: Titles and tooltips of the number columns, in :attr:`Line.numbers` order.
COLUMNS: tuple[tuple[str, str], ...] = (
    ("BEV E", "Car BEV AP, easy (%), with the run's bootstrap interval below"),
    ("BEV M", "Car BEV AP, moderate (%), with the run's bootstrap interval below"),
    ("BEV H", "Car BEV AP, hard (%), with the run's bootstrap interval below"),
    ("clean M", "BEV AP at moderate of the clean row with the same victim and proposals (%)"),
    ("rel. drop M %", "(clean − attacked) / clean, BEV AP at moderate (%)"),
    ("ASR %", "attack success rate: Cars matched clean and missed attacked (moderate, BEV IoU 0.7) (%)"),
)
PAPER_IOU = 0.7


@dataclass(frozen=True)
class Number:
    """One number for both recall samplings; ``kind`` ``ap`` (percent, two decimals), ``paper`` (percent as
    published, one decimal) or ``percent`` (a fraction shown in percent); ``ci40``/``ci11`` the recorded
    interval (percent) or None. A number without recall sampling (the paper's, an ASR) is :func:`single`."""

    kind: str
    r40: float | None
    r11: float | None
    ci40: tuple[float, float] | None = None
    ci11: tuple[float, float] | None = None
    by_recall: bool = True

    def value(self, recall: str) -> float | None:
        return self.r40 if recall == "R40" else self.r11

    def text(self, recall: str) -> str:
        """The value as shown ('–' for none)."""
        v = self.value(recall)
        if v is None:
            return "–"
        return f"{100 * v:.1f}" if self.kind == "percent" else f"{v:.1f}" if self.kind == "paper" else f"{v:.2f}"

    def interval(self, recall: str) -> tuple[float, float] | None:
        return self.ci40 if recall == "R40" else self.ci11

    def ci_text(self, recall: str) -> str:
        """``[lo, hi]`` (one decimal, as ``seed_table.md``), '' without an interval."""
        ci = self.interval(recall)
        return "" if ci is None else f"[{ci[0]:.1f}, {ci[1]:.1f}]"


def single(kind: str, value: float | None) -> Number:
    """A number that is the same for R40 and R11 (the paper's, an attack success rate)."""
    return Number(kind, value, value, by_recall=False)


@dataclass(frozen=True)
class Line:
    """One line of a group: the paper's (``cell`` empty) or a measured cell's (``cell`` its name, ``source``
    where its numbers are read); ``numbers`` in :data:`COLUMNS` order, empty for a cell with no AP
    (``no_ap`` says its status and reason)."""

    who: str
    what: str
    numbers: tuple[Number, ...] = ()
    cell: str = ""
    source: str = ""
    no_ap: str = ""


@dataclass(frozen=True)
class Group:
    """A row of the paper and its measured lines; ``attacks`` the attacks that fill it."""

    paper: PaperRow
    attacks: tuple[str, ...]
    lines: tuple[Line, ...]


@dataclass
class Table1:
    """The block of one section: its groups (paper order), notes and legend."""

    groups: list[Group]
    legend: str
    notes: list[str] = field(default_factory=list)


def _paper_line(paper: PaperRow) -> Line:
    attacked = paper != PAPER_CLEAN
    numbers = [single("paper", v) for v in paper.bev]
    numbers += [single("paper", PAPER_CLEAN.bev[1] if attacked else None),
                single("percent", paper_relative_drop(paper) if attacked else None), single("percent", None)]
    return Line("seed paper", "Table 1", tuple(numbers))


def _numbers(m: MeasuredRow) -> tuple[Number, ...]:
    numbers = [Number("ap", m.bev["R40"][d], m.bev["R11"][d], m.ci["R40"][d], m.ci["R11"][d]) for d in range(3)]
    clean = (None, None) if m.clean is None else (m.clean["R40"][1], m.clean["R11"][1])
    rel = (None, None) if m.relative_drop is None else (m.relative_drop["R40"], m.relative_drop["R11"])
    numbers += [Number("ap", *clean), Number("percent", *rel), single("percent", m.success_rate)]
    return tuple(numbers)


def _line(m: MeasuredRow, section: Section) -> Line:
    name = f"{m.victim}+{m.spec.attack}+{m.spec.proposals}"
    source = next(rc.source for rc in section.cells if rc.name == name)
    what = proposal_label(m.spec.proposals)
    if m.status != "ok":
        return Line(m.victim, what, (), name, source, m.status + (f": {m.reason}" if m.reason else ""))
    return Line(m.victim, what, _numbers(m), name, source)


def _absent(layout: dict[str, list[tuple[SeedRow, MeasuredRow | None]]]) -> list[str]:
    """One note naming the rows of the paper each victim has no cell for, with what fills them."""
    parts = []
    for victim, rows in layout.items():
        missing = [f"{s.paper.label} (--attacks {s.attack} --proposals {s.proposals})"
                   for s, m in rows if s.paper is not None and m is None]
        if missing:
            parts.append(f"{victim}: {', '.join(missing)}")
    return [f"No cell for these rows of Table 1 in this section: {'; '.join(parts)}."] if parts else []


def _outside(section: Section, specs: Sequence[SeedRow]) -> list[str]:
    """One note naming, per run, the section's cells that are no row of the paper."""
    rows = {(s.attack, s.proposals) for s in specs if s.paper is not None}
    by_run: dict[str, list[str]] = {}
    for rc in section.cells:
        if CellResult(rc.cell).id[1:] not in rows:
            by_run.setdefault(str(rc.run), []).append(rc.name)
    if not by_run:
        return []
    where = "; ".join(f"from {run}: {', '.join(names)}" for run, names in by_run.items())
    return [f"Not rows of Table 1 (controls, or an attack and proposal source the paper has no row for; they are "
            f"in the leaderboard): {where}."]


def _iou(section: Section) -> float | None:
    iou = ((section.key["protocol"].get("iou") or {}).get(HEADLINE.cls) or {}).get(HEADLINE.metric)
    return iou if isinstance(iou, int | float) else None


def _legend(section: Section, cells: Sequence[Any]) -> str:
    iou = _iou(section)
    text = (f"Car BEV AP (%) at IoU {'?' if iou is None else iou} (the paper's at {PAPER_IOU}), easy, moderate, "
            "hard (the paper's as published); clean M: the clean row's BEV AP at moderate with the same victim and "
            "proposals (the paper's: its clean row); rel. drop M: (clean − attacked) / clean at moderate; ASR: "
            "attack success rate, Cars matched clean and missed attacked (moderate, BEV IoU 0.7)")
    meta = interval_meta(cells)
    if meta is not None:
        text += (f"; [lo, hi]: the {100 * meta['level']:.0f} % bootstrap interval over frames ({meta['resamples']} "
                 "resamples) the run recorded")
    return text + "."


def build(section: Section) -> Table1:
    """The Table 1 block of ``section``."""
    cells = [rc.cell for rc in section.cells]
    layout = victim_layout(cells)
    specs = layout_rows(CellResult(c).proposals for c in cells)
    groups = []
    for paper in PAPER_ROWS:
        lines = [_paper_line(paper)]
        for rows in layout.values():
            lines += [_line(m, section) for spec, m in rows if spec.paper == paper and m is not None]
        attacks = tuple(dict.fromkeys(s.attack for s in specs if s.paper == paper))
        groups.append(Group(paper, attacks, tuple(lines)))
    notes = _absent(layout) + _outside(section, specs)
    iou = _iou(section)
    if iou is not None and iou != PAPER_IOU:
        notes.insert(0, f"This section's Car BEV AP is at IoU {iou}, the paper's at {PAPER_IOU}: the levels are not "
                        "comparable.")
    return Table1(groups, _legend(section, cells), notes)


def attacks_text(group: Group) -> str:
    """What a group's cells are: ``attack NAME`` (``attacks A, B`` where several fill one row)."""
    return f"attack{'s' if len(group.attacks) > 1 else ''} {', '.join(group.attacks)}"


__all__ = ["COLUMNS", "PAPER_ROWS", "Group", "Line", "Number", "Table1", "attacks_text", "build", "single"]
