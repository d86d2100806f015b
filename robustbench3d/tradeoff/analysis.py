"""Scoring tradeoff points: AP with bootstrap intervals, |ΔAP| against the sweep's reference, Pareto fronts.

Every cell is prepared once for the frame bootstrap (:class:`~robustbench3d.eval.bootstrap.FrameBootstrap`)
and resampled with the same frame counts (:func:`~robustbench3d.eval.bootstrap.resample_weights`, one seed),
so the interval of a difference between two cells of the same frames is *paired*: AP drop (clean -
attacked) and ΔAP of a point against its sweep's reference. The ``frames`` sweep scores the default
setting on its first N frames (resampling those N) against all frames of the run; its ΔAP is the error
of the smaller evaluation, not a paired difference.

A point's error is max(|ΔAP clean|, |ΔAP attacked|) of the chosen AP (default Car BEV R40 moderate), its
cost the wall seconds of its clean and attacked cells on its frames (``time_vs_default``: over the default
setting's on the same frames; the ``frames`` sweep: over all frames of the run). A point is on a Pareto front when no
other point of the same set is at most as slow and at most as wrong, and better in one of the two: within
a sweep by wall time (``pareto_sweep``), across the knob sweeps by time relative to the default setting on
the same frames (``pareto_all``; some sweeps run on fewer frames).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from robustbench3d.eval.bootstrap import APKey, FrameBootstrap, percentile_interval, resample_weights
from robustbench3d.kitti.labels import Labels
from robustbench3d.metrics import HEADLINE
from robustbench3d.metrics import drop as ap_drop
from robustbench3d.tradeoff.measure import CellMeasure
from robustbench3d.tradeoff.sweeps import CLEAN, FrameSweep, Setting, Sweep

#: The AP every point is scored on (class, metric, recall sampling, difficulty).
DEFAULT_AP: APKey = (HEADLINE.cls, HEADLINE.metric, HEADLINE.recall, HEADLINE.difficulty)


@dataclass
class _Scores:
    """One cell's AP on a frame subset: the estimate and its resampled values."""

    ap: float
    samples: np.ndarray


class Scorer:
    """AP and resampled AP of cells on the first ``n`` frames, computed once per (cell, n)."""

    def __init__(self, gt: Sequence[Labels], resamples: int, seed: int, key: APKey = DEFAULT_AP):
        self.gt, self.resamples, self.seed, self.key = list(gt), resamples, seed, key
        self._cache: dict[tuple[str, int], _Scores] = {}
        self._weights: dict[int, np.ndarray] = {}

    def weights(self, n: int) -> np.ndarray:
        if n not in self._weights:
            self._weights[n] = resample_weights(n, self.resamples, self.seed)
        return self._weights[n]

    def scores(self, cell: CellMeasure, n: int) -> _Scores:
        k = (cell.spec.key, n)
        if k not in self._cache:
            cls = self.key[0]
            prep = FrameBootstrap(self.gt[:n], cell.detections[:n], classes=(cls,), metrics=(self.key[1],))
            c, m, r, d = self.key
            ap = float(prep.full[c][m][r][d])
            self._cache[k] = _Scores(ap, prep.resampled(self.weights(n))[self.key])
        return self._cache[k]


def _interval(values: np.ndarray) -> list[float]:
    return percentile_interval(values)


def _row(sweep: str, knob: str, value: str, setting: Setting | None, n: int, clean: _Scores, att: _Scores,
         ref_clean: _Scores, ref_att: _Scores, paired: bool, wall: float, cpu: float, is_ref: bool,
         is_default: bool, default_wall: float) -> dict[str, Any]:
    drop = ap_drop(clean.samples, att.samples)  # paired: the same resampled frames
    row: dict[str, Any] = {
        "sweep": sweep, "knob": knob, "value": value, "reference": is_ref, "default": is_default, "frames": n,
        "wall_s": wall, "cpu_s": cpu, "wall_s_per_frame": wall / n,
        "time_vs_default": wall / default_wall if default_wall > 0 else None,
        "ap_clean": clean.ap, "ap_attacked": att.ap, "drop": ap_drop(clean.ap, att.ap),
        "d_clean": clean.ap - ref_clean.ap, "d_attacked": att.ap - ref_att.ap,
    }
    row["d_drop"] = row["drop"] - ap_drop(ref_clean.ap, ref_att.ap)
    for name, values in (("ap_clean", clean.samples), ("ap_attacked", att.samples), ("drop", drop)):
        row[f"{name}_lo"], row[f"{name}_hi"] = _interval(values)
    if paired:
        for name, values in (("d_clean", clean.samples - ref_clean.samples),
                             ("d_attacked", att.samples - ref_att.samples)):
            row[f"{name}_lo"], row[f"{name}_hi"] = _interval(values)
    else:
        for name in ("d_clean", "d_attacked"):
            row[f"{name}_lo"] = row[f"{name}_hi"] = None
    row["error"] = max(abs(row["d_clean"]), abs(row["d_attacked"]))
    row["ci_width"] = row["ap_attacked_hi"] - row["ap_attacked_lo"]
    row["setting"] = None if setting is None else {"victim": setting.victim, "victim_args": dict(setting.victim_args),
                                                   "attack_args": dict(setting.attack_args),
                                                   "decimation": setting.decimation}
    return row


def score(sweeps: Sequence[Sweep | FrameSweep], measures: Mapping[str, CellMeasure], attack: str, scorer: Scorer,
          default: Setting) -> list[dict[str, Any]]:
    """One row per point of every sweep (module docstring), Pareto flags included."""
    rows: list[dict[str, Any]] = []
    n_all = len(scorer.gt)

    def cells(s: Setting, frames: int | None = None) -> tuple[CellMeasure, CellMeasure]:
        n = None if s == default else frames
        return measures[s.cell(CLEAN, n).key], measures[s.cell(attack, n).key]

    dc, da = cells(default)

    def default_wall(n: int) -> float:
        return dc.time_of(n) + da.time_of(n)

    for sweep in sweeps:
        if isinstance(sweep, FrameSweep):
            rc, ra = scorer.scores(dc, n_all), scorer.scores(da, n_all)
            for n in sweep.counts:
                rows.append(_row(sweep.name, sweep.knob, str(n), default, n, scorer.scores(dc, n),
                                 scorer.scores(da, n), rc, ra, n == n_all, default_wall(n),
                                 dc.time_of(n, "cpu") + da.time_of(n, "cpu"), n == n_all, n == n_all,
                                 default_wall(n_all)))
            continue
        n = n_all if sweep.frames is None else min(sweep.frames, n_all)
        rc_m, ra_m = cells(sweep.points[sweep.reference].setting, sweep.frames)
        rc, ra = scorer.scores(rc_m, n), scorer.scores(ra_m, n)
        for i, p in enumerate(sweep.points):
            c, a = cells(p.setting, sweep.frames)
            rows.append(_row(sweep.name, sweep.knob, p.value, p.setting, n, scorer.scores(c, n),
                             scorer.scores(a, n), rc, ra, True, c.time_of(n) + a.time_of(n),
                             c.time_of(n, "cpu") + a.time_of(n, "cpu"), i == sweep.reference,
                             p.setting == default, default_wall(n)))
    for sweep_name in dict.fromkeys(r["sweep"] for r in rows):
        group = [r for r in rows if r["sweep"] == sweep_name]
        for r, on in zip(group, pareto_front([(r["wall_s"], r["error"]) for r in group]), strict=True):
            r["pareto_sweep"] = on
    knobs = [r for r in rows if r["sweep"] != "frames"]  # across sweeps (some on fewer frames): relative time
    for r, on in zip(knobs, pareto_front([(r["time_vs_default"], r["error"]) for r in knobs]), strict=True):
        r["pareto_all"] = on
    for r in rows:
        r.setdefault("pareto_all", None)
    return rows


def pareto_front(points: Sequence[tuple[float, float]]) -> list[bool]:
    """For each (cost, error): True when no other point has cost <= and error <= with one strictly less."""
    out = []
    for i, (ci, ei) in enumerate(points):
        dominated = any((cj <= ci and ej <= ei and (cj < ci or ej < ei))
                        for j, (cj, ej) in enumerate(points) if j != i)
        out.append(not dominated)
    return out
