"""The pytest plugin (robustbench3d.pytest_plugin) run the way a user runs it: a pytest subprocess on a
test file. Fast: the marker and fixture on a 3-frame slice with the example LiDAR-only victim, its numbers
against the evaluator rescoring the result files on disk; slow: examples/test_my_victim_robustness.py."""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
import time
from importlib.metadata import entry_points
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
EXAMPLE = REPO / "examples" / "test_my_victim_robustness.py"

needs_plugin_victim = pytest.mark.skipif(
    importlib.util.find_spec("rb3d_lidar_cluster") is None,
    reason="example plugin not installed: pip install -c constraints.txt -e examples/lidar_cluster_victim",
)


def plugin_args() -> list[str]:
    """``-p robustbench3d.pytest_plugin`` unless the ``pytest11`` entry point already loads it."""
    installed = any(ep.value == "robustbench3d.pytest_plugin" for ep in entry_points(group="pytest11"))
    return [] if installed else ["-p", "robustbench3d.pytest_plugin"]


def run_pytest(path: Path, cwd: Path, *extra: str, timeout: float = 300) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *plugin_args(), *extra, str(path)]
    return subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)


USER_TESTS = '''
import json
import pytest
from robustbench3d.eval import evaluate_dirs
from robustbench3d.kitti import read_split

MARK = pytest.mark.robustbench3d(victim="lidar-cluster", attacks="benign-sphere", frames=3)
SEEN = []


@MARK
def test_numbers_are_the_result_files_rescored(robustbench3d_run):
    run = robustbench3d_run
    assert run.frames == 3 and run.victim == "lidar-cluster"
    data = run.cells[0]["dataset"]["root"]
    ids = read_split(data + "/ImageSets/val.txt")[:3]
    (run.out / "split.txt").write_text("\\n".join(ids) + "\\n")
    rescored = {}
    for attack in ("none", "benign-sphere"):
        res = evaluate_dirs(data + "/training/label_2", run.out / "cells" / f"lidar-cluster+{attack}+detector" / "data",
                            split=run.out / "split.txt", classes=["Car"])
        rescored[attack] = res["Car"]["bev"]["R40"]["moderate"]
    assert run.clean_ap() == rescored["none"]
    assert run.ap("benign-sphere") == rescored["benign-sphere"]
    assert run.drop("benign-sphere") == pytest.approx(rescored["none"] - rescored["benign-sphere"], abs=1e-12)
    assert {f["code"] for f in run.flags()} == {"partial-split"}
    SEEN.append(id(run.cells))


@MARK
def test_same_marker_shares_the_run(robustbench3d_run):
    SEEN.append(id(robustbench3d_run.cells))
    assert len(SEEN) == 2 and SEEN[0] == SEEN[1]


@MARK
def test_a_failing_gate(robustbench3d_run):
    assert robustbench3d_run.clean_ap() >= 101.0


def test_fixture_without_marker(robustbench3d_run):
    pass


@pytest.mark.robustbench3d(victim="lidar-cluster", frames=3, proposals="gt")
def test_skipped_cell_fails_with_its_reason(robustbench3d_run):
    robustbench3d_run.clean_ap(proposals="gt")
'''


@needs_plugin_victim
def test_marker_and_fixture_in_a_user_suite(tmp_path):
    path = tmp_path / "test_user.py"
    path.write_text(USER_TESTS, encoding="utf-8")
    proc = run_pytest(path, tmp_path, "-rA")
    out = proc.stdout + proc.stderr
    assert proc.returncode == 1, out
    assert "PASSED test_user.py::test_numbers_are_the_result_files_rescored" in out
    assert "PASSED test_user.py::test_same_marker_shares_the_run" in out
    assert "FAILED test_user.py::test_a_failing_gate" in out and ">= 101.0" in out
    assert "needs @pytest.mark.robustbench3d(victim=...)" in out
    assert "lidar-cluster / none / gt is skipped: victim 'lidar-cluster' supports proposals detector only" in out


@pytest.mark.slow
def test_readme_example_passes_in_under_a_minute(tmp_path):
    t0 = time.perf_counter()
    proc = run_pytest(EXAMPLE, tmp_path)
    wall = time.perf_counter() - t0
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "3 passed" in proc.stdout
    print(f"examples/test_my_victim_robustness.py: {wall:.1f} s wall")


REPORTED_TESTS = '''
import pytest

MARK = pytest.mark.robustbench3d(victim="lidar-cluster", attacks="benign-sphere", frames=3)


@MARK
def test_reads_numbers(robustbench3d_run):
    assert robustbench3d_run.clean_ap() >= 0.0
    assert robustbench3d_run.clean_ap() >= 0.0  # twice: one property
    assert robustbench3d_run.ap("benign-sphere", metric="3d", difficulty="hard") >= 0.0
    assert robustbench3d_run.drop("benign-sphere") <= 100.0


@MARK
def test_gate_fails(robustbench3d_run):
    assert robustbench3d_run.drop("benign-sphere", metric="3d") >= 101.0


@MARK
def test_fails_before_reading(robustbench3d_run):
    assert robustbench3d_run.victim == "another"
'''


@needs_plugin_victim
def test_junit_properties_and_failure_section(tmp_path):
    """A passing test's --junitxml testcase carries the run and every number it was handed; a failing one's
    report names the cells it read, the frame count, and those cells' flags and evaluator notes, all checked
    against the run's summary.json read here."""
    import json
    import xml.etree.ElementTree as ET

    path = tmp_path / "test_reported.py"
    path.write_text(REPORTED_TESTS, encoding="utf-8")
    proc = run_pytest(path, tmp_path, "--junitxml", str(tmp_path / "junit.xml"))
    out = proc.stdout + proc.stderr
    assert proc.returncode == 1 and "2 failed, 1 passed" in out, out
    cases = {c.get("name"): c for c in ET.parse(tmp_path / "junit.xml").getroot().iter("testcase")}
    props = {p.get("name"): p.get("value") for p in cases["test_reads_numbers"].iter("property")}
    run_dir = Path(props["robustbench3d.out"])
    cells = {f"{c['victim']}+{c['attack']}+{c['proposals']}": c
             for c in json.loads((run_dir / "summary.json").read_text(encoding="utf-8"))}
    clean, attacked = cells["lidar-cluster+none+detector"], cells["lidar-cluster+benign-sphere+detector"]
    assert props["robustbench3d.victim"] == "lidar-cluster" and props["robustbench3d.frames"] == "3"
    assert clean["dataset"]["frames"] == 3
    assert props["robustbench3d.cells"] == ", ".join(cells)
    numbers = {k: float(v) for k, v in props.items() if k.count(".") > 2}
    assert numbers == {
        "robustbench3d.clean_ap.detector.Car.bev.R40.moderate": clean["metrics"]["Car"]["bev"]["R40"]["moderate"],
        "robustbench3d.ap.benign-sphere.detector.Car.3d.R40.hard": attacked["metrics"]["Car"]["3d"]["R40"]["hard"],
        "robustbench3d.drop.benign-sphere.detector.Car.bev.R40.moderate":
            attacked["attack_effect"]["drop"]["Car"]["bev"]["R40"]["moderate"]}
    # the failing gate: its report (terminal and junit failure text) names cell, frames, flags and notes
    failure = cases["test_gate_fails"].find("failure").text
    blocks = re.split(r"\n_{3,} (\w+) _{3,}\n", out)  # the terminal's failure reports, by test name
    section = blocks[blocks.index("test_gate_fails") + 1]
    assert re.search(r"\n-{3,} robustbench3d -{3,}\n", section), section
    for text in (failure, section):
        assert "victim lidar-cluster, 3 frame(s) of split 'val'" in text
        assert "  lidar-cluster+benign-sphere+detector: ok" in text and "lidar-cluster+none+detector:" not in text
        assert attacked["flags"] and attacked["metrics"]["meta"]["notes"]
        for flag in attacked["flags"]:
            assert f"flag {flag['code']}: {flag['message']}" in text
        for note in attacked["metrics"]["meta"]["notes"]:
            assert f"evaluator note: {note}" in text
        drop = attacked["attack_effect"]["drop"]["Car"]["3d"]["R40"]["moderate"]
        assert f"robustbench3d.drop.benign-sphere.detector.Car.3d.R40.moderate = {drop}" in text
    before = cases["test_fails_before_reading"].find("failure").text
    assert f"cell(s) this test read: none (the run's cells: {', '.join(cells)})" in before
