"""What the page and the markdown both show of a section: its columns, number formats, figures and texts.

The leaderboard's columns come in groups: the default ones fit a 1280 px wide page; those of a group
(:data:`GROUPS`: 3D AP, intervals, run and the object's victim) are shown on demand in the HTML page (the
table then scrolls inside its own box) and always in the markdown.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from robustbench3d.metrics import ATTACK_METRICS, AttackMetric, of_kind
from robustbench3d.report.data import CLASS, DIFFICULTIES, RECALLS, Section, ap_column, effect_column, left_out

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


@dataclass
class SectionView:
    """A section with its table and figures, ready to write."""

    section: Section
    df: Any
    figures: list[Figure] = field(default_factory=list)
    transfer: Figure | None = None
    transfer_note: str = ""
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
