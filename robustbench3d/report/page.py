"""``leaderboard.html`` (one self-contained file: inline CSS and JavaScript, figures as base64 PNG, no network)
and ``leaderboard.md`` (figures as PNG files beside it) from the report's sections.

The HTML table sorts on a click on any column header (numbers numerically, empty values last, ties in table
order) and shows R40 or R11 AP by a toggle; every number's cell carries both values (``data-r40``,
``data-r11``, shortest exact float text) and shows the other on hover. Each row links to a ``<details>`` block
with the cell's full JSON as the run wrote it (provenance, dataset, metrics, attack effect, flags).
"""

from __future__ import annotations

import base64
import html
import json
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from robustbench3d.report.data import DIFFICULTIES, RECALLS, Section, ap_column, effect_column


@dataclass(frozen=True)
class Column:
    """A table column: ``key`` a DataFrame column, or with ``recall`` a template filled with R40/R11."""

    title: str
    key: str
    kind: str = "str"  # str | ap | points | percent | flags | ci
    by_recall: bool = False
    tip: str = ""

    def field(self, recall: str) -> str:
        return self.key.format(recall=recall) if self.by_recall else self.key


def columns(has_ci: bool, has_flags: bool, several_runs: bool, has_drop_ci: bool = False) -> list[Column]:
    """The leaderboard's columns."""
    cols = [Column("victim", "victim"), Column("attack", "attack"), Column("proposals", "proposals")]
    if several_runs:
        cols.insert(0, Column("run", "run"))
    for metric, name in (("bev", "BEV"), ("3d", "3D")):
        for d in DIFFICULTIES:
            cols.append(Column(f"{name} {d[0].upper()}", ap_column(metric, "{recall}", d), "ap", True,
                               f"Car {name} AP, {d}, IoU 0.7 (%)"))
    cols += [
        Column("clean BEV M", effect_column("clean", "{recall}"), "ap", True,
               "BEV AP, moderate, of the clean cell with the same proposals (%)"),
        Column("drop pts", effect_column("drop", "{recall}"), "points", True,
               "clean − attacked BEV AP, moderate (points)"),
        Column("rel. drop %", effect_column("rel_drop", "{recall}"), "percent", True,
               "drop / clean BEV AP, moderate (%)"),
        Column("ASR %", "asr", "percent", False,
               "attack success rate: Cars matched clean and missed attacked (moderate, BEV IoU 0.7) (%)"),
    ]
    if has_ci:
        cols.append(Column("BEV M CI", effect_column("ci_low", "{recall}"), "ci", True,
                           "confidence interval of BEV AP, moderate, as the run recorded it (%)"))
    if has_drop_ci:
        cols.append(Column("drop CI", effect_column("dci_low", "{recall}"), "ci", True,
                           "confidence interval of the BEV moderate drop, as the run recorded it (points)"))
    if has_flags:
        cols.append(Column("flags", "flags", "flags"))
    cols.append(Column("trained against", "trained_against", "str", False,
                       "victim the attack object was optimised against"))
    cols.append(Column("status", "status"))
    return cols


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


def _raw(value: Any) -> str:
    return "" if value is None or (isinstance(value, float) and math.isnan(value)) else repr(float(value))


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


def section_title(view: SectionView, k: int) -> str:
    key = view.section.key
    ds = key["dataset"]
    return (f"Section {k + 1}: split {ds['split']}, {ds['frames']} of {ds['split_frames']} frames, dataset "
            f"sha256 {str(ds['sha256'])[:12]}, robustbench3d {key['versions']['robustbench3d']}, "
            f"seed {key['protocol']['seed']}")


def section_facts(view: SectionView) -> str:
    key = view.section.key
    iou = key["protocol"]["iou"] or {}
    ious = ", ".join(f"{m} {v}" for m, v in (iou.get("Car") or {}).items())
    return (f"Runs: {', '.join(map(str, view.section.runs))}. Car AP in % at IoU {ious}; recall points "
            f"{', '.join(key['protocol']['recall_points'])}; drops and the transfer matrix compare cells "
            "with the same proposal source only.")


def _cell_html(row: Any, col: Column, recall: str = "R40") -> str:
    if col.kind == "flags":
        flags = row["flags"]
        inner = " ".join(f'<span class="flag" title="{html.escape(m)}">{html.escape(c)}</span>' for c, m in flags)
        return f'<td data-v="{html.escape(",".join(c for c, _ in flags))}">{inner}</td>'
    if col.kind == "str":
        text = str(row[col.key])
        title = f' title="{html.escape(row["reason"])}"' if col.key == "status" and row["reason"] else ""
        return f'<td data-v="{html.escape(text)}"{title}>{html.escape(text)}</td>'
    if col.kind == "ci":
        vals = {r: (row[col.field(r)], row[col.field(r).replace("ci_low_", "ci_high_")]) for r in RECALLS}
        texts = {r: ("–" if math.isnan(lo) else f"[{lo:.2f}, {hi:.2f}]") for r, (lo, hi) in vals.items()}
        return (f'<td class="num" data-r40="{_raw(vals["R40"][0])}" data-r11="{_raw(vals["R11"][0])}" '
                f'data-t40="{texts["R40"]}" data-t11="{texts["R11"]}">{texts[recall]}</td>')
    if not col.by_recall:
        v = row[col.key]
        return f'<td class="num" data-v="{_raw(v)}">{fmt(v, col.kind)}</td>'
    v40, v11 = row[col.field("R40")], row[col.field("R11")]
    t40, t11 = fmt(v40, col.kind), fmt(v11, col.kind)
    return (f'<td class="num" data-r40="{_raw(v40)}" data-r11="{_raw(v11)}" data-t40="{t40}" data-t11="{t11}" '
            f'title="R40 {t40} · R11 {t11}">{t40 if recall == "R40" else t11}</td>')


def img_html(fig: Figure) -> str:
    data = base64.b64encode(fig.png).decode("ascii")
    return (f'<figure><img src="data:image/png;base64,{data}" alt="{html.escape(fig.alt)}">'
            f"<figcaption>{html.escape(fig.caption)}</figcaption></figure>")


CSS = """
body{font:14px/1.45 system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:0 auto;max-width:1500px;
 padding:1rem 1.5rem;color:#1d2330;background:#fff}
h1{font-size:1.5rem;margin:.2rem 0}h2{font-size:1.15rem;margin-top:2rem;border-bottom:1px solid #ccd}
h3{font-size:1rem;margin:1.3rem 0 .4rem}
.why{background:#fff4e0;border-left:4px solid #f0a030;padding:.4rem .8rem}
.note{color:#555}
.toolbar{position:sticky;top:0;background:#fff;padding:.4rem 0;z-index:2;border-bottom:1px solid #eee}
.toolbar button{font:inherit;padding:.2rem .7rem;border:1px solid #99a;background:#f4f5f8;cursor:pointer}
.toolbar button.on{background:#2b5797;color:#fff;border-color:#2b5797}
.wrap{overflow-x:auto}
table.lb{border-collapse:collapse;font-size:13px;white-space:nowrap}
table.lb th,table.lb td{padding:.25rem .5rem;border-bottom:1px solid #e3e5ea}
table.lb th{background:#eef0f5;cursor:pointer;user-select:none;position:relative;text-align:left}
table.lb th[aria-sort=ascending]::after{content:" ▲"}table.lb th[aria-sort=descending]::after{content:" ▼"}
table.lb td.num{text-align:right;font-variant-numeric:tabular-nums}
table.lb tbody tr:nth-child(even){background:#fafbfd}table.lb tbody tr:hover{background:#eef4ff}
.flag{display:inline-block;background:#c0392b;color:#fff;border-radius:3px;padding:0 .3rem;font-size:11px}
figure{margin:1rem 0}figure img{max-width:100%;height:auto;border:1px solid #dde}
figcaption{color:#444;font-size:12.5px}
details{margin:.2rem 0}details pre{background:#f6f7f9;padding:.6rem;overflow:auto;max-height:28rem;font-size:12px}
details summary{cursor:pointer}
details,section{scroll-margin-top:3.2rem}details:target>summary{background:#fff4c0}
"""

JS = """
(function(){
  var recall = 'R40';
  function key(td, type){
    if(type === 'num'){
      var raw = td.hasAttribute('data-r40') ? td.getAttribute(recall === 'R40' ? 'data-r40' : 'data-r11')
                                            : td.getAttribute('data-v');
      return raw === '' || raw === null ? null : parseFloat(raw);
    }
    return td.getAttribute('data-v') || '';
  }
  function sortTable(th){
    var table = th.closest('table'), body = table.tBodies[0];
    var col = Array.prototype.indexOf.call(th.parentNode.children, th), type = th.getAttribute('data-type');
    var asc = th.getAttribute('aria-sort') !== 'ascending';
    Array.prototype.forEach.call(th.parentNode.children, function(h){ h.removeAttribute('aria-sort'); });
    th.setAttribute('aria-sort', asc ? 'ascending' : 'descending');
    var rows = Array.prototype.slice.call(body.rows).sort(function(a, b){
      var ka = key(a.cells[col], type), kb = key(b.cells[col], type);
      if(ka === null || kb === null){
        if(ka === null && kb === null){ return a.getAttribute('data-i') - b.getAttribute('data-i'); }
        return ka === null ? 1 : -1;
      }
      var c = type === 'num' ? ka - kb : (ka < kb ? -1 : ka > kb ? 1 : 0);
      if(!asc){ c = -c; }
      return c !== 0 ? c : a.getAttribute('data-i') - b.getAttribute('data-i');
    });
    rows.forEach(function(r){ body.appendChild(r); });
  }
  function setRecall(r){
    recall = r;
    document.querySelectorAll('td[data-t40]').forEach(function(td){
      td.textContent = td.getAttribute(r === 'R40' ? 'data-t40' : 'data-t11');
    });
    document.querySelectorAll('.recall-label').forEach(function(s){ s.textContent = r; });
    document.querySelectorAll('button[data-recall]').forEach(function(b){
      b.classList.toggle('on', b.getAttribute('data-recall') === r);
      b.setAttribute('aria-pressed', b.getAttribute('data-recall') === r ? 'true' : 'false');
    });
    document.querySelectorAll('th[aria-sort]').forEach(function(th){
      th.setAttribute('aria-sort', th.getAttribute('aria-sort') === 'ascending' ? 'descending' : 'ascending');
      sortTable(th);
    });
  }
  document.querySelectorAll('table.lb th').forEach(function(th){
    th.addEventListener('click', function(){ sortTable(th); });
  });
  document.querySelectorAll('button[data-recall]').forEach(function(b){
    b.addEventListener('click', function(){ setRecall(b.getAttribute('data-recall')); });
  });
  document.querySelectorAll('a.prov').forEach(function(a){
    a.addEventListener('click', function(){
      var d = document.getElementById(a.getAttribute('href').slice(1));
      if(d){ d.open = true; }
    });
  });
})();
"""


def _columns(view: SectionView) -> list[Column]:
    df = view.df
    has = {k: any(bool(df[effect_column(k, r)].notna().any()) for r in RECALLS) for k in ("ci_low", "dci_low")}
    return columns(has["ci_low"], any(len(f) for f in df["flags"]), len(view.section.runs) > 1, has["dci_low"])


def cell_json(view: SectionView, i: int) -> str:
    return json.dumps(view.section.cells[i].cell, indent=1, sort_keys=False, ensure_ascii=False)


def html_page(views: Sequence[SectionView], title: str, runs: Sequence[str], notes: Sequence[str],
              extra: Sequence[str] = ()) -> str:
    """The whole self-contained page; ``extra``: further ``<section>`` markup (e.g. speed/accuracy trades)."""
    out = ['<!DOCTYPE html><html lang="en"><head><meta charset="utf-8">',
           '<meta name="viewport" content="width=device-width, initial-scale=1">',
           f"<title>{html.escape(title)}</title><style>{CSS}</style></head><body>",
           f"<h1>{html.escape(title)}</h1>",
           f'<p class="note">From {html.escape(", ".join(runs))}. Click a column header to sort; hover a '
           "number for both recall samplings; “cell.json” opens the cell's provenance.</p>"]
    out += [f'<p class="why">{html.escape(n)}</p>' for n in notes]
    out.append('<div class="toolbar">AP recall sampling: <button data-recall="R40" class="on" aria-pressed="true">'
               'R40</button> <button data-recall="R11" aria-pressed="false">R11</button> '
               '(figures: R40)</div>')
    for k, view in enumerate(views):
        df = view.df
        cols = _columns(view)
        out.append(f'<section id="sec-{k}"><h2>{html.escape(section_title(view, k))}</h2>')
        if view.section.differs:
            out.append('<p class="why">Kept apart from section 1 because these differ (section 1 != this): '
                       + html.escape("; ".join(view.section.differs)) + "</p>")
        out.append(f'<p class="note">{html.escape(section_facts(view))}</p>')
        out.append(f'<h3>Leaderboard (<span class="recall-label">R40</span>)</h3><div class="wrap">'
                   f'<table class="lb" id="lb-{k}"><thead><tr>')
        for c in cols:
            kind = "str" if c.kind in ("str", "flags") else "num"
            tip = f' title="{html.escape(c.tip)}"' if c.tip else ""
            out.append(f'<th data-type="{kind}" data-key="{html.escape(c.key)}"{tip}>{html.escape(c.title)}</th>')
        out.append("<th data-type=\"str\" data-key=\"source\">provenance</th></tr></thead><tbody>")
        for i, row in df.iterrows():
            cells = "".join(_cell_html(row, c) for c in cols)
            src = html.escape(row["source"])
            out.append(f'<tr data-i="{i}" data-cell="{html.escape(row["cell"])}">{cells}'
                       f'<td data-v="{src}"><a class="prov" href="#prov-{k}-{i}" title="{src}">cell.json</a></td></tr>')
        out.append("</tbody></table></div>")
        for fig in view.figures:
            out.append(img_html(fig))
        out.append("<h3>Transfer matrix</h3>")
        out.append(img_html(view.transfer) if view.transfer
                   else f'<p class="note">{html.escape(view.transfer_note)}</p>')
        out.append("<h3>Scenes</h3>")
        out += [img_html(s) for s in view.scenes]
        out += [f'<p class="note">{html.escape(n)}</p>' for n in view.scene_notes]
        out.append("<h3>Provenance of every cell</h3>")
        for i in range(len(view.section.cells)):
            rc = view.section.cells[i]
            out.append(f'<details id="prov-{k}-{i}"><summary>{html.escape(rc.name)} — {html.escape(rc.source)}'
                       f"</summary><pre>{html.escape(cell_json(view, i))}</pre></details>")
        out.append("</section>")
    out += list(extra)
    out.append(f"<script>{JS}</script></body></html>")
    return "\n".join(out)


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


def _md_row(row: Any, cols: Sequence[Column]) -> str:
    """One table row (R40, R11 in parentheses); every string of the summary through :func:`md_text`."""
    texts = []
    for c in cols:
        if c.kind == "flags":
            texts.append(", ".join(f"{md_text(code)}: {md_text(msg)}" for code, msg in row["flags"]))
        elif c.kind == "str":
            texts.append(md_text(row[c.key]))
        elif c.kind == "ci":
            lo, hi = row[c.field("R40")], row[c.field("R40").replace("ci_low_", "ci_high_")]
            texts.append("–" if math.isnan(lo) else f"[{lo:.2f}, {hi:.2f}]")
        elif c.by_recall:
            texts.append(f"{fmt(row[c.field('R40')], c.kind)} ({fmt(row[c.field('R11')], c.kind)})")
        else:
            texts.append(fmt(row[c.key], c.kind))
    return "| " + " | ".join(texts) + f" | {md_code(row['source'])} |"


def _md_figure(fig: Figure, figure_dir: str) -> list[str]:
    return [f"![{md_text(fig.alt)}]({figure_dir}/{fig.name})", "", f"*{md_text(fig.caption)}*", ""]


def markdown(views: Sequence[SectionView], title: str, runs: Sequence[str], notes: Sequence[str],
             figure_dir: str, extra: Sequence[str] = ()) -> str:
    """The leaderboard as markdown: per section the table (R40, R11 in parentheses) and the figures as links;
    ``extra``: further markdown sections appended (already markdown). Every string that comes from a summary,
    a path or the command line is written through :func:`md_text` or :func:`md_code`: inert as markdown and
    as HTML. Figure file names are the report's own (``[A-Za-z0-9._-]``)."""
    lines = [f"# {md_text(title)}", "", f"From {md_text(', '.join(runs))}. AP in % (R40, R11 in parentheses); drops "
             "and the relative drop are BEV moderate against the clean cell with the same proposals; ASR in %.", ""]
    lines += [f"> {md_text(n)}" for n in notes] + ([""] if notes else [])
    for k, view in enumerate(views):
        cols = _columns(view)
        lines += [f"## {md_text(section_title(view, k))}", ""]
        if view.section.differs:
            lines += ["Kept apart from section 1 because these differ: " + md_text("; ".join(view.section.differs)),
                      ""]
        lines += [md_text(section_facts(view)), ""]
        lines.append("| " + " | ".join(md_text(c.title) for c in cols) + " | source |")
        lines.append("|" + "---|" * (len(cols) + 1))
        lines += [_md_row(row, cols) for _, row in view.df.iterrows()]
        lines.append("")
        for fig in [*view.figures, *([view.transfer] if view.transfer else []), *view.scenes]:
            lines += _md_figure(fig, figure_dir)
        if not view.transfer:
            lines += [md_text(view.transfer_note), ""]
        lines += [*map(md_text, view.scene_notes), ""] if view.scene_notes else []
    lines += [e.rstrip() + "\n" for e in extra]
    return "\n".join(lines).rstrip() + "\n"
