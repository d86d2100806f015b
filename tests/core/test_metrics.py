"""The attack metrics' table (robustbench3d.metrics): the definitions by hand, the schema holding every metric, a
new metric needing only its entry; the shared words (difficulties, target class) defined once; the readers of
summaries going through CellResult (issue #38)."""

from __future__ import annotations

import ast
import copy
import json
from pathlib import Path

import numpy as np
import pytest
from cell_builders import hand_provenance

import robustbench3d
from robustbench3d import metrics
from robustbench3d.metrics import (
    ATTACK_METRICS,
    HEADLINE,
    AttackMetric,
    ReportColumn,
    ap_tables,
    clean_reference,
    drop,
    paired_interval,
    relative_drop,
)
from robustbench3d.results import AP_COLUMNS, CSV_COLUMNS, APResult, CellResult, long_csv_text, long_rows

ROOT = Path(__file__).resolve().parents[2]
#: Read as a plain file, not through robustbench3d.results.load_schema.
SCHEMA_FILE = Path(robustbench3d.__file__).parent / "schemas" / "summary.schema.json"
SHA = "cd" * 32
DIFFS = ("easy", "moderate", "hard")


def _by_diff(values: tuple) -> dict:
    return dict(zip(DIFFS, values, strict=True))


def _evaluation(bev40: tuple, bev11: tuple, with_3d: bool = True) -> dict:
    """The evaluator's JSON for Car: BEV AP (percent) by hand; 3D AP = BEV AP when ``with_3d``."""
    car = {"bev": {"R40": _by_diff(bev40), "R11": _by_diff(bev11)}}
    if with_3d:
        car["3d"] = copy.deepcopy(car["bev"])
    metric_names = ["bev", "3d"] if with_3d else ["bev"]
    return {"Car": car, "meta": {"evaluator": "robustbench3d.eval", "version": "1", "ap_unit": "percent",
                                 "frames": 4, "classes": ["Car"], "metrics": metric_names,
                                 "min_overlap": {"Car": {m: 0.7 for m in metric_names}}}}


CLEAN = _evaluation((80.0, 64.0, 50.0), (81.0, 66.0, 52.0))
ATTACKED = _evaluation((60.0, 48.0, 40.0), (62.0, 55.0, 41.0), with_3d=False)


def _cell(attack: str, evaluation: dict, effect: dict | None = None) -> dict:
    cell = {"schema_version": 1, "victim": "v", "attack": attack, "proposals": "detector", "status": "ok",
            "reason": None, "dataset": {"root": "/d", "split": "val", "frames": 4, "split_frames": 4, "sha256": SHA,
                                        "embedded": None, "manifest": None},
            "metrics": evaluation, "provenance": hand_provenance("v", attack, "detector", SHA)}
    if effect is not None:
        cell["attack_effect"] = effect
    return cell


def _table(r40: tuple, r11: tuple) -> dict:
    return {"Car": {"bev": {"R40": _by_diff(r40), "R11": _by_diff(r11)}}}


#: The attacked cell's effect as a run records it, by hand: drop = clean - attacked, relative = drop / clean,
#: 3 of the 8 Cars matched clean missed attacked; the paired drop's interval at BEV moderate.
EFFECT = {
    "clean_cell": "v+none+detector", "clean_fingerprint": SHA,
    "clean": _table((80.0, 64.0, 50.0), (81.0, 66.0, 52.0)),
    "drop": _table((20.0, 16.0, 10.0), (19.0, 11.0, 11.0)),
    "relative_drop": _table((0.25, 0.25, 0.2), (19 / 81, 1 / 6, 11 / 52)),
    "success": {"class": "Car", "metric": "bev", "iou": 0.7, "difficulty": "moderate", "score_threshold": 0.5,
                "clean_matched": 8, "attacked_missed": 3, "rate": 0.375},
    "drop_ci": {"Car": {"bev": {"R40": {"moderate": [12.0, 19.5]}}},
                "meta": {"method": "m", "statistic": "s", "level": 0.95, "resamples": 10, "seed": 0, "frames": 4,
                         "rng": "r"}},
}


# ---- the definitions and the schema ---------------------------------------------------------------------------

def test_every_attack_metric_is_a_field_of_the_schemas_attack_effect():
    effect = json.loads(SCHEMA_FILE.read_text(encoding="utf-8"))["$defs"]["attack_effect"]
    missing = [name for name in ATTACK_METRICS if name not in effect["properties"]]
    assert not missing, (f"{SCHEMA_FILE}: $defs.attack_effect.properties has no entry for attack metric(s) "
                         f"{missing} of robustbench3d.metrics.ATTACK_METRICS: add one for each")
    measured = [m.name for m in ATTACK_METRICS.values() if m.kind != "interval"]
    assert set(measured) <= set(effect["required"]), f"{SCHEMA_FILE}: every measured metric is required"
    unknown = set(effect["properties"]) - set(ATTACK_METRICS) - {"clean_cell", "clean_fingerprint"}
    assert not unknown, f"{SCHEMA_FILE}: attack_effect fields that are no attack metric: {sorted(unknown)}"


def test_each_entry_is_complete():
    for name, m in ATTACK_METRICS.items():
        assert m.name == name and m.kind in metrics.KINDS and m.unit in metrics.UNITS and m.description
        if m.kind == "interval":
            assert m.of in ATTACK_METRICS and ATTACK_METRICS[m.of].kind == "ap", name
        else:
            assert callable(m.compute), name
        if m.kind == "cell":
            assert m.value_key, name


def test_the_definitions_by_hand():
    assert drop(80.0, 60.0) == 20.0 and drop(50.0, 55.0) == -5.0
    assert relative_drop(80.0, 60.0) == 0.25 and relative_drop(64.0, 80.0) == -0.25
    assert relative_drop(0.0, 0.0) is None and relative_drop(0.0, 3.0) is None  # undefined from a clean AP of 0
    assert clean_reference(80.0, 60.0) == 80.0
    assert np.array_equal(drop(np.array([3.0, 4.0]), np.array([1.0, 5.0])), [2.0, -1.0])  # the paired bootstrap's
    assert HEADLINE == ("Car", "bev", "R40", "moderate")


def test_ap_tables_cover_every_ap_both_evaluations_have():
    tables = ap_tables(APResult(CLEAN), APResult(ATTACKED))
    assert list(tables) == ["clean", "drop", "relative_drop"]
    assert tables["clean"] == _table((80.0, 64.0, 50.0), (81.0, 66.0, 52.0))  # no 3D: the attacked cell has none
    assert tables["drop"] == _table((20.0, 16.0, 10.0), (19.0, 11.0, 11.0))
    assert tables["relative_drop"]["Car"]["bev"]["R40"] == {"easy": 0.25, "moderate": 0.25, "hard": 0.2}
    assert tables["relative_drop"]["Car"]["bev"]["R11"]["moderate"] == pytest.approx(1 / 6)


def test_paired_interval_is_the_percentile_interval_of_the_paired_drops():
    key = ("Car", "bev", "R40", "moderate")
    clean = {key: np.array([50.0, 60.0, 70.0, 80.0]), ("Car", "bev", "R40", "easy"): np.array([1.0, 2.0, 3.0, 4.0])}
    attacked = {key: np.array([40.0, 55.0, 70.0, 60.0])}
    table = paired_interval(ATTACK_METRICS["drop_ci"], clean, attacked, frames=4, resamples=4, seed=3)
    # drops 10, 5, 0, 20 -> sorted 0 5 10 20; 2.5th and 97.5th percentiles by linear interpolation (numpy's):
    # positions 0.075 and 2.925 -> 0 + 0.075 * 5 and 10 + 0.925 * 10
    assert table["Car"]["bev"]["R40"] == {"moderate": pytest.approx([0.375, 19.25])}
    assert (table["meta"]["resamples"], table["meta"]["seed"], table["meta"]["frames"]) == (4, 3, 4)
    with pytest.raises(ValueError, match="not an interval"):
        paired_interval(ATTACK_METRICS["drop"], clean, attacked, 4, 4, 3)


def test_the_csv_columns_are_the_aps_then_the_metrics():
    assert CSV_COLUMNS == ("victim", "attack", "proposals", "class", "metric", "iou", "recall_points", "difficulty",
                           "ap", "clean_ap", "ap_drop", "relative_drop", "attack_success_rate")
    assert CSV_COLUMNS[:len(AP_COLUMNS)] == AP_COLUMNS


def test_cell_result_reads_every_kind_of_metric():
    cell = CellResult(_cell("adv", ATTACKED, EFFECT))
    assert cell.effect_value("drop") == 16.0
    assert cell.effect_value("relative_drop", recall="R11") == pytest.approx(1 / 6)
    assert cell.effect_value("success") == 0.375 == cell.attack_success_rate
    assert cell.interval(table="drop_ci") == [12.0, 19.5]
    assert cell.interval(difficulty="easy", table="drop_ci") is None
    assert cell.interval() is None  # no metrics_ci
    with pytest.raises(LookupError, match="unknown attack metric 'asr'"):
        cell.effect_value("asr")
    with pytest.raises(LookupError, match="interval"):
        cell.effect_value("drop_ci")
    with pytest.raises(LookupError, match="no drop for class 'Car' metric '3d'"):
        cell.effect_value("drop", metric="3d")
    clean = CellResult(_cell("none", CLEAN))
    with pytest.raises(LookupError, match="no clean-cell comparison"):
        clean.effect_value("clean")
    assert clean.attack_success_rate is None and clean.clean_cell is None
    assert (cell.name, cell.fingerprint, cell.seed, cell.frames) == ("v+adv+detector", SHA, 0, 4)


# ---- a new metric: one entry ----------------------------------------------------------------------------------

def test_a_new_ap_metric_needs_only_its_entry(monkeypatch, tmp_path):
    """An ``ap`` metric added to the table is computed, read by CellResult, written to the CSV and shown by the
    report with no other change (the schema needs its field too: the schema test above)."""
    from robustbench3d.report import data as rdata
    from robustbench3d.report.view import columns

    ratio = AttackMetric("ratio", "ap", "fraction", "attacked AP / clean AP", lambda c, a: a / c if c > 0 else None,
                         column="ap_ratio", report=ReportColumn("ratio", "ratio %", "percent", "attacked / clean"))
    monkeypatch.setitem(metrics.ATTACK_METRICS, "ratio", ratio)
    tables = ap_tables(APResult(CLEAN), APResult(ATTACKED))
    assert tables["ratio"]["Car"]["bev"]["R40"] == {"easy": 0.75, "moderate": 0.75, "hard": 0.8}  # 60/80 48/64 40/50
    effect = {**EFFECT, "ratio": tables["ratio"]}
    cells = [_cell("none", CLEAN), _cell("adv", ATTACKED, effect)]
    assert CellResult(cells[1]).effect_value("ratio") == 0.75
    row = next(r for r in long_rows(cells) if r["attack"] == "adv" and r["recall_points"] == 40
               and r["difficulty"] == "hard")
    assert (row["ap_drop"], row["ap_ratio"]) == (10.0, 0.8)
    header = long_csv_text(long_rows(cells)).splitlines()[0].split(",")
    assert header[-1] == "ap_ratio"
    section = rdata.Section(key={}, cells=[rdata.RunCell(tmp_path, i, c) for i, c in enumerate(cells)])
    frame = rdata.table(section)
    assert frame["ratio_R40"].iloc[1] == 0.75 and np.isnan(frame["ratio_R40"].iloc[0])
    assert "ratio %" in [c.title for c in columns(False, False, False)]


# ---- shared words, defined once -------------------------------------------------------------------------------

def _package_files() -> list[Path]:
    """Every module of the package (robustbench3d/, and eval/, attacks/, victims/ as mapped into it)."""
    return sorted(p for d in ("robustbench3d", "eval", "attacks", "victims") for p in (ROOT / d).rglob("*.py"))


def _strings(node: ast.AST) -> list[str] | None:
    """The strings of a tuple, list or set literal, or a dict literal's keys, if every one is a string."""
    items = node.keys if isinstance(node, ast.Dict) else getattr(node, "elts", None)
    if not isinstance(node, ast.Tuple | ast.List | ast.Set | ast.Dict) or not items:
        return None
    if not all(isinstance(e, ast.Constant) and isinstance(e.value, str) for e in items):
        return None
    return [e.value for e in items]  # type: ignore[union-attr]


def test_the_difficulties_are_listed_once():
    """Only eval/rules.py spells out easy, moderate, hard as a list (others import DIFFICULTIES)."""
    found = [f"{p.relative_to(ROOT)}:{node.lineno}" for p in _package_files()
             for node in ast.walk(ast.parse(p.read_text(encoding="utf-8")))
             if _strings(node) == ["easy", "moderate", "hard"]]
    assert found == [f"eval/rules.py:{_line_of(ROOT / 'eval/rules.py', 'DIFFICULTIES: tuple')}"], found


def _line_of(path: Path, text: str) -> int:
    return next(n for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1) if line.startswith(text))


#: Modules that name the benchmark's target class: each takes it from eval.rules.TARGET_CLASS (or metrics.HEADLINE).
#: Not checked: KITTI's own type vocabulary (kitti/, synth/, the evaluator's devkit tables in eval/rules.py), the
#: evaluator's benchmarks and test fixtures (eval/bench*.py, testing.py), sensors/, attacks/ and victims/ (their
#: TARGET_TYPES), draw.py (colours per KITTI type) and ``victims train-fpointnet``'s ``--types`` (KITTI types).
TARGET_CLASS_READERS = (
    "robustbench3d/results.py", "robustbench3d/metrics.py", "robustbench3d/gate.py", "robustbench3d/seed_table.py",
    "robustbench3d/pytest_plugin.py", "robustbench3d/dataset_stats.py", "robustbench3d/api.py",
    "robustbench3d/report", "robustbench3d/runner", "robustbench3d/tradeoff",
    "eval/matches.py", "eval/kitti_eval.py", "eval/bootstrap.py", "eval/report.py",
    *(f"robustbench3d/commands/{p.name}" for p in sorted((ROOT / "robustbench3d/commands").glob("*.py"))
      if p.name != "victims_train_fpointnet.py"),
)


def _files(entries: tuple[str, ...]) -> list[Path]:
    return sorted(p for e in entries for p in ([ROOT / e] if e.endswith(".py") else (ROOT / e).rglob("*.py")))


def test_the_target_class_is_written_once():
    found = [f"{p.relative_to(ROOT)}:{node.lineno}" for p in _files(TARGET_CLASS_READERS)
             for node in ast.walk(ast.parse(p.read_text(encoding="utf-8")))
             if isinstance(node, ast.Constant) and node.value == "Car"]
    assert not found, f"'Car' written out (use robustbench3d.eval.rules.TARGET_CLASS): {found}"


# ---- summaries read through CellResult ------------------------------------------------------------------------

#: The modules that read summary cells (runner/effect.py, which writes ``attack_effect`` and ``metrics_ci``, aside).
CELL_READERS = (
    "robustbench3d/gate.py", "robustbench3d/seed_table.py", "robustbench3d/pytest_plugin.py", "robustbench3d/report",
    "robustbench3d/commands/victims_pack.py", "robustbench3d/runner/flags.py", "robustbench3d/runner/collect.py",
    "robustbench3d/runner/grid.py",
    "robustbench3d/runner/outcome.py", "robustbench3d/runner/table.py",
)
#: A cell's nested records, read through CellResult's accessors.
NESTED = {"metrics", "attack_effect", "metrics_ci", "provenance"}


def _nested_reads(path: Path) -> list[str]:
    out = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        key = None
        if isinstance(node, ast.Subscript) and isinstance(node.ctx, ast.Load) and isinstance(node.slice, ast.Constant):
            key = node.slice.value
        elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "get"
              and node.args and isinstance(node.args[0], ast.Constant)):
            key = node.args[0].value
        if key in NESTED:
            out.append(f"{path.relative_to(ROOT)}:{node.lineno} [{key!r}]")
    return out


def test_summary_cells_are_read_through_cell_result():
    found = [hit for p in _files(CELL_READERS) for hit in _nested_reads(p)]
    assert not found, f"a cell's nested record indexed by hand (use robustbench3d.results.CellResult): {found}"
