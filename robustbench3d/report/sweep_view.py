"""The dose–response sweep in the leaderboard: a ``robustbench3d sweep`` directory's figure and table.

HTML (:func:`sweep_model`, shown by the page's template): the figure inline, the "smallest object" sentences, a
sortable table (the leaderboard's script sorts any ``table.lb`` on ``data-v``), the sweep's provenance one click
away. Markdown: the sweep's own ``sweep.md`` under a section heading (every string escaped), the figure beside it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from robustbench3d.sweep.output import figure, markdown, read_doc

#: (title, key, kind) of the HTML table's columns; kind "num" sorts numerically, "pct" is a fraction shown in %.
COLUMNS = (("victim", "victim", "str"), ("proposals", "proposals", "str"), ("object", "name", "str"),
           ("level", "level", "num"), ("radius m", "radius", "num"), ("vertex colours", "vertex_colours", "num"),
           ("clean AP", "clean_ap", "num"), ("attacked AP", "attacked_ap", "num"),
           ("rel. drop %", "relative_drop", "pct"), ("rel. drop CI", "relative_drop_ci", "ci"),
           ("ASR %", "asr", "pct"), ("ASR CI", "asr_ci", "ci"))


@dataclass
class SweepView:
    """One sweep as the report shows it."""

    source: str
    doc: dict[str, Any]
    png: bytes

    @classmethod
    def read(cls, path: str | Path) -> SweepView:
        doc = read_doc(Path(path))
        return cls(str(path), doc, figure(doc))

    @property
    def title(self) -> str:
        c = self.doc["config"]
        return f"Dose–response sweep: {c['mode']} against {c['victim']} ({self.doc['dataset']['frames']} frames)"

    @property
    def figure_name(self) -> str:
        return "sweep_" + "".join(ch if ch.isalnum() else "_" for ch in Path(self.source).resolve().name) + ".png"


def _td(row: dict[str, Any], key: str, kind: str) -> dict[str, Any]:
    v = row.get(key)
    if kind == "ci":
        text = "–" if not v else f"{100 * v[0]:.1f}–{100 * v[1]:.1f}"
        return {"v": text, "num": False, "text": text}
    if kind in ("num", "pct"):
        if not isinstance(v, int | float) or isinstance(v, bool):
            return {"v": "", "num": True, "text": "–"}
        text = f"{100 * v:.1f}" if kind == "pct" else (str(v) if isinstance(v, int) else f"{v:.2f}")
        return {"v": repr(float(v)), "num": True, "text": text}
    text = f"{v} ★" if key == "name" and row.get("seed_point") else str(v)
    return {"v": str(v), "num": False, "text": text}


def sweep_model(view: SweepView, k: int, fig: dict[str, str]) -> dict[str, Any]:
    """What the page's template shows of one sweep (``fig``: :func:`robustbench3d.report.page.image` of its
    figure); plain values, escaped by the template."""
    doc = view.doc
    prov = {k2: doc[k2] for k2 in ("config", "dataset", "training_data", "victim", "points", "provenance")
            if k2 in doc}
    return {
        "k": k, "title": view.title, "source": view.source, "figure": fig,
        "sentences": list(doc["sentences"].values()),
        "frames": doc["dataset"]["frames"], "split": doc["dataset"]["split"],
        "columns": [{"title": title, "key": key, "type": "num" if kind in ("num", "pct") else "str"}
                    for title, key, kind in COLUMNS],
        "rows": [[_td(row, key, kind) for _, key, kind in COLUMNS] for row in doc["scores"]],
        "costs": [{"name": p["name"], "steps": p["training"].get("steps"),
                   "stopped": p["training"].get("stopped") or "–",
                   "wall": "–" if p["cost"].get("train_wall_s") is None else f"{p['cost']['train_wall_s']:.0f}"}
                  for p in doc["points"]],
        "provenance": json.dumps(prov, indent=1, ensure_ascii=False),
    }


def sweep_markdown(view: SweepView, figure_dir: str) -> str:
    """The sweep's ``sweep.md`` (headings one level down; every string escaped) and its figure."""
    from robustbench3d.report.mdpage import md_text
    from robustbench3d.report.tradeoff_view import _inert

    body = markdown(_inert(view.doc)).split("\n", 1)[1]
    body = "\n".join("#" + line if line.startswith("## ") else line for line in body.split("\n"))
    title = md_text(view.title)
    return (f"## {title}\n\nFrom {md_text(view.source)}.\n\n![{title}]({figure_dir}/{view.figure_name})\n"
            + body.rstrip() + "\n")
