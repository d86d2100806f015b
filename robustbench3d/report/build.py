"""The leaderboard a person reads, made in memory (``robustbench3d report RUN_DIR [RUN_DIR ...] --out DIR``).

Writes ``DIR/leaderboard.html`` (one self-contained file: per section the seed paper's Table 1 beside the
measured rows, a sortable table with an R40/R11 toggle that fits a 1280 px wide page, the cells merged or
left out and why, the worst case (victims ranked by their worst attacked AP, :mod:`robustbench3d.report.worst`),
figures, the transfer matrix (every attack object by every victim, a table and a heat-map), scene figures, each
cell's provenance one click away),
``DIR/leaderboard.md``, the
figures as ``DIR/figures/*.png`` and ``DIR/report_manifest.json`` (the files written). Runs on different
datasets, protocols or package versions go to separate sections, each saying what differs; ``--strict``
refuses them instead (exit 2).

``DIR`` must be new, empty or an earlier report's: a report there is replaced (one line says so), any other
non-empty directory is refused unless ``--force`` (:mod:`robustbench3d.report.outdir`). Options, ``DIR`` and
the input files are checked before any work; nothing is written until every figure is made.

Standard library only at module level.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from typing import Any

HTML_FILE = "leaderboard.html"
MD_FILE = "leaderboard.md"
FIGURES = "figures"
#: ``--scenes``: scene figures per section, 0..20. One is drawn per attack (a grid rarely has more than 20
#: attacks), each takes seconds to render and adds about 1 MB to the self-contained HTML page; past 20 the
#: page gets too heavy to open comfortably (``robustbench3d show`` draws any cell and frame instead).
SCENES_RANGE = (0, 20)


def check_scenes(scenes: int) -> None:
    """Refuse a ``--scenes`` outside :data:`SCENES_RANGE` (one line naming the option and the range)."""
    from robustbench3d.errors import RobustBenchError

    low, high = SCENES_RANGE
    if not low <= scenes <= high:
        raise RobustBenchError(f"--scenes must be in {low}..{high} (scene figures per section), got {scenes}")


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text)


def build(runs: list[str], scenes: int = 3, strict: bool = False, log: Any = print) -> tuple[list[Any], list[str]]:
    """The report's section views (tables and figures) and page notes."""
    from robustbench3d.report import data, figures
    from robustbench3d.report.scenes import SceneSource, scene
    from robustbench3d.report.view import NO_ATTACK, Figure, SectionView
    from robustbench3d.results import CellResult

    check_scenes(scenes)
    secs = data.sections(data.read_runs(runs), strict=strict)
    notes = []
    if len(secs) > 1:
        notes.append(f"The runs hold {len(secs)} groups of cells that are not comparable (different dataset, "
                     "protocol or package versions); each is its own section and nothing is compared across them.")
    for merged in (m for sec in secs for m in sec.merged):
        log(f"report: {merged.note()}")
    views = []
    for k, sec in enumerate(secs):
        df = data.table(sec)
        view = SectionView(sec, df)
        ok = df[df["status"] == "ok"]
        for victim in dict.fromkeys(ok["victim"]):
            view.figures.append(Figure(f"s{k + 1}_ap_{_slug(victim)}.png", figures.ap_figure(df, victim),
                                       f"{victim}: Car AP per difficulty per attack (R40), BEV (top) and 3D "
                                       "(bottom), one column per proposal source.", f"AP per attack, {victim}"))
        if ok["drop_R40"].notna().any():
            view.figures.append(Figure(f"s{k + 1}_drop.png", figures.drop_figure(df),
                                       "BEV AP drop at moderate (R40), clean − attacked, per victim and attack, "
                                       "against the clean cell with the same proposals.", "AP drop per victim"))
        if view.grids:
            view.transfer = Figure(f"s{k + 1}_transfer.png", figures.transfer_figure(view.grids),
                                   "Transfer matrix: relative BEV AP drop at moderate (R40, %) of each attack object "
                                   "(rows: the victim it was trained against · the object) on each victim of the "
                                   "section (columns); outlined: white-box (trained against the evaluated victim); "
                                   "not run: no such cell; other text: why the cell has no relative drop.",
                                   "transfer matrix")
        else:
            view.transfer_note = NO_ATTACK
        if not scenes:
            view.scene_notes.append("Scene figures were not asked for (--scenes 0).")
        else:
            attacked = ok[ok["rel_drop_R40"].notna()].sort_values("rel_drop_R40", ascending=False, kind="stable")
            picked = attacked.drop_duplicates("attack").head(scenes)
            if len(picked):
                source = SceneSource(CellResult(sec.cells[int(picked.index[0])].cell).dataset)
                for i in picked.index:
                    log(f"report: scene figure of {sec.cells[int(i)].name}")
                    sc = scene(source, sec.cells[int(i)])
                    if sc.png is None:
                        view.scene_notes.append(sc.caption)
                    else:
                        name = f"s{k + 1}_scene_{_slug(sc.cell.name)}_{_slug(str(sc.frame))}.png"
                        view.scenes.append(Figure(name, sc.png, sc.caption, f"scene {sc.cell.name} frame {sc.frame}"))
            else:
                view.scene_notes.append("No attacked cell with a clean comparison: no scene figure.")
        views.append(view)
    return views, notes


def contents(views: list[Any], trades: list[Any], runs: list[str], title: str, notes: list[str],
             sweeps: Sequence[Any] = ()) -> dict[str, bytes]:
    """Every file of the report (relative path -> bytes), made in memory before anything is written; ``sweeps``:
    dose–response sweeps (:class:`~robustbench3d.report.sweep_view.SweepView`)."""
    from robustbench3d.report.mdpage import markdown
    from robustbench3d.report.page import html_page, image
    from robustbench3d.report.sweep_view import sweep_markdown, sweep_model
    from robustbench3d.report.tradeoff_view import tradeoff_markdown, tradeoff_model
    from robustbench3d.report.view import Figure

    out: dict[str, bytes] = {}
    for view in views:
        for fig in [*view.figures, *([view.transfer] if view.transfer else []), *view.scenes]:
            out[f"{FIGURES}/{fig.name}"] = fig.png
    html_trades, md_extra = [], []
    for k, trade in enumerate(trades):
        out[f"{FIGURES}/{trade.figure_name}"] = trade.png
        fig = Figure(trade.figure_name, trade.png, "Wall time of the clean + attacked cell relative to the "
                     "default setting's on the same frames against |ΔAP| from each sweep's reference (left, Pareto "
                     "front dashed); frames evaluated against the interval width (right).", trade.title)
        html_trades.append(tradeoff_model(trade, k, image(fig)))
        md_extra.append(tradeoff_markdown(trade, FIGURES))
    html_sweeps = []
    for k, sweep in enumerate(sweeps):
        out[f"{FIGURES}/{sweep.figure_name}"] = sweep.png
        fig = Figure(sweep.figure_name, sweep.png, "Relative moderate BEV drop and attack success rate against the "
                     "object's radius (one line per icosphere level) and against its colour freedom (vertex colours "
                     "at the seed's radius), 95 % bootstrap interval bars; ringed: the seed's object (level 2, r 0.40 "
                     "m); dashed grey: the benign grey sphere of each radius.", sweep.title)
        html_sweeps.append(sweep_model(sweep, k, image(fig)))
        md_extra.append(sweep_markdown(sweep, FIGURES))
    out[MD_FILE] = markdown(views, title, runs, notes, FIGURES, md_extra).encode("utf-8")
    out[HTML_FILE] = html_page(views, title, runs, notes, html_trades, html_sweeps).encode("utf-8")
    return out
