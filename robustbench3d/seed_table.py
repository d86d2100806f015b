"""The run's results in the layout of the seed paper's Table 1 (Car BEV AP @ IoU 0.7, easy / moderate / hard).

The seed paper's Table 1 has four rows: clean, LiDAR-only attack, image-only attack and both. They map to
the registered attacks as :data:`SEED_ROWS` says: ``none`` (clean), the controls ``benign-sphere`` and
``random-shape`` (no counterpart in the paper), ``adv-shape`` (LiDAR-only, scored with ground-truth 2D
boxes: proposals ``gt``), ``adv-texture`` (image-only) and ``adv-object`` (both), the last two with the
victim's own 2D detector (proposals ``detector``). Clean and control rows appear for every proposal
source. The LiDAR-only row appears for each LiDAR protocol the summary has (:func:`layout_rows`): ``adv-shape``
under ``gt`` (GT 2D boxes, the object outside the frustum), and under a further protocol such as ``gt-object``
or ``gt-append`` the shape trained for it (``adv-shape-gt-object``, ``adv-shape-gt-append``) and ``adv-shape``
itself, each beside the paper's row, with that protocol's clean and control rows (``benign-sphere``: the grey
sphere). Per victim, one row per ``ok`` summary cell of that map:

* BEV AP R40 and R11 (easy moderate hard, percent);
* the clean reference: BEV AP R40 of the ``none`` cell with the same proposals, as the cell's
  ``attack_effect`` records it (:mod:`robustbench3d.runner.effect`);
* the relative drop at moderate, (clean - attacked) / clean in percent, R40 and R11;
* the attack success rate (percent);
* the seed paper's row and numbers, and its relative drop at moderate against its clean row.

Rows appear only for cells the summary has; a victim without attacked cells of the map gets one line
naming the attacks that would fill its table instead. :func:`victim_layout` gives the same rows as numbers
(``robustbench3d report``'s Table 1 block). A summary with only ``detector`` and ``gt`` cells gets
:data:`SEED_ROWS` exactly. Standard library only.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from robustbench3d.eval.rules import DIFFICULTIES, MIN_OVERLAP
from robustbench3d.fileio import atomic_write_text
from robustbench3d.metrics import HEADLINE, relative_drop
from robustbench3d.results import RECALL_POINTS, CellResult
from robustbench3d.texttable import format_table
from robustbench3d.victims.spec import PROTOCOL_LABELS

#: File name of the markdown table next to ``summary.json``.
SEED_TABLE_FILE = "seed_table.md"
#: The layout's AP: the headline's class and metric (Car BEV), its difficulty for the relative drop (moderate).
CLASS, METRIC, MODERATE = HEADLINE.cls, HEADLINE.metric, HEADLINE.difficulty
#: Recall samplings of the layout, in column order (R40, R11).
RECALLS: tuple[str, ...] = tuple(RECALL_POINTS)


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

#: The proposal source of the victim's own 2D detector (the paper's image-only and LiDAR+image rows). Every
#: other source gives ground-truth 2D boxes: a LiDAR protocol, whose ``adv-shape`` cell is a LiDAR-only row.
DETECTOR_PROPOSALS = "detector"
#: The proposal source whose rows :func:`layout_rows` repeats for a further LiDAR protocol.
GT_PROPOSALS = "gt"
#: The attack of the paper's LiDAR-only row under ``gt``; under a further protocol ``P`` the shape trained for it
#: is shipped as ``adv-shape-P`` (:func:`protocol_shape`).
LIDAR_SHAPE = "adv-shape"
#: How a reader is told each proposal source (the protocols' words, :data:`robustbench3d.victims.spec.PROTOCOL_LABELS`);
#: a source not named there is shown as ``<name> proposals``.
PROPOSAL_LABELS: dict[str, str] = dict(PROTOCOL_LABELS)


def proposal_label(source: str) -> str:
    """A proposal source as a reader is told it: its protocol's words (:data:`PROPOSAL_LABELS`), after its name
    for a further LiDAR protocol (``"gt-object: GT 2D box united with ..."``, as ``--proposals`` names it)."""
    if source not in PROPOSAL_LABELS:
        return f"{source} proposals"
    label = PROPOSAL_LABELS[source]
    return label if source in (DETECTOR_PROPOSALS, GT_PROPOSALS) else f"{source}: {label}"


def protocol_shape(source: str) -> str:
    """The attack of the LiDAR-only shape trained under the LiDAR protocol ``source``: ``adv-shape`` for ``gt``,
    else ``adv-shape-<source>`` (e.g. ``adv-shape-gt-object``)."""
    return LIDAR_SHAPE if source == GT_PROPOSALS else f"{LIDAR_SHAPE}-{source}"


def _further_rows(spec: SeedRow, source: str) -> list[SeedRow]:
    """The rows a further LiDAR protocol ``source`` adds after the ``gt`` row ``spec``: the same control under
    ``source``; for the LiDAR-only row, the shape trained for ``source`` (:func:`protocol_shape`), then the
    ``gt`` shape evaluated under ``source``, both beside the paper's LiDAR-only row."""
    if spec.attack != LIDAR_SHAPE:
        return [SeedRow(spec.name, spec.attack, source, spec.paper)]
    trained = protocol_shape(source)
    return [SeedRow(trained, trained, source, spec.paper), SeedRow(spec.name, spec.attack, source, spec.paper)]


def layout_rows(sources: Iterable[str] = ()) -> tuple[SeedRow, ...]:
    """:data:`SEED_ROWS` and, for each source of ``sources`` that no row of it uses (a further LiDAR protocol:
    ground-truth 2D boxes made another way, e.g. ``gt-object``, ``gt-append``), the rows :data:`GT_PROPOSALS`
    has with that source, each right after its ``gt`` row: the clean and control rows, and beside the paper's
    LiDAR-only row the shape trained for the protocol (``adv-shape-<source>``) and ``adv-shape`` itself.
    Without further sources: :data:`SEED_ROWS` exactly."""
    known = {spec.proposals for spec in SEED_ROWS}
    further = list(dict.fromkeys(s for s in sources if s not in known))
    rows: list[SeedRow] = []
    for spec in SEED_ROWS:
        rows.append(spec)
        if spec.proposals == GT_PROPOSALS:
            rows += [row for source in further for row in _further_rows(spec, source)]
    return tuple(rows)


HEADER: tuple[str, ...] = (
    "row", "proposals", "BEV R40 (E M H)", "BEV R11 (E M H)", "clean R40 (E M H)", "rel. drop M % (R40 R11)",
    "ASR %", "seed paper", "paper BEV (E M H)", "paper rel. drop M %",
)
_ALIGN = "llrrrrrlrr"
_NONE = "-"


def paper_relative_drop(row: PaperRow) -> float:
    """The paper row's relative drop at moderate against the paper's clean row (a fraction)."""
    value = relative_drop(PAPER_CLEAN.bev[1], row.bev[1])
    assert value is not None  # the paper's clean AP is not 0
    return value


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
    for recall in RECALLS:
        try:
            parts.append(_percent(cell.drop(CLASS, METRIC, recall, MODERATE, relative=True)))
        except LookupError:
            return _NONE
    return " ".join(parts)


def _row(spec: SeedRow, cell: CellResult) -> list[str]:
    """The layout's strings for one ``ok`` cell."""
    attacked = cell.effect is not None
    paper = spec.paper
    return [
        spec.name, spec.proposals,
        *(_aps(lambda d, r=r: cell.ap(CLASS, METRIC, r, d), "6.2f", lambda d, r=r: cell.interval(CLASS, METRIC, r, d))
          for r in RECALLS),
        _aps(lambda d: cell.clean_ap(CLASS, METRIC, HEADLINE.recall, d), "6.2f") if attacked else _NONE,
        _relative(cell) if attacked else _NONE,
        _percent(cell.attack_success_rate) if attacked else _NONE,
        paper.label if paper else _NONE,
        " ".join(f"{v:.1f}" for v in paper.bev) if paper else _NONE,
        _percent(paper_relative_drop(paper)) if paper and spec.attack != CLEAN_ATTACK else _NONE,
    ]


#: Easy, moderate, hard values (None where the cell has none).
Triple = tuple[float | None, float | None, float | None]


@dataclass(frozen=True)
class MeasuredRow:
    """One summary cell of the layout as numbers (the data behind a row of :data:`HEADER`). An ``ok`` cell has
    its Car BEV AP per recall sampling (easy, moderate, hard; percent) and their bootstrap intervals
    (``metrics_ci``: [lo, hi] or None); an attacked one also its clean reference (the ``none`` cell with the
    same proposals, E M H), its relative drop at moderate (a fraction; None where the clean AP is 0) and its
    attack success rate (a fraction or None). ``clean``, ``relative_drop`` are None for a cell without a
    clean-cell comparison; every number is None for a cell that is not ``ok`` (``status``, ``reason``)."""

    spec: SeedRow
    victim: str
    status: str
    reason: str | None
    frames: int
    bev: Mapping[str, Triple]
    ci: Mapping[str, tuple[tuple[float, float] | None, ...]]
    clean: Mapping[str, Triple] | None
    relative_drop: Mapping[str, float | None] | None
    success_rate: float | None


def _triple(get: Callable[[str], float | None]) -> Triple:
    values = []
    for d in DIFFICULTIES:
        try:
            values.append(get(d))
        except LookupError:
            values.append(None)
    return (values[0], values[1], values[2])


def _pair(ci: Sequence[float] | None) -> tuple[float, float] | None:
    return None if ci is None else (float(ci[0]), float(ci[1]))


def measured_row(spec: SeedRow, cell: CellResult) -> MeasuredRow:
    """The numbers of ``cell`` in the row ``spec`` of the layout (:class:`MeasuredRow`)."""
    ok = cell.status == "ok"
    attacked = ok and cell.effect is not None

    def rel(recall: str) -> float | None:
        try:
            return cell.drop(CLASS, METRIC, recall, MODERATE, relative=True)
        except LookupError:
            return None

    return MeasuredRow(
        spec=spec, victim=cell.victim, status=cell.status, reason=cell.reason, frames=cell.frames,
        bev={r: _triple(lambda d, r=r: cell.ap(CLASS, METRIC, r, d)) if ok else (None, None, None)
             for r in RECALLS},
        ci={r: tuple(_pair(cell.interval(CLASS, METRIC, r, d)) if ok else None for d in DIFFICULTIES)
            for r in RECALLS},
        clean={r: _triple(lambda d, r=r: cell.clean_ap(CLASS, METRIC, r, d)) for r in RECALLS} if attacked else None,
        relative_drop={r: rel(r) for r in RECALLS} if attacked else None,
        success_rate=cell.attack_success_rate if attacked else None,
    )


def victim_layout(cells: Sequence[Mapping[str, Any]]) -> dict[str, list[tuple[SeedRow, MeasuredRow | None]]]:
    """Per victim of ``cells`` (summary cells, in order of first appearance) every row of
    :func:`layout_rows` (with the cells' proposal sources) and its :class:`MeasuredRow`, or None where the
    summary has no such cell (the first cell counts where one appears twice)."""
    by_victim: dict[str, dict[tuple[str, str], CellResult]] = {}
    for cell in map(CellResult, cells):
        by_victim.setdefault(cell.victim, {}).setdefault((cell.attack, cell.proposals), cell)
    rows = layout_rows(CellResult(c).proposals for c in cells)
    out = {}
    for victim, have in by_victim.items():
        found = ((spec, have.get((spec.attack, spec.proposals))) for spec in rows)
        out[victim] = [(spec, None if cell is None else measured_row(spec, cell)) for spec, cell in found]
    return out


def interval_meta(cells: Sequence[Mapping[str, Any]]) -> Mapping[str, Any] | None:
    """How the first cell with ``metrics_ci`` drew its intervals (its ``meta``: level, resamples, ...), or None."""
    return next((meta for meta in (CellResult(c).interval_meta for c in cells) if meta is not None), None)


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
    #: The rows of the map (:func:`layout_rows` of the summary's proposal sources).
    specs: tuple[SeedRow, ...] = SEED_ROWS

    @property
    def has_attacked(self) -> bool:
        """Whether the summary has any attacked cell of the map for this victim (``ok`` or not)."""
        return any(spec.attack != CLEAN_ATTACK and spec not in self.absent for spec in self.specs)


def sections(cells: Sequence[dict[str, Any]]) -> list[VictimSection]:
    """One :class:`VictimSection` per victim of ``cells`` (summary cells), in order of first appearance."""
    by_victim: dict[str, dict[tuple[str, str], CellResult]] = {}
    for cell in map(CellResult, cells):
        by_victim.setdefault(cell.victim, {}).setdefault((cell.attack, cell.proposals), cell)
    specs = layout_rows(CellResult(c).proposals for c in cells)
    out = []
    for victim, have in by_victim.items():
        section = VictimSection(victim, next(iter(have.values())).frames, specs=specs)
        for spec in specs:
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
    return MIN_OVERLAP[METRIC][CLASS]  # the devkit's, when no cell evaluated it


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
    specs = secs[0].specs if secs else SEED_ROWS
    return f"no attacked cell of it in this run; these attacks fill it: {_fill_hint(specs)}"


def _notes(section: VictimSection) -> list[str]:
    notes = [f"no AP: {line}" for line in section.no_ap]
    if not section.has_attacked:
        notes.append(f"no attacked cell of the layout; these attacks fill it: {_fill_hint(section.absent)}")
    elif missing := [f"{s.attack} / {s.proposals}" for s in section.absent if s.attack != CLEAN_ATTACK]:
        notes.append(f"not in this run: {', '.join(missing)}")
    return notes


def _protocols(cells: Sequence[dict[str, Any]]) -> str:
    """With a further LiDAR protocol among the cells' proposal sources, ``"; proposals: gt = ..., ..."`` (each
    source with its protocol's words, :data:`PROPOSAL_LABELS`), else ''."""
    sources = list(dict.fromkeys(CellResult(c).proposals for c in cells))
    if all(s in (DETECTOR_PROPOSALS, GT_PROPOSALS) for s in sources):
        return ""
    return "; proposals: " + ", ".join(f"{s} = {PROPOSAL_LABELS.get(s, 'another source')}" for s in sources)


def _legend(cells: Sequence[dict[str, Any]]) -> str:
    """The legend, plus what ``[lo, hi]`` means when some cell carries bootstrap intervals, and each proposal
    source's protocol when there is a further one (``seed paper`` then stands beside every source)."""
    meta = interval_meta(cells)
    protocols = _protocols(cells)
    legend = LEGEND.replace("both proposal sources", "every proposal source") + protocols if protocols else LEGEND
    if meta is None:
        return legend
    return (f"{legend}; [lo, hi] = {100 * meta['level']:.0f} % bootstrap interval over frames "
            f"({meta['resamples']} resamples)")


def seed_table_text(cells: Sequence[dict[str, Any]], table: Callable[..., str] = format_table) -> str:
    """The layout as plain text (:func:`robustbench3d.texttable.format_table`, or ``table``, called as
    ``table(header, rows, align=...)``, e.g. the run's terminal folding), one section per victim."""
    secs = sections(cells)
    if (empty := _no_layout(secs)) is not None:
        return f"{TITLE}: {empty}"
    lines = [f"{TITLE}: {_subtitle(cells)}", _legend(cells)]
    for section in secs:
        lines.append(f"victim {section.victim}, {section.frames} frames")
        if section.rows:
            lines.append(table(HEADER, section.rows, align=_ALIGN))
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
    "CLEAN_ATTACK", "DETECTOR_PROPOSALS", "GT_PROPOSALS", "HEADER", "LEGEND", "LIDAR_SHAPE", "PAPER_BOTH",
    "PAPER_CLEAN", "PAPER_IMAGE", "PAPER_LIDAR", "PROPOSAL_LABELS", "SEED_ROWS", "SEED_TABLE_FILE", "TITLE",
    "MeasuredRow", "PaperRow", "SeedRow", "VictimSection", "interval_meta", "layout_rows", "measured_row",
    "paper_relative_drop", "proposal_label", "protocol_shape", "sections", "seed_table_markdown", "seed_table_text",
    "victim_layout", "write_seed_table",
]
