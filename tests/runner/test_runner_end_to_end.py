"""``robustbench3d run`` end to end with the lidar-cluster plugin on a small generated dataset:
schema-valid summary, result files that rescore to the same metrics, CSV, determinism, resume,
error cells that do not stop the run, skipped cells."""

from __future__ import annotations

import csv
import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest

from robustbench3d.attacks import register_attack
from robustbench3d.attacks.base import Attack
from robustbench3d.attacks.spec import AttackRequirements
from robustbench3d.cli import main
from robustbench3d.errors import RobustBenchError
from robustbench3d.eval import evaluate_dirs
from robustbench3d.kitti import read_split
from robustbench3d.results import load_schema, read_summary
from robustbench3d.runner import RunConfig, run_benchmark
from robustbench3d.victims import VICTIMS
from robustbench3d.victims.spec import Capabilities, EntryInfo, VictimSpec

pytestmark = pytest.mark.skipif(
    importlib.util.find_spec("rb3d_lidar_cluster") is None,
    reason="example plugin not installed: pip install -c constraints.txt -e examples/lidar_cluster_victim",
)

FRAMES = 4
CELL = "lidar-cluster+none+detector"


@pytest.fixture(scope="module")
def dataset(shared_split) -> Path:
    """Four generated frames, all in the val split."""
    return shared_split(FRAMES, seed=5, val_fraction=1.0)


def run_cli(dataset: Path, out: Path, *extra: str, victims: str = "lidar-cluster",
            proposals: str = "detector,gt") -> int:
    return main(["run", "--victims", victims, "--attacks", "none", "--proposals", proposals, "--data", str(dataset),
                 "--out", str(out), "--no-progress", "--batch-size", "3", *extra])


def result_files(cell_dir: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted((cell_dir / "data").iterdir())}


def test_lidar_cluster_end_to_end(dataset, tmp_path, capsys):
    out = tmp_path / "run"
    assert run_cli(dataset, out) == 0
    printed = capsys.readouterr().out
    summary = read_summary(out / "summary.json")
    import jsonschema  # the shipped schema, applied by a plain validator

    jsonschema.validate(json.loads((out / "summary.json").read_text()), load_schema())
    from robustbench3d.seed_table import seed_table_markdown

    assert (out / "seed_table.md").read_text(encoding="utf-8") == seed_table_markdown(summary)

    det, gt = summary
    assert (det["victim"], det["attack"], det["proposals"]) == ("lidar-cluster", "none", "detector")
    assert det["status"] == "ok" and det["reason"] is None
    assert (gt["proposals"], gt["status"], gt["metrics"]) == ("gt", "skipped", None)
    assert "supports proposals detector only" in gt["reason"]
    assert not (out / "cells" / "lidar-cluster+none+gt" / "data").exists()

    metrics = det["metrics"]
    aps = [v for m in metrics["Car"].values() for r in m.values() for v in r.values()]
    assert len(aps) == 4 * 2 * 3 and all(isinstance(v, float) and 0.0 <= v <= 100.0 for v in aps)
    assert metrics["meta"]["frames"] == FRAMES and sum(metrics["meta"]["detections"].values()) > 0
    assert det["dataset"]["frames"] == FRAMES and det["dataset"]["root"] == str(dataset.resolve())

    # one result file per frame, empty ones included, and they rescore to exactly the same numbers
    val = read_split(dataset / "ImageSets" / "val.txt")
    cell_dir = out / "cells" / CELL
    assert sorted(result_files(cell_dir)) == [f"{i}.txt" for i in val]
    rescored = evaluate_dirs(dataset / "training" / "label_2", cell_dir / "data", dataset / "ImageSets" / "val.txt",
                             classes=["Car"])
    assert rescored["Car"] == metrics["Car"]
    assert rescored["meta"]["frames_without_results"] == 0

    # the long-format CSV holds every AP of the ok cell
    with open(out / "results.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(aps)
    for row in rows:
        assert row["victim"] == "lidar-cluster" and row["proposals"] == "detector"
        recall = "R40" if row["recall_points"] == "40" else "R11"
        assert float(row["ap"]) == metrics[row["class"]][row["metric"]][recall][row["difficulty"]]

    # the printed table shows BEV and 3D AP with both recall samplings
    bev40 = metrics["Car"]["bev"]["R40"]
    assert "BEV R40 (E M H)" in printed and "3D R11 (E M H)" in printed
    ci = det["metrics_ci"]["Car"]["bev"]["R40"]  # the run's default: 1000-resample bootstrap intervals
    assert det["metrics_ci"]["meta"]["resamples"] == 1000
    assert " ".join(f"{bev40[d]:6.2f} [{ci[d][0]:.1f}, {ci[d][1]:.1f}]" for d in ("easy", "moderate", "hard")
                    ) in printed

    prov = det["provenance"]
    assert prov["seed"] == 0 and prov["run"]["victims"] == ["lidar-cluster"]
    assert prov["config"]["victim"]["origin"].startswith("plugin rb3d-lidar-cluster")
    assert prov["config"]["dataset"]["sha256"] == det["dataset"]["sha256"]
    # the cell's own cost: CPU time and the process's peak RSS while it ran (Linux resets the peak per cell)
    assert prov["cpu_seconds"] >= 0 and prov["seconds"] > 0
    if sys.platform.startswith("linux"):
        assert prov["peak_rss_mb"] > 20


def test_two_runs_give_identical_metrics_and_files_and_torch_is_not_imported(dataset, tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    assert run_cli(dataset, a) == 0
    # the second run in a fresh interpreter: nothing is shared but the command line
    cmd = [sys.executable, "-m", "robustbench3d", "run", "--victims", "lidar-cluster", "--attacks", "none",
           "--proposals", "detector,gt", "--data", str(dataset), "--out", str(b), "--no-progress", "--batch-size", "3"]
    subprocess.run(cmd, check=True, capture_output=True, env={**os.environ, "OMP_WAIT_POLICY": "PASSIVE"})
    sa, sb = read_summary(a / "summary.json"), read_summary(b / "summary.json")
    assert [c["metrics"] for c in sa] == [c["metrics"] for c in sb]
    assert [c["provenance"]["fingerprint"] for c in sa] == [c["provenance"]["fingerprint"] for c in sb]
    assert result_files(a / "cells" / CELL) == result_files(b / "cells" / CELL)
    assert (a / "results.csv").read_bytes() == (b / "results.csv").read_bytes()
    assert sb[0]["provenance"]["determinism"]["torch_loaded"] is False


def test_resume_reuses_finished_cells_and_recomputes_after_a_change(dataset, tmp_path):
    out = tmp_path / "run"
    lines: list[str] = []

    def config(**kw) -> RunConfig:
        return RunConfig(victims=("lidar-cluster",), attacks=("none",), proposals=("detector", "gt"), out=out,
                         data=dataset, progress=False, **kw)

    first = run_benchmark(config(), lines.append)
    assert [o.reused for o in first.outcomes] == [False, False]
    cell_json = out / "cells" / CELL / "cell.json"
    stamp = cell_json.stat().st_mtime_ns
    files = result_files(out / "cells" / CELL)

    again = run_benchmark(config(), lines.append)
    assert [o.reused for o in again.outcomes] == [True, True]
    assert cell_json.stat().st_mtime_ns == stamp and result_files(out / "cells" / CELL) == files
    assert again.cells == first.cells and read_summary(out / "summary.json") == first.cells

    # a lost result file makes the cell incomplete: recomputed, same bytes
    (out / "cells" / CELL / "data" / sorted(files)[-1]).unlink()
    repaired = run_benchmark(config(), lines.append)
    assert [o.reused for o in repaired.outcomes] == [False, True]
    assert result_files(out / "cells" / CELL) == files

    # a changed configuration is refused before any work, and recomputed under force
    with pytest.raises(RobustBenchError) as refused:
        run_benchmark(config(max_frames=2), lines.append)
    assert (f"finished cell {CELL} (and 1 more cell(s)) was computed with another configuration (on disk vs this "
            "run: frames (--max-frames) 4 vs 2;") in str(refused.value)
    assert result_files(out / "cells" / CELL) == files and (out / "summary.json").is_file()
    shorter = run_benchmark(config(max_frames=2, force=True), lines.append)
    assert [o.reused for o in shorter.outcomes] == [False, False]
    assert shorter.cells[0]["metrics"]["meta"]["frames"] == 2 and len(result_files(out / "cells" / CELL)) == 2
    assert shorter.cells[0]["provenance"]["fingerprint"] != first.cells[0]["provenance"]["fingerprint"]
    seeded = run_benchmark(config(max_frames=2, seed=1, force=True), lines.append)
    assert not any(o.reused for o in seeded.outcomes)


class BrokenDetector:
    """TEST ONLY: a victim whose second detect call raises."""

    supported_proposals = ("detector",)

    def __init__(self) -> None:
        self.calls = 0

    def detect(self, frames, proposals="detector"):
        self.calls += 1
        if self.calls == 2:
            raise RuntimeError("simulated crash inside the victim")
        from robustbench3d.kitti.labels import Labels

        return [Labels.empty(with_score=True) for _ in frames]


VICTIMS.register("test-broken-victim", VictimSpec(
    factory=BrokenDetector,
    info=EntryInfo(Capabilities(modalities=("lidar",), backend="other", gradients=False, deterministic=True))))


def _unloadable_victim():
    """TEST ONLY: a factory that fails as a victim without weights does (every F-PN victim ships some)."""
    from robustbench3d.errors import RobustBenchError

    raise RobustBenchError("victim 'test-unloadable-victim' has no shipped weights; pass --victim-arg "
                           "test-unloadable-victim:weights=FILE")


VICTIMS.register("test-unloadable-victim", VictimSpec(
    factory=_unloadable_victim,
    info=EntryInfo(Capabilities(modalities=("lidar",), backend="other", gradients=False, deterministic=True))))


@register_attack("test-camera-texture", requirements=AttackRequirements(needs_camera=True),
                 summary="TEST ONLY: a camera-only attack that must never be applied to a LiDAR-only victim")
class CameraOnlyAttack(Attack):
    def apply(self, frame, targets, rng: np.random.Generator):
        raise AssertionError("a skipped cell was run")

    def describe(self):
        return {"texture": "test"}


def test_failing_victims_make_error_cells_and_the_run_goes_on(dataset, tmp_path, capsys):
    out = tmp_path / "run"
    rc = run_cli(dataset, out, victims="test-broken-victim,test-unloadable-victim,lidar-cluster", proposals="detector")
    assert rc == 1
    assert "2 of 3 cells failed" in capsys.readouterr().err
    broken, fpn, good = read_summary(out / "summary.json")
    assert broken["status"] == "error" and broken["metrics"] is None
    assert ("victim 'test-broken-victim' failed on frames 000003..000003: RuntimeError: simulated crash"
            in broken["reason"])
    assert "simulated crash" in broken["provenance"]["traceback"]
    assert fpn["status"] == "error" and "no shipped weights" in fpn["reason"] and "--victim-arg" in fpn["reason"]
    assert good["status"] == "ok" and good["metrics"]["meta"]["frames"] == FRAMES
    for cell in ("test-broken-victim+none+detector", "test-unloadable-victim+none+detector"):
        assert not (out / "cells" / cell / "data").exists() and not (out / "cells" / cell / "data.partial").exists()
    # error cells are retried on the next run, finished ones are not
    report = run_benchmark(RunConfig(victims=("test-broken-victim", "lidar-cluster"), attacks=("none",),
                                     proposals=("detector",), out=out, data=dataset, batch_size=3, progress=False),
                           lambda line: None)
    assert [o.reused for o in report.outcomes] == [False, True]


def test_attack_requirements_skip_cells(dataset, tmp_path):
    report = run_benchmark(RunConfig(victims=("lidar-cluster",), attacks=("none", "test-camera-texture"),
                                     proposals=("detector",), out=tmp_path / "run", data=dataset, progress=False),
                           lambda line: None)
    none, texture = report.cells
    assert none["status"] == "ok"
    assert texture["status"] == "skipped"
    assert texture["reason"] == ("attack 'test-camera-texture' needs the camera; the victim offers lidar, "
                                 "no gradients")
    assert texture["provenance"]["config"]["attack"]["object"] == {"texture": "test"}


@register_attack("test-counted-attack", summary="TEST ONLY: numbers its instances, leaves frames as they are")
class CountedAttack(Attack):
    created: ClassVar[list[CountedAttack]] = []

    def __init__(self) -> None:
        self.number, self.prepared, self.applied = len(CountedAttack.created) + 1, [], 0
        CountedAttack.created.append(self)

    def prepare(self, victim) -> None:
        self.prepared.append(type(victim).__name__)

    def apply(self, frame, targets, rng: np.random.Generator):
        self.applied += 1
        return frame

    def describe(self):
        return {"instance": self.number}


def test_each_attack_is_built_once_and_the_described_instance_is_applied(dataset, tmp_path):
    CountedAttack.created.clear()
    report = run_benchmark(RunConfig(victims=("lidar-cluster", "test-broken-victim"), attacks=("test-counted-attack",),
                                     proposals=("detector",), out=tmp_path / "run", data=dataset, progress=False),
                           lambda line: None)  # 4 frames in one batch: one detect call per cell
    # The clean cell 'none' of each victim is added (and runs first): the broken victim's second call,
    # in its attacked cell, fails.
    assert [(c["attack"], c["status"]) for c in report.cells] == [
        ("none", "ok"), ("test-counted-attack", "ok"), ("none", "ok"), ("test-counted-attack", "error")]
    counted = [c for c in report.cells if c["attack"] == "test-counted-attack"]
    assert len(CountedAttack.created) == 1  # one instance for the whole run ...
    (attack,) = CountedAttack.created
    assert [c["provenance"]["config"]["attack"]["object"] for c in counted] == [{"instance": 1}] * 2
    assert attack.prepared == ["LidarClusterDetector", "BrokenDetector"]  # ... prepared for each cell
    assert attack.applied == 2 * FRAMES  # ... and it is the one that attacked every frame of both cells


def test_unknown_names_and_bad_arguments_fail_before_any_work(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", "--victims", "lidar-clustr", "--out", str(out), "--data", str(tmp_path)]) == 2
    assert "unknown victim 'lidar-clustr'; did you mean 'lidar-cluster'?" in capsys.readouterr().err
    assert main(["run", "--victims", "lidar-cluster", "--attacks", "nnoe", "--out", str(out)]) == 2
    assert "did you mean 'none'?" in capsys.readouterr().err
    assert main(["run", "--victims", "lidar-cluster", "--proposals", "oracle", "--out", str(out)]) == 2
    assert "--proposals: unknown source 'oracle'" in capsys.readouterr().err
    assert main(["run", "--victims", "lidar-cluster", "--victim-arg", "lidar-cluster=3", "--out", str(out)]) == 2
    assert "expected NAME:KEY=VALUE" in capsys.readouterr().err
    assert main(["run", "--victims", "lidar-cluster", "--data", str(tmp_path / "nowhere"), "--out", str(out)]) == 2
    assert "nowhere: dataset directory not found" in capsys.readouterr().err
    assert not (out / "summary.json").exists() and not (out / "cells").exists()


class InterruptOnceDetector:
    """TEST ONLY: the first instance ever created is interrupted (Ctrl-C) in its second batch."""

    supported_proposals = ("detector",)
    interrupted = False

    def __init__(self) -> None:
        self.calls = 0

    def detect(self, frames, proposals="detector"):
        self.calls += 1
        if self.calls == 2 and not InterruptOnceDetector.interrupted:
            InterruptOnceDetector.interrupted = True
            raise KeyboardInterrupt
        from robustbench3d.kitti.labels import Labels

        return [Labels.empty(with_score=True) for _ in frames]


VICTIMS.register("test-interrupt-once", VictimSpec(
    factory=InterruptOnceDetector,
    info=EntryInfo(Capabilities(modalities=("lidar",), backend="other", gradients=False, deterministic=True))))


def test_interrupted_run_resumes_without_redoing_finished_cells(dataset, tmp_path):
    out = tmp_path / "run"
    config = RunConfig(victims=("lidar-cluster", "test-interrupt-once"), attacks=("none",), proposals=("detector",),
                       out=out, data=dataset, batch_size=3, progress=False)
    with pytest.raises(KeyboardInterrupt):
        run_benchmark(config, lambda line: None)
    interrupted = out / "cells" / "test-interrupt-once+none+detector"
    assert (out / "cells" / CELL / "cell.json").is_file()
    assert not (interrupted / "cell.json").exists() and not (out / "summary.json").exists()
    assert not (out / "seed_table.md").exists()  # written with summary.json, at the end
    assert (interrupted / "data.partial").is_dir()  # what the interrupted cell had written so far
    report = run_benchmark(config, lambda line: None)
    assert [o.reused for o in report.outcomes] == [True, False]
    assert [c["status"] for c in report.cells] == ["ok", "ok"]
    assert not (interrupted / "data.partial").exists() and len(result_files(interrupted)) == FRAMES


def test_a_second_run_into_the_same_directory_is_refused(tmp_path):
    import fcntl

    out = tmp_path / "run"
    out.mkdir()
    with open(out / ".lock", "w") as held:
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        with pytest.raises(RobustBenchError, match="another robustbench3d run is writing there"):
            run_benchmark(RunConfig(victims=("lidar-cluster",), attacks=("none",), proposals=("detector",), out=out,
                                    data=tmp_path, progress=False), lambda line: None)
