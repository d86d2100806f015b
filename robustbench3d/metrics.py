"""The attack metrics, defined once: what an attacked cell's ``attack_effect`` records against its clean cell.

:data:`ATTACK_METRICS` (name -> :class:`AttackMetric`, in the order the record, ``results.csv`` and the report's
leaderboard show them) holds each metric's computation and where it appears:

* ``clean`` (kind ``ap``): the clean cell's AP (percent), the reference of the others (:func:`clean_reference`);
* ``drop`` (``ap``): clean AP - attacked AP (percentage points; negative when the attack helps; :func:`drop`);
* ``relative_drop`` (``ap``): drop / clean AP (a fraction; None where the clean AP is 0; :func:`relative_drop`);
* ``success`` (``cell``): the attack success rate, of the target-class objects the evaluator matches clean the
  share it does not match attacked (:func:`success_rate`);
* ``drop_ci`` (``interval``): the percentile bootstrap interval of the paired drop, clean and attacked AP on the
  same resampled frames (:func:`paired_interval`).

Kinds: an ``ap`` metric is a function of one clean and one attacked AP value, recorded as a table
``{class: {metric: {recall: {difficulty: value}}}}`` over every AP both evaluations have (:func:`ap_tables`); a
``cell`` metric is one record per cell from the frames' ground truth and both cells' detections, its number under
``value_key``; an ``interval`` metric is the bootstrap interval (an
:func:`~robustbench3d.eval.bootstrap.interval_table`) of the ``ap`` metric ``of`` over paired resamples, recorded
when the run draws intervals.

**Adding a metric**: write its function and add its entry to :data:`ATTACK_METRICS`. The runner's record
(:func:`measure`), ``results.csv`` (:data:`robustbench3d.results.CSV_COLUMNS`, from ``column``),
:meth:`robustbench3d.results.CellResult.effect_value` and the report's leaderboard (from ``report``) follow from
the entry; its field must also be added to ``attack_effect`` in ``robustbench3d/schemas/summary.schema.json``
(tests/core/test_metrics.py fails, naming that file, until it is).

:data:`HEADLINE` is the AP every one-number summary reads (the seed paper's: target class, BEV, R40, moderate);
the attack success rate's matching criterion is its class, metric and difficulty.

Standard library only: numpy and the evaluator's matching are imported by the functions that need them.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple, Protocol

from robustbench3d.eval.rules import MIN_OVERLAP, TARGET_CLASS


class APKey(NamedTuple):
    """Where one AP value sits in an evaluation."""

    cls: str
    metric: str
    recall: str
    difficulty: str


#: The AP every one-number summary reads (the run's tables, flags, the gate's drop, the tradeoff's score).
HEADLINE = APKey(TARGET_CLASS, "bev", "R40", "moderate")
#: The attack-success-rate criterion: class, metric, difficulty (the IoU is the evaluator's for the metric).
SUCCESS_CLASS, SUCCESS_METRIC, SUCCESS_DIFFICULTY = HEADLINE.cls, HEADLINE.metric, HEADLINE.difficulty

KINDS: tuple[str, ...] = ("ap", "cell", "interval")
UNITS: tuple[str, ...] = ("percent", "points", "fraction")


class APTable(Protocol):
    """What the metrics read of an evaluation (:class:`robustbench3d.results.APResult` is one)."""

    @property
    def classes(self) -> tuple[str, ...]: ...

    def metrics(self, cls: str) -> tuple[str, ...]: ...

    def iou(self, cls: str, metric: str) -> float: ...

    def ap(self, cls: str, metric: str, recall: str, difficulty: str) -> float: ...

    def values(self) -> Iterable[Any]: ...  # each with cls, metric, recall, difficulty and ap


# ---- the definitions ------------------------------------------------------------------------------------------

def clean_reference(clean: Any, attacked: Any) -> Any:
    """The clean AP itself (percent): the reference each attacked value is compared with."""
    return clean


def drop(clean: Any, attacked: Any) -> Any:
    """Clean AP - attacked AP, percentage points (negative when the attack helps). Elementwise on arrays: the
    paired bootstrap applies it to resampled APs (:func:`paired_interval`)."""
    return clean - attacked


def relative_drop(clean: float, attacked: float) -> float | None:
    """:func:`drop` / clean AP, a fraction; None where the clean AP is 0 (undefined)."""
    return drop(clean, attacked) / clean if clean > 0 else None


def success_rate(gt: Sequence[Any], clean: Sequence[Any], attacked: Sequence[Any], iou: float) -> dict[str, Any]:
    """The attack success rate (an attack effect's ``success`` record) from the frames' GT and both cells'
    detections (one :class:`~robustbench3d.kitti.labels.Labels` per frame each): of the target-class objects
    matched clean, the share not matched attacked; "matched" is the evaluator's greedy matching
    (:mod:`robustbench3d.eval.matches`) at :data:`SUCCESS_CLASS`, :data:`SUCCESS_METRIC`,
    :data:`SUCCESS_DIFFICULTY`, at the score threshold that maximises F1 on the clean detections (the same
    threshold for the attacked ones). ``rate`` is None when nothing is matched clean."""
    from robustbench3d.eval.matches import best_f1_threshold, matched_ground_truth

    crit = {"cls": SUCCESS_CLASS, "metric": SUCCESS_METRIC, "difficulty": SUCCESS_DIFFICULTY}
    threshold = best_f1_threshold(gt, clean, **crit)
    before = matched_ground_truth(gt, clean, threshold, **crit).matched
    after = matched_ground_truth(gt, attacked, threshold, **crit).matched
    n_clean = int(sum(int(b.sum()) for b in before))
    missed = int(sum(int((b & ~a).sum()) for b, a in zip(before, after, strict=True)))
    return {"class": SUCCESS_CLASS, "metric": SUCCESS_METRIC, "iou": iou, "difficulty": SUCCESS_DIFFICULTY,
            "score_threshold": threshold, "clean_matched": n_clean, "attacked_missed": missed,
            "rate": missed / n_clean if n_clean else None}


def success_record(gt: Sequence[Any], clean_dets: Sequence[Any], attacked_dets: Sequence[Any],
                   clean: APTable) -> dict[str, Any]:
    """:func:`success_rate` at the clean evaluation's IoU threshold for the criterion (the devkit's,
    :data:`~robustbench3d.eval.rules.MIN_OVERLAP`, when the clean cell did not evaluate it)."""
    have = SUCCESS_CLASS in clean.classes and SUCCESS_METRIC in clean.metrics(SUCCESS_CLASS)
    iou = clean.iou(SUCCESS_CLASS, SUCCESS_METRIC) if have else MIN_OVERLAP[SUCCESS_METRIC][SUCCESS_CLASS]
    return success_rate(gt, clean_dets, attacked_dets, iou)


# ---- the table ------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class ReportColumn:
    """How the report's leaderboard shows a metric: its DataFrame column ``key`` (``key_R40``, ``key_R11`` for an
    ``ap`` metric; ``key_low_R40``, ``key_high_R40``, ... for an ``interval``), header ``title``, number format
    ``kind`` (``ap``: percent; ``points``; ``percent``: a fraction shown in percent) and tooltip ``tip``."""

    key: str
    title: str
    kind: str
    tip: str


@dataclass(frozen=True)
class AttackMetric:
    """One attack metric (module doc): its record field ``name``, ``kind`` (:data:`KINDS`), ``unit``
    (:data:`UNITS`), ``description`` and ``compute``: ``(clean AP, attacked AP) -> value`` for ``ap``;
    ``(gt, clean detections, attacked detections, clean evaluation) -> record`` for ``cell`` (the number under
    ``value_key``); for ``interval`` the bootstrap interval of the ``ap`` metric ``of`` (:func:`paired_interval`).
    ``column``: its ``results.csv`` column (None: not in the CSV); ``report``: its leaderboard column (None: not
    shown); ``higher_is_stronger``: whether a larger value means a stronger attack (None for the reference)."""

    name: str
    kind: str
    unit: str
    description: str
    compute: Callable[..., Any] | None = None
    column: str | None = None
    report: ReportColumn | None = None
    value_key: str | None = None
    of: str | None = None
    higher_is_stronger: bool | None = None


_AT = "BEV AP, moderate"  # the leaderboard's attack columns are of the HEADLINE AP (tooltips)

#: Every attack metric, in record, CSV and leaderboard order (module doc).
ATTACK_METRICS: dict[str, AttackMetric] = {m.name: m for m in (
    AttackMetric("clean", "ap", "percent", "AP of the clean cell (attack 'none') with the same victim, proposals "
                 "and dataset: the reference", clean_reference, column="clean_ap",
                 report=ReportColumn("clean", "clean BEV M", "ap", f"{_AT}, of the clean cell with the same proposals "
                                     "(%)")),
    AttackMetric("drop", "ap", "points", "clean AP - attacked AP (negative when the attack helps)", drop,
                 column="ap_drop",
                 report=ReportColumn("drop", "drop pts", "points", f"clean − attacked {_AT} (points)"),
                 higher_is_stronger=True),
    AttackMetric("relative_drop", "ap", "fraction", "drop / clean AP (null where the clean AP is 0)", relative_drop,
                 column="relative_drop", report=ReportColumn("rel_drop", "rel. drop %", "percent",
                                                             f"drop / clean {_AT} (%)"),
                 higher_is_stronger=True),
    AttackMetric("success", "cell", "fraction", "attack success rate: of the target-class objects matched in the "
                 "clean cell (moderate, BEV IoU of the evaluator, at the clean cell's F1-maximising score "
                 "threshold), the share not matched in the attacked cell at the same threshold (null when none is "
                 "matched clean)", success_record, column="attack_success_rate",
                 report=ReportColumn("asr", "ASR %", "percent", "attack success rate: Cars matched clean and missed "
                                     "attacked (moderate, BEV IoU 0.7) (%)"),
                 value_key="rate", higher_is_stronger=True),
    AttackMetric("drop_ci", "interval", "points", "percentile bootstrap interval of the paired drop: clean and "
                 "attacked AP on the same resampled frames", of="drop",
                 report=ReportColumn("dci", "drop CI", "ci", "confidence interval of the BEV moderate drop, as the "
                                     "run recorded it (points)")),
)}


def of_kind(kind: str) -> tuple[AttackMetric, ...]:
    """The metrics of ``kind`` (:data:`KINDS`), in table order."""
    return tuple(m for m in ATTACK_METRICS.values() if m.kind == kind)


def attack_metric(name: str) -> AttackMetric:
    """The entry ``name`` of :data:`ATTACK_METRICS` (:class:`LookupError` naming the known ones otherwise)."""
    if name not in ATTACK_METRICS:
        raise LookupError(f"unknown attack metric {name!r}; expected one of {', '.join(ATTACK_METRICS)}")
    return ATTACK_METRICS[name]


def csv_columns() -> tuple[str, ...]:
    """The ``results.csv`` columns of the attack metrics, in table order."""
    return tuple(m.column for m in ATTACK_METRICS.values() if m.column is not None)


# ---- computing the record -------------------------------------------------------------------------------------

def ap_tables(clean: APTable, attacked: APTable) -> dict[str, dict[str, Any]]:
    """Every ``ap`` metric as ``{name: {class: {metric: {recall: {difficulty: value}}}}}``, for every AP value both
    evaluations have (in the clean evaluation's order)."""
    metrics = of_kind("ap")
    out: dict[str, dict[str, Any]] = {m.name: {} for m in metrics}
    for v in clean.values():
        if v.cls not in attacked.classes or v.metric not in attacked.metrics(v.cls):
            continue
        after = attacked.ap(v.cls, v.metric, v.recall, v.difficulty)
        for m in metrics:
            assert m.compute is not None
            table = out[m.name].setdefault(v.cls, {}).setdefault(v.metric, {}).setdefault(v.recall, {})
            table[v.difficulty] = m.compute(v.ap, after)
    return out


def drop_tables(clean: APTable, attacked: APTable) -> tuple[dict, dict, dict]:
    """The ``clean``, ``drop`` and ``relative_drop`` tables of :func:`ap_tables` (``attack train``'s held-out
    curve reads them)."""
    tables = ap_tables(clean, attacked)
    return tables["clean"], tables["drop"], tables["relative_drop"]


def measure(clean: APTable, attacked: APTable, gt: Sequence[Any], clean_dets: Sequence[Any],
            attacked_dets: Sequence[Any]) -> dict[str, Any]:
    """The ``ap`` and ``cell`` metrics of an attacked cell against its clean cell, ``{name: table or record}`` in
    table order: the attack effect's measured fields (its intervals come from :func:`paired_interval`)."""
    tables = ap_tables(clean, attacked)
    out: dict[str, Any] = {}
    for m in ATTACK_METRICS.values():
        if m.kind == "ap":
            out[m.name] = tables[m.name]
        elif m.kind == "cell":
            assert m.compute is not None
            out[m.name] = m.compute(gt, clean_dets, attacked_dets, clean)
    return out


def paired_interval(interval: AttackMetric, clean: Mapping[Any, Any], attacked: Mapping[Any, Any], frames: int,
                    resamples: int, seed: int) -> dict[str, Any]:
    """The ``interval`` metric's table: per AP key both resamplings have (clean and attacked APs on the same
    resampled frames, :meth:`robustbench3d.eval.bootstrap.FrameBootstrap.resampled`), the percentile interval of
    its ``of`` metric applied to the paired values."""
    from robustbench3d.eval.bootstrap import interval_table

    if interval.kind != "interval" or interval.of is None:
        raise ValueError(f"attack metric {interval.name!r} is not an interval")
    fn = attack_metric(interval.of).compute
    assert fn is not None
    return interval_table({k: fn(clean[k], attacked[k]) for k in clean if k in attacked}, frames, resamples, seed,
                          paired=True)


__all__ = [
    "ATTACK_METRICS", "HEADLINE", "KINDS", "SUCCESS_CLASS", "SUCCESS_DIFFICULTY", "SUCCESS_METRIC", "UNITS",
    "APKey", "APTable", "AttackMetric", "ReportColumn", "ap_tables", "attack_metric", "clean_reference",
    "csv_columns", "drop", "drop_tables", "measure", "of_kind", "paired_interval", "relative_drop", "success_rate",
    "success_record",
]
