"""The pytest plugin (robustbench3d.pytest_plugin) run the way a user runs it: a pytest subprocess on a
test file. Fast: the marker and fixture on a 3-frame slice with the example LiDAR-only victim, its numbers
against the evaluator rescoring the result files on disk; slow: examples/test_my_victim_robustness.py."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
import time
from importlib.metadata import entry_points
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
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
    SEEN.append(id(run))


@MARK
def test_same_marker_shares_the_run(robustbench3d_run):
    SEEN.append(id(robustbench3d_run))
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
