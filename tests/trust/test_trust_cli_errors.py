"""Every user mistake at the command line: a one-line error naming the path, exit 2, no traceback,
and nothing half-written left behind. One test per case, on a one-frame hand-built dataset."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from cli_checks import fails_cleanly

from robustbench3d.kitti import write_image, write_split
from robustbench3d.testing import write_kitti_frame

CAR = "Car 0.00 0 -1.57 500.00 150.00 700.00 250.00 1.50 1.60 3.90 0.00 1.65 15.00 -1.57\n"
needs_plugin = pytest.mark.skipif(
    importlib.util.find_spec("rb3d_lidar_cluster") is None,
    reason="example plugin not installed: pip install -c constraints.txt -e examples/lidar_cluster_victim",
)


def tiny_dataset(root: Path, scan: np.ndarray | None = None) -> Path:
    """One frame 000000 (listed in ImageSets/val.txt): 1242x375 black image, one car."""
    rng = np.random.default_rng(0)
    if scan is None:
        scan = np.concatenate([rng.uniform(-20, 20, (300, 3)), rng.uniform(0, 1, (300, 1))], axis=1)
    write_kitti_frame(root, "000000", scan=scan, labels=CAR)
    write_split(root / "ImageSets" / "val.txt", ["000000"])
    return root


@pytest.fixture
def ds(tmp_path: Path) -> Path:
    return tiny_dataset(tmp_path / "ds")


@pytest.fixture
def a_file(tmp_path: Path) -> Path:
    path = tmp_path / "a_file"
    path.write_text("keep me\n")
    return path


# ---- --out / --json that cannot be written ---------------------------------------------------------
def test_run_out_is_an_existing_file(tmp_path, capsys, ds, a_file) -> None:
    line = fails_cleanly(tmp_path, capsys, ["run", "--victims", "fpointnet-v1-lite", "--data", str(ds),
                                            "--out", str(a_file), "--no-progress"], f"--out {a_file}")
    assert line.endswith("exists and is not a directory")


def test_run_out_under_a_file(tmp_path, capsys, ds, a_file) -> None:
    line = fails_cleanly(tmp_path, capsys, ["run", "--victims", "fpointnet-v1-lite", "--data", str(ds),
                                            "--out", str(a_file / "run"), "--no-progress"], str(a_file / "run"))
    assert line.endswith(f"{a_file} is not a directory")


def test_run_out_not_writable(tmp_path, capsys, ds) -> None:
    """/proc takes no new files, for root too (chmod does not stop root)."""
    line = fails_cleanly(tmp_path, capsys, ["run", "--victims", "fpointnet-v1-lite", "--data", str(ds),
                                            "--out", "/proc/rb3d-run", "--no-progress"], "--out /proc/rb3d-run")
    assert "cannot create files in /proc" in line


@pytest.mark.skipif(os.geteuid() == 0, reason="root ignores directory permission bits")
def test_run_out_in_a_read_only_directory(tmp_path, capsys, ds) -> None:
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    try:
        line = fails_cleanly(tmp_path, capsys, ["run", "--victims", "fpointnet-v1-lite", "--data", str(ds),
                                                "--out", str(locked / "run"), "--no-progress"], str(locked))
        assert "Permission denied" in line
    finally:
        locked.chmod(0o700)


def test_data_synth_out_is_an_existing_file(tmp_path, capsys, a_file) -> None:
    fails_cleanly(tmp_path, capsys, ["data", "synth", "--out", str(a_file), "--frames", "1", "--workers", "1",
                                     "--no-progress"], f"--out {a_file}: exists and is not a directory")


def test_data_synth_out_under_a_file(tmp_path, capsys, a_file) -> None:
    fails_cleanly(tmp_path, capsys, ["data", "synth", "--out", str(a_file / "ds"), "--frames", "1", "--workers", "1",
                                     "--no-progress"], f"{a_file} is not a directory")


def test_show_out_is_a_directory(tmp_path, capsys, ds) -> None:
    out = tmp_path / "pictures"
    out.mkdir()
    fails_cleanly(tmp_path, capsys, ["show", str(ds), "000000", "--out", str(out)],
                  f"--out {out}: is a directory; expected a file name")


def test_show_out_under_a_file(tmp_path, capsys, ds, a_file) -> None:
    fails_cleanly(tmp_path, capsys, ["show", str(ds), "000000", "--out", str(a_file / "x.png")],
                  f"{a_file} is not a directory")


def test_eval_json_is_a_directory(tmp_path, capsys, ds) -> None:
    labels = str(ds / "training" / "label_2")
    out = tmp_path / "json_dir"
    out.mkdir()
    fails_cleanly(tmp_path, capsys, ["eval", "--gt", labels, "--pred", str(tmp_path / "json_dir"), "--json", str(out)],
                  f"--json {out}: is a directory")


def test_eval_json_not_writable(tmp_path, capsys, ds) -> None:
    labels = str(ds / "training" / "label_2")
    pred = tmp_path / "pred"
    pred.mkdir()
    fails_cleanly(tmp_path, capsys, ["eval", "--gt", labels, "--pred", str(pred), "--json", "/proc/rb3d.json"],
                  "--json /proc/rb3d.json: cannot create files in /proc")


def test_data_stats_json_under_a_file(tmp_path, capsys, ds, a_file) -> None:
    fails_cleanly(tmp_path, capsys, ["data", "stats", str(ds), "--json", str(a_file / "s.json")],
                  f"{a_file} is not a directory")


def test_export_onnx_out_is_an_existing_file(tmp_path, capsys, a_file) -> None:
    fails_cleanly(tmp_path, capsys, ["export-onnx", "fpointnet-v1-lite", "--out", str(a_file), "--exporter", "dynamo"],
                  f"--out {a_file}: exists and is not a directory")


def test_victims_pack_out_is_a_directory(tmp_path, capsys) -> None:
    out = tmp_path / "weights"
    out.mkdir()
    fails_cleanly(tmp_path, capsys, ["victims", "pack", "--yolo", "y.pt", "--fpointnet", "f.pt", "--out", str(out)],
                  f"--out {out}: is a directory")


def test_train_yolo_out_is_an_existing_file(tmp_path, capsys, ds, a_file) -> None:
    fails_cleanly(tmp_path, capsys, ["train", "yolo", "--data", str(ds), "--out", str(a_file)],
                  f"--out {a_file}: exists and is not a directory")


def test_train_fpointnet_out_under_a_file(tmp_path, capsys, ds, a_file) -> None:
    fails_cleanly(tmp_path, capsys, ["train", "fpointnet", "--data", str(ds), "--out", str(a_file / "fpn")],
                  f"{a_file} is not a directory")


# ---- unreadable or unusable data ---------------------------------------------------------------------
def test_velodyne_bin_that_is_a_directory(tmp_path, capsys, ds) -> None:
    scan = ds / "training" / "velodyne" / "000000.bin"
    scan.unlink()
    scan.mkdir()
    fails_cleanly(tmp_path, capsys, ["data", "stats", str(ds)], f"{scan}: is a directory, expected a file")
    fails_cleanly(tmp_path, capsys, ["show", str(ds), "000000", "--out", str(tmp_path / "x.png")],
                  f"{scan}: is a directory")


def test_label_2_symlink_loop_in_run(tmp_path, capsys, ds) -> None:
    labels = ds / "training" / "label_2"
    (labels / "000000.txt").unlink()
    labels.rmdir()
    labels.symlink_to("label_2")  # label_2 -> label_2
    out = tmp_path / "run"
    line = fails_cleanly(tmp_path, capsys, ["run", "--victims", "fpointnet-v1-lite", "--data", str(ds),
                                            "--out", str(out), "--no-progress"], "label_2/000000.txt: cannot read")
    assert "symbolic links" in line
    assert not out.exists()


def test_label_2_symlink_loop_is_not_a_frame_without_labels(tmp_path, capsys, ds) -> None:
    labels = ds / "training" / "label_2"
    (labels / "000000.txt").unlink()
    labels.rmdir()
    labels.symlink_to("label_2")
    fails_cleanly(tmp_path, capsys, ["show", str(ds), "000000", "--out", str(tmp_path / "x.png")],
                  "label_2/000000.txt: cannot read")


def test_data_stats_on_an_empty_scan(tmp_path, capsys) -> None:
    ds = tiny_dataset(tmp_path / "ds", scan=np.zeros((0, 4), dtype=np.float32))
    fails_cleanly(tmp_path, capsys, ["data", "stats", str(ds)],
                  "velodyne/000000.bin: empty scan (0 points)")


def test_show_image_of_the_wrong_size(tmp_path, capsys, ds) -> None:
    write_image(ds / "training" / "image_2" / "000000.png", np.zeros((187, 621, 3), dtype=np.uint8))
    fails_cleanly(tmp_path, capsys, ["show", str(ds), "000000", "--out", str(tmp_path / "x.png")],
                  "image_2/000000.png: field 'size': image 621x187 does not match its calibration")


def test_run_on_negative_label_dimensions(tmp_path, capsys, ds) -> None:
    (ds / "training" / "label_2" / "000000.txt").write_text(CAR.replace("1.60 3.90", "-1.60 3.90"))
    fails_cleanly(tmp_path, capsys, ["run", "--victims", "fpointnet-v1-lite", "--data", str(ds),
                                     "--out", str(tmp_path / "run"), "--no-progress"],
                  "label_2/000000.txt:1: field 'dimensions'")


@needs_plugin
def test_run_fails_on_a_scan_directory_and_removes_its_new_out(tmp_path, capsys, ds) -> None:
    """The scan is read inside a cell: the run stops, and the directory it created goes away."""
    scan = ds / "training" / "velodyne" / "000000.bin"
    scan.unlink()
    scan.mkdir()
    out = tmp_path / "run"
    fails_cleanly(tmp_path, capsys, ["run", "--victims", "lidar-cluster", "--data", str(ds), "--out", str(out),
                                     "--no-progress"], f"{scan}: is a directory")
    assert not out.exists()


def test_as_a_process_one_line_and_exit_2(tmp_path, ds) -> None:
    out = tmp_path / "pictures"
    out.mkdir()
    proc = subprocess.run([sys.executable, "-m", "robustbench3d", "show", str(ds), "000000", "--out", str(out)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr == f"robustbench3d: error: --out {out}: is a directory; expected a file name\n"
    assert list(out.iterdir()) == []


def test_remove_created_dir_never_removes_output(tmp_path) -> None:
    from robustbench3d.fileio import remove_created_dir

    scaffold = tmp_path / "scaffold"
    (scaffold / "cells" / "a" / "data.partial").mkdir(parents=True)
    (scaffold / ".lock").write_text("")
    assert remove_created_dir(scaffold) and not scaffold.exists()

    kept = tmp_path / "kept"
    (kept / "cells" / "a" / "data.partial").mkdir(parents=True)
    (kept / ".lock").write_text("")
    (kept / "cells" / "a" / "data.partial" / "000000.txt").write_text("result\n")
    assert not remove_created_dir(kept)
    assert (kept / "cells" / "a" / "data.partial" / "000000.txt").read_text() == "result\n"
