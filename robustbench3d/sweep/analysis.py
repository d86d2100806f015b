"""The dose–response rows of a sweep, read from its benchmark run, and the "smallest object" sentence.

Per victim x proposal source x attack (each point's object, each benign sphere): the relative moderate BEV drop
and the attack success rate exactly as the run recorded them (:class:`~robustbench3d.results.CellResult`,
:mod:`robustbench3d.metrics`), the paired drop interval the run recorded (``drop_ci``), and 95 % percentile
bootstrap intervals of the relative drop and of the success rate drawn here with the run's resampled frame
counts (:func:`~robustbench3d.eval.bootstrap.resample_weights`, the run's seed and resample count, so clean and
attacked AP are paired): the relative drop of each resample is :func:`robustbench3d.metrics.relative_drop` of its
clean and attacked AP; the success rate of each resample is the share of its clean-matched Cars missed attacked,
matched as the run matched them (at the score threshold the run recorded, the criteria of
:data:`robustbench3d.metrics.SUCCESS_CLASS` ...; the per-frame counts are checked to add up to the run's record).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from robustbench3d.errors import RobustBenchError
from robustbench3d.kitti.labels import Labels
from robustbench3d.metrics import HEADLINE, SUCCESS_CLASS, SUCCESS_DIFFICULTY, SUCCESS_METRIC, relative_drop
from robustbench3d.results import CellResult

#: The share of moderate BEV AP the README's sentence asks an object to take.
HALF = 0.5


def _detections(cell_dir: Path, frame_ids: Sequence[str]) -> list[Labels]:
    from robustbench3d.kitti.labels import read_labels

    return [read_labels(cell_dir / "data" / f"{fid}.txt", scored=True) for fid in frame_ids]


def _interval(values: np.ndarray) -> list[float] | None:
    from robustbench3d.eval.bootstrap import percentile_interval

    values = values[np.isfinite(values)]
    return percentile_interval(values) if len(values) else None


class Scorer:
    """Intervals of the cells of one run over its frames (module doc); clean cells prepared once."""

    def __init__(self, run_dir: Path, gt: Sequence[Labels], frame_ids: Sequence[str], resamples: int, seed: int):
        from robustbench3d.eval.bootstrap import resample_weights

        self.run_dir, self.gt, self.ids = run_dir, list(gt), list(frame_ids)
        self.weights = resample_weights(len(self.ids), resamples, seed) if resamples else None
        self._prepared: dict[str, tuple[list[Labels], np.ndarray]] = {}

    def _prepare(self, cell: CellResult) -> tuple[list[Labels], np.ndarray]:
        from robustbench3d.eval.bootstrap import FrameBootstrap

        if cell.name not in self._prepared:
            dets = _detections(self.run_dir / "cells" / cell.name, self.ids)
            prep = FrameBootstrap(self.gt, dets, classes=(HEADLINE.cls,), metrics=(HEADLINE.metric,))
            assert self.weights is not None
            self._prepared[cell.name] = (dets, prep.resampled(self.weights)[tuple(HEADLINE)])
        return self._prepared[cell.name]

    def intervals(self, clean: CellResult, attacked: CellResult) -> dict[str, list[float] | None]:
        """``relative_drop_ci`` (fractions) and ``asr_ci`` of ``attacked`` against ``clean``."""
        if self.weights is None:
            return {"relative_drop_ci": None, "asr_ci": None}
        clean_dets, clean_ap = self._prepare(clean)
        att_dets, att_ap = self._prepare(attacked)
        rel = np.array([np.nan if (r := relative_drop(float(c), float(a))) is None else r
                        for c, a in zip(clean_ap, att_ap, strict=True)])
        return {"relative_drop_ci": _interval(rel), "asr_ci": self._asr_interval(attacked, clean_dets, att_dets)}

    def _asr_interval(self, attacked: CellResult, clean_dets: list[Labels], att_dets: list[Labels]
                      ) -> list[float] | None:
        from robustbench3d.eval.matches import matched_ground_truth

        record = (attacked.effect or {}).get("success") or {}
        if record.get("rate") is None:
            return None
        crit = {"cls": SUCCESS_CLASS, "metric": SUCCESS_METRIC, "difficulty": SUCCESS_DIFFICULTY}
        before = matched_ground_truth(self.gt, clean_dets, record["score_threshold"], **crit).matched
        after = matched_ground_truth(self.gt, att_dets, record["score_threshold"], **crit).matched
        matched = np.array([int(b.sum()) for b in before], dtype=np.float64)
        missed = np.array([int((b & ~a).sum()) for b, a in zip(before, after, strict=True)], dtype=np.float64)
        if (int(matched.sum()), int(missed.sum())) != (record["clean_matched"], record["attacked_missed"]):
            raise RobustBenchError(f"{self.run_dir}: cell {attacked.name}: its result files do not give the success "
                                   "rate its summary records (changed since the run?); rerun the sweep with --force")
        assert self.weights is not None
        den = self.weights @ matched
        with np.errstate(invalid="ignore", divide="ignore"):
            rates = np.where(den > 0, (self.weights @ missed) / den, np.nan)
        return _interval(rates)


def score_row(cell: CellResult, clean: CellResult | None, scorer: Scorer) -> dict[str, Any]:
    """One attacked cell's dose–response values (module doc); ``status`` says why values are missing."""
    row: dict[str, Any] = {"status": cell.status, "reason": cell.reason,
                           "seconds": cell.provenance.get("seconds"), "cpu_seconds": cell.provenance.get("cpu_seconds")}
    empty = {"clean_ap": None, "attacked_ap": None, "drop": None, "drop_ci": None, "relative_drop": None,
             "relative_drop_ci": None, "asr": None, "asr_ci": None}
    if not cell.ok or cell.effect is None or clean is None or not clean.ok:
        return {**row, **empty}
    row.update(clean_ap=cell.clean_ap(), attacked_ap=cell.ap(), drop=cell.drop(),
               drop_ci=cell.interval(table="drop_ci"), relative_drop=cell.drop(relative=True),
               asr=cell.attack_success_rate)
    row.update(scorer.intervals(clean, cell))
    return row


def scores(summary: Sequence[Mapping[str, Any]], attacks: Mapping[str, dict[str, Any]], scorer: Scorer
           ) -> list[dict[str, Any]]:
    """A row per cell of ``summary`` whose attack is a key of ``attacks`` (its point or control record, merged
    into the row), in summary order."""
    cells = [CellResult(c) for c in summary]
    by_name = {c.name: c for c in cells}
    rows = []
    for cell in cells:
        if cell.attack not in attacks:
            continue
        clean = by_name.get(cell.clean_cell or f"{cell.victim}+none+{cell.proposals}")
        rows.append({"victim": cell.victim, "proposals": cell.proposals, "attack": cell.attack,
                     **attacks[cell.attack], **score_row(cell, clean, scorer)})
    return rows


def _pct(x: float) -> str:
    return f"{100 * x:.1f} %"


def _ci(ci: Sequence[float] | None) -> str:
    return "" if not ci else f" (95 % CI {100 * ci[0]:.1f}–{100 * ci[1]:.1f} %)"


def smallest_sentence(doc: Mapping[str, Any], victim: str) -> str:
    """The README's answer for ``victim``: per proposal source, the smallest object swept (smallest radius, then
    fewest vertex colours) whose relative moderate BEV drop is at least :data:`HALF`, or that none is, with the
    largest drop measured. ``doc``: a ``sweep.json`` document."""
    rows = [r for r in doc["scores"] if r["victim"] == victim and r["kind"] == "object"]
    if not rows:
        raise RobustBenchError(f"the sweep scored no object against victim {victim!r}")
    mode = doc["config"]["mode"]
    parts = []
    for proposals in dict.fromkeys(r["proposals"] for r in rows):
        group = sorted((r for r in rows if r["proposals"] == proposals), key=lambda r: (r["radius"], r["level"]))
        measured = [r for r in group if r["relative_drop"] is not None]
        strong = [r for r in measured if r["relative_drop"] >= HALF]
        if strong:
            r = strong[0]
            parts.append(f"with {proposals} proposals the smallest that takes ≥ 50 % of moderate BEV AP is "
                         f"radius {r['radius']:.2f} m with {r['vertex_colours']} vertex colours "
                         f"({r['name']}): {_pct(r['relative_drop'])}{_ci(r['relative_drop_ci'])}")
        elif measured:
            best = max(measured, key=lambda r: r["relative_drop"])
            parts.append(f"with {proposals} proposals none does (largest: {best['name']}, "
                         f"{_pct(best['relative_drop'])}{_ci(best['relative_drop_ci'])})")
        else:
            parts.append(f"with {proposals} proposals no object has a measured drop (clean AP 0 or failed cells)")
    radii = sorted({r["radius"] for r in rows})
    colours = sorted({r["vertex_colours"] for r in rows})
    return (f"{victim}: of the {len({r['name'] for r in rows})} {mode} objects swept (radius "
            f"{radii[0]:.2f}–{radii[-1]:.2f} m, {colours[0]}–{colours[-1]} vertex colours, "
            f"{doc['dataset']['frames']} frames of {doc['dataset']['split']}), " + "; ".join(parts) + ".")


__all__ = ["HALF", "Scorer", "score_row", "scores", "smallest_sentence"]
