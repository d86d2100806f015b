"""``leaderboard.md``: the report as markdown, figures as PNG files beside it.

Tables are GitHub pipe tables written by ``tabulate``; every string that comes from a summary, a path or the
command line goes through :func:`md_text` (or :func:`md_code`) first, so it is inert as markdown and as HTML.
``tabulate`` is imported inside :func:`markdown`.
"""

from __future__ import annotations

import html
import re
from collections.abc import Sequence
from typing import Any

from robustbench3d.report.table1 import COLUMNS as T1_COLUMNS
from robustbench3d.report.table1 import Line, Number, Table1, attacks_text
from robustbench3d.report.view import (
    NO_ATTACK,
    TRANSFER_LEGEND,
    WORST_COLUMNS,
    WORST_LEGEND,
    Column,
    Figure,
    SectionView,
    Shown,
    ci_high,
    ci_text,
    fmt,
    section_facts,
    section_title,
    transfer_row,
    worst_row,
)
from robustbench3d.report.worst import objects_text

#: Characters that start markdown markup anywhere in a line (code, emphasis, links and images, tables,
#: strikethrough) and the backslash itself; each is written backslash-escaped (``_``: see below).
_MD_INLINE = re.compile(r"([\\`*\[\]|~])")
#: An underscore that could open or close emphasis: not between two letters or digits (``run_dir`` stays).
_MD_UNDERSCORE = re.compile(r"(?<![^\W_])_|_(?![^\W_])")
#: Markup that only counts at the start of a line: headings, list items, setext underlines, ordered lists.
_MD_LINE_START = re.compile(r"^(\s*)(?:([#+=-])|(\d+)([.)]))")


def md_text(value: Any) -> str:
    """``value`` as inert markdown text on one line: HTML's ``& < >`` as entities (no tag, comment or entity of
    the input survives), markdown punctuation backslash-escaped (no link, image, code span, emphasis or table
    cell break), line-start markup escaped and line breaks as spaces. A renderer shows the text as given."""
    text = " ".join(str(value).splitlines())
    text = _MD_UNDERSCORE.sub(r"\\_", _MD_INLINE.sub(r"\\\1", html.escape(text, quote=False)))
    return _MD_LINE_START.sub(lambda m: m[1] + ("\\" + m[2] if m[2] else m[3] + "\\" + m[4]), text)


def md_code(value: Any) -> str:
    """``value`` as an inline code span on one line in a table cell (shown literally): fenced by more backticks
    than it holds in a row, ``|`` escaped as GitHub tables require."""
    text = " ".join(str(value).splitlines()).replace("|", "\\|")
    fence = "`" * (max((len(run) for run in re.findall("`+", text)), default=0) + 1)
    pad = " " if text.startswith("`") or text.endswith("`") else ""
    return f"{fence}{pad}{text}{pad}{fence}"


def md_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> list[str]:
    """A GitHub pipe table of cells that are markdown already (escaped by the caller), as lines."""
    from tabulate import tabulate

    return tabulate(rows, headers=list(header), tablefmt="github", disable_numparse=True).split("\n")


def _md_cells(row: Any, cols: Sequence[Column]) -> list[str]:
    """One leaderboard row (R40, R11 in parentheses); every string of the summary through :func:`md_text`."""
    texts = []
    for c in cols:
        if c.kind == "flags":
            texts.append(", ".join(f"{md_text(code)}: {md_text(msg)}" for code, msg in row["flags"]))
        elif c.kind == "str":
            texts.append(md_text(row[c.key]))
        elif c.kind == "ci":
            texts.append(ci_text(row[c.field("R40")], row[ci_high(c.field("R40"))]))
        elif c.by_recall:
            texts.append(f"{fmt(row[c.field('R40')], c.kind)} ({fmt(row[c.field('R11')], c.kind)})")
        else:
            texts.append(fmt(row[c.key], c.kind))
    return [*texts, md_code(row["source"])]


def _md_number(n: Number) -> str:
    """R40 with its interval, then R11 in parentheses (a number with recall sampling)."""
    ci = n.ci_text("R40")
    text = n.text("R40") + (f" {ci}" if ci else "")
    return f"{text} ({n.text('R11')})" if n.by_recall else text


def _t1_cells(line: Line, first: str) -> list[str]:
    who = md_text(line.who if not line.cell else f"{line.who} · {line.what}")
    if line.no_ap:
        numbers = [f"no AP: {md_text(line.no_ap)}", *["–"] * (len(T1_COLUMNS) - 1)]
    else:
        numbers = [_md_number(n) for n in line.numbers]
    return [first, who, *numbers, md_code(line.source) if line.source else ""]


def table1_markdown(t1: Table1) -> list[str]:
    """The Table 1 block: legend, one table (each paper row, then the measured rows of it), notes."""
    rows = []
    for group in t1.groups:
        label = f"**{md_text(group.paper.label)}** ({md_text(attacks_text(group))})"
        rows += [_t1_cells(line, label if i == 0 else "") for i, line in enumerate(group.lines)]
    header = ["Table 1 row", "measured", *(md_text(t) for t, _ in T1_COLUMNS), "source"]
    legend = md_text(t1.legend) + " A measured number: R40 [interval] (R11)."
    return [legend, "", *md_table(header, rows), "", *(f"- {md_text(n)}" for n in t1.notes),
            *([""] if t1.notes else [])]


def _md_figure(fig: Figure, figure_dir: str) -> list[str]:
    return [f"![{md_text(fig.alt)}]({figure_dir}/{fig.name})", "", f"*{md_text(fig.caption)}*", ""]


def _section(view: SectionView, t1: Table1, k: int, figure_dir: str) -> list[str]:
    cols = view.columns()
    lines = [f"## {md_text(section_title(view, k))}", ""]
    if view.section.differs:
        lines += ["Kept apart from section 1 because these differ: " + md_text("; ".join(view.section.differs)), ""]
    lines += [md_text(section_facts(view)), "", "### Seed paper Table 1 beside the measured rows", ""]
    lines += table1_markdown(t1)
    lines += ["### Leaderboard", ""]
    lines += md_table([*(md_text(c.title) for c in cols), "source"],
                      [_md_cells(row, cols) for _, row in view.df.iterrows()])
    lines.append("")
    if notes := view.cell_notes():
        lines += ["### Cells merged or left out", "", *(f"- {md_text(n)}" for n in notes), ""]
    lines += worst_markdown(view)
    for fig in view.figures:
        lines += _md_figure(fig, figure_dir)
    lines += transfer_markdown(view)
    if view.transfer:
        lines += _md_figure(view.transfer, figure_dir)
    for fig in view.scenes:
        lines += _md_figure(fig, figure_dir)
    lines += [*map(md_text, view.scene_notes), ""] if view.scene_notes else []
    return lines


def _md_shown(cell: Shown) -> str:
    """A worst-case or transfer cell: a number (the report's own text) as it is, any other text inert."""
    text = f"{cell.text} {cell.sub}" if cell.sub else cell.text
    return text if cell.num else md_text(text)


def worst_markdown(view: SectionView) -> list[str]:
    """The worst-case block: per proposal source the ranked table (the worst cell's source last), the line on
    victims evaluated against fewer attack objects; a line when the section ran no attack object."""
    lines = ["### Worst case: victims ranked by their worst attacked AP", ""]
    if not view.worst:
        return [*lines, md_text(view.transfer_note or NO_ATTACK), ""]
    lines += [md_text(WORST_LEGEND), ""]
    for wc in view.worst:
        rows = [[*map(_md_shown, worst_row(r, wc)), md_code(r.source.source) if r.source else "–"] for r in wc.rows]
        lines += [f"Proposals {md_code(wc.proposals)}, {objects_text(len(wc.objects))}: "
                  f"{md_text(', '.join(wc.objects))}.", ""]
        lines += md_table([*(md_text(t) for t, _ in WORST_COLUMNS), "source"], rows)
        lines += ["", *([f"⚑ {md_text(wc.unequal)}", ""] if wc.unequal else [])]
    return lines


def transfer_markdown(view: SectionView) -> list[str]:
    """The transfer-matrix block: per proposal source a table, every attack object by every victim (white-box
    entries bold), its legend; a line when there is none."""
    lines = ["### Transfer matrix", ""]
    if not view.grids:
        return [*lines, md_text(view.transfer_note or NO_ATTACK), ""]
    lines += [md_text(TRANSFER_LEGEND), ""]
    for grid in view.grids:
        rows = []
        for row in grid.rows:
            cells = [f"**{_md_shown(s)}**" if wb else _md_shown(s) for s, wb in transfer_row(grid, row)]
            rows.append([md_text(row.label), *cells])
        lines += [f"Proposals {md_code(grid.proposals)} (rel. drop %, R40):", ""]
        lines += md_table(["trained against · object", *map(md_text, grid.victims)], rows)
        lines.append("")
    return lines


def markdown(views: Sequence[SectionView], title: str, runs: Sequence[str], notes: Sequence[str],
             figure_dir: str, extra: Sequence[str] = ()) -> str:
    """The leaderboard as markdown: per section the Table 1 block, the table (R40, R11 in parentheses), the
    cells merged or left out and the figures as links; ``extra``: further markdown sections appended (already
    markdown). Every string that comes from a summary, a path or the command line is written through
    :func:`md_text` or :func:`md_code`: inert as markdown and as HTML. Figure file names are the report's own
    (``[A-Za-z0-9._-]``)."""
    from robustbench3d.report.table1 import build

    lines = [f"# {md_text(title)}", "", f"From {md_text(', '.join(runs))}. AP in % (R40, R11 in parentheses); drops "
             "and the relative drop are BEV moderate against the clean cell with the same proposals; ASR in %.", ""]
    lines += [f"> {md_text(n)}" for n in notes] + ([""] if notes else [])
    for k, view in enumerate(views):
        lines += _section(view, build(view.section), k, figure_dir)
    lines += [e.rstrip() + "\n" for e in extra]
    return "\n".join(lines).rstrip() + "\n"
