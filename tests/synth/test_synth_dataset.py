"""``data synth``: KITTI layout, determinism across worker counts, resume after interruption."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from robustbench3d.cli import main
from robustbench3d.errors import RobustBenchError
from robustbench3d.fileio import sha256_file
from robustbench3d.kitti import KittiDataset, read_split
from robustbench3d.synth.writer import generate_dataset

SEED = 7
FRAMES = 3


def _digest(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): sha256_file(p) for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("ref")
    report = generate_dataset(root, FRAMES, SEED, val_fraction=0.5, workers=1, progress=False)
    assert report.generated == FRAMES and report.train + report.val == FRAMES
    return root


def test_kitti_layout(reference):
    files = set(_digest(reference))
    for i in range(FRAMES):
        for sub, ext in (("image_2", "png"), ("velodyne", "bin"), ("calib", "txt"), ("label_2", "txt")):
            assert f"training/{sub}/{i:06d}.{ext}" in files
    assert {"ImageSets/train.txt", "ImageSets/val.txt", "ImageSets/trainval.txt"} <= files
    assert not [f for f in files if f.endswith(".tmp")]
    train = read_split(reference / "ImageSets" / "train.txt")
    val = read_split(reference / "ImageSets" / "val.txt")
    assert sorted(train + val) == [f"{i:06d}" for i in range(FRAMES)] and not set(train) & set(val)
    assert len(KittiDataset(reference, split="trainval")) == FRAMES


def test_same_seed_same_bytes_for_any_worker_count(reference, tmp_path):
    generate_dataset(tmp_path / "w2", FRAMES, SEED, val_fraction=0.5, workers=2, progress=False)
    assert _digest(tmp_path / "w2") == _digest(reference)
    generate_dataset(tmp_path / "other", 1, SEED + 1, workers=1, progress=False)
    a = sha256_file(tmp_path / "other" / "training" / "velodyne" / "000000.bin")
    assert a != sha256_file(reference / "training" / "velodyne" / "000000.bin")


def test_resume_completes_a_partial_directory(reference, tmp_path):
    part = tmp_path / "part"
    shutil.copytree(reference, part)
    train = part / "training"
    # frame 1 died after its image was written (no label); frame 2 died while writing its image
    (train / "label_2" / "000001.txt").unlink()
    (train / "label_2" / "000002.txt").unlink()
    (train / "image_2" / "000002.png").write_bytes(b"\x89PNG truncated")
    (train / "image_2" / ".000002.png.abc.tmp").write_bytes(b"stale temp file")
    shutil.rmtree(part / "ImageSets")
    kept = (train / "velodyne" / "000000.bin").stat().st_mtime_ns
    report = generate_dataset(part, FRAMES, SEED, val_fraction=0.5, workers=1, progress=False)
    assert (report.generated, report.skipped) == (2, 1)
    assert (train / "velodyne" / "000000.bin").stat().st_mtime_ns == kept  # a finished frame is not rewritten
    assert _digest(part) == _digest(reference)  # the stale temporary file is gone too


def test_killed_run_resumes_to_identical_bytes(reference, tmp_path):
    out = tmp_path / "killed"
    cmd = [sys.executable, "-m", "robustbench3d", "data", "synth", "--out", str(out), "--frames", str(FRAMES),
           "--seed", str(SEED), "--workers", "1", "--no-progress"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    first = out / "training" / "label_2" / "000000.txt"
    deadline = time.monotonic() + 120
    while not first.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert first.exists() and not (out / "ImageSets").exists()
    assert main(["data", "synth", "--out", str(out), "--frames", str(FRAMES), "--seed", str(SEED),
                 "--workers", "1", "--no-progress"]) == 0
    assert {k: v for k, v in _digest(out).items() if "synth_manifest" not in k} == {
        k: v for k, v in _digest(reference).items() if "synth_manifest" not in k}


def test_refuses_to_mix_seeds_or_foreign_data(reference, tmp_path):
    with pytest.raises(RobustBenchError, match="seed"):
        generate_dataset(reference, FRAMES, SEED + 1, workers=1, progress=False)
    foreign = tmp_path / "kitti"
    (foreign / "training" / "label_2").mkdir(parents=True)
    (foreign / "training" / "label_2" / "000000.txt").write_text("")
    with pytest.raises(RobustBenchError, match="not generated here"):
        generate_dataset(foreign, 1, SEED, workers=1, progress=False)


def test_cli_reports_progress_and_rejects_bad_arguments(reference, tmp_path, capsys):
    part = tmp_path / "cli"
    shutil.copytree(reference, part)
    (part / "training" / "label_2" / "000002.txt").unlink()
    assert main(["data", "synth", "--out", str(part), "--frames", str(FRAMES), "--seed", str(SEED),
                 "--workers", "1"]) == 0
    captured = capsys.readouterr()
    assert "1 generated, 2 already present" in captured.out
    assert "synth" in captured.err and "frame" in captured.err  # tqdm progress bar on stderr
    assert main(["data", "synth", "--out", str(part), "--frames", "0", "--seed", str(SEED)]) == 2
    assert main(["data", "synth", "--out", str(part), "--frames", "2", "--val-fraction", "1.5"]) == 2
