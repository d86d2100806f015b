"""Summary schema (shipped as package data), validation errors, and the long-format CSV."""

from __future__ import annotations

import copy
import csv
import io
import json
import math
from pathlib import Path

import pytest

from robustbench3d.errors import DataFormatError
from robustbench3d.results import (
    CSV_COLUMNS,
    RECALL_POINTS,
    APResult,
    CellResult,
    load_schema,
    long_csv_text,
    long_rows,
    read_summary,
    schema_errors,
    validate_summary,
    write_validated,
)

REPO = Path(__file__).resolve().parents[2]
SHA = "ab" * 32


def ap_table(easy: float, moderate: float, hard: float) -> dict:
    return {"easy": easy, "moderate": moderate, "hard": hard}


def valid_cell() -> dict:
    """A hand-written ``ok`` cell with Car BEV and 3D AP."""
    return {
        "schema_version": 1, "victim": "lidar-cluster", "attack": "none", "proposals": "detector",
        "status": "ok", "reason": None,
        "dataset": {"root": "/data/kitti", "split": "val", "frames": 3769, "split_frames": 3769, "sha256": SHA,
                    "embedded": None, "manifest": None},
        "metrics": {
            "Car": {"bev": {"R40": ap_table(85.5, 80.25, 75.0), "R11": ap_table(86.0, 81.0, 76.5)},
                    "3d": {"R40": ap_table(70.0, 60.0, 50.0), "R11": ap_table(71.0, 61.0, 51.0)}},
            "meta": {"evaluator": "robustbench3d.eval", "version": "1.0.0", "ap_unit": "percent", "frames": 3769,
                     "classes": ["Car"], "metrics": ["bev", "3d"], "min_overlap": {"Car": {"bev": 0.7, "3d": 0.7}}},
        },
        "provenance": {
            "fingerprint": SHA,
            "config": {"victim": {"name": "lidar-cluster", "origin": "in-tree", "kwargs": {}, "capabilities": None,
                                  "weights_sha256": None, "weight_files": {}},
                       "attack": {"name": "none", "origin": "in-tree", "params": {}, "object": {},
                                  "requirements": {"needs_gradients": False, "needs_camera": False,
                                                   "needs_lidar": False}},
                       "proposals": "detector", "dataset": {}, "seed": 0, "batch_size": 4, "evaluation": {}},
            "run": {"victims": ["lidar-cluster"], "attacks": ["none"], "proposals": ["detector"]},
            "package": {"name": "robustbench3d", "version": "0.1.0"}, "git": {"commit": None, "dirty": None},
            "versions": {"python": "3.11.7", "numpy": "2.4.6", "torch": None, "onnxruntime": None},
            "platform": {"system": "Linux", "machine": "x86_64", "cpu": None, "cpu_count": 2},
            "seed": 0, "determinism": {}, "started": "2026-01-01T00:00:00Z", "finished": "2026-01-01T00:01:00Z",
            "seconds": 60.0,
        },
    }


def skipped_cell() -> dict:
    cell = valid_cell()
    cell.update(proposals="gt", status="skipped", reason="victim supports proposals detector only", metrics=None)
    return cell


def test_valid_summary_passes():
    summary = [valid_cell(), skipped_cell()]
    assert schema_errors(summary) == []
    validate_summary(summary)
    validate_summary(valid_cell(), cell_only=True)


def test_string_ap_is_rejected_naming_file_and_json_path():
    cell = valid_cell()
    cell["metrics"]["Car"]["bev"]["R40"]["easy"] = "85.5"
    with pytest.raises(DataFormatError) as err:
        validate_summary([cell], "runs/a/summary.json")
    msg = str(err.value)
    assert msg.startswith("runs/a/summary.json: field '$[0].metrics.Car.bev.R40.easy'"), msg
    assert "'85.5' is not of type 'number'" in msg


def test_missing_provenance_is_rejected():
    cell = valid_cell()
    del cell["provenance"]
    with pytest.raises(DataFormatError, match="'provenance' is a required property"):
        validate_summary([cell])


@pytest.mark.parametrize("mutate, problem", [
    (lambda c: c["metrics"]["Car"]["bev"]["R11"].update(hard=100.5), "greater than the maximum of 100"),
    (lambda c: c["metrics"]["Car"]["bev"]["R11"].pop("hard"), "'hard' is a required property"),
    (lambda c: c["metrics"]["Car"].update(bev2=c["metrics"]["Car"]["bev"]), "bev2"),
    (lambda c: c.update(metrics=None), "None is not of type 'object'"),
    (lambda c: c.update(reason="why not"), "'why not' is not of type 'null'"),
    (lambda c: c.update(status="done"), "'done' is not one of"),
    (lambda c: c["dataset"].update(sha256="xyz"), "does not match"),
    (lambda c: c["provenance"].update(seed="0"), "'0' is not of type 'integer'"),
    (lambda c: c["provenance"]["git"].update(commit="HEAD"), "commit"),
    (lambda c: c.update(extra=1), "Additional properties are not allowed"),
])
def test_malformed_ok_cells_are_rejected(mutate, problem):
    cell = valid_cell()
    mutate(cell)
    errors = schema_errors([cell])
    assert errors and any(problem in e for e in errors), errors


def test_skipped_cell_needs_reason_and_no_metrics():
    cell = skipped_cell()
    cell["reason"] = None
    assert any("None is not of type 'string'" in e for e in schema_errors([cell]))
    cell = skipped_cell()
    cell["metrics"] = valid_cell()["metrics"]
    assert any("is not of type 'null'" in e for e in schema_errors([cell]))


def test_summary_must_be_a_list(tmp_path):
    with pytest.raises(DataFormatError, match="is not of type 'array'"):
        validate_summary(valid_cell())
    bad = tmp_path / "summary.json"
    bad.write_text("[{")
    with pytest.raises(DataFormatError, match=r"summary\.json: not valid JSON"):
        read_summary(bad)


def test_write_validated_checks_what_lands_on_disk(tmp_path):
    path = tmp_path / "summary.json"
    cell = valid_cell()
    cell["metrics"]["Car"]["bev"]["R40"]["easy"] = math.nan
    with pytest.raises(ValueError, match="not JSON compliant"):
        write_validated(path, [cell])
    cell["metrics"]["Car"]["bev"]["R40"]["easy"] = "1"
    with pytest.raises(DataFormatError):
        write_validated(path, [cell])
    assert not path.exists()
    data = write_validated(path, [valid_cell()])
    assert read_summary(path) == data == json.loads(json.dumps([valid_cell()]))


def test_long_rows_one_per_ap_value_of_ok_cells():
    cells = [valid_cell(), skipped_cell()]
    rows = long_rows(cells)
    assert len(rows) == 2 * 2 * 3  # metrics x recall samplings x difficulties; the skipped cell adds none
    first = rows[0]
    assert first == {"victim": "lidar-cluster", "attack": "none", "proposals": "detector", "class": "Car",
                     "metric": "bev", "iou": 0.7, "recall_points": 40, "difficulty": "easy", "ap": 85.5,
                     "clean_ap": None, "ap_drop": None, "relative_drop": None, "attack_success_rate": None}
    by_key = {(r["metric"], r["recall_points"], r["difficulty"]): r["ap"] for r in rows}
    assert by_key[("bev", 11, "hard")] == 76.5
    assert by_key[("3d", 40, "moderate")] == 60.0


def test_cell_result_reads_ap_values_by_name():
    ok, skipped = CellResult(valid_cell()), CellResult(skipped_cell())
    assert (ok.victim, ok.attack, ok.proposals, ok.status, ok.reason, ok.frames) == (
        "lidar-cluster", "none", "detector", "ok", None, 3769)
    assert ok.ap("Car", "bev", "R11", "hard") == 76.5 and ok.ap("Car", "3d", "R40", "moderate") == 60.0
    assert ok.result.classes == ("Car",) and ok.result.metrics("Car") == ("bev", "3d")
    assert ok.result.metrics("Pedestrian") == () and ok.result.iou("Car", "3d") == 0.7
    values = list(ok.result.values())
    assert [tuple(v) for v in values[:4]] == [
        ("Car", "bev", "R40", "easy", 85.5), ("Car", "bev", "R40", "moderate", 80.25),
        ("Car", "bev", "R40", "hard", 75.0), ("Car", "bev", "R11", "easy", 86.0)]
    assert len(values) == 12 and values[-1] == ("Car", "3d", "R11", "hard", 51.0)
    assert RECALL_POINTS == {"R40": 40, "R11": 11}
    assert skipped.result is None
    with pytest.raises(LookupError, match="is skipped: no AP"):
        skipped.ap("Car", "bev", "R40", "easy")
    with pytest.raises(LookupError, match=r"no AP for class 'Car' metric '2d' \(evaluated: Car/bev, Car/3d\)"):
        ok.ap("Car", "2d", "R40", "easy")
    with pytest.raises(LookupError, match="unknown difficulty 'medium'"):
        ok.ap("Car", "bev", "R40", "medium")
    with pytest.raises(LookupError, match="unknown recall sampling 'R41'"):
        APResult(valid_cell()["metrics"]).ap("Car", "bev", "R41", "easy")


def test_csv_round_trips_exact_numbers():
    cell = valid_cell()
    cell["metrics"]["Car"]["bev"]["R40"]["moderate"] = 1 / 3 * 100
    text = long_csv_text(long_rows([cell]))
    reader = csv.DictReader(io.StringIO(text))
    assert tuple(reader.fieldnames) == CSV_COLUMNS
    parsed = list(reader)
    row = next(r for r in parsed
               if (r["metric"], r["recall_points"], r["difficulty"]) == ("bev", "40", "moderate"))
    assert float(row["ap"]) == 1 / 3 * 100


def test_schema_is_package_data_and_a_valid_draft_2020_12_schema():
    import jsonschema

    schema = load_schema()
    jsonschema.Draft202012Validator.check_schema(schema)
    on_disk = json.loads((REPO / "robustbench3d" / "schemas" / "summary.schema.json").read_text())
    assert schema == on_disk
    package_data = (REPO / "pyproject.toml").read_text().split("[tool.setuptools.package-data]", 1)[1]
    assert '"schemas/*.json"' in package_data.split("\n[", 1)[0]


def test_validation_does_not_mutate_the_summary():
    summary = [valid_cell()]
    before = copy.deepcopy(summary)
    validate_summary(summary)
    assert summary == before
