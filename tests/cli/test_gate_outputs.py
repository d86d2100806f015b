"""``robustbench3d check --json / --junit`` and a run over another dataset or protocol (issue #37).

Hand-made runs whose numbers are known: the JSON is checked against those numbers and against the
terminal table the same command printed; the JUnit XML is parsed with ElementTree (its counts against
its own testcases, its failure messages against the moved values). A run over another dataset (other
frame count, other labels) or protocol is reported by the differing fields alone, in all three outputs.
"""

from __future__ import annotations

import copy
import json
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
from cell_builders import hand_provenance, write_run

from robustbench3d.cli import main

SHA, OTHER_SHA = "ab" * 32, "cd" * 32
DIFFS = ("easy", "moderate", "hard")
EVALUATION = {"evaluator": "robustbench3d.eval", "classes": ["Car"], "result_precision": 2}
# the hand-made baseline's numbers: (victim+attack+proposals) -> metric -> (easy, moderate, hard)
CLEAN = {"bev": (80.0, 64.0, 50.0), "3d": (70.0, 52.0, 40.0)}
ADV = {"bev": (60.0, 48.0, 40.0), "3d": (58.0, 40.0, 30.0)}
ADV_DROP = {"bev": 16.0, "3d": 12.0}  # moderate drops, percentage points


def _ap_table(values: dict[str, tuple[float, float, float]]) -> dict:
    return {m: {r: dict(zip(DIFFS, v, strict=True)) for r in ("R40", "R11")} for m, v in values.items()}


def _drop_table(values: dict[str, float]) -> dict:
    return {"Car": {m: {r: {"easy": 0.0, "moderate": v, "hard": 0.0} for r in ("R40", "R11")}
                    for m, v in values.items()}}


def make_cell(attack: str, proposals: str, ap: dict | None, drop: dict[str, float] | None = None,
              status: str = "ok") -> dict:
    """A schema-valid cell of victim "v" over 10 val frames (labels' sha256 :data:`SHA`)."""
    meta = {"evaluator": "robustbench3d.eval", "version": "1", "ap_unit": "percent", "frames": 10,
            "classes": ["Car"], "metrics": ["bev", "3d"], "min_overlap": {"Car": {"bev": 0.7, "3d": 0.7}}}
    cell = {
        "schema_version": 1, "victim": "v", "attack": attack, "proposals": proposals, "status": status,
        "reason": None if status == "ok" else "not supported",
        "dataset": {"root": "/data", "split": "val", "frames": 10, "split_frames": 10, "sha256": SHA,
                    "embedded": {"generator": "robustbench3d.synth", "generator_version": 1, "frames": 2000,
                                 "seed": 0, "val_fraction": 0.5}, "manifest": None},
        "metrics": {"Car": _ap_table(ap), "meta": meta} if status == "ok" else None,
        "provenance": hand_provenance("v", attack, proposals, SHA, weights_sha256=SHA, evaluation=EVALUATION),
    }
    if drop is not None:
        zero = _drop_table({m: 0.0 for m in drop})
        cell["attack_effect"] = {
            "clean_cell": f"v+none+{proposals}", "clean_fingerprint": SHA, "clean": zero, "drop": _drop_table(drop),
            "relative_drop": zero,
            "success": {"class": "Car", "metric": "bev", "iou": 0.7, "difficulty": "moderate", "score_threshold": 0.5,
                        "clean_matched": 4, "attacked_missed": 1, "rate": 0.25}}
    return cell


def summary() -> list[dict]:
    """A clean cell, an attacked one, a skipped one."""
    return [make_cell("none", "detector", CLEAN), make_cell("adv", "detector", ADV, drop=ADV_DROP),
            make_cell("none", "gt", None, status="skipped")]


@pytest.fixture
def base(tmp_path: Path) -> Path:
    run = write_run(tmp_path / "base_run", summary())
    assert main(["check", str(run), "--write-baseline", str(tmp_path / "baseline.json")]) == 0
    return tmp_path / "baseline.json"


def moved_run(tmp_path: Path) -> Path:
    """Clean BEV moderate AP 64 -> 62.5 (a regression of 1.5), attacked 3D moderate drop 12 -> 10 (an
    improvement of 2); every other value as in the baseline."""
    cells = summary()
    cells[0]["metrics"]["Car"]["bev"]["R40"]["moderate"] = 62.5
    cells[1]["attack_effect"]["drop"]["Car"]["3d"]["R40"]["moderate"] = 10.0
    return write_run(tmp_path / "moved", cells)


def other_dataset_run(tmp_path: Path) -> Path:
    """The run over another slice: 9 frames, other labels, and therefore every AP far off and a cell gone."""
    cells = summary()[:2]
    for cell in cells:
        cell["dataset"].update(frames=9, sha256=OTHER_SHA)
        for table in cell["metrics"]["Car"].values():
            for d in DIFFS:
                table["R40"][d] -= 20.0
    return write_run(tmp_path / "other", cells)


def table_rows(out: str) -> list[list[str]]:
    """The rows of the printed table of moved values (cell, metric in 3 words, 5 numbers/words)."""
    lines = out.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("cell ") and "verdict" in line)
    rows = []
    for line in lines[start + 2:]:
        if not line.startswith("v+"):
            break
        rows.append(line.split())
    return rows


def junit(path: Path) -> tuple[ET.Element, list[ET.Element]]:
    root = ET.parse(path).getroot()
    suites = root.findall("testsuite")
    assert root.tag == "testsuites" and len(suites) == 1
    return suites[0], suites[0].findall("testcase")


def check(run: Path, baseline: Path, *extra: str) -> int:
    return main(["check", str(run), "--baseline", str(baseline), *extra])


# ---- 1. --json and --junit ---------------------------------------------------------------------------

def test_json_lists_every_compared_value_as_the_terminal_table_says(base, tmp_path, capsys):
    capsys.readouterr()
    out_json = tmp_path / "check.json"
    assert check(moved_run(tmp_path), base, "--json", str(out_json)) == 1
    out = capsys.readouterr().out
    data = json.loads(out_json.read_text(encoding="utf-8"))
    assert (data["verdict"], data["exit_status"]) == ("failed", 1)
    assert data["tolerances"] == {"ap": 1.0, "drop": 1.0} and data["comparable"] is True
    # 2 ok cells x 6 AP + 1 attacked cell x 2 drops = 14 values in 3 cells, as the terminal says
    assert "3 cell(s), 14 value(s) compared" in out
    assert (data["counts"]["cells"], data["counts"]["values"]) == (3, 14)
    values = [(c["cell"], v) for c in data["cells"] for v in c["values"]]
    assert len(values) == 14
    # every value against the hand-made numbers (baseline) and the run's (current)
    expected = {("v+none+detector", "ap", m, d): (CLEAN[m][i], CLEAN[m][i]) for m in CLEAN for i, d in enumerate(DIFFS)}
    expected.update({("v+adv+detector", "ap", m, d): (ADV[m][i], ADV[m][i]) for m in ADV for i, d in enumerate(DIFFS)})
    expected.update({("v+adv+detector", "drop", m, "moderate"): (v, v) for m, v in ADV_DROP.items()})
    expected[("v+none+detector", "ap", "bev", "moderate")] = (64.0, 62.5)
    expected[("v+adv+detector", "drop", "3d", "moderate")] = (12.0, 10.0)
    got = {(cell, v["quantity"], v["metric"], v["difficulty"]): v for cell, v in values}
    assert set(got) == set(expected)
    for key, (before, now) in expected.items():
        v = got[key]
        assert (v["baseline"], v["current"], v["tolerance"]) == (before, now, 1.0), key
        assert v["difference"] == pytest.approx(now - before, abs=1e-12)
        assert v["pass"] is (abs(now - before) <= 1.0), key
    # the failing values are exactly the terminal table's rows, number for number
    rows = table_rows(out)
    assert len(rows) == 2
    failing = [(cell, v) for cell, v in values if not v["pass"]]
    label = {"bev": "BEV", "3d": "3D"}
    as_rows = [[cell, label[v["metric"]], "AP" if v["quantity"] == "ap" else "drop", v["difficulty"],
                f"{v['baseline']:.2f}", f"{v['current']:.2f}", f"{v['difference']:+.2f}", f"{v['tolerance']:.2f}",
                v["verdict"]] for cell, v in failing]
    assert sorted(as_rows) == sorted(rows)
    assert "1 regression(s), 1 improvement(s)" in out
    assert (data["counts"]["regressions"], data["counts"]["improvements"]) == (1, 1)
    # each cell's reasons name the cell, the value and its numbers; the skipped cell passes
    cells = {c["cell"]: c for c in data["cells"]}
    assert cells["v+none+detector"]["reasons"] == [
        "v+none+detector BEV AP moderate: baseline 64.00, now 62.50, delta -1.50, tolerance 1.00: regression"]
    assert cells["v+adv+detector"]["pass"] is False and cells["v+none+gt"]["pass"] is True
    assert cells["v+none+gt"]["values"] == [] and cells["v+none+gt"]["baseline_status"] == "skipped"
    assert f"wrote {out_json} (JSON)" in out


def test_junit_has_one_testcase_per_cell_and_metric_and_names_the_numbers(base, tmp_path, capsys):
    out_xml = tmp_path / "check.xml"
    assert check(moved_run(tmp_path), base, "--junit", str(out_xml)) == 1
    suite, cases = junit(out_xml)
    failed = [c for c in cases if c.find("failure") is not None]
    assert int(suite.get("tests")) == len(cases) and int(suite.get("failures")) == len(failed)
    # dataset/protocol + (2 ok cells x BEV, 3D) + the skipped cell's status = 6
    names = [(c.get("classname"), c.get("name")) for c in cases]
    assert names == [("robustbench3d check", "dataset and evaluation protocol"),
                     ("v+none+detector", "BEV AP and drop"), ("v+none+detector", "3D AP and drop"),
                     ("v+adv+detector", "BEV AP and drop"), ("v+adv+detector", "3D AP and drop"),
                     ("v+none+gt", "status")]
    messages = {(c.get("classname"), c.get("name")): c.find("failure").get("message") for c in failed}
    assert messages == {
        ("v+none+detector", "BEV AP and drop"):
            "v+none+detector BEV AP moderate: baseline 64.00, now 62.50, delta -1.50, tolerance 1.00: regression",
        ("v+adv+detector", "3D AP and drop"):
            "v+adv+detector 3D drop moderate: baseline 12.00, now 10.00, delta -2.00, tolerance 1.00: improvement"}
    # --allow-improvements: the improvement's testcase passes, as the exit status does
    allowed = tmp_path / "allowed.xml"
    assert check(moved_run(tmp_path), base, "--junit", str(allowed), "--allow-improvements") == 1
    suite, cases = junit(allowed)
    assert int(suite.get("failures")) == 1 == sum(c.find("failure") is not None for c in cases)


def test_passing_check_json_and_junit(base, tmp_path, capsys):
    run = write_run(tmp_path / "same", summary())
    assert check(run, base, "--json", str(tmp_path / "c.json"), "--junit", str(tmp_path / "c.xml")) == 0
    data = json.loads((tmp_path / "c.json").read_text())
    assert data["verdict"] == "passed" and data["reasons"] == []
    assert all(v["pass"] and v["difference"] == 0.0 for c in data["cells"] for v in c["values"])
    suite, cases = junit(tmp_path / "c.xml")
    assert (int(suite.get("tests")), int(suite.get("failures"))) == (len(cases), 0) == (6, 0)


def test_missing_and_extra_cells_fail_their_testcases(base, tmp_path, capsys):
    cells = summary()
    extra = make_cell("other", "detector", CLEAN, drop={"bev": 0.0, "3d": 0.0})
    run = write_run(tmp_path / "shape", [cells[0], cells[2], extra])
    assert check(run, base, "--json", str(tmp_path / "c.json"), "--junit", str(tmp_path / "c.xml")) == 1
    out = capsys.readouterr().out
    problems = [line.removeprefix("problem: ") for line in out.splitlines() if line.startswith("problem: ")]
    assert problems == ["cell v+adv+detector is in the baseline but not in the run",
                        "cell v+other+detector is in the run but not in the baseline"]
    data = json.loads((tmp_path / "c.json").read_text())
    assert [r for c in data["cells"] for r in c["reasons"]] == problems == data["reasons"]
    suite, cases = junit(tmp_path / "c.xml")
    failed = {(c.get("classname"), c.get("name")): c.find("failure").get("message")
              for c in cases if c.find("failure") is not None}
    assert failed == {("v+adv+detector", "BEV AP and drop"): problems[0],
                      ("v+adv+detector", "3D AP and drop"): problems[0],
                      ("v+other+detector", "in baseline"): problems[1]}
    assert int(suite.get("failures")) == 3 and int(suite.get("tests")) == len(cases) == 7


def test_outputs_are_written_once_unless_forced(base, tmp_path, capsys):
    run = write_run(tmp_path / "same", summary())
    mine = tmp_path / "mine.json"
    mine.write_text("my notes\n")
    xml = tmp_path / "c.xml"
    assert check(run, base, "--junit", str(xml), "--json", str(mine)) == 2
    err = capsys.readouterr().err
    assert f"--json {mine}: exists; pass --force to replace it (nothing was written)" in err
    assert mine.read_text() == "my notes\n" and not xml.exists()  # checked up front: nothing written
    assert check(run, base, "--junit", str(xml), "--json", str(mine), "--force") == 0
    out = capsys.readouterr().out.splitlines()
    assert f"replacing {mine} (--force)" in out and f"replacing {xml} (--force)" not in out
    assert json.loads(mine.read_text())["verdict"] == "passed" and xml.is_file()


@pytest.mark.parametrize("argv, message", [
    (["--write-baseline", "{tmp}/new.json", "--json", "{tmp}/c.json"], "--json: applies to --baseline only"),
    (["--write-baseline", "{tmp}/new.json", "--junit", "{tmp}/c.xml"], "--junit: applies to --baseline only"),
    (["--baseline", "{base}", "--json", "{base}", "--force"], "is the baseline being read"),
    (["--baseline", "{base}", "--junit", "{run}/summary.json", "--force"], "is the run's summary"),
    (["--baseline", "{base}", "--json", "{tmp}/x", "--junit", "{tmp}/x"], "--junit {tmp}/x: is the --json file"),
    (["--baseline", "{tmp}/missing.json", "--json", "{tmp}/c.json"], "missing.json: file not found"),
])
def test_refusals_write_nothing(base, tmp_path, capsys, argv, message):
    run = write_run(tmp_path / "same", summary())
    before = {p: p.read_bytes() for p in (base, run / "summary.json")}
    fill = {"tmp": str(tmp_path), "base": str(base), "run": str(run)}
    assert main(["check", str(run), *(a.format(**fill) for a in argv)]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and err[0].startswith("robustbench3d: error: ") and message.format(**fill) in err[0]
    assert {p: p.read_bytes() for p in before} == before
    assert not any((tmp_path / name).exists() for name in ("new.json", "c.json", "c.xml", "x"))


# ---- 2. another dataset or protocol: the mismatch alone -------------------------------------------------

def test_other_dataset_reports_the_mismatch_alone(base, tmp_path, capsys):
    capsys.readouterr()
    assert check(other_dataset_run(tmp_path), base) == 1
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert lines[0].startswith("check FAILED: ") and lines[0].endswith(": another dataset")
    assert lines[1:3] == ["  dataset frames: baseline 10, run 9",
                          f"  dataset sha256: baseline {SHA[:16]}..., run {OTHER_SHA[:16]}..."]
    # no per-cell line: no table, no regression, no missing cell
    assert "regression" not in out and "problem:" not in out and "verdict" not in out
    assert not any(line.startswith("v+") or "v+none" in line for line in lines)
    assert "no cell was compared" in out


def test_other_dataset_json_and_junit_say_the_same(base, tmp_path, capsys):
    run = other_dataset_run(tmp_path)
    assert check(run, base, "--json", str(tmp_path / "c.json"), "--junit", str(tmp_path / "c.xml")) == 1
    data = json.loads((tmp_path / "c.json").read_text())
    assert (data["verdict"], data["comparable"], data["cells"]) == ("failed", False, [])
    assert data["mismatch"] == [{"section": "dataset", "field": "frames", "baseline": 10, "run": 9},
                                {"section": "dataset", "field": "sha256", "baseline": SHA, "run": OTHER_SHA}]
    assert len(data["reasons"]) == 1 and "frames: baseline 10, run 9" in data["reasons"][0]
    assert data["counts"]["regressions"] == data["counts"]["values"] == 0
    suite, cases = junit(tmp_path / "c.xml")
    assert (int(suite.get("tests")), int(suite.get("failures")), len(cases)) == (1, 1, 1)
    failure = cases[0].find("failure")
    assert cases[0].get("name") == "dataset and evaluation protocol" and failure.get("type") == "mismatch"
    assert "dataset frames: baseline 10, run 9" in failure.get("message") and "v+" not in failure.get("message")


def test_nested_dataset_and_protocol_fields_are_named(base, tmp_path, capsys):
    cells = summary()
    for cell in cells:
        cell["dataset"]["embedded"]["seed"] = 1
        cell["provenance"]["config"]["evaluation"]["result_precision"] = 3
    capsys.readouterr()
    assert check(write_run(tmp_path / "nested", cells), base) == 1
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].endswith(": another dataset and another evaluation protocol")
    assert lines[1:3] == ["  dataset embedded.seed: baseline 0, run 1",
                          "  protocol evaluation.result_precision: baseline 2, run 3"]


def test_other_root_alone_is_compared(base, tmp_path, capsys):
    cells = copy.deepcopy(summary())
    for cell in cells:
        cell["dataset"]["root"] = "/ci/data"
    assert check(write_run(tmp_path / "ci", cells), base) == 0
    assert "note: dataset root /ci/data (baseline: /data); recorded, not compared" in capsys.readouterr().out
