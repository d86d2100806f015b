"""What the page and the markdown both show of a section: its columns, number formats, figures and texts.

The leaderboard's columns come in groups: the default ones fit a 1280 px wide page; those of a group
(:data:`GROUPS`: 3D AP, intervals, run and the object's victim) are shown on demand in the HTML page (the
table then scrolls inside its own box) and always in the markdown.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

from robustbench3d.metrics import ATTACK_METRICS, AttackMetric, of_kind
from robustbench3d.report.data import (
    CLASS,
    DIFFICULTIES,
    RECALLS,
    Section,
    TransferGrid,
    ap_column,
    effect_column,
    left_out,
    transfer_grids,
)
from robustbench3d.report.worst import WorstCase, WorstRow, worst_cases

#: Optional column groups of the HTML table: (id, the toggle's label), in toolbar order.
GROUPS: tuple[tuple[str, str], ...] = (("3d", "3D AP"), ("ci", "intervals"), ("more", "run, object's victim"))


@dataclass(frozen=True)
class Column:
    """A table column: ``key`` a DataFrame column, or with ``by_recall`` a template filled with R40/R11;
    ``group`` one of :data:`GROUPS` (hidden by default in the HTML page) or "" (always shown)."""

    title: str
    key: str
    kind: str = "str"  # str | ap | points | percent | flags | ci
    by_recall: bool = False
    tip: str = ""
    group: str = ""

    def field(self, recall: str) -> str:
        return self.key.format(recall=recall) if self.by_recall else self.key


def columns(has_ci: bool, has_flags: bool, several_runs: bool, has_drop_ci: bool = False) -> list[Column]:
    """The leaderboard's columns."""
    cols = [Column("victim", "victim"), Column("attack", "attack"), Column("proposals", "proposals")]
    if several_runs:
        cols.insert(0, Column("run", "run", group="more"))
    for metric, name in (("bev", "BEV"), ("3d", "3D")):
        for d in DIFFICULTIES:
            cols.append(Column(f"{name} {d[0].upper()}", ap_column(metric, "{recall}", d), "ap", True,
                               f"Car {name} AP, {d}, IoU 0.7 (%)", "3d" if metric == "3d" else ""))
    cols += [metric_column(m) for m in ATTACK_METRICS.values() if m.kind != "interval" and m.report is not None]
    if has_ci:
        cols.append(Column("BEV M CI", effect_column("ci_low", "{recall}"), "ci", True,
                           "confidence interval of BEV AP, moderate, as the run recorded it (%)", "ci"))
    if has_drop_ci:
        cols += [metric_column(m) for m in of_kind("interval") if m.report is not None]
    if has_flags:
        cols.append(Column("flags", "flags", "flags"))
    cols.append(Column("trained against", "trained_against", "str", False,
                       "victim the attack object was optimised against", "more"))
    cols.append(Column("status", "status"))
    return cols


def metric_column(m: AttackMetric) -> Column:
    """The leaderboard column of an attack metric with a ``report`` column (an interval's is in group ``ci``)."""
    assert m.report is not None
    if m.kind == "interval":
        return Column(m.report.title, effect_column(f"{m.report.key}_low", "{recall}"), m.report.kind, True,
                      m.report.tip, "ci")
    key = effect_column(m.report.key, "{recall}") if m.kind == "ap" else m.report.key
    return Column(m.report.title, key, m.report.kind, m.kind == "ap", m.report.tip)


LEGEND = ("E, M, H: easy, moderate, hard. BEV, 3D: Car AP (%) in bird's-eye view and in 3D at the section's IoU. "
          "clean BEV M: BEV AP at moderate of the clean cell with the same victim and proposals; drop pts: clean − "
          "attacked (points); rel. drop %: drop / clean; ASR %: attack success rate, the Cars matched clean and "
          "missed attacked (moderate, BEV IoU 0.7); CI: the interval the run recorded. A header's tooltip says the "
          "same.")


def fmt(value: Any, kind: str) -> str:
    """Display text of one number ('–' for none)."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–"
    if kind == "ap":
        return f"{value:.2f}"
    if kind == "points":
        return f"{value:+.2f}"
    if kind == "percent":
        return f"{100 * value:.1f}"
    return str(value)


def raw(value: Any) -> str:
    """A number as its shortest exact text ('' for none): what the page's sorting reads."""
    return "" if value is None or (isinstance(value, float) and math.isnan(value)) else repr(float(value))


def ci_text(lo: float, hi: float) -> str:
    """``[lo, hi]`` of the leaderboard (two decimals), '–' where there is none."""
    return "–" if math.isnan(lo) else f"[{lo:.2f}, {hi:.2f}]"


def ci_high(field_name: str) -> str:
    """The column holding the upper end of the interval whose lower end is ``field_name``."""
    return field_name.replace("ci_low_", "ci_high_")


@dataclass
class Figure:
    """One figure of a section: a PNG, its file name for the markdown and a caption."""

    name: str
    png: bytes
    caption: str
    alt: str


#: What the worst case and the transfer matrix say of a section that ran no attack object.
NO_ATTACK = ("No attack object was run (clean cells and controls only), so there is no worst case and no transfer "
             "matrix.")


@dataclass
class SectionView:
    """A section with its table and figures, ready to write."""

    section: Section
    df: Any
    figures: list[Figure] = field(default_factory=list)
    transfer: Figure | None = None
    transfer_note: str = ""  # why there is no transfer matrix (set when there is none; NO_ATTACK if unset)
    scenes: list[Figure] = field(default_factory=list)
    scene_notes: list[str] = field(default_factory=list)

    def columns(self) -> list[Column]:
        """The leaderboard's columns for this section's cells."""
        df = self.df
        lows = ["ci_low", *(f"{m.report.key}_low" for m in of_kind("interval") if m.report is not None)]
        has = {k: any(bool(df[effect_column(k, r)].notna().any()) for r in RECALLS) for k in lows}
        return columns(has["ci_low"], any(len(f) for f in df["flags"]), len(self.section.runs) > 1,
                       any(has[k] for k in lows[1:]))

    def cell_notes(self) -> list[str]:
        """Every cell given but not shown (a duplicate) or left out of the figures or transfer matrix, and why."""
        return [m.note() for m in self.section.merged] + left_out(self.section)

    @cached_property
    def worst(self) -> list[WorstCase]:
        """The worst case of each proposal source that ran an attack object (:mod:`robustbench3d.report.worst`)."""
        return worst_cases(self.section)

    @cached_property
    def grids(self) -> list[TransferGrid]:
        """The transfer matrix of each proposal source that ran an attack object (every attack object of the
        section by every victim of the section)."""
        return [g for g in transfer_grids(rc.cell for rc in self.section.cells) if g.entries]


def section_title(view: SectionView, k: int) -> str:
    key = view.section.key
    ds = key["dataset"]
    return (f"Section {k + 1}: split {ds['split']}, {ds['frames']} of {ds['split_frames']} frames, dataset "
            f"sha256 {str(ds['sha256'])[:12]}, robustbench3d {key['versions']['robustbench3d']}, "
            f"seed {key['protocol']['seed']}")


def section_facts(view: SectionView) -> str:
    key = view.section.key
    iou = key["protocol"]["iou"] or {}
    ious = ", ".join(f"{m} {v}" for m, v in (iou.get(CLASS) or {}).items())
    return (f"Runs: {', '.join(map(str, view.section.runs))}. Car AP in % at IoU {ious}; recall points "
            f"{', '.join(key['protocol']['recall_points'])}; drops and the transfer matrix compare cells "
            "with the same proposal source only.")


# ---- the worst case and the transfer matrix, as both pages show them ----------------------------------------

WORST_LEGEND = ("Ranked by the worst attacked AP: the lowest Car BEV AP at moderate (R40, %) over every attack object "
                "run against the victim with these proposals, highest (most robust) first, as robustness leaderboards "
                "rank by the strongest evaluated attack. The clean cell and the controls (benign-sphere, random-shape: "
                "an unoptimised object) are no attacks: shown for reference, never the worst case. Equal recorded APs "
                "share a rank (2=) and name every object reaching it (drop columns: the first's). drop pts: clean − "
                "worst attacked, with the run's paired bootstrap interval [95 %] where recorded; rel. drop: drop / "
                "clean. attack objects: evaluated of those run with these proposals; ⚑: fewer than the others.")


@dataclass(frozen=True)
class Shown:
    """One cell of the worst-case or transfer table: ``text``, a second line ``sub`` ("" for none), a number
    (right-aligned) or not, a tooltip and, for a list, its items."""

    text: str
    sub: str = ""
    num: bool = False
    tip: str = ""
    parts: tuple[str, ...] = ()  # the text's items ("; "-joined), each kept on one line in the page


#: The worst-case table's columns: (title, tooltip).
WORST_COLUMNS: tuple[tuple[str, str], ...] = (
    ("rank", "by worst attacked AP, highest first; = a tie"),
    ("victim", ""),
    ("clean BEV M", "Car BEV AP, moderate, R40, of the clean cell (%)"),
    ("worst attacked BEV M", "the lowest Car BEV AP, moderate, R40, over the attack objects (%), [95 % interval]"),
    ("by object", "the attack object(s) reaching the worst attacked AP"),
    ("rel. drop %", "(clean − worst attacked) / clean (%)"),
    ("drop pts", "clean − worst attacked (points), [paired bootstrap 95 % interval]"),
    ("attack objects", "attack objects evaluated against the victim, of those run with these proposals"),
    ("controls (reference)", "Car BEV AP, moderate, R40, of each control (%): not attacks, not in the worst case"),
)


def _pair(ci: tuple[float, float] | None, sign: str = "") -> str:
    return "" if ci is None else f"[{ci[0]:{sign}.2f}, {ci[1]:{sign}.2f}]"


def worst_row(row: WorstRow, wc: WorstCase) -> list[Shown]:
    """The worst-case table's cells of ``row`` (:data:`WORST_COLUMNS`): every missing number says why."""
    rank = "unranked" if row.rank is None else f"{row.rank}{'=' if row.tied else ''}"
    clean = Shown(fmt(row.clean, "ap") if row.clean is not None else row.clean_note, num=row.clean is not None)
    if row.worst_ap is None:
        worst, by = Shown("none evaluated"), Shown("–")
    else:
        worst = Shown(fmt(row.worst_ap, "ap"), _pair(row.worst_ci), True)
        by = Shown(" = ".join(row.by) + (" (tie)" if len(row.by) > 1 else ""))
    note = row.drop_note
    rel = Shown(fmt(row.relative_drop, "percent"), num=True) if row.relative_drop is not None else Shown(note)
    drop = Shown(fmt(row.drop, "points"), _pair(row.drop_ci, "+"), True) if row.drop is not None else Shown(note)
    count = f"{len(row.evaluated)} of {len(wc.objects)}" + (" ⚑" if row.flagged else "")
    missing = "; ".join(f"{obj} ({why})" for obj, why in row.missing)
    objects = Shown(count, f"not evaluated: {missing}" if missing else "",
                    tip="evaluated: " + (", ".join(row.evaluated) or "none"))
    parts = tuple(f"{name} {fmt(ap, 'ap') if ap is not None else status}" for name, ap, status in row.controls)
    controls = Shown("; ".join(parts) or "none run", parts=parts)
    return [Shown(rank, num=True), Shown(row.victim), clean, worst, by, rel, drop, objects, controls]


TRANSFER_LEGEND = ("Relative drop of Car BEV AP at moderate (R40, %) of each attack object (rows: the victim it was "
                   "trained against · the object; (object file): no training victim recorded) on each victim of the "
                   "section (columns), against the clean cell of the same victim and proposals. Highlighted (bold in "
                   "the markdown): the victim the object was trained against (white-box); every other entry is a "
                   "transfer. not run: no such cell; clean AP 0: the relative drop is undefined; no clean cell: "
                   "nothing to compare with; skipped, error: the cell's status.")


def transfer_row(grid: TransferGrid, row: Any) -> list[tuple[Shown, bool]]:
    """The transfer table's cells of ``row`` (one per victim of ``grid``) and whether each is white-box."""
    out = []
    for victim in grid.victims:
        e = grid.entry(row, victim)
        out.append((Shown(e.text, num=e.value is not None, tip=e.cell or f"{victim}+{row.object}+{grid.proposals}: "
                          "not run"), e.white_box))
    return out
