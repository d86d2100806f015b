"""What an attack did to a victim: AP drop against the clean cell and the attack success rate.

An attacked cell (attack other than ``none``) is compared with the **clean cell** of the same victim,
proposal source and dataset: the ``none`` cell, which the runner adds to any run that has attacked
cells (:func:`with_clean_cells`). The comparison (the cell's ``attack_effect``, recomputed whenever
the summary is written, so it always refers to the clean cell on disk) holds:

* the attack metrics of :data:`robustbench3d.metrics.ATTACK_METRICS`, defined there: ``clean`` (the clean
  cell's AP per class, metric, recall sampling and difficulty, percent), ``drop`` (clean - attacked,
  percentage points), ``relative_drop`` (drop / clean, a fraction) and ``success`` (the attack success rate:
  of the Cars the evaluator matches clean, the share it misses attacked).

Both cells' numbers come from their result files on disk (``cells/<cell>/data/*.txt``). The clean cell
counts as the reference only when its configuration equals the attacked cell's but for the attack
(:func:`reference_mismatch`: victim and its arguments, proposals, dataset and frames, seed, batch size,
evaluation, versions); a clean cell recomputed with, say, other victim arguments leaves an earlier
attacked cell without a reference (``attack_effect`` null), never compared with the wrong one.

With ``bootstrap`` resamples (the run's ``RunConfig.bootstrap``; 0: none), every ``ok`` cell also gets
``metrics_ci``, the percentile bootstrap 95 % interval over frames of each AP in ``metrics``, and every
attack effect ``drop_ci``, the interval of the paired drop (clean and attacked AP on the same resampled
frames; each ``interval`` metric of the table, :func:`robustbench3d.metrics.paired_interval`);
:mod:`robustbench3d.eval.bootstrap`, resampling weights from the run seed. This module finds the clean cell,
reads the result files and keeps what is current; the numbers are :mod:`robustbench3d.metrics`'.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from robustbench3d.kitti.labels import Labels, read_labels
from robustbench3d.metrics import AttackMetric, measure, of_kind, paired_interval, success_rate
from robustbench3d.results import CellResult
from robustbench3d.runner.config import CellKey, RunConfig, config_differences

CLEAN_ATTACK = "none"
# The attack metrics are robustbench3d.metrics' (pure functions of evaluations and detections), so that
# ``attack train``'s held-out curve (robustbench3d.attacks, below the runner) computes them the same way.


def with_clean_cells(config: RunConfig) -> RunConfig:
    """``config`` with the clean control ``none`` first among the attacks when it has attacked cells
    but no clean one (unchanged otherwise)."""
    if CLEAN_ATTACK in config.attacks or not config.attacks:
        return config
    return dataclasses.replace(config, attacks=(CLEAN_ATTACK, *config.attacks))


def clean_key(key: CellKey) -> CellKey:
    """The clean cell compared with ``key``."""
    return CellKey(key.victim, CLEAN_ATTACK, key.proposals)


def reference_mismatch(clean: dict[str, Any], attacked: dict[str, Any]) -> str | None:
    """Why ``clean`` is not ``attacked``'s clean reference: their cell configurations differ outside the
    attack (:func:`~robustbench3d.runner.config.config_differences`, clean vs attacked), or None."""
    a, b = ({k: v for k, v in CellResult(c).config.items() if k != "attack"} for c in (clean, attacked))
    return None if a == b else config_differences(a, b)


def read_results(data_dir: Path, frame_ids: Sequence[str]) -> list[Labels]:
    """A cell's detections, one :class:`Labels` per frame (its result files)."""
    return [read_labels(data_dir / f"{fid}.txt", scored=True) for fid in frame_ids]


class Intervals:
    """Bootstrap intervals of the cells of one run (resampled APs cached per cell directory).

    Args:
        gt, frame_ids: the run's ground truth and frame ids (the cells' frames).
        resamples: bootstrap resamples (at least 1); seed: the run seed (the resampling weights).
    """

    def __init__(self, gt: Sequence[Labels], frame_ids: Sequence[str], resamples: int, seed: int):
        from robustbench3d.eval.bootstrap import resample_weights

        self.gt, self.frame_ids, self.resamples, self.seed = gt, frame_ids, resamples, seed
        self.weights = resample_weights(len(frame_ids), resamples, seed)
        self._cache: dict[Path, dict] = {}

    def resampled(self, cell: dict[str, Any], cell_dir: Path) -> dict:
        """Resampled APs of an ``ok`` cell's result files (the classes and metrics of its ``metrics``)."""
        from robustbench3d.eval.bootstrap import FrameBootstrap

        if cell_dir not in self._cache:
            result = CellResult(cell).result
            if result is None:
                raise ValueError(f"cell {cell_dir.name} is not ok: it has no AP to resample")
            prep = FrameBootstrap(self.gt, read_results(cell_dir / "data", self.frame_ids), result.classes,
                                  result.evaluated_metrics)
            self._cache[cell_dir] = prep.resampled(self.weights)
        return self._cache[cell_dir]

    def _table(self, values: dict) -> dict[str, Any]:
        from robustbench3d.eval.bootstrap import interval_table

        return interval_table(values, len(self.frame_ids), self.resamples, self.seed)

    def _current(self, table: Any) -> bool:
        meta = table.get("meta", {}) if isinstance(table, dict) else {}
        return (meta.get("resamples"), meta.get("seed"), meta.get("frames")) == (
            self.resamples, self.seed, len(self.frame_ids))

    def metrics_ci(self, cell: dict[str, Any], cell_dir: Path) -> dict[str, Any]:
        """The cell's ``metrics_ci`` (kept as recorded when drawn with the same resamples, seed and frames)."""
        old = cell.get("metrics_ci")
        return old if self._current(old) else self._table(self.resampled(cell, cell_dir))

    def paired(self, interval: AttackMetric, clean: dict[str, Any], clean_dir: Path, attacked: dict[str, Any],
               attacked_dir: Path) -> dict[str, Any]:
        """The ``interval`` attack metric of the pair, e.g. ``drop_ci`` (kept as recorded when current, see
        :meth:`metrics_ci`)."""
        old = CellResult(attacked).effect or {}
        if self._current(old.get(interval.name)) and old.get("clean_fingerprint") == CellResult(clean).fingerprint:
            return old[interval.name]
        return paired_interval(interval, self.resampled(clean, clean_dir), self.resampled(attacked, attacked_dir),
                               len(self.frame_ids), self.resamples, self.seed)


def attack_effect(clean_cell: dict[str, Any], attacked_cell: dict[str, Any], clean_dir: Path, attacked_dir: Path,
                  gt: Sequence[Labels], frame_ids: Sequence[str], intervals: Intervals | None = None) -> dict[str, Any]:
    """The ``attack_effect`` record of an ``ok`` attacked cell against its ``ok`` clean cell: the clean cell's name
    and fingerprint, every measured attack metric (:func:`robustbench3d.metrics.measure`) and, when ``intervals``
    are given, every ``interval`` metric (``drop_ci``)."""
    clean, attacked = CellResult(clean_cell), CellResult(attacked_cell)
    clean_ap, attacked_ap = clean.result, attacked.result
    if clean_ap is None or attacked_ap is None:
        raise ValueError(f"attack effect of {attacked.name} against {clean.name}: both cells must be ok")
    measured = measure(clean_ap, attacked_ap, gt, read_results(clean_dir / "data", frame_ids),
                       read_results(attacked_dir / "data", frame_ids))
    out = {"clean_cell": clean_dir.name, "clean_fingerprint": clean.fingerprint, **measured}
    if intervals is not None:
        for interval in of_kind("interval"):
            out[interval.name] = intervals.paired(interval, clean_cell, clean_dir, attacked_cell, attacked_dir)
    return out


def attach_effects(cells: list[dict[str, Any]], cells_dir: Path, gt: Sequence[Labels],
                   frame_ids: Sequence[str], bootstrap: int = 0, seed: int = 0,
                   log: Callable[[str], None] | None = None) -> list[int]:
    """Set ``attack_effect`` on every attacked cell of ``cells`` (in place): the record for an ``ok`` one whose
    clean cell is among ``cells``, ``ok`` and of the same configuration but for the attack
    (:func:`reference_mismatch`; ``log`` gets a line for each one that is not), else null (clean cells are
    left as they are); with ``bootstrap`` resamples also ``metrics_ci`` on every ``ok`` cell and ``drop_ci``
    in each record (``bootstrap=0`` removes them). Returns the indices of changed cells."""
    results = [CellResult(c) for c in cells]
    clean = {(r.victim, r.proposals): r.cell for r in results if r.attack == CLEAN_ATTACK and r.ok}
    intervals = Intervals(gt, frame_ids, bootstrap, seed) if bootstrap > 0 else None
    changed = []
    for i, (cell, r) in enumerate(zip(cells, results, strict=True)):
        if r.ok and intervals is not None:
            ci = intervals.metrics_ci(cell, cells_dir / r.name)
            if cell.get("metrics_ci") != ci:
                cell["metrics_ci"] = ci
                changed.append(i)
        elif "metrics_ci" in cell:
            del cell["metrics_ci"]
            changed.append(i)
    for i, (cell, r) in enumerate(zip(cells, results, strict=True)):
        if r.attack == CLEAN_ATTACK:  # the clean cells themselves carry no comparison (no key)
            continue
        key = CellKey(*r.id)
        base = clean.get((key.victim, key.proposals))
        effect = None
        mismatch = reference_mismatch(base, cell) if r.ok and base is not None else None
        if mismatch is not None and log is not None:
            log(f"no clean reference for {key}: its clean cell {clean_key(key).dirname} was computed with another "
                f"configuration (clean vs attacked: {mismatch}); attack_effect left null")
        if r.ok and base is not None and mismatch is None:
            effect = attack_effect(base, cell, cells_dir / clean_key(key).dirname, cells_dir / key.dirname, gt,
                                   frame_ids, intervals)
        if cell.get("attack_effect", None) != effect or "attack_effect" not in cell:
            cell["attack_effect"] = effect
            changed.append(i)
    return sorted(set(changed))


__all__ = ["CLEAN_ATTACK", "Intervals", "attach_effects", "attack_effect", "clean_key", "read_results",
           "reference_mismatch", "success_rate", "with_clean_cells"]
