"""The sweep's files: ``sweep.json`` (everything, provenance included), ``sweep.csv`` (one row per victim x
proposals x attack), ``sweep.md`` (the table, the training cost per point, the "smallest object" sentences) and
``sweep.png`` (matplotlib: relative moderate BEV drop and ASR against radius, one line per level, and against
colour freedom at the seed's radius; 95 % bootstrap interval bars; the seed's point ringed; benign spheres dashed
grey; one row of panels per proposal source)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from robustbench3d.studies import figure_png, read_study, write_study

JSON_FILE, CSV_FILE, MD_FILE, PNG_FILE = "sweep.json", "sweep.csv", "sweep.md", "sweep.png"
#: CSV columns, in order (intervals flattened to _lo/_hi).
CSV_COLUMNS = ("victim", "proposals", "attack", "kind", "name", "level", "radius", "vertex_colours", "seed_point",
               "status", "clean_ap", "attacked_ap", "drop", "drop_lo", "drop_hi", "relative_drop",
               "relative_drop_lo", "relative_drop_hi", "asr", "asr_lo", "asr_hi", "seconds", "cpu_seconds")
#: The keys of ``sweep.json`` that describe this invocation's machine and time, not its results.
RUNTIME_KEYS = ("provenance",)


def _lohi(ci: Any) -> tuple[Any, Any]:
    return (ci[0], ci[1]) if ci else (None, None)


def csv_rows(doc: Mapping[str, Any]) -> list[dict[str, Any]]:
    rows = []
    for r in doc["scores"]:
        row = {k: r.get(k) for k in CSV_COLUMNS}
        for name in ("drop", "relative_drop", "asr"):
            row[f"{name}_lo"], row[f"{name}_hi"] = _lohi(r.get(f"{name}_ci"))
        rows.append(row)
    return rows


def _f(x: Any, pct: bool = False) -> str:
    if x is None:
        return "–"
    return f"{100 * x:.1f}" if pct else f"{x:.2f}"


def _ci(ci: Any, pct: bool = False) -> str:
    if not ci:
        return ""
    return f" [{_f(ci[0], pct)}, {_f(ci[1], pct)}]"


def markdown(doc: Mapping[str, Any]) -> str:
    """``sweep.md`` from the sweep document."""
    cfg, ds = doc["config"], doc["dataset"]
    lines = [f"# Dose–response sweep: {cfg['mode']} against {cfg['victim']}", "",
             f"{len(doc['points'])} objects (icosphere level × radius; ★ the seed's object, level 2, r 0.40 m), each "
             f"trained by `attack train` on {doc['training_data'].get('frames', '?')} frames of "
             f"`{cfg['train_split']}` and scored with the clean control and the benign sphere of each radius on "
             f"{ds['frames']} frames of `{ds['split']}` (labels sha256 {ds['sha256'][:12]}), seed {cfg['seed']}, "
             f"in one benchmark run (`run/`). Relative drop: of moderate BEV AP (R40), with its 95 % paired bootstrap "
             "interval; ASR: attack success rate (moderate, BEV IoU 0.7) with its interval.", "",
             *[f"- {s}" for s in doc["sentences"].values()], "",
             "| victim | proposals | object | level | radius m | vertex colours | clean AP | attacked AP | "
             "rel. drop % [CI] | ASR % [CI] | drop pts [CI] |",
             "|---|---|---|---:|---:|---:|---:|---:|---|---|---|"]
    for r in doc["scores"]:
        star = " ★" if r.get("seed_point") else ""
        lines.append(f"| {r['victim']} | {r['proposals']} | {r['name']}{star} | {r['level'] or '–'} | "
                     f"{r['radius']:.2f} | {r['vertex_colours'] or '–'} | {_f(r['clean_ap'])} | "
                     f"{_f(r['attacked_ap'])} | {_f(r['relative_drop'], True)}{_ci(r['relative_drop_ci'], True)} | "
                     f"{_f(r['asr'], True)}{_ci(r['asr_ci'], True)} | {_f(r['drop'])}{_ci(r['drop_ci'])} |")
    host = doc["provenance"]["host"]["platform"]
    lines += ["", "## Cost per point", "",
              "Training: `attack train`'s held-out curve and plateau stop decide when each object stopped; wall and "
              f"CPU seconds of every training session on this machine ({host.get('cpu')}, "
              f"{host.get('cpu_count')} cores; a point trains in one process). "
              "Scoring: the object's cells of the run.", "",
              "| object | steps | object of step | stopped | training wall s | training CPU s | scoring wall s |",
              "|---|---:|---:|---|---:|---:|---:|"]
    for p in doc["points"]:
        t, c = p["training"], p["cost"]
        lines.append(f"| {p['name']}{' ★' if p['seed_point'] else ''} | {t.get('steps', '–')} | "
                     f"{t.get('object_step', '–')} | {t.get('stopped') or '–'} | {_f(c.get('train_wall_s'))} | "
                     f"{_f(c.get('train_cpu_s'))} | {_f(c.get('score_wall_s'))} |")
    lines.append("")
    return "\n".join(lines)


def _errbars(ax: Any, xs: list[float], rows: list[dict[str, Any]], key: str, **style: Any) -> None:
    import numpy as np

    ys = np.array([np.nan if r[key] is None else 100 * r[key] for r in rows], dtype=float)
    lo = np.array([np.nan if not r[f"{key}_ci"] else 100 * r[f"{key}_ci"][0] for r in rows], dtype=float)
    hi = np.array([np.nan if not r[f"{key}_ci"] else 100 * r[f"{key}_ci"][1] for r in rows], dtype=float)
    err = np.vstack([np.nan_to_num(ys - lo), np.nan_to_num(hi - ys)])
    ax.errorbar(xs, ys, yerr=np.clip(err, 0, None), capsize=3, **style)


def figure(doc: Mapping[str, Any]) -> bytes:
    """``sweep.png`` (module doc)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = doc["scores"]
    groups = list(dict.fromkeys((r["victim"], r["proposals"]) for r in rows)) or [("?", "?")]
    metrics = (("relative_drop", "relative moderate BEV drop (%)"), ("asr", "attack success rate (%)"))
    fig, axes = plt.subplots(len(groups), 4, figsize=(16, 3.8 * len(groups)), squeeze=False)
    seed_r = doc["seed_point"]["radius"]
    for g, (victim, proposals) in enumerate(groups):
        mine = [r for r in rows if r["victim"] == victim and r["proposals"] == proposals]
        objs = [r for r in mine if r["kind"] == "object"]
        benign = sorted((r for r in mine if r["kind"] == "benign"), key=lambda r: r["radius"])
        for m, (key, label) in enumerate(metrics):
            ax, bx = axes[g][2 * m], axes[g][2 * m + 1]
            for level in sorted({r["level"] for r in objs}):
                line = sorted((r for r in objs if r["level"] == level), key=lambda r: r["radius"])
                _errbars(ax, [r["radius"] for r in line], line, key, marker="o", lw=1.5,
                         label=f"level {level} ({line[0]['vertex_colours']} colours)")
            if benign:
                _errbars(ax, [r["radius"] for r in benign], benign, key, marker="s", ls="--", color="0.5",
                         label="benign grey sphere")
            at = sorted((r for r in objs if r["radius"] == seed_r), key=lambda r: r["vertex_colours"])
            if at:
                _errbars(bx, [r["vertex_colours"] for r in at], at, key, marker="o", lw=1.5, color="C3",
                         label=f"objects, r {seed_r:.2f} m")
                bx.set_xscale("log")
                bx.minorticks_off()
                bx.set_xticks([r["vertex_colours"] for r in at], [str(r["vertex_colours"]) for r in at])
            base = [r for r in benign if r["radius"] == seed_r]
            if base and base[0][key] is not None:
                bx.axhline(100 * base[0][key], color="0.5", ls="--", label="benign grey sphere")
            for axis, x in ((ax, "radius"), (bx, "vertex_colours")):
                for r in objs:
                    if r["seed_point"] and r[key] is not None:
                        axis.plot([r[x]], [100 * r[key]], marker="o", ms=14, mfc="none", mec="k", mew=1.5,
                                  ls="none", label="the seed's object (l2, r 0.40)")
                axis.axhline(0, color="0.8", lw=0.8)
                axis.grid(alpha=0.3)
                axis.set_ylabel(label)
                axis.legend(fontsize=7)
            ax.set_xlabel("radius (m)")
            bx.set_xlabel(f"vertex colours (level 2/3/4), radius {seed_r:.2f} m")
            ax.set_title(f"{victim}, {proposals}: vs radius", fontsize=9)
            bx.set_title(f"{victim}, {proposals}: vs colour freedom", fontsize=9)
    fig.suptitle(f"{doc['config']['mode']} dose–response, {doc['dataset']['frames']} frames of "
                 f"{doc['dataset']['split']} (95 % bootstrap intervals)")
    fig.tight_layout()
    return figure_png(fig, dpi=100)


def write_all(out: Path, doc: Mapping[str, Any]) -> list[Path]:
    """Write the four files atomically; their paths."""
    import pandas as pd

    frame = pd.DataFrame(csv_rows(doc), columns=list(CSV_COLUMNS))
    return write_study([out / JSON_FILE, out / CSV_FILE, out / MD_FILE, out / PNG_FILE], doc,
                       frame.to_csv(index=False, lineterminator="\n"), markdown(doc), figure(doc))


def read_doc(path: Path) -> dict[str, Any]:
    """A ``sweep.json`` (a directory holding one, or the file)."""
    return read_study(path, JSON_FILE, "sweep", "sweep",
                      ("format", "config", "points", "scores", "dataset", "seed_point", "sentences", "provenance"))


__all__ = ["CSV_COLUMNS", "CSV_FILE", "JSON_FILE", "MD_FILE", "PNG_FILE", "RUNTIME_KEYS", "csv_rows", "figure",
           "markdown", "read_doc", "write_all"]
