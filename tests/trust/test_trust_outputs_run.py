"""Trust, second pass: ``run``, ``tradeoff`` and ``data synth`` never replace what they did not write
without ``--force``, refuse a dangling ``--out`` link and an unreachable or malformed Ray address in one
line, and check every numeric option's range up front.

Each command is run through the CLI entry point; "nothing changed" is checked on the bytes of every
file under the test's directory, read here independently of the code under test.
"""

from __future__ import annotations

import csv
import importlib.util
import json
import os
import shutil
import socket
from pathlib import Path

import numpy as np
import pytest
from cli_checks import fails_cleanly

from robustbench3d.attacks import ATTACKS, register_attack
from robustbench3d.attacks.base import Attack
from robustbench3d.cli import main
from robustbench3d.kitti import write_split
from robustbench3d.testing import write_kitti_frame

REPO = Path(__file__).resolve().parents[2]
needs_plugin = pytest.mark.skipif(
    importlib.util.find_spec("rb3d_lidar_cluster") is None,
    reason="example plugin not installed: pip install -c constraints.txt -e examples/lidar_cluster_victim",
)
VICTIM = "lidar-cluster"
CLEAN = f"{VICTIM}+none+detector"
NOOP = "test-outputs-noop"
CAR = "Car 0.00 0 -1.57 500.00 150.00 700.00 250.00 1.50 1.60 3.90 0.00 1.65 15.00 -1.57\n"


@register_attack(NOOP, summary="TEST ONLY: returns every frame as it is (an attacked cell with the clean numbers)")
class NoopAttack(Attack):
    def apply(self, frame, targets, rng: np.random.Generator):
        return frame

    def describe(self):
        return {"noop": True}


@pytest.fixture(scope="module")
def dataset(shared_split) -> Path:
    """Four generated frames, all in the val split."""
    return shared_split(4, seed=5, val_fraction=1.0)


def run_argv(dataset: Path, out: Path, *extra: str, attacks: str = "none") -> list[str]:
    return ["run", "--victims", VICTIM, "--attacks", attacks, "--proposals", "detector", "--data", str(dataset),
            "--out", str(out), "--no-progress", "--jobs", "1", "--bootstrap", "20", *extra]


def result_names(cell_dir: Path) -> list[str]:
    return sorted(p.name for p in (cell_dir / "data").iterdir())


def read_cell(path: Path) -> dict:
    return json.loads(path.read_text(encoding="utf-8"))


# ---- 1. run: a finished cell of another configuration is never replaced silently --------------------------------
@needs_plugin
def test_run_refuses_a_finished_cell_of_another_max_frames_and_force_replaces_it(dataset, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(run_argv(dataset, out, "--max-frames", "4")) == 0
    capsys.readouterr()
    line = fails_cleanly(tmp_path, capsys, run_argv(dataset, out, "--max-frames", "3"),
                         f"--out {out}: finished cell {CLEAN}", "frames (--max-frames) 4 vs 3", "--force",
                         "another --out")
    assert "(and " not in line  # one cell, named
    assert result_names(out / "cells" / CLEAN) == [f"{i:06d}.txt" for i in range(4)]

    assert main(run_argv(dataset, out, "--max-frames", "3", "--force")) == 0
    err = capsys.readouterr().err
    assert f"replacing finished cell {CLEAN} (--force): on disk vs this run: frames (--max-frames) 4 vs 3" in err
    assert result_names(out / "cells" / CLEAN) == [f"{i:06d}.txt" for i in range(3)]
    assert read_cell(out / "cells" / CLEAN / "cell.json")["dataset"]["frames"] == 3


@needs_plugin
def test_run_refuses_another_object_file_of_the_same_name(dataset, tmp_path, capsys):
    first, second = tmp_path / "a" / "roof.ply", tmp_path / "b" / "roof.ply"
    for path, shipped in ((first, "adv-shape"), (second, "adv-object")):
        path.parent.mkdir()
        shutil.copy(REPO / "attacks" / "objects" / f"{shipped}.ply", path)
        shutil.copy(REPO / "attacks" / "objects" / f"{shipped}.json", path.with_suffix(".json"))
    out = tmp_path / "run"
    try:
        assert main(run_argv(dataset, out, "--max-frames", "2", attacks=str(first))) == 0
        capsys.readouterr()
        ATTACKS.unregister("roof")  # a new invocation registers the other file under the same name
        line = fails_cleanly(out, capsys, run_argv(dataset, out, "--max-frames", "2", attacks=str(second)),
                             f"finished cell {VICTIM}+roof+detector", "--force")
        from robustbench3d.fileio import sha256_file

        old_sha, new_sha = sha256_file(first), sha256_file(second)
        assert f"object sha256 {old_sha[:12]}… vs {new_sha[:12]}…" in line
        assert "keeping" not in line
    finally:
        if "roof" in ATTACKS:
            ATTACKS.unregister("roof")


@needs_plugin
def test_run_says_how_many_unchanged_finished_cells_it_keeps(dataset, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(run_argv(dataset, out, "--max-frames", "2", attacks=f"none,{NOOP}")) == 0
    capsys.readouterr()
    stamp = (out / "cells" / CLEAN / "cell.json").read_bytes()
    assert main(run_argv(dataset, out, "--max-frames", "2", attacks=f"none,{NOOP}")) == 0
    err = capsys.readouterr().err
    assert f"keeping 2 finished cell(s) already in {out}" in err
    assert (out / "cells" / CLEAN / "cell.json").read_bytes() == stamp


@needs_plugin
def test_an_attacked_cell_is_not_compared_with_a_clean_cell_of_other_victim_arguments(dataset, tmp_path, capsys):
    """The earlier attacked cell (default victim settings) stays in the summary (same dataset, seed and
    evaluation), but the clean cell now there was computed with another victim argument: no reference."""
    out = tmp_path / "run"
    attacked = f"{VICTIM}+{NOOP}+detector"
    assert main(run_argv(dataset, out, "--max-frames", "2", attacks=f"none,{NOOP}")) == 0
    capsys.readouterr()
    assert read_cell(out / "cells" / attacked / "cell.json")["attack_effect"]["clean_cell"] == CLEAN
    shutil.rmtree(out / "cells" / CLEAN)  # the state a --force rerun with the other argument leaves
    assert main(run_argv(dataset, out, "--max-frames", "2", "--victim-arg", f"{VICTIM}:max_range=60.0")) == 0
    err = capsys.readouterr().err
    summary = json.loads((out / "summary.json").read_text(encoding="utf-8"))
    assert [(c["attack"], c["provenance"]["config"]["victim"]["kwargs"].get("max_range")) for c in summary] == [
        ("none", 60.0), (NOOP, None)]
    assert summary[1]["attack_effect"] is None
    assert read_cell(out / "cells" / attacked / "cell.json")["attack_effect"] is None
    assert f"no clean reference for {VICTIM} / {NOOP} / detector" in err and "--victim-arg max_range" in err
    with open(out / "results.csv", newline="", encoding="utf-8") as f:
        rows = [r for r in csv.DictReader(f) if r["attack"] == NOOP]
    assert rows and all(r["clean_ap"] == "" for r in rows)


@needs_plugin
def test_a_clean_cell_of_another_frame_set_is_never_the_reference(dataset, tmp_path, capsys):
    """The earlier attacked cell covers 4 frames, the clean cell now there 3: the attacked cell is left out
    of the summary and its comparison is not recomputed against the 3-frame cell."""
    out = tmp_path / "run"
    attacked = out / "cells" / f"{VICTIM}+{NOOP}+detector"
    assert main(run_argv(dataset, out, "--max-frames", "4", attacks=f"none,{NOOP}")) == 0
    capsys.readouterr()
    before = (attacked / "cell.json").read_bytes()
    shutil.rmtree(out / "cells" / CLEAN)
    assert main(run_argv(dataset, out, "--max-frames", "3")) == 0
    err = capsys.readouterr().err
    summary = json.loads((out / "summary.json").read_text(encoding="utf-8"))
    assert [(c["attack"], c["dataset"]["frames"]) for c in summary] == [("none", 3)]
    assert f"left out of the summary: {attacked.name}: another dataset: frames 4 (this run: 3)" in err
    assert (attacked / "cell.json").read_bytes() == before


@needs_plugin
def test_replacing_a_clean_cell_names_the_attacked_cells_compared_with_it(dataset, tmp_path, capsys):
    out = tmp_path / "run"
    attacked = f"{VICTIM}+{NOOP}+detector"
    assert main(run_argv(dataset, out, "--max-frames", "4", attacks=f"none,{NOOP}")) == 0
    capsys.readouterr()
    note = (f"1 attacked cell(s) of earlier runs are compared with it and lose their clean reference when it is "
            f"replaced: {attacked}")
    fails_cleanly(out, capsys, run_argv(dataset, out, "--max-frames", "3"), f"finished cell {CLEAN}", note)
    assert main(run_argv(dataset, out, "--max-frames", "3", "--force")) == 0
    err = capsys.readouterr().err
    assert f"replacing finished cell {CLEAN} (--force)" in err and note in err
    summary = json.loads((out / "summary.json").read_text(encoding="utf-8"))
    assert [(c["attack"], c["dataset"]["frames"]) for c in summary] == [("none", 3)]


# ---- 2. tradeoff: its own directory only ---------------------------------------------------------------------------
def tradeoff_argv(dataset: Path, out: Path, *extra: str, frames: str = "3") -> list[str]:
    return ["tradeoff", "--out", str(out), "--data", str(dataset), "--frames", frames, "--victim", VICTIM,
            "--attack", NOOP, "--sweeps", "frames", "--resamples", "20", "--no-progress", *extra]


@needs_plugin
def test_tradeoff_refuses_a_run_directory(dataset, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(run_argv(dataset, out, "--max-frames", "2")) == 0
    capsys.readouterr()
    fails_cleanly(tmp_path, capsys, tradeoff_argv(dataset, out), f"--out {out}: is a `robustbench3d run` directory",
                  "--force")
    other = tmp_path / "notes"
    other.mkdir()
    (other / "notes.txt").write_text("mine\n")
    fails_cleanly(tmp_path, capsys, tradeoff_argv(dataset, other), f"--out {other}: is not empty and not a tradeoff "
                  "directory")


@needs_plugin
def test_tradeoff_resumes_its_own_and_refuses_another_configuration(dataset, tmp_path, capsys):
    out = tmp_path / "t"
    assert main(tradeoff_argv(dataset, out)) == 0
    capsys.readouterr()
    cells = sorted(p.name for p in (out / "cells").iterdir())
    assert len(cells) == 2  # the default setting, clean and attacked
    assert main(tradeoff_argv(dataset, out)) == 0  # the same configuration: resumed, every cell kept
    assert f"tradeoff: keeping 2 finished cell(s) already in {out}" in capsys.readouterr().err

    fails_cleanly(tmp_path, capsys, tradeoff_argv(dataset, out, frames="2"),
                  f"--out {out}: holds a tradeoff of another configuration", "--frames 3 vs 2", "--force")
    fails_cleanly(tmp_path, capsys, tradeoff_argv(dataset, out, "--tolerance", "2"), "--tolerance 1.0 vs 2.0")
    (out / "tradeoff.json").unlink()  # an interrupted run of 3 frames: its finished cells are checked one by one
    line = fails_cleanly(tmp_path, capsys, tradeoff_argv(dataset, out, frames="2"), "finished tradeoff cell",
                         "frames (--frames) 3 vs 2", "--force")
    assert any(f"cell {name}" in line for name in cells)

    assert main(tradeoff_argv(dataset, out, "--force", frames="2")) == 0
    err = capsys.readouterr().err
    assert sum(f"tradeoff: replacing finished cell {name} (--force)" in err for name in cells) == 2
    assert json.loads((out / "tradeoff.json").read_text(encoding="utf-8"))["dataset"]["frames"] == 2


# ---- 3. a dangling symbolic link as --out ----------------------------------------------------------------------
@pytest.mark.parametrize("command", ["run", "tradeoff", "data synth"])
def test_a_dangling_out_link_is_refused_in_one_line(tmp_path, capsys, monkeypatch, command):
    ds = tmp_path / "ds"
    write_kitti_frame(ds, "000000", scan=np.zeros((10, 4), np.float32), labels=CAR)
    write_split(ds / "ImageSets" / "val.txt", ["000000"])
    link = tmp_path / "out"
    link.symlink_to(tmp_path / "nowhere")
    monkeypatch.setenv("ROBUSTBENCH3D_CACHE", str(tmp_path / "cache"))
    argv = {"run": ["run", "--victims", "fpointnet-v1-lite", "--data", str(ds), "--no-progress"],
            "tradeoff": ["tradeoff", "--data", str(ds), "--frames", "1", "--sweeps", "frames", "--no-progress"],
            "data synth": ["data", "synth", "--frames", "1", "--workers", "1", "--no-progress"]}[command]
    line = fails_cleanly(tmp_path, capsys, [*argv, "--out", str(link)], f"--out {link}", "broken symbolic link")
    assert line.endswith(f"(to {tmp_path / 'nowhere'})")
    assert not (tmp_path / "nowhere").exists()


# ---- 4. Ray addresses ----------------------------------------------------------------------------------------
def closed_port() -> int:
    """A local TCP port nothing listens on (bound, then released)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("form", ["{port}", "ray://{port}"])
def test_run_refuses_a_ray_address_nothing_listens_on(tmp_path, capsys, form):
    pytest.importorskip("ray")
    address = form.replace("{port}", f"127.0.0.1:{closed_port()}")
    line = fails_cleanly(tmp_path, capsys, ["run", "--victims", "fpointnet-v1-lite", "--executor", "ray", "--address",
                                            address, "--data", str(tmp_path / "ds"), "--out", str(tmp_path / "r"),
                                            "--no-progress"], f"--address {address}: connection refused")
    assert "ray start --head" in line


@pytest.mark.parametrize("address", ["127.0.0.1", "127.0.0.1:0", "127.0.0.1:65536", "head:port", ":6379", "ray://",
                                     "http://127.0.0.1:6379", "head:6379:1", "a b:6379"])
def test_run_refuses_a_malformed_ray_address(tmp_path, capsys, address):
    pytest.importorskip("ray")
    fails_cleanly(tmp_path, capsys, ["run", "--victims", "fpointnet-v1-lite", "--executor", "ray", "--address", address,
                                     "--data", str(tmp_path / "ds"), "--out", str(tmp_path / "r"), "--no-progress"],
                  f"--address {address!r}: expected HOST:PORT (port 1..65535), ray://HOST:PORT, auto or local")


# ---- 5. numeric options: documented ranges, enforced up front ----------------------------------------------------
CPUS = os.cpu_count() or 1
RANGES = [
    ("run", "--max-frames", "0", "in 1..1000000"), ("run", "--max-frames", "1000001", "in 1..1000000"),
    ("run", "--seed", "-1", "in 0..4294967295"), ("run", "--seed", "4294967296", "in 0..4294967295"),
    ("run", "--batch-size", "0", "in 1..256"), ("run", "--batch-size", "257", "in 1..256"),
    ("run", "--workers", "0", "in 1..1024"), ("run", "--workers", "1025", "in 1..1024"),
    ("run", "--jobs", "0", "in 1..1024"), ("run", "--jobs", "1025", "in 1..1024"),
    ("run", "--bootstrap", "-1", "0 (no intervals) or in 10..100000"),
    ("run", "--bootstrap", "5", "0 (no intervals) or in 10..100000"),
    ("run", "--bootstrap", "100001", "0 (no intervals) or in 10..100000"),
    ("tradeoff", "--frames", "1000001", "in 1..1000000"), ("tradeoff", "--threads", "0", f"in 1..{CPUS}"),
    ("tradeoff", "--threads", str(CPUS + 1), f"in 1..{CPUS}"), ("tradeoff", "--resamples", "9", "in 10..100000"),
    ("tradeoff", "--resamples", "100001", "in 10..100000"), ("tradeoff", "--tolerance", "-0.5", "in 0.0..100.0"),
    ("tradeoff", "--tolerance", "100.5", "in 0.0..100.0"), ("tradeoff", "--tolerance", "nan", "in 0.0..100.0"),
    ("tradeoff", "--tolerance", "inf", "in 0.0..100.0"), ("tradeoff", "--seed", "-1", "in 0..4294967295"),
    ("tradeoff", "--seed", "4294967296", "in 0..4294967295"), ("tradeoff", "--batch-size", "257", "in 1..256"),
    ("data synth", "--frames", "0", "in 1..1000000"), ("data synth", "--frames", "1000001", "in 1..1000000"),
    ("data synth", "--seed", "-1", "in 0..4294967295"), ("data synth", "--seed", "4294967296", "in 0..4294967295"),
    ("data synth", "--val-fraction", "1.5", "in 0.0..1.0"), ("data synth", "--val-fraction", "nan", "in 0.0..1.0"),
    ("data synth", "--workers", "0", "in 1..1024"), ("data synth", "--workers", "1025", "in 1..1024"),
]


@pytest.mark.parametrize(("command", "option", "value", "rule"), RANGES)
def test_numeric_options_outside_their_range_are_refused_up_front(tmp_path, capsys, monkeypatch, command, option,
                                                                  value, rule):
    def no_work(*args, **kwargs):
        raise AssertionError(f"{command} started working with {option} {value}")

    monkeypatch.setattr("robustbench3d.runner.run_benchmark", no_work)
    monkeypatch.setattr("robustbench3d.tradeoff.run.run_tradeoff", no_work)
    monkeypatch.setattr("robustbench3d.synth.writer.generate_dataset", no_work)
    monkeypatch.setenv("ROBUSTBENCH3D_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "out"
    argv = {"run": ["run", "--victims", "fpointnet-v1-lite", "--data", str(tmp_path)],
            "tradeoff": ["tradeoff", "--data", str(tmp_path)], "data synth": ["data", "synth"]}[command]
    line = fails_cleanly(tmp_path, capsys, [*argv, "--out", str(out), option, value], f"{option} must be")
    assert rule in line and line.endswith(f"got {float(value) if '.' in value or value.isalpha() else int(value)!r}")


def test_the_range_boundaries_are_accepted():
    from robustbench3d.commands.run import check_bootstrap, check_range
    from robustbench3d.runner import RunConfig

    for value in (1, 1_000_000):
        check_range("--frames", value, 1, 1_000_000, "frames")
    for value in (0, 10, 100_000):
        check_bootstrap(value)
    check_range("--tolerance", 0.0, 0.0, 100.0, "AP points", integer=False)
    check_range("--tolerance", 100, 0.0, 100.0, "AP points", integer=False)
    config = RunConfig(("v",), ("none",), ("gt",), "o", max_frames=1_000_000, seed=2**32 - 1, batch_size=256,
                       workers=1024, bootstrap=100_000)
    assert (config.seed, config.batch_size) == (2**32 - 1, 256)
