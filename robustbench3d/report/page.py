"""``leaderboard.html``: one self-contained file (inline CSS and JavaScript, figures as base64 PNG, no network),
rendered by Jinja2 from ``templates/leaderboard.html.j2`` with autoescape on: every string the page shows
or puts in an attribute is escaped by the template engine (no string is marked safe).

The leaderboard table sorts on a click on any column header (numbers numerically, empty values last, ties in
table order) and shows R40 or R11 AP by a toggle; every number's cell carries both values (``data-r40``,
``data-r11``, shortest exact float text) and shows the other on hover. Its default columns fit a 1280 px
wide page; the 3D AP, the intervals and the run / object columns are shown by toolbar toggles (the table
then scrolls inside its own box). Each row links to a ``<details>`` block with the cell's full JSON as the
run wrote it (provenance, dataset, metrics, attack effect, flags). Each section starts with the seed
paper's Table 1 beside its measured rows (:mod:`robustbench3d.report.table1`); after its leaderboard come the
cells it merged or left out, each named with its run and why, then the worst case (per proposal source the
victims ranked by their worst attacked AP, tables ``#wc-K-J``) and, after the figures, the transfer matrix
(tables ``#tm-K-J``: every attack object by every victim, the white-box entry highlighted, ``not run`` where
there is no cell) above its heat-map. ``leaderboard.md`` is
:func:`robustbench3d.report.mdpage.markdown` (re-exported here).

jinja2 is imported inside :func:`environment`.
"""

from __future__ import annotations

import base64
import functools
import json
from collections.abc import Sequence
from typing import Any

from robustbench3d.report.mdpage import markdown, md_code, md_text
from robustbench3d.report.table1 import COLUMNS as T1_COLUMNS
from robustbench3d.report.table1 import attacks_text
from robustbench3d.report.table1 import build as build_table1
from robustbench3d.report.view import (
    GROUPS,
    LEGEND,
    NO_ATTACK,
    TRANSFER_LEGEND,
    WORST_COLUMNS,
    WORST_LEGEND,
    Column,
    Figure,
    SectionView,
    ci_high,
    ci_text,
    columns,
    fmt,
    raw,
    section_facts,
    section_title,
    transfer_row,
    worst_row,
)
from robustbench3d.report.worst import objects_text

TEMPLATE = "leaderboard.html.j2"
#: Text columns whose long values wrap (at a hyphen or space, at most 12rem wide) instead of widening the table.
NAMES = ("victim", "attack", "run", "trained_against")


@functools.lru_cache(maxsize=1)
def environment() -> Any:
    """The Jinja2 environment of the page's templates (package data): autoescape on, undefined names an error."""
    import jinja2

    env = jinja2.Environment(loader=jinja2.PackageLoader("robustbench3d.report", "templates"), autoescape=True,
                             undefined=jinja2.StrictUndefined, trim_blocks=True, lstrip_blocks=True)
    env.filters["raw"] = raw
    env.filters["pair"] = lambda ci: "" if ci is None else f"{ci[0]!r} {ci[1]!r}"
    env.globals["attacks_text"] = attacks_text
    return env


def _cell(attrs: dict[str, str], text: str, flags: Sequence[tuple[str, str]] = (), wrap: bool = False
          ) -> dict[str, Any]:
    return {"attrs": attrs, "text": text, "flags": list(flags), "wrap": wrap}


def _td(row: Any, col: Column) -> dict[str, Any]:
    """One leaderboard cell: its attributes (``xmlattr``), its text, whether it may wrap (:data:`NAMES`) and,
    for the flags column, the flags."""
    group = {"data-g": col.group} if col.group else {}
    if col.kind == "flags":
        return _cell({"class": "flags", "data-v": ",".join(c for c, _ in row["flags"]), **group}, "", row["flags"])
    if col.kind == "str":
        text = str(row[col.key])
        title = {"title": row["reason"]} if col.key == "status" and row["reason"] else {}
        return _cell({"data-v": text, **title, **group}, text, wrap=col.key in NAMES)
    if col.kind == "ci":
        vals = {r: (row[col.field(r)], row[ci_high(col.field(r))]) for r in ("R40", "R11")}
        texts = {r: ci_text(lo, hi) for r, (lo, hi) in vals.items()}
        return _cell({"class": "num", "data-r40": raw(vals["R40"][0]), "data-r11": raw(vals["R11"][0]),
                      "data-t40": texts["R40"], "data-t11": texts["R11"], **group}, texts["R40"])
    if not col.by_recall:
        v = row[col.key]
        return _cell({"class": "num", "data-v": raw(v), **group}, fmt(v, col.kind))
    v40, v11 = row[col.field("R40")], row[col.field("R11")]
    t40, t11 = fmt(v40, col.kind), fmt(v11, col.kind)
    return _cell({"class": "num", "data-r40": raw(v40), "data-r11": raw(v11), "data-t40": t40, "data-t11": t11,
                  "title": f"R40 {t40} · R11 {t11}", **group}, t40)


def image(fig: Figure) -> dict[str, str]:
    """A figure as the template shows it: the PNG as a data URI, its alt text and caption."""
    return {"src": "data:image/png;base64," + base64.b64encode(fig.png).decode("ascii"), "alt": fig.alt,
            "caption": fig.caption}


def cell_json(view: SectionView, i: int) -> str:
    return json.dumps(view.section.cells[i].cell, indent=1, sort_keys=False, ensure_ascii=False)


def _worst(view: SectionView, k: int, prov_ids: dict[str, str]) -> list[dict[str, Any]]:
    """The worst-case tables of a section as the template shows them (one per proposal source)."""
    return [{"id": f"wc-{k}-{j}", "proposals": wc.proposals, "objects": ", ".join(wc.objects),
             "n": objects_text(len(wc.objects)),
             "unequal": wc.unequal,
             "rows": [{"victim": r.victim, "rank": "" if r.rank is None else r.rank, "flagged": r.flagged,
                       "cells": [vars(c) for c in worst_row(r, wc)],
                       "prov": prov_ids[r.source.name] if r.source else "",
                       "source": r.source.source if r.source else ""}
                      for r in wc.rows]}
            for j, wc in enumerate(view.worst)]


def _grids(view: SectionView, k: int) -> list[dict[str, Any]]:
    """The transfer tables of a section as the template shows them (one per proposal source)."""
    out = []
    for j, g in enumerate(view.grids):
        rows = [{"object": row.object, "trained": row.trained_against or "", "label": row.label,
                 "away": row.trained_against is not None and row.trained_against not in g.victims,
                 "cells": [{"victim": v, "text": c.text, "tip": c.tip,
                            "cls": " ".join(n for n, on in (("num", c.num), ("nr", not c.num), ("wb", wb)) if on)}
                           for v, (c, wb) in zip(g.victims, transfer_row(g, row), strict=True)]}
                for row in g.rows]
        out.append({"id": f"tm-{k}-{j}", "proposals": g.proposals, "victims": list(g.victims), "rows": rows})
    return out


def _section(view: SectionView, k: int) -> dict[str, Any]:
    """What the template needs of one section (plain values; the template escapes every string)."""
    cols = view.columns()
    cells = view.section.cells
    return {
        "k": k, "title": section_title(view, k), "differs": "; ".join(view.section.differs),
        "facts": section_facts(view), "table1": build_table1(view.section), "t1_columns": T1_COLUMNS,
        "prov_ids": {rc.name: f"prov-{k}-{i}" for i, rc in enumerate(cells)},
        "columns": [{"title": c.title, "key": c.key, "type": "str" if c.kind in ("str", "flags") else "num",
                     "tip": c.tip, "group": c.group} for c in cols],
        "rows": [{"i": i, "cell": row["cell"], "source": row["source"], "tds": [_td(row, c) for c in cols]}
                 for i, row in view.df.iterrows()],
        "groups": [g for g, _ in GROUPS if any(c.group == g for c in cols)],
        "legend": LEGEND, "cell_notes": view.cell_notes(),
        "worst": _worst(view, k, {rc.name: f"prov-{k}-{i}" for i, rc in enumerate(cells)}),
        "worst_columns": WORST_COLUMNS, "worst_legend": WORST_LEGEND, "grids": _grids(view, k),
        "transfer_legend": TRANSFER_LEGEND,
        "figures": [image(f) for f in view.figures], "transfer": image(view.transfer) if view.transfer else None,
        "transfer_note": view.transfer_note or NO_ATTACK, "scenes": [image(s) for s in view.scenes],
        "scene_notes": view.scene_notes,
        "provenance": [{"id": f"prov-{k}-{i}", "name": rc.name, "source": rc.source, "json": cell_json(view, i)}
                       for i, rc in enumerate(cells)],
    }


def html_page(views: Sequence[SectionView], title: str, runs: Sequence[str], notes: Sequence[str],
              trades: Sequence[dict[str, Any]] = (), sweeps: Sequence[dict[str, Any]] = ()) -> str:
    """The whole self-contained page; ``trades``: speed/accuracy sections
    (:func:`robustbench3d.report.tradeoff_view.tradeoff_model`); ``sweeps``: dose–response sections
    (:func:`robustbench3d.report.sweep_view.sweep_model`)."""
    sections = [_section(view, k) for k, view in enumerate(views)]
    used = {g for s in sections for g in s["groups"]}
    return environment().get_template(TEMPLATE).render(
        title=title, runs=", ".join(runs), notes=list(notes), sections=sections, trades=list(trades),
        sweeps=list(sweeps),
        groups=[(g, label) for g, label in GROUPS if g in used])


__all__ = ["Column", "Figure", "SectionView", "cell_json", "columns", "environment", "fmt", "html_page", "image",
           "markdown", "md_code", "md_text"]
