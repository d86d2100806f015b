"""The report's data: run summaries read back, grouped into comparable sections, as tables.

A *section* holds the cells that may share one table: the same dataset (sha256 over split and labels,
split, frame count, generator parameters), the same protocol (the evaluation configuration, each
metric's IoU threshold, the recall points, the difficulty definitions and the run seed) and the same
package versions. Cells that differ in any of these are never put in one table: :func:`sections`
separates them and says which fields differ, and ``strict`` refuses instead. The proposal source is a
column of every table and every comparison (clean reference, drop, transfer) stays within one source.

Every cell is read through :class:`robustbench3d.results.CellResult`; the attack columns of :func:`table` are
the attack metrics' (:data:`robustbench3d.metrics.ATTACK_METRICS`, their ``report`` columns). pandas is imported
inside the functions that build tables; the module itself is standard library only.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from robustbench3d.errors import DataFormatError, RobustBenchError
from robustbench3d.eval.rules import DIFFICULTIES
from robustbench3d.metrics import HEADLINE, of_kind
from robustbench3d.results import RECALL_POINTS, CellResult

#: The leaderboard's AP: the headline's class (Car); its attack columns are at the headline's metric and difficulty.
CLASS = HEADLINE.cls
#: Recall samplings, in column order (R40, R11).
RECALLS: tuple[str, ...] = tuple(RECALL_POINTS)
METRICS = ("bev", "3d")
SUMMARY = "summary.json"
CLEAN_ATTACK = "none"


@dataclass(frozen=True)
class RunCell:
    """One summary cell and the run directory it came from."""

    run: Path
    index: int
    cell: Mapping[str, Any]

    @property
    def name(self) -> str:
        """The cell's directory name, ``victim+attack+proposals``."""
        return CellResult(self.cell).name

    @property
    def source(self) -> str:
        """``RUN/summary.json[index]``: where the cell's numbers are read from."""
        return f"{self.run / SUMMARY}[{self.index}]"


def read_summary_tolerant(path: Path) -> list[dict[str, Any]]:
    """A ``summary.json`` validated against the shipped schema; cell keys the schema does not know (``flags``,
    confidence intervals written by newer runs) are kept but not validated."""
    from robustbench3d.results import load_schema, read_json, validate_summary  # jsonschema on use

    data = read_json(path)
    known = set(load_schema()["$defs"]["cell"]["properties"])
    if isinstance(data, list):
        validate_summary([{k: v for k, v in c.items() if k in known} if isinstance(c, dict) else c for c in data],
                         path)
    else:
        validate_summary(data, path)
    return data


def read_runs(runs: Sequence[str | Path]) -> list[RunCell]:
    """Every cell of each run's validated ``summary.json``, in run and summary order."""

    if not runs:
        raise RobustBenchError("report: no run directory given")
    out: list[RunCell] = []
    seen: set[Path] = set()
    for run in map(Path, runs):
        if not run.is_dir():
            raise DataFormatError(run, "not a run directory (expected the --out directory of `robustbench3d run`)")
        if run.resolve() in seen:
            raise RobustBenchError(f"report: run directory {run} is given twice")
        seen.add(run.resolve())
        cells = read_summary_tolerant(run / SUMMARY)
        if not cells:
            raise DataFormatError(run / SUMMARY, "the summary lists no cell")
        out += [RunCell(run, i, c) for i, c in enumerate(cells)]
    return out


#: Protocol fields read from the evaluator's output: unknown for a cell without metrics (skipped, error).
FROM_METRICS = ("iou", "recall_points", "difficulty")


def comparability_key(cell: Mapping[str, Any]) -> dict[str, Any]:
    """What must be equal for two cells to share a table (see the module doc); plain JSON types. A cell
    without metrics has None for the :data:`FROM_METRICS` fields."""
    r = CellResult(cell)
    ds = r.dataset
    prov = r.provenance
    meta = None if r.result is None else r.result.meta
    return {
        "dataset": {k: ds.get(k) for k in ("sha256", "split", "frames", "split_frames", "embedded")},
        "protocol": {
            "evaluation": r.config.get("evaluation"),
            "iou": None if meta is None else meta.get("min_overlap"),
            "recall_points": None if meta is None else meta.get("recall_points", sorted(RECALLS)),
            "difficulty": None if meta is None else meta.get("difficulty"),
            "seed": r.config.get("seed"),
        },
        "versions": {"robustbench3d": prov["package"]["version"], **prov.get("versions", {})},
    }


def _flat(obj: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(obj, Mapping) and obj:
        out: dict[str, Any] = {}
        for k, v in obj.items():
            out.update(_flat(v, f"{prefix}.{k}" if prefix else str(k)))
        return out
    return {prefix: obj}


def key_differences(a: Mapping[str, Any], b: Mapping[str, Any]) -> list[str]:
    """``field: A != B`` for every leaf where two comparability keys differ (dotted paths, sorted)."""
    fa, fb = _flat(a), _flat(b)
    out = []
    for k in sorted(set(fa) | set(fb)):
        if fa.get(k, "(absent)") != fb.get(k, "(absent)"):
            va, vb = (json.dumps(x.get(k, "(absent)"))[:80] for x in (fa, fb))
            out.append(f"{k}: {va} != {vb}")
    return out


@dataclass(frozen=True)
class Merged:
    """A cell shown once although given twice: ``dropped`` (a later run's, or later in one summary) is the same
    cell as ``kept`` (same victim, attack, proposals and configuration fingerprint on the same dataset and
    protocol); ``same_results`` whether their metrics and attack effect are equal too."""

    kept: RunCell
    dropped: RunCell
    same_results: bool

    def note(self) -> str:
        """One sentence naming the cell, both places and why one is not shown."""
        results = "identical results" if self.same_results else "but different results: the first one's are shown"
        return (f"{self.dropped.name} ({self.dropped.source}) is left out: it is the same cell as {self.kept.source} "
                f"(same configuration fingerprint, dataset and protocol), {results}.")


@dataclass
class Section:
    """Cells that are comparable (one :func:`comparability_key`), why they differ from section 1, and the
    cells given more than once that it shows once (:class:`Merged`)."""

    key: dict[str, Any]
    cells: list[RunCell] = field(default_factory=list)
    differs: list[str] = field(default_factory=list)
    merged: list[Merged] = field(default_factory=list)

    @property
    def runs(self) -> list[Path]:
        return list(dict.fromkeys(c.run for c in self.cells))


def _masked(key: dict[str, Any]) -> dict[str, Any]:
    return {**key, "protocol": {**key["protocol"], **dict.fromkeys(FROM_METRICS)}}


def sections(cells: Iterable[RunCell], strict: bool = False) -> list[Section]:
    """Group cells by :func:`comparability_key`, in order of first appearance. With ``strict`` more than
    one group is refused (:class:`RobustBenchError` naming the runs and the fields that differ). The
    same cell (victim, attack, proposals) twice in a section is kept once when its configuration
    fingerprint is equal (recorded in the section's ``merged``) and refused otherwise. A cell without
    metrics joins a section that agrees with it on every other field (one holding cells of its own run
    first)."""
    groups: list[Section] = []
    cells_list = list(cells)
    for rc in sorted(cells_list, key=lambda c: CellResult(c.cell).result is None):  # cells with metrics found sections
        key = comparability_key(rc.cell)
        partial = key["protocol"]["iou"] is None and key["protocol"]["recall_points"] is None
        # a cell without metrics prefers a section holding cells of its own run
        candidates = sorted(groups, key=lambda s: rc.run not in s.runs) if partial else groups
        for sec in candidates:
            if sec.key == key or (partial and _masked(sec.key) == key):
                break
        else:
            sec = Section(key)
            groups.append(sec)
        twin = next((c for c in sec.cells if c.name == rc.name), None)
        if twin is None:
            sec.cells.append(rc)
        elif CellResult(twin.cell).fingerprint != CellResult(rc.cell).fingerprint:
            raise RobustBenchError(f"report: cell {rc.name} is in {twin.source} and {rc.source} with different "
                                   "configurations on the same dataset and protocol; report the runs separately")
        else:
            sec.merged.append(Merged(twin, rc, _results(twin.cell) == _results(rc.cell)))
    order = {id(rc): i for i, rc in enumerate(cells_list)}
    for sec in groups:
        sec.cells.sort(key=lambda c: order[id(c)])  # back to run and summary order
        sec.merged.sort(key=lambda m: order[id(m.dropped)])
    for sec in groups[1:]:
        sec.differs = key_differences(groups[0].key, sec.key)
    if strict and len(groups) > 1:
        why = "; ".join(f"{', '.join(map(str, s.runs))} vs {', '.join(map(str, groups[0].runs))}: "
                        + ", ".join(s.differs) for s in groups[1:])
        raise RobustBenchError(f"report: the runs are not comparable (different dataset, protocol or versions) "
                               f"and --strict refuses to separate them: {why}")
    return groups


def _results(cell: Mapping[str, Any]) -> tuple[Any, ...]:
    """What a cell measured: status, metrics, intervals, attack effect."""
    return tuple(cell.get(k) for k in ("status", "metrics", "metrics_ci", "attack_effect"))


def _status(cell: Mapping[str, Any]) -> str:
    r = CellResult(cell)
    return r.status + (f", {r.reason}" if r.reason else "")


def left_out(section: Section) -> list[str]:
    """Why cells of ``section`` are missing from its figures or have no number in its transfer matrix (one
    sentence per reason, naming each cell and where it comes from): cells with no AP (not ``ok``), and attacked
    cells without a clean comparison (no ``attack_effect``: no ``ok`` clean cell of the same victim and proposals)."""
    out = []
    no_ap = [rc for rc in section.cells if not CellResult(rc.cell).ok]
    if no_ap:
        out.append("No AP, so not in the figures (the leaderboard, the worst case and the transfer matrix show their "
                   "status): "
                   + "; ".join(f"{rc.name} ({rc.source}): {_status(rc.cell)}" for rc in no_ap) + ".")
    lone = [rc for rc in section.cells if (r := CellResult(rc.cell)).ok and r.attack != CLEAN_ATTACK and not r.effect]
    if lone:
        out.append("No clean cell with the same victim and proposals to compare with, so no drop (not in the drop "
                   "figure; \"no clean cell\" in the transfer matrix): "
                   + "; ".join(f"{rc.name} ({rc.source})" for rc in lone) + ".")
    return out


def _get(tree: Any, *path: str) -> Any:
    for p in path:
        if not isinstance(tree, Mapping) or p not in tree:
            return None
        tree = tree[p]
    return tree


def _interval(value: Any) -> tuple[float, float] | None:
    """(low, high) of a confidence interval written as [lo, hi] or {low|lo|lower, high|hi|upper}."""
    if isinstance(value, Sequence) and not isinstance(value, str) and len(value) == 2:
        lo, hi = value
    elif isinstance(value, Mapping):
        lo = next((value[k] for k in ("low", "lo", "lower") if k in value), None)
        hi = next((value[k] for k in ("high", "hi", "upper") if k in value), None)
    else:
        return None
    if isinstance(lo, int | float) and isinstance(hi, int | float):
        return float(lo), float(hi)
    return None


def cell_ci(cell: Mapping[str, Any], metric: str, recall: str, difficulty: str) -> tuple[float, float] | None:
    """The AP's confidence interval when the cell carries one (``metrics_ci`` in the metrics' layout)."""
    for name in ("metrics_ci", "ci"):
        found = _interval(CellResult(cell).interval(CLASS, metric, recall, difficulty, table=name))
        if found is not None:
            return found
    return None


#: The controls: attack kinds whose object is not optimised (what a mere object costs). Neither they nor the clean
#: cell (attack ``none``) are attacks: never in a worst case or a row of the transfer matrix. A cell is a control
#: when its object's ``made_by.attack`` (any size or seed, e.g. the sweep's ``benign-sphere-r0.20``) or its attack
#: name is one of these.
CONTROLS: tuple[str, ...] = ("benign-sphere", "random-shape")
#: :func:`role` values.
ROLES = ("clean", "control", "attack")


def _object(cell: Mapping[str, Any]) -> Mapping[str, Any]:
    """The cell's object record (``config.attack.object.object``; empty for an attack without an object)."""
    obj = _get(CellResult(cell).config, "attack", "object", "object")
    return obj if isinstance(obj, Mapping) else {}


def role(cell: Mapping[str, Any]) -> str:
    """``clean`` (attack ``none``), ``control`` (:data:`CONTROLS`) or ``attack`` (every other attack: an object
    trained against a victim, an object file, an attack without an object)."""
    r = CellResult(cell)
    if r.attack == CLEAN_ATTACK:
        return "clean"
    made = _object(cell).get("made_by")
    kind = made.get("attack") if isinstance(made, Mapping) else None
    return "control" if r.attack in CONTROLS or kind in CONTROLS else "attack"


def trained_against(cell: Mapping[str, Any]) -> str | None:
    """The victim the cell's attack object was optimised against (its sidecar's ``made_by.victim``, a record with
    a ``name`` or a bare name), or None (clean cell, controls, an object file made otherwise)."""
    made = _object(cell).get("made_by")
    victim = made.get("victim") if isinstance(made, Mapping) else None
    name = victim.get("name") if isinstance(victim, Mapping) else victim
    return name if isinstance(name, str) and name else None


def ap_column(metric: str, recall: str, difficulty: str) -> str:
    return f"{metric}_{recall}_{difficulty}"


def effect_column(what: str, recall: str) -> str:
    return f"{what}_{recall}"


def _number(get: Callable[..., Any], *args: str) -> float:
    """``get(*args)`` as a float; NaN where the cell has no such value (None, or :class:`LookupError`)."""
    try:
        value = get(*args)
    except LookupError:
        return float("nan")
    return float("nan") if value is None else float(value)


def _effect_columns(r: CellResult, row: dict[str, Any]) -> None:
    """The attack metrics' columns of ``row`` (their ``report`` columns, at the headline's metric and difficulty;
    NaN for a cell that is not ``ok``), with the AP interval's after the ``ap`` metrics of each recall sampling."""
    nan = float("nan")
    for recall in RECALLS:
        where = (CLASS, HEADLINE.metric, recall, HEADLINE.difficulty)
        for m in of_kind("ap"):
            if m.report is not None:
                row[effect_column(m.report.key, recall)] = _number(r.effect_value, m.name, *where) if r.ok else nan
        for key, bounds in (("ci", cell_ci(r.cell, *where[1:])),
                            *((m.report.key, _interval(r.interval(*where, table=m.name)) if r.ok else None)
                              for m in of_kind("interval") if m.report is not None)):
            row[effect_column(f"{key}_low", recall)] = nan if bounds is None else bounds[0]
            row[effect_column(f"{key}_high", recall)] = nan if bounds is None else bounds[1]
    for m in of_kind("cell"):
        if m.report is not None:
            row[m.report.key] = _number(r.effect_value, m.name) if r.ok else nan


def table(section: Section) -> Any:
    """One row per cell: identity, status, BEV and 3D AP (R40 and R11, E/M/H); the attack metrics' columns
    (:data:`robustbench3d.metrics.ATTACK_METRICS`: clean AP, drop and relative drop of BEV moderate, R40 and R11;
    attack success rate; the interval of the drop where recorded) and the interval of BEV moderate AP where
    recorded; flags; the object's training victim and where the numbers come from. A pandas DataFrame (AP in
    percent, relative drop and ASR as fractions, NaN where there is no value)."""
    import pandas as pd

    rows = []
    nan = float("nan")
    for rc in section.cells:
        r = CellResult(rc.cell)
        row: dict[str, Any] = {"run": str(rc.run), "cell": rc.name, "victim": r.victim, "attack": r.attack,
                               "proposals": r.proposals, "status": r.status, "reason": r.reason or "",
                               "trained_against": trained_against(rc.cell) or "", "source": rc.source}
        for metric in METRICS:
            for recall in RECALLS:
                for d in DIFFICULTIES:
                    row[ap_column(metric, recall, d)] = _number(r.ap, CLASS, metric, recall, d) if r.ok else nan
        _effect_columns(r, row)
        row["flags"] = [(str(f.get("code", "?")), str(f.get("message", ""))) for f in r.flags
                        if isinstance(f, Mapping)]
        rows.append(row)
    return pd.DataFrame(rows)


@dataclass(frozen=True)
class TransferRow:
    """A row of the transfer matrix: an attack object (the cells' attack name), the victim it was trained against
    (None: an object file made otherwise, or an attack without an object) and whether it places an object file."""

    object: str
    trained_against: str | None
    has_file: bool

    @property
    def label(self) -> str:
        """``victim · object``; ``(object file) · object`` or ``(no object) · object`` without a training victim."""
        who = self.trained_against or ("(object file)" if self.has_file else "(no object)")
        return f"{who} · {self.object}"


@dataclass(frozen=True)
class TransferEntry:
    """One entry of the transfer matrix: ``value`` the relative drop of the headline AP (a fraction), or None
    and ``note`` why (:data:`NOT_RUN`, ``clean AP 0``, ``no clean cell``, the cell's status); ``white_box``: the
    evaluated victim is the one the object was trained against; ``cell``: the cell's name (None when not run)."""

    value: float | None
    note: str
    white_box: bool
    cell: str | None = None

    @property
    def text(self) -> str:
        """The relative drop in percent (one decimal), or the note."""
        return self.note if self.value is None else f"{100 * self.value:.1f}"


#: What the transfer matrix and the worst case say of an (object, victim) pair without a cell.
NOT_RUN = "not run"


@dataclass(frozen=True)
class TransferGrid:
    """The transfer matrix of one proposal source: every attack object of the cells (rows) on every victim of the
    cells (columns, in order of first appearance); a pair without a cell is :data:`NOT_RUN`."""

    proposals: str
    rows: tuple[TransferRow, ...]
    victims: tuple[str, ...]
    entries: Mapping[tuple[str, str], TransferEntry]

    def entry(self, row: TransferRow, victim: str) -> TransferEntry:
        """The entry of ``row`` on ``victim`` (:data:`NOT_RUN` where there is no cell)."""
        found = self.entries.get((row.object, victim))
        return found if found is not None else TransferEntry(None, NOT_RUN, row.trained_against == victim)

    def values(self) -> Any:
        """A DataFrame: rows (victim trained against or "", object), columns the victims, values the relative
        drop (fraction; NaN where :meth:`entry` has a note instead)."""
        import pandas as pd

        index = pd.MultiIndex.from_tuples([(r.trained_against or "", r.object) for r in self.rows],
                                          names=["trained_against", "object"])
        data = [[float("nan") if (e := self.entry(r, v)).value is None else e.value for v in self.victims]
                for r in self.rows]
        return pd.DataFrame(data, index=index, columns=pd.Index(self.victims, name="evaluated"), dtype="float64")


def _transfer_entry(c: Mapping[str, Any], white_box: bool, metric: str, recall: str, difficulty: str
                    ) -> TransferEntry:
    r = CellResult(c)
    if not r.ok:
        return TransferEntry(None, r.status, white_box, r.name)
    if not r.effect:
        return TransferEntry(None, "no clean cell", white_box, r.name)
    try:
        value = r.drop(CLASS, metric, recall, difficulty, relative=True)
    except LookupError:
        return TransferEntry(None, "no such AP", white_box, r.name)
    return TransferEntry(None if value is None else float(value), "clean AP 0" if value is None else "", white_box,
                         r.name)


def transfer_grids(cells: Iterable[Mapping[str, Any]], metric: str = HEADLINE.metric, recall: str = HEADLINE.recall,
                   difficulty: str = HEADLINE.difficulty) -> list[TransferGrid]:
    """The transfer matrix of each proposal source of ``cells`` (in order of first appearance), each over every
    attack object (:func:`role` ``attack``) and every victim of ``cells``, whatever the proposal source. Rows are
    ordered by the column of the victim they were trained against (objects trained against a victim that is not
    a column, then those without one, last), then by first appearance. The same (object, victim, proposals) twice
    with different results, or one object name standing for two object files, is refused."""
    cells = list(cells)
    victims = tuple(dict.fromkeys(CellResult(c).victim for c in cells))
    objects: dict[str, TransferRow] = {}
    shas: dict[str, Any] = {}
    entries: dict[str, dict[tuple[str, str], TransferEntry]] = {}
    for c in cells:
        r = CellResult(c)
        entries.setdefault(r.proposals, {})
        if role(c) != "attack":
            continue
        sha = _object(c).get("ply_sha256")
        if shas.setdefault(r.attack, sha) != sha:
            raise RobustBenchError(f"report: attack {r.attack!r} names two different object files "
                                   f"({shas[r.attack]} and {sha}); report their runs separately")
        row = objects.setdefault(r.attack, TransferRow(r.attack, trained_against(c), sha is not None))
        entry = _transfer_entry(c, row.trained_against == r.victim, metric, recall, difficulty)
        known = entries[r.proposals].setdefault((r.attack, r.victim), entry)
        if (known.value, known.note) != (entry.value, entry.note):
            raise RobustBenchError(f"report: two cells evaluate object {r.attack!r} on {r.victim} with "
                                   f"{r.proposals} proposals with different results")
    first = {name: i for i, name in enumerate(objects)}

    def order(row: TransferRow) -> tuple[int, int]:
        if row.trained_against is None:
            return len(victims) + 1, first[row.object]
        column = victims.index(row.trained_against) if row.trained_against in victims else len(victims)
        return column, first[row.object]

    rows = tuple(sorted(objects.values(), key=order))
    return [TransferGrid(p, rows, victims, e) for p, e in entries.items()]


def transfer_matrix(cells: Iterable[Mapping[str, Any]], proposals: str, metric: str = HEADLINE.metric,
                    recall: str = HEADLINE.recall, difficulty: str = HEADLINE.difficulty) -> Any:
    """The transfer matrix of one proposal source as numbers (:meth:`TransferGrid.values`); empty (no rows) when
    no cell with those proposals runs an attack object."""
    import pandas as pd

    grid = next((g for g in transfer_grids(cells, metric, recall, difficulty) if g.proposals == proposals), None)
    return pd.DataFrame() if grid is None or not grid.entries else grid.values()
