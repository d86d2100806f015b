"""The report's figures (matplotlib, Agg backend), each returned as PNG bytes.

* :func:`ap_figure`: per victim, Car AP per difficulty per attack (BEV and 3D, one panel per proposal source);
* :func:`drop_figure`: the BEV moderate AP drop per victim and attack (percentage points);
* :func:`transfer_figure`: the transfer heat-map (rows: every attack object, with the victim it was trained
  against; columns: every victim; value: relative BEV moderate drop in percent, or why there is none).

matplotlib is imported inside the functions.
"""

from __future__ import annotations

import io
from collections.abc import Sequence
from typing import Any

from robustbench3d.report.data import DIFFICULTIES, ap_column, effect_column

#: A colour per difficulty (easy, moderate, hard).
DIFF_COLOURS = dict(zip(DIFFICULTIES, ("#4c78a8", "#f58518", "#54a24b"), strict=True))


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def png_bytes(fig: Any, dpi: int = 100) -> bytes:
    """The figure as PNG (metadata without a creation date, so equal figures give equal bytes); closes it."""
    plt = _pyplot()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight", metadata={"Software": None})
    plt.close(fig)
    return buf.getvalue()


def ap_figure(df: Any, victim: str, recall: str = "R40") -> bytes:
    """Grouped bars: x = attacks (table order), bars = easy/moderate/hard AP; rows BEV and 3D, columns the
    proposal sources of ``victim``'s ``ok`` cells."""
    plt = _pyplot()
    sub = df[(df["victim"] == victim) & (df["status"] == "ok")]
    sources = list(dict.fromkeys(sub["proposals"]))
    fig, axes = plt.subplots(2, len(sources), figsize=(max(5.0, 0.9 * sub["attack"].nunique() + 2) * len(sources),
                                                       6.4), squeeze=False)
    for j, prop in enumerate(sources):
        cells = sub[sub["proposals"] == prop]
        attacks = list(cells["attack"])
        for i, metric in enumerate(("bev", "3d")):
            ax = axes[i][j]
            width = 0.27
            for k, d in enumerate(DIFFICULTIES):
                xs = [a + (k - 1) * width for a in range(len(attacks))]
                ax.bar(xs, cells[ap_column(metric, recall, d)], width, label=d if i == j == 0 else None,
                       color=DIFF_COLOURS[d])
            ax.set_xticks(range(len(attacks)), attacks, rotation=25, ha="right", fontsize=8)
            ax.set_ylim(0, 100)
            ax.set_ylabel(f"Car {metric.upper()} AP {recall} (%)")
            ax.set_title(f"{victim} · proposals {prop} · {metric.upper()}", fontsize=9)
            ax.grid(axis="y", alpha=0.3)
    fig.legend(fontsize=8, ncols=3, loc="upper center", bbox_to_anchor=(0.5, 1.03), frameon=False)
    fig.tight_layout()
    return png_bytes(fig)


def drop_figure(df: Any, recall: str = "R40") -> bytes:
    """Bars of the BEV moderate AP drop (clean - attacked, points) per victim, one bar per attack; one panel per
    proposal source. Negative bars: the attack raised AP."""
    plt = _pyplot()
    sub = df[(df["status"] == "ok") & df[effect_column("drop", recall)].notna()]
    sources = list(dict.fromkeys(sub["proposals"]))
    victims = list(dict.fromkeys(sub["victim"]))
    attacks = list(dict.fromkeys(sub["attack"]))
    cmap = plt.get_cmap("tab10")
    fig, axes = plt.subplots(1, len(sources), figsize=(max(4.5, 1.2 * len(victims) * len(attacks) / 2 + 2)
                                                       * len(sources), 3.8), squeeze=False)
    width = 0.8 / max(1, len(attacks))
    for j, prop in enumerate(sources):
        ax = axes[0][j]
        cells = sub[sub["proposals"] == prop]
        victims = list(dict.fromkeys(cells["victim"]))
        for k, attack in enumerate(attacks):
            xs, ys = [], []
            for v, victim in enumerate(victims):
                hit = cells[(cells["victim"] == victim) & (cells["attack"] == attack)]
                if len(hit):
                    xs.append(v + (k - (len(attacks) - 1) / 2) * width)
                    ys.append(float(hit[effect_column("drop", recall)].iloc[0]))
            bars = ax.bar(xs, ys, width, label=attack if xs else None, color=cmap(k % 10))
            ax.bar_label(bars, fmt="%.2f", fontsize=7, padding=1)
        ax.axhline(0, color="black", lw=0.8)
        ax.set_xticks(range(len(victims)), victims, fontsize=8)
        ax.set_ylabel(f"BEV AP drop, moderate, {recall} (points)")
        ax.set_title(f"AP drop (clean − attacked) · proposals {prop}", fontsize=9)
        ax.grid(axis="y", alpha=0.3)
        ax.legend(fontsize=7, ncols=2, loc="upper left", bbox_to_anchor=(1.0, 1.0), frameon=False)
        ax.margins(y=0.15)
    fig.tight_layout()
    return png_bytes(fig)


def transfer_figure(grids: Sequence[Any], recall: str = "R40") -> bytes:
    """One heat-map per proposal source (``grids``: :class:`~robustbench3d.report.data.TransferGrid`, each every
    attack object by every victim), values in percent, diverging around 0; white-box entries (trained against =
    evaluated) outlined; an entry without a number shows why (``not run``, ``clean AP 0``, the cell's status)."""
    import numpy as np
    from matplotlib.colors import TwoSlopeNorm

    plt = _pyplot()
    items = [(g, g.values().to_numpy(dtype=float) * 100) for g in grids if g.rows]
    values = np.concatenate([v.ravel() for _, v in items])
    span = max(1.0, float(np.nanmax(np.abs(values))) if np.isfinite(values).any() else 1.0)
    norm = TwoSlopeNorm(vcenter=0.0, vmin=-span, vmax=span)
    fig, axes = plt.subplots(1, len(items), squeeze=False,
                             figsize=(sum(3.2 + 1.3 * len(g.victims) for g, _ in items),
                                      1.8 + 0.45 * max(len(g.rows) for g, _ in items)))
    for ax, (grid, data) in zip(axes[0], items, strict=True):
        image = ax.imshow(np.ma.masked_invalid(data), cmap="RdBu_r", norm=norm, aspect="auto")
        ax.set_yticks(range(len(grid.rows)), [r.label for r in grid.rows], fontsize=8)
        ax.set_xticks(range(len(grid.victims)), list(grid.victims), rotation=20, ha="right", fontsize=8)
        ax.set_xlabel("evaluated victim")
        ax.set_ylabel("trained against · object")
        ax.set_title(f"relative BEV drop, moderate, {recall} (%) · proposals {grid.proposals}", fontsize=9)
        for r, row in enumerate(grid.rows):
            for c, victim in enumerate(grid.victims):
                entry = grid.entry(row, victim)
                dark = entry.value is not None and abs(data[r, c]) > 0.6 * span
                ax.text(c, r, entry.text, ha="center", va="center", fontsize=8 if entry.value is not None else 6.5,
                        color="white" if dark else "black" if entry.value is not None else "#777777")
                if entry.white_box:
                    ax.add_patch(plt.Rectangle((c - 0.5, r - 0.5), 1, 1, fill=False, lw=1.5, ec="black"))
        fig.colorbar(image, ax=ax, fraction=0.05, pad=0.02)
    fig.tight_layout()
    return png_bytes(fig)
