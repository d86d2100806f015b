"""The README's flows, end to end, as a new user meets them: ``run`` with ``--max-frames`` on the lazily
generated embedded dataset (only the evaluated frames exist), then ``report`` with scene figures, ``check``
(baseline, then a gate with JUnit and JSON), the pytest gate on the same frames, and a replay of the run from
its recorded configuration. Each step's output is checked against another step's, read independently."""

from __future__ import annotations

import csv
import json
import os
import stat
import subprocess
import sys
import xml.etree.ElementTree as ET

import pytest

from robustbench3d.cli import main

FRAMES = 3
VICTIM = "fpointnet-v1-lite"

GATE_TEST = '''
import json
from pathlib import Path

import pytest

SUMMARY = Path({summary!r})


@pytest.mark.robustbench3d(victim="{victim}", attacks=["benign-sphere"], proposals=["gt"], frames={frames})
def test_the_gate_sees_the_runs_numbers(robustbench3d_run):
    cells = json.loads(SUMMARY.read_text())
    clean = next(c for c in cells if c["attack"] == "none" and c["proposals"] == "gt")
    attacked = next(c for c in cells if c["attack"] == "benign-sphere" and c["proposals"] == "gt")
    want = clean["metrics"]["Car"]["bev"]["R40"]["moderate"]
    assert robustbench3d_run.clean_ap(proposals="gt") == want
    drop = want - attacked["metrics"]["Car"]["bev"]["R40"]["moderate"]
    assert abs(robustbench3d_run.drop("benign-sphere", proposals="gt") - drop) < 1e-9
'''


def cli(*argv: str) -> int:
    return main(list(argv))


def test_run_report_check_gate_and_replay_on_a_lazily_generated_slice(cache, tmp_path, capsys):
    old_mask = os.umask(0o022)
    try:
        run = tmp_path / "runs" / "main"
        assert cli("run", "--victims", VICTIM, "--attacks", "none,benign-sphere", "--proposals", "detector,gt",
                   "--max-frames", str(FRAMES), "--out", str(run), "--bootstrap", "20", "--jobs", "1",
                   "--no-progress") == 0
        labels = sorted((cache / "datasets" / "synth" / "training" / "label_2").glob("*.txt"))
        assert len(labels) == FRAMES  # lazily generated: only the evaluated frames exist

        report = run / "report"
        assert cli("report", str(run), "--out", str(report), "--scenes", "1") == 0
        html = (report / "leaderboard.html").read_text(encoding="utf-8")
        assert "Table 1" in html and "object outside the frustum" in html
        scenes = [p for p in (report / "figures").rglob("*.png") if "scene" in p.name]
        assert scenes, "the report drew no scene figure"
        assert "has changed since the run" not in html

        baseline = tmp_path / "baseline.json"
        assert cli("check", str(run), "--write-baseline", str(baseline)) == 0
        junit, verdict = tmp_path / "check.xml", tmp_path / "check.json"
        assert cli("check", str(run), "--baseline", str(baseline), "--junit", str(junit), "--json", str(verdict)) == 0
        suite = ET.parse(junit).getroot()
        suite = suite if suite.tag == "testsuite" else suite.find("testsuite")
        assert int(suite.get("tests")) >= 4 and int(suite.get("failures")) == 0
        assert json.loads(verdict.read_text())["verdict"] == "passed"

        test_file = tmp_path / "test_gate.py"
        test_file.write_text(GATE_TEST.format(summary=str(run / "summary.json"), victim=VICTIM, frames=FRAMES))
        env = {**os.environ, "OMP_NUM_THREADS": "1"}
        done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", str(test_file)],
                              cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]

        capsys.readouterr()
        assert cli("run", "--config-from", str(run), "--print-config") == 0
        run_file = tmp_path / "run.toml"
        run_file.write_text(capsys.readouterr().out)
        replay = tmp_path / "runs" / "replay"
        assert cli("run", "--config", str(run_file), "--out", str(replay), "--jobs", "1", "--no-progress") == 0
    finally:
        os.umask(old_mask)

    assert (replay / "results.csv").read_bytes() == (run / "results.csv").read_bytes()
    assert (replay / "seed_table.md").read_bytes() == (run / "seed_table.md").read_bytes()
    for cell in (run / "cells").iterdir():
        for f in (cell / "data").iterdir():
            assert (replay / "cells" / cell.name / "data" / f.name).read_bytes() == f.read_bytes()
    with open(run / "results.csv", newline="") as f:
        assert {r["proposals"] for r in csv.DictReader(f)} == {"detector", "gt"}
    written = [p for d in (run, replay, report) for p in d.rglob("*") if p.is_file() and p.name != ".lock"]
    written += [baseline, junit, verdict]
    modes = {p: stat.S_IMODE(p.stat().st_mode) for p in written}
    assert {str(p): oct(m) for p, m in modes.items() if m != 0o644} == {}


@pytest.fixture(autouse=True)
def _one_thread(monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
