"""Trust, second pass (issue #32): the regression gate, the summary reader, ``parity`` and the victim
registry's errors. A NaN or Infinity anywhere in a summary is refused naming the field; ``check
--write-baseline`` never replaces a file without ``--force``; ``check --baseline DIR`` is one line;
``parity --onnx BADDIR`` fails before any model or dataset work; a plugin/in-tree name clash says what
to do (not ``--victim-arg``); numeric options and victim factory arguments are range-checked up front."""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from cell_builders import hand_provenance, write_run
from plugin_dists import write_dist

from robustbench3d.cli import main
from robustbench3d.errors import DataFormatError, RobustBenchError
from robustbench3d.gate import read_baseline
from robustbench3d.kitti import write_split
from robustbench3d.registry import Registry, RegistryError
from robustbench3d.results import read_summary, validate_summary
from robustbench3d.testing import write_kitti_frame
from robustbench3d.victims import create_victim
from robustbench3d.victims.shipped import weights_dir

SHA = "ab" * 32
DIFFS = ("easy", "moderate", "hard")
EVALUATION = {"evaluator": "robustbench3d.eval", "classes": ["Car"]}  # the cells' configured evaluation
CAR = "Car 0.00 0 -1.57 500.00 150.00 700.00 250.00 1.50 1.60 3.90 0.00 1.65 15.00 -1.57\n"


# ---- hand-made runs ----------------------------------------------------------------------------------
def _table(bev: tuple[float, float, float], d3: tuple[float, float, float]) -> dict:
    return {m: {r: dict(zip(DIFFS, v, strict=True)) for r in ("R40", "R11")} for m, v in (("bev", bev), ("3d", d3))}


def _cell(attack: str, bev: tuple[float, float, float], d3: tuple[float, float, float]) -> dict:
    """A schema-valid ok cell of victim "v", detector proposals."""
    return {
        "schema_version": 1, "victim": "v", "attack": attack, "proposals": "detector", "status": "ok", "reason": None,
        "dataset": {"root": "/data", "split": "val", "frames": 10, "split_frames": 10, "sha256": SHA,
                    "embedded": None, "manifest": None},
        "metrics": {"Car": _table(bev, d3),
                    "meta": {"evaluator": "robustbench3d.eval", "version": "1", "ap_unit": "percent", "frames": 10,
                             "classes": ["Car"], "metrics": ["bev", "3d"],
                             "min_overlap": {"Car": {"bev": 0.7, "3d": 0.7}}}},
        "provenance": hand_provenance("v", attack, "detector", SHA, weights_sha256=SHA, evaluation=EVALUATION),
    }


def summary() -> list[dict]:
    """Two cells whose AP values are all distinct, so one can be found in the text and edited."""
    return [_cell("none", (80.5, 64.25, 50.5), (70.5, 52.5, 40.5)),
            _cell("adv", (60.5, 48.5, 40.25), (58.5, 40.75, 30.5))]


def one_error_line(err: str) -> str:
    """The single ``robustbench3d: error:`` line of a refused command (no traceback)."""
    lines = [x for x in err.splitlines() if x.strip()]
    assert len(lines) == 1 and lines[0].startswith("robustbench3d: error: ") and "Traceback" not in err, err
    return lines[0]


# ---- 1. a NaN AP ---------------------------------------------------------------------------------------
# the clean cell's BEV R40 moderate AP (64.25) appears once in the summary's text, under this JSON path
NAN_FIELD = "$[0].metrics.Car.bev.R40.moderate"


@pytest.mark.parametrize("token", ["NaN", "Infinity", "-Infinity"])
def test_non_finite_ap_in_summary_is_refused_naming_the_field(tmp_path, capsys, token):
    run = write_run(tmp_path / "run", summary())
    text = (run / "summary.json").read_text()
    assert text.count('"moderate": 64.25') == 2  # R40 and R11 of the clean BEV table: edit the first
    (run / "summary.json").write_text(text.replace('"moderate": 64.25', f'"moderate": {token}', 1))
    with pytest.raises(DataFormatError) as exc:
        read_summary(run / "summary.json")
    assert exc.value.field == NAN_FIELD and token in exc.value.problem
    baseline = tmp_path / "baseline.json"
    assert main(["check", str(run), "--write-baseline", str(baseline)]) == 2  # was a ValueError traceback
    line = one_error_line(capsys.readouterr().err)
    assert f"{run / 'summary.json'}: field '{NAN_FIELD}': {token}" in line
    assert not baseline.exists()
    good = write_run(tmp_path / "good", summary())
    assert main(["check", str(good), "--write-baseline", str(baseline)]) == 0
    capsys.readouterr()
    assert main(["check", str(run), "--baseline", str(baseline)]) == 2
    assert f"field '{NAN_FIELD}'" in one_error_line(capsys.readouterr().err)


def test_report_refuses_a_nan_summary_instead_of_showing_a_dash(tmp_path, capsys):
    run = write_run(tmp_path / "run", summary())
    text = (run / "summary.json").read_text()
    (run / "summary.json").write_text(text.replace('"moderate": 64.25', '"moderate": NaN', 1))
    assert main(["report", str(run), "--out", str(tmp_path / "report")]) == 2
    assert f"field '{NAN_FIELD}'" in one_error_line(capsys.readouterr().err)


def test_in_memory_nan_fails_validation_naming_the_field():
    cells = summary()
    cells[1]["metrics"]["Car"]["3d"]["R11"]["hard"] = math.nan
    # NaN compares false with "minimum"/"maximum": the schema alone lets it through
    with pytest.raises(DataFormatError) as exc:
        validate_summary(cells, "mine.json")
    assert exc.value.field == "$[1].metrics.Car.3d.R11.hard" and str(exc.value).startswith("mine.json: ")
    cells[1]["metrics"]["Car"]["3d"]["R11"]["hard"] = -math.inf
    with pytest.raises(DataFormatError, match=r"field '\$\[1\]\.metrics\.Car\.3d\.R11\.hard'"):
        validate_summary(cells)


# ---- 2. --write-baseline never replaces a file without --force ------------------------------------------
def test_write_baseline_refuses_an_existing_file_unless_forced(tmp_path, capsys):
    run = write_run(tmp_path / "run", summary())
    out = tmp_path / "baseline.json"
    out.write_text("my notes\n")
    assert main(["check", str(run), "--write-baseline", str(out)]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert f"--write-baseline {out}: exists; pass --force" in line
    assert out.read_text() == "my notes\n"
    assert main(["check", str(run), "--write-baseline", str(out), "--force"]) == 0
    printed = capsys.readouterr().out.splitlines()
    assert printed[0] == f"replacing {out} (--force)"
    cells = read_baseline(out)["cells"]
    assert [(c["attack"], c["ap"]["bev"]["moderate"]) for c in cells] == [("none", 64.25), ("adv", 48.5)]
    # a new file: no replacing line
    fresh = tmp_path / "fresh.json"
    assert main(["check", str(run), "--write-baseline", str(fresh)]) == 0
    assert "replacing" not in capsys.readouterr().out and fresh.is_file()


def test_write_baseline_never_replaces_the_summary_it_reads(tmp_path, capsys):
    run = write_run(tmp_path / "run", summary())
    before = (run / "summary.json").read_bytes()
    assert main(["check", str(run), "--write-baseline", str(run / "summary.json"), "--force"]) == 2
    assert "is the run's summary being read" in one_error_line(capsys.readouterr().err)
    assert (run / "summary.json").read_bytes() == before


def test_force_without_write_baseline_is_refused(tmp_path, capsys):
    run = write_run(tmp_path / "run", summary())
    base = tmp_path / "b.json"
    assert main(["check", str(run), "--write-baseline", str(base)]) == 0
    assert main(["check", str(run), "--baseline", str(base), "--force"]) == 2
    assert "--force: applies to --write-baseline only" in one_error_line(capsys.readouterr().err)


# ---- 3. check --baseline DIR / missing / malformed ------------------------------------------------------
def test_baseline_that_is_a_directory_or_malformed_is_one_line(tmp_path, capsys):
    run = write_run(tmp_path / "run", summary())
    folder = tmp_path / "folder"
    folder.mkdir()
    assert main(["check", str(run), "--baseline", str(folder)]) == 2  # was an IsADirectoryError traceback
    assert one_error_line(capsys.readouterr().err) == f"robustbench3d: error: {folder}: is a directory, expected a file"
    broken = tmp_path / "broken.json"
    broken.write_text('{"format": "robustbench3d.baseline",\n "version": 1\n "cells": []}\n')
    assert main(["check", str(run), "--baseline", str(broken)]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert f"{broken}: not valid JSON" in line and "line 3" in line
    good = tmp_path / "good.json"
    assert main(["check", str(run), "--write-baseline", str(good)]) == 0
    capsys.readouterr()
    (run / "results.csv").write_text("victim\n")
    assert main(["check", str(run / "results.csv"), "--baseline", str(good)]) == 2
    assert one_error_line(capsys.readouterr().err) == (f"robustbench3d: error: {run / 'results.csv'}: is a file; "
                                                      "expected a run directory or its summary.json")


# ---- 4. parity --onnx BADDIR: checked before any model or dataset work -----------------------------------
@pytest.fixture
def no_parity_work(monkeypatch):
    """Make loading the torch victim or resolving the dataset fail the test: parity must refuse first."""
    def forbidden(*args, **kwargs):
        raise AssertionError("parity started work before checking its arguments")

    monkeypatch.setattr("robustbench3d.commands.victims_export_onnx.create_cascade", forbidden)
    monkeypatch.setattr("robustbench3d.datasets.resolve_dataset", forbidden)
    monkeypatch.setattr("robustbench3d.datasets.load_ground_truth", forbidden)


def shipped_onnx_copy(parent: Path) -> Path:
    src = weights_dir() / "fpointnet-v1-lite-onnx"
    if not (src / "manifest.json").is_file():
        pytest.skip("the shipped ONNX victim is not present")
    return Path(shutil.copytree(src, parent / "onnx"))


def parity_refusal(capsys, onnx: Path, *argv: str) -> str:
    """The one error line of ``parity fpointnet-v1-lite --onnx ONNX ARGV``, which must exit 2."""
    assert main(["parity", "fpointnet-v1-lite", "--onnx", str(onnx), *argv]) == 2
    return one_error_line(capsys.readouterr().err)


def test_parity_missing_onnx_dir_fails_before_any_work(tmp_path, capsys, no_parity_work):
    missing = tmp_path / "nowhere"
    line = parity_refusal(capsys, missing)
    assert line == f"robustbench3d: error: {missing}: ONNX victim directory not found"
    empty = tmp_path / "empty"
    empty.mkdir()
    assert f"{empty / 'manifest.json'}: manifest not found" in parity_refusal(capsys, empty)


def test_parity_onnx_dir_with_a_missing_or_changed_stage_fails_before_any_work(tmp_path, capsys, no_parity_work):
    onnx = shipped_onnx_copy(tmp_path)
    stage = onnx / "center_regression.onnx"
    stage.write_bytes(stage.read_bytes() + b"\0")
    assert f"{stage}: sha256 " in parity_refusal(capsys, onnx)
    stage.unlink()
    assert f"{stage}: stage 'center_regression' file missing" in parity_refusal(capsys, onnx)


def test_parity_json_is_not_replaced_without_force(tmp_path, capsys, no_parity_work):
    onnx = shipped_onnx_copy(tmp_path)
    report = tmp_path / "parity.json"
    report.write_text("{}\n")
    assert f"--json {report}: exists; pass --force" in parity_refusal(capsys, onnx, "--json", str(report))
    assert report.read_text() == "{}\n"


@pytest.mark.parametrize(("argv", "named"), [
    (["--max-frames", "0"], "--max-frames: 0 is out of range (an integer >= 1)"),
    (["--seed", "-1"], "--seed: -1 is out of range"),
])
def test_parity_numeric_options_are_checked_before_any_work(tmp_path, capsys, no_parity_work, argv, named):
    onnx = shipped_onnx_copy(tmp_path)
    assert named in parity_refusal(capsys, onnx, *argv)


def test_parity_unknown_victim_argument_is_one_line_before_loading(tmp_path, capsys, monkeypatch):
    onnx = shipped_onnx_copy(tmp_path)
    monkeypatch.setattr("robustbench3d.victims.zoo._cascade", lambda *a, **k: pytest.fail("weights loaded"))
    monkeypatch.setattr("robustbench3d.datasets.resolve_dataset", lambda *a, **k: pytest.fail("dataset resolved"))
    line = parity_refusal(capsys, onnx, "--victim-arg", "threads=2")  # was a TypeError traceback
    assert "victim 'fpointnet-v1-lite' takes no argument 'threads'" in line and "num_points" in line


# ---- 5. a plugin entry point clashing with an in-tree victim ---------------------------------------------
def test_in_tree_clash_names_the_plugin_to_rename(tmp_path, monkeypatch):
    site = tmp_path / "site"
    write_dist(site, "rb3d-clash", "1.0", {"taken": "rb3d_clash_mod:SPEC"})
    monkeypatch.syspath_prepend(str(site))
    reg: Registry[dict] = Registry("victim", group="robustbench3d.victims")
    reg.register("taken", {"label": "in-tree"})
    with pytest.raises(RegistryError) as exc:
        reg.get("taken")
    message = str(exc.value)
    assert "the plugin must rename its entry point" in message and "uninstall 'rb3d-clash'" in message
    assert "'taken = rb3d_clash_mod:SPEC'" in message
    assert "uninstall one" not in message and "(loaded)" not in message  # the in-tree one cannot be uninstalled


def test_run_with_a_clashing_plugin_gives_no_victim_arg_hint(tmp_path, cache):
    data = tmp_path / "data"
    rng = np.random.default_rng(0)
    write_kitti_frame(data, "000000", labels=CAR,
                      scan=np.concatenate([rng.uniform(-20, 20, (300, 3)), rng.uniform(0, 1, (300, 1))], axis=1))
    write_split(data / "ImageSets" / "val.txt", ["000000"])
    site = tmp_path / "site"
    write_dist(site, "rb3d-clash", "1.0", {"fpointnet-v1-lite": "rb3d_clash_mod:SPEC"})
    (site / "rb3d_clash_mod.py").write_text("SPEC = None\n")
    env = {**os.environ, "PYTHONPATH": str(site), "ROBUSTBENCH3D_CACHE": str(cache), "OMP_NUM_THREADS": "1"}
    env.pop("ROBUSTBENCH3D_NO_PLUGINS", None)
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "robustbench3d", "run", "--victims", "fpointnet-v1-lite",
                           "--attacks", "none", "--proposals", "gt", "--data", str(data), "--out", str(out),
                           "--no-progress"], capture_output=True, text=True, env=env)
    assert proc.returncode == 1, proc.stderr
    [cell] = json.loads((out / "summary.json").read_text())
    assert cell["status"] == "error"
    assert "claimed by both the in-tree victim and plugin rb3d-clash 1.0" in cell["reason"]
    assert "--victim-arg" not in cell["reason"]


# ---- 6. numeric options and victim factory arguments ------------------------------------------------------
@pytest.mark.parametrize("tol", ["100.5", "1e3", "inf", "nan", "-0.5"])
def test_tolerances_outside_0_100_are_usage_errors(tmp_path, capsys, tol):
    run = write_run(tmp_path / "run", summary())
    base = tmp_path / "b.json"
    assert main(["check", str(run), "--write-baseline", str(base)]) == 0
    for option in ("--tol-ap", "--tol-drop"):
        with pytest.raises(SystemExit) as exc:
            main(["check", str(run), "--baseline", str(base), option, tol])
        assert exc.value.code == 2
        assert f"argument {option}: expected a number of percentage points in [0, 100]" in capsys.readouterr().err


def test_tolerance_bounds_are_accepted(tmp_path):
    run = write_run(tmp_path / "run", summary())
    base = tmp_path / "b.json"
    assert main(["check", str(run), "--write-baseline", str(base)]) == 0
    assert main(["check", str(run), "--baseline", str(base), "--tol-ap", "0", "--tol-drop", "100"]) == 0


@pytest.fixture
def no_weights(monkeypatch):
    """Loading a cascade's weights fails the test: factory arguments must be refused before."""
    monkeypatch.setattr("robustbench3d.victims.zoo._cascade", lambda *a, **k: pytest.fail("weights loaded"))


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"seed": -1}, "victim argument 'seed': -1 is not an integer in [0, 9223372036854775807]"),
    ({"seed": 2**63}, "victim argument 'seed'"),
    ({"seed": 1.5}, "victim argument 'seed': 1.5 is not an integer"),
    ({"gather": "nearest"}, "victim argument 'gather': 'nearest' is not one of random, topk"),
    ({"precision": "float16"}, "victim argument 'precision': 'float16' is not one of"),
    ({"input_size": "8192x288"}, "victim argument 'input_size': 8192x288 has a side over 4096 px"),
    ({"num_points": 0}, "victim argument 'num_points': 0 is not an integer in [1, 65536]"),
])
def test_cascade_factory_arguments_are_checked_before_weights_load(no_weights, kwargs, message):
    for name in ("fpointnet-v1", "fpointnet-v1-lite"):
        with pytest.raises(RobustBenchError) as exc:
            create_victim(name, **kwargs)
        assert message in str(exc.value)


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"threads": 0}, "victim argument 'threads': 0 is not an integer in [1, 256]"),
    ({"threads": "2"}, "victim argument 'threads': '2' is not an integer"),
    ({"seed": -3}, "victim argument 'seed': -3 is not an integer"),
    ({"gather": "all"}, "victim argument 'gather': 'all' is not one of random, topk"),
])
def test_onnx_victim_arguments_are_checked_before_reading_the_directory(tmp_path, kwargs, message):
    from robustbench3d.victims.onnx.runtime import OnnxCascade

    with pytest.raises(RobustBenchError) as exc:  # the directory does not exist: the argument is refused first
        OnnxCascade(tmp_path / "nowhere", **kwargs)
    assert message in str(exc.value)


@pytest.mark.parametrize(("argv", "message"), [
    (["--opset", "12"], "--opset: 12 is out of range (an integer in [18, 23])"),
    (["--batch-2d", "0"], "--batch-2d: 0 is out of range (an integer in [1, 64])"),
    (["--batch-seg", "257"], "--batch-seg: 257 is out of range (an integer in [1, 256])"),
])
def test_export_onnx_numeric_options_are_checked_up_front(tmp_path, capsys, monkeypatch, argv, message):
    monkeypatch.setattr("robustbench3d.commands.victims_export_onnx.create_cascade",
                        lambda *a, **k: pytest.fail("victim built"))
    out = tmp_path / "out"
    assert main(["export-onnx", "fpointnet-v1-lite", "--out", str(out), "--exporter", "legacy", *argv]) == 2
    assert message in one_error_line(capsys.readouterr().err)
    assert not out.exists()


@pytest.mark.parametrize(("kwargs", "named"), [
    ({"frames": 0}, "frames=0"), ({"frames": 2.5}, "frames=2.5"), ({"frames": "8"}, "frames='8'"),
    ({"frames": True}, "frames=True"), ({"seed": -1}, "seed=-1"),
])
def test_pytest_marker_numbers_are_checked(tmp_path, kwargs, named):
    from robustbench3d.pytest_plugin import _config_from_marker

    mark = pytest.mark.robustbench3d(victim="lidar-cluster", **kwargs).mark
    with pytest.raises(pytest.UsageError, match=f"@pytest.mark.robustbench3d: {named} is not an integer"):
        _config_from_marker(mark, tmp_path)
