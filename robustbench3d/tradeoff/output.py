"""The tradeoff run's files: ``tradeoff.json`` (everything, provenance included), ``tradeoff.csv`` (one
row per point, pandas), ``tradeoff.md`` (a table per sweep, the settings within tolerance) and
``tradeoff.png`` (matplotlib: wall time against |ΔAP| with the Pareto front; wall time against the
interval width for the frames sweep)."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from robustbench3d.studies import figure_png, read_study, write_study
from robustbench3d.victims.spec import PROTOCOL_LABELS

JSON_FILE = "tradeoff.json"
CSV_FILE = "tradeoff.csv"
MD_FILE = "tradeoff.md"
PNG_FILE = "tradeoff.png"
#: CSV columns, in order (``setting`` is flattened to JSON text).
CSV_COLUMNS = ("sweep", "knob", "value", "reference", "default", "frames", "wall_s", "cpu_s", "wall_s_per_frame",
               "time_vs_default",
               "ap_clean", "ap_clean_lo", "ap_clean_hi", "ap_attacked", "ap_attacked_lo", "ap_attacked_hi",
               "drop", "drop_lo", "drop_hi", "d_clean", "d_clean_lo", "d_clean_hi", "d_attacked", "d_attacked_lo",
               "d_attacked_hi", "d_drop", "error", "ci_width", "pareto_sweep", "pareto_all", "setting")


def _f(x: float | None, digits: int = 2) -> str:
    return "–" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{digits}f}"


def _ci(lo: float | None, hi: float | None) -> str:
    return "" if lo is None else f" [{lo:.1f}, {hi:.1f}]"


def within_tolerance(rows: Sequence[dict[str, Any]], tolerance: float) -> list[dict[str, Any]]:
    """Per sweep, the fastest point whose error is at most ``tolerance`` AP points."""
    out = []
    for sweep in dict.fromkeys(r["sweep"] for r in rows):
        ok = [r for r in rows if r["sweep"] == sweep and r["error"] <= tolerance]
        if ok:
            out.append(min(ok, key=lambda r: r["wall_s"]))
    return out


def markdown(doc: dict[str, Any]) -> str:
    """``tradeoff.md`` from the run document (:data:`JSON_FILE`'s content)."""
    rows, cfg = doc["points"], doc["config"]
    c, m, r, d = doc["ap"]
    default = next((x for x in rows if x["sweep"] != "frames" and x["default"]), None)
    lines = [
        "# Speed/accuracy trade", "",
        f"Victim `{cfg['victim']}`, attack `{cfg['attack']}`, proposals `{cfg['proposals']}` "
        f"({PROTOCOL_LABELS.get(cfg['proposals'], 'unknown source')}), "
        f"{doc['dataset']['frames']} frames of `{doc['dataset']['split']}` (labels sha256 "
        f"{doc['dataset']['sha256'][:12]}), seed {cfg['seed']}, {cfg['threads']} torch thread(s), "
        f"{cfg['resamples']} bootstrap resamples.",
        f"Machine: {doc['machine']['cpu']} ({doc['machine']['cpu_count']} cores), measured "
        f"{doc['measured_at']}; every point in this one run.", "",
        f"AP: {c} {m.upper()} {r} {d} (%). ΔAP: the point minus its sweep's reference (ref), with the paired "
        "95 % bootstrap interval (same resampled frames); |ΔAP| = max over the clean and the attacked cell. "
        "Time: wall seconds of the clean and the attacked cell together on the point's frames; × default: over "
        "the default setting's on the same frames (frames sweep: over all frames)"
        + (f" (default setting: {default['wall_s']:.1f} s, {default['wall_s_per_frame']:.2f} s per frame)"
           if default else "") + ". ★: on the sweep's Pareto front (time, |ΔAP|).", "",
    ]
    for sweep in dict.fromkeys(x["sweep"] for x in rows):
        group = [x for x in rows if x["sweep"] == sweep]
        note = doc["sweeps"].get(sweep, "")
        lines += [f"## {group[0]['knob']} (`{sweep}`)", "", *([note, ""] if note else []),
                  "| value | frames | wall s | × default | CPU s | clean AP [CI] | attacked AP [CI] | drop [CI] | "
                  "ΔAP attacked [paired CI] | |ΔAP| | CI width | |",
                  "|---|---:|---:|---:|---:|---|---|---|---|---:|---:|---|"]
        for x in group:
            tag = " (ref)" if x["reference"] else ""
            lines.append(
                f"| {x['value']}{tag} | {x['frames']} | {x['wall_s']:.1f} | {_f(x['time_vs_default'])} | "
                f"{x['cpu_s']:.1f} | "
                f"{_f(x['ap_clean'])}{_ci(x['ap_clean_lo'], x['ap_clean_hi'])} | "
                f"{_f(x['ap_attacked'])}{_ci(x['ap_attacked_lo'], x['ap_attacked_hi'])} | "
                f"{_f(x['drop'])}{_ci(x['drop_lo'], x['drop_hi'])} | "
                f"{x['d_attacked']:+.2f}{_ci(x['d_attacked_lo'], x['d_attacked_hi'])} | {_f(x['error'])} | "
                f"{_f(x['ci_width'], 1)} | {'★' if x['pareto_sweep'] else ''} |")
        lines.append("")
    tol = cfg["tolerance"]
    best = within_tolerance(rows, tol)
    lines += [f"## Fastest point of each sweep within {tol:g} AP point(s) of its reference", "",
              "| sweep | value | frames | wall s | × default time (same frames) | |ΔAP| |",
              "|---|---|---:|---:|---:|---:|"]
    for x in best:
        lines.append(f"| {x['sweep']} | {x['value']} | {x['frames']} | {x['wall_s']:.1f} | "
                     f"{_f(x['time_vs_default'])} | {_f(x['error'])} |")
    lines.append("")
    return "\n".join(lines)


def figure(doc: dict[str, Any]) -> bytes:
    """``tradeoff.png``: (left) wall time relative to the default setting (same frames) against |ΔAP| of every
    knob point, the Pareto front across sweeps drawn;
    (right) the frames sweep's wall time against the attacked AP's interval width and its |ΔAP|."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = doc["points"]
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(12, 4.8))
    knobs = [x for x in rows if x["sweep"] != "frames"]
    markers = "osD^v<>Ph*"
    for i, sweep in enumerate(dict.fromkeys(x["sweep"] for x in knobs)):
        g = [x for x in knobs if x["sweep"] == sweep]
        ax.scatter([x["time_vs_default"] for x in g], [x["error"] for x in g], marker=markers[i % len(markers)],
                   s=42, label=sweep, zorder=3)
        for x in g:
            ax.annotate(x["value"].split(" ")[0], (x["time_vs_default"], x["error"]), fontsize=7, xytext=(3, 3),
                        textcoords="offset points")
    front = sorted((x["time_vs_default"], x["error"]) for x in knobs if x["pareto_all"])
    if front:
        ax.step([p[0] for p in front], [p[1] for p in front], where="post", color="0.4", lw=1, ls="--",
                label="Pareto front", zorder=2)
    ax.set_xscale("log")
    ax.set_xlabel("wall time of clean + attacked cell / the default setting's, same frames (log)")
    ax.set_ylabel("|ΔAP| vs the sweep's reference (points)")
    ax.set_title(f"{doc['config']['victim']} / {doc['config']['attack']}, {doc['dataset']['frames']} frames")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fr = [x for x in rows if x["sweep"] == "frames"]
    if fr:
        bx.plot([x["wall_s"] for x in fr], [x["ci_width"] for x in fr], "o-", label="95 % CI width, attacked AP")
        bx.plot([x["wall_s"] for x in fr], [x["error"] for x in fr], "s--", label="|ΔAP| vs all frames")
        for x in fr:
            bx.annotate(f"N={x['frames']}", (x["wall_s"], x["ci_width"]), fontsize=7, xytext=(3, 3),
                        textcoords="offset points")
        bx.set_xscale("log")
        bx.set_xlabel("wall time (s, log)")
        bx.set_ylabel("AP points")
        bx.set_title("frames evaluated")
        bx.grid(alpha=0.3)
        bx.legend(fontsize=8)
    else:
        bx.set_axis_off()
    fig.tight_layout()
    return figure_png(fig, dpi=110)


def write_all(out: Path, doc: dict[str, Any]) -> list[Path]:
    """Write the four files (each atomically); returns their paths."""
    import pandas as pd

    frame = pd.DataFrame([{k: (json.dumps(x[k], sort_keys=True) if k == "setting" else x.get(k))
                           for k in CSV_COLUMNS} for x in doc["points"]], columns=list(CSV_COLUMNS))
    return write_study([out / JSON_FILE, out / CSV_FILE, out / MD_FILE, out / PNG_FILE], doc,
                       frame.to_csv(index=False, lineterminator="\n"), markdown(doc), figure(doc))


def read_doc(path: Path) -> dict[str, Any]:
    """A ``tradeoff.json`` (a directory holding one, or the file)."""
    return read_study(path, JSON_FILE, "tradeoff", "tradeoff",
                      ("points", "config", "dataset", "machine", "ap", "sweeps", "measured_at"))
