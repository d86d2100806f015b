"""The speed/accuracy trade in the leaderboard: a ``robustbench3d tradeoff`` run's Pareto table and figure.

HTML (:func:`tradeoff_model`, shown by the page's template): a sortable table (the leaderboard's script sorts
any ``table.lb`` on ``data-v``), the figure inline, the run's machine and provenance one click away.
Markdown: the run's own ``tradeoff.md`` tables under a section heading, the figure as a file beside the page.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from robustbench3d.tradeoff.output import figure, markdown, read_doc

#: (title, key, kind) of the HTML table's columns; kind "num" sorts numerically.
COLUMNS = (("sweep", "sweep", "str"), ("value", "value", "str"), ("frames", "frames", "num"),
           ("wall s", "wall_s", "num"), ("× default", "time_vs_default", "num"),
           ("CPU s", "cpu_s", "num"), ("clean AP", "ap_clean", "num"),
           ("attacked AP", "ap_attacked", "num"), ("drop", "drop", "num"), ("ΔAP attacked", "d_attacked", "num"),
           ("|ΔAP|", "error", "num"), ("CI width", "ci_width", "num"), ("Pareto", "pareto_sweep", "str"))


@dataclass
class TradeoffView:
    """One tradeoff run as the report shows it."""

    source: str
    doc: dict[str, Any]
    png: bytes

    @classmethod
    def read(cls, path: str | Path) -> TradeoffView:
        doc = read_doc(Path(path))
        return cls(str(path), doc, figure(doc))

    @property
    def title(self) -> str:
        c = self.doc["config"]
        return f"Speed/accuracy trade: {c['victim']} / {c['attack']} ({self.doc['dataset']['frames']} frames)"

    @property
    def figure_name(self) -> str:
        return "tradeoff_" + "".join(ch if ch.isalnum() else "_" for ch in Path(self.source).name) + ".png"


def _td(row: dict[str, Any], key: str, kind: str) -> dict[str, str]:
    """One cell of the table: its sort key (``data-v``), whether it is a number, and its text."""
    v = row.get(key)
    if key == "pareto_sweep":
        text = "★" if v else ""
        return {"v": text, "num": False, "text": text}
    if key == "value":
        return {"v": str(v), "num": False, "text": f"{v} (ref)" if row["reference"] else str(v)}
    if kind == "num":
        if not isinstance(v, int | float) or isinstance(v, bool):  # None, or not a number: shown, never parsed
            return {"v": "", "num": True, "text": "–" if v is None else str(v)}
        text = f"{v:+.2f}" if key == "d_attacked" else (str(v) if key == "frames" else f"{v:.2f}")
        return {"v": repr(float(v)), "num": True, "text": text}
    return {"v": str(v), "num": False, "text": str(v)}


def tradeoff_model(view: TradeoffView, k: int, fig: dict[str, str]) -> dict[str, Any]:
    """What the page's template shows of one tradeoff run (``fig``: the figure as
    :func:`robustbench3d.report.page.image` gives it); plain values, escaped by the template."""
    doc = view.doc
    m = doc["machine"]
    c, metric, r, d = doc["ap"]
    prov = {k2: doc[k2] for k2 in ("config", "dataset", "machine", "provenance", "sweeps") if k2 in doc}
    return {
        "k": k, "title": view.title, "source": view.source, "cpu": str(m.get("cpu")),
        "cpu_count": str(m.get("cpu_count")), "measured_at": str(doc["measured_at"]),
        "ap": f"{c} {metric.upper()} {r} {d}", "figure": fig,
        "columns": [{"title": title, "key": key, "type": kind} for title, key, kind in COLUMNS],
        "rows": [[_td(row, key, kind) for _, key, kind in COLUMNS] for row in doc["points"]],
        "provenance": json.dumps(prov, indent=1, ensure_ascii=False),
    }


def _inert(tree: Any) -> Any:
    """A copy of a tradeoff document with every string (keys too) through :func:`~robustbench3d.report.mdpage.md_text`:
    what ``tradeoff.md`` writes from it is inert as markdown and HTML (names a run writes have no markup
    character and come out unchanged)."""
    from robustbench3d.report.mdpage import md_text

    if isinstance(tree, str):
        return md_text(tree)
    if isinstance(tree, dict):
        return {_inert(k): _inert(v) for k, v in tree.items()}
    if isinstance(tree, list | tuple):
        return [_inert(v) for v in tree]
    return tree


def tradeoff_markdown(view: TradeoffView, figure_dir: str) -> str:
    """The run's ``tradeoff.md`` (headings one level down; every string of the run escaped) and its figure."""
    from robustbench3d.report.mdpage import md_text

    body = markdown(_inert(view.doc)).split("\n", 1)[1]  # drop the run's own title
    body = "\n".join("#" + line if line.startswith("## ") else line for line in body.split("\n"))
    title = md_text(view.title)
    return (f"## {title}\n\nFrom {md_text(view.source)}.\n\n![{title}]({figure_dir}/{view.figure_name})\n"
            + body.rstrip() + "\n")
