"""The weights that ship with the package: manifest, hashes, registry, loading, provenance.

Hashes are recomputed here with hashlib (independently of :func:`robustbench3d.fileio.sha256_file`).
"""

from __future__ import annotations

import hashlib
import json
import shlex
import shutil
from pathlib import Path

import pytest
import torch

from robustbench3d.errors import DataFormatError, RobustBenchError
from robustbench3d.victims import VICTIMS, create_victim
from robustbench3d.victims.shipped import MANIFEST_FORMAT, read_manifest, shipped, weights_dir

MAX_TOTAL_BYTES = 50 * 1024 * 1024  # from 30 MiB for fpointnet-v1 (issue 17), from 40 for pointpillars + twin (#35)


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_manifest_lists_the_lite_cascade_with_matching_hashes():
    data = read_manifest()
    assert data["format"] == MANIFEST_FORMAT
    names = [e["victim"] for e in data["weights"]]
    assert "fpointnet-v1-lite" in names
    for entry in data["weights"]:
        path = weights_dir() / entry["file"]
        assert path.is_file(), path
        assert path.stat().st_size == entry["size_bytes"]
        assert _sha256(path) == entry["sha256"]
        assert VICTIMS.get(entry["victim"]).info.weights_sha256 == entry["sha256"]


def test_everything_shipped_fits_the_size_budget():
    total = sum(p.stat().st_size for p in weights_dir().rglob("*") if p.is_file())
    assert 0 < total <= MAX_TOTAL_BYTES


def test_manifest_records_how_the_weights_were_made_and_measured():
    entry = shipped("fpointnet-v1-lite").record
    script = (weights_dir() / entry["reproduce"]["script"]).read_text(encoding="utf-8")
    commands = [ln for ln in script.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    assert entry["reproduce"]["commands"] == commands
    runs: dict[str, list[list[str]]] = {}
    for c in commands:
        if c.startswith("robustbench3d train "):
            argv = shlex.split(c)
            runs.setdefault(argv[2], []).append(argv)
    assert set(runs) == {"yolo", "fpointnet"}
    for net, argvs in runs.items():
        # the last run of a network made the shipped weights; each earlier one is the --init of the next
        record = entry["training"][net]
        for argv in reversed(argvs):
            assert record["run_config"]["loop"]["seed"] == int(argv[argv.index("--seed") + 1])
            assert record["run_config"]["loop"]["batch_size"] == int(argv[argv.index("--batch-size") + 1])
            assert record["epochs"] == int(argv[argv.index("--epochs") + 1])
            layout = argv[argv.index("--layout") + 1] if "--layout" in argv else None
            assert layout is None or record["run_config"]["task"]["layout"] == layout
            record = record.get("init")
        assert record is None
    assert entry["networks"]["fpointnet"]["config"]["name"] == "lite"
    assert entry["networks"]["yolo"]["config"]["layout"] == "mini3"
    acc = entry["accuracy"]
    assert set(acc["cells"]) == {"detector", "gt"}
    assert acc["dataset"]["embedded"]["seed"] == 0 and acc["dataset"]["split"] == "val"
    for cell in acc["cells"].values():
        for metric in ("2d", "bev", "3d"):
            for rp in ("R40", "R11"):
                assert set(cell[metric][rp]) == {"easy", "moderate", "hard"}


def test_default_victim_loads_the_shipped_file():
    victim = create_victim("fpointnet-v1-lite")
    data = torch.load(shipped("fpointnet-v1-lite").path, map_location="cpu", weights_only=True)
    for name, tensor in data["fpointnet"]["state_dict"].items():
        assert torch.equal(victim.fpn.state_dict()[name], tensor), name
    for name, tensor in data["yolo"]["state_dict"].items():
        assert torch.equal(victim.yolo.net.state_dict()[name], tensor), name


def test_a_tampered_or_missing_file_is_refused(tmp_path):
    entry = shipped("fpointnet-v1-lite")
    shutil.copy(entry.path, tmp_path / entry.path.name)
    manifest = tmp_path / "manifest.json"
    manifest.write_text(json.dumps(read_manifest()), encoding="utf-8")
    copy = shipped("fpointnet-v1-lite", manifest)
    copy.verify()
    with open(copy.path, "r+b") as f:
        f.seek(copy.size_bytes // 2)
        byte = f.read(1)
        f.seek(copy.size_bytes // 2)
        f.write(bytes([byte[0] ^ 1]))
    with pytest.raises(RobustBenchError, match="does not match the sha256"):
        copy.verify()
    copy.path.unlink()
    with pytest.raises(RobustBenchError, match="missing"):
        copy.verify()


def test_bad_manifest_names_the_file_and_field(tmp_path):
    bad = tmp_path / "manifest.json"
    bad.write_text("{not json", encoding="utf-8")
    with pytest.raises(DataFormatError, match=r"manifest\.json: not valid JSON"):
        read_manifest(bad)
    bad.write_text(json.dumps({"format": MANIFEST_FORMAT, "weights": [{"victim": "x", "file": "x.pt"}]}),
                   encoding="utf-8")
    with pytest.raises(DataFormatError, match=r"weights\[0\]: field 'sha256' is missing"):
        read_manifest(bad)


def test_full_v1_loads_its_shipped_full_width_network():
    entry = shipped("fpointnet-v1")
    assert entry is not None
    victim = create_victim("fpointnet-v1")
    cfg = entry.record["networks"]["fpointnet"]["config"]
    assert cfg["name"] == "full" and cfg["num_points"] == 1024 and cfg["seg_global_mlp"] == [128, 1024]
    assert victim.fpn.cfg.num_points == 1024
    data = torch.load(entry.path, map_location="cpu", weights_only=True)
    sd = data["fpointnet"]["state_dict"]
    assert all(torch.equal(v, sd[k]) for k, v in victim.fpn.state_dict().items())
    # the same 2D stage as the lite cascade
    assert entry.record["networks"]["yolo"]["state_sha256"] == \
        shipped("fpointnet-v1-lite").record["networks"]["yolo"]["state_sha256"]


def test_full_v1_manifest_matches_its_reproduce_script():
    entry = shipped("fpointnet-v1").record
    script = (weights_dir() / entry["reproduce"]["script"]).read_text(encoding="utf-8")
    commands = [ln for ln in script.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    assert entry["reproduce"]["commands"] == commands
    (train,) = [shlex.split(c) for c in commands if c.startswith("robustbench3d train fpointnet")]
    record = entry["training"]["fpointnet"]
    task, loop = record["run_config"]["task"], record["run_config"]["loop"]
    assert task["model"] == train[train.index("--model") + 1] == "full"
    assert record["epochs"] == int(train[train.index("--epochs") + 1])
    assert loop["batch_size"] == int(train[train.index("--batch-size") + 1])
    assert loop["seed"] == int(train[train.index("--seed") + 1])
    assert task["lr"] == float(train[train.index("--lr") + 1])
    assert task["bn_decay_step"] == int(train[train.index("--bn-decay-step") + 1])
    assert task["cache"] is ("--cache" in train)
    assert record["steps"] == record["epochs"] * -(-task["train_frustums"] // loop["batch_size"])
    assert record["device"]["wall_seconds"] > 0 and record["device"]["peak_gpu_mib"] > 0
    for cell in entry["accuracy"]["cells"].values():
        for metric in ("2d", "bev", "3d"):
            for rp in ("R40", "R11"):
                assert set(cell[metric][rp]) == {"easy", "moderate", "hard"}
