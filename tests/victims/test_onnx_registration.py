"""ONNX victims in the registry: ``victims add-onnx`` (user registry file in the cache), listing
without heavy imports, name rules, a broken registry file, and a directory given directly to
``run --victims``."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from robustbench3d.cli import main
from robustbench3d.errors import DataFormatError
from robustbench3d.fileio import sha256_file
from robustbench3d.registry import sanitise_name
from robustbench3d.testing import link_frames
from robustbench3d.victims import VICTIMS, create_victim
from robustbench3d.victims.cascade import FPointNetCascade
from robustbench3d.victims.onnx.export import legacy_exporter_available
from robustbench3d.victims.onnx.registration import user_registry_file
from robustbench3d.victims.onnx.runtime import OnnxCascade

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def onnx_dir(tmp_path_factory) -> Path:
    """An ONNX victim written by the export-onnx command (weights: a seeded untrained cascade)."""
    root = tmp_path_factory.mktemp("reg")
    FPointNetCascade.untrained("lite", "mini", seed=1).save(root / "w.pt")
    out = root / "My_Export.v1"
    exporter = "legacy" if legacy_exporter_available() else "dynamo"
    assert main(["export-onnx", "fpointnet-v1-lite", "--out", str(out), "--exporter", exporter,
                 "--victim-arg", f"weights={root / 'w.pt'}"]) == 0
    return out


def _env(cache: Path) -> dict[str, str]:
    return {"PATH": "", "ROBUSTBENCH3D_CACHE": str(cache), "ROBUSTBENCH3D_NO_PLUGINS": "1", "OMP_NUM_THREADS": "1"}


def test_add_onnx_registers_a_directory(onnx_dir, cache, capsys):
    assert main(["victims", "add-onnx", str(onnx_dir), "--name", "my-onnx"]) == 0
    assert "registered ONNX victim 'my-onnx'" in capsys.readouterr().out
    data = json.loads(user_registry_file().read_text())
    assert user_registry_file() == cache / "victims" / "onnx.json"
    assert data == {"format": "robustbench3d.onnx_victims/1", "victims": {"my-onnx": str(onnx_dir.resolve())}}
    info = VICTIMS.get("my-onnx").info
    assert info.capabilities.backend == "onnx" and not info.capabilities.gradients
    assert info.weights_sha256 == sha256_file(onnx_dir / "manifest.json")
    victim = create_victim("my-onnx", seed=2)
    assert isinstance(victim, OnnxCascade) and victim.settings.seed == 2
    # a fresh process finds it through the registry file, lists it, and imports neither torch nor onnxruntime
    code = ("import sys; from robustbench3d.victims import VICTIMS; info = VICTIMS.get('my-onnx').info; "
            "print(info.capabilities.backend, 'torch' in sys.modules, 'onnxruntime' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=_env(cache))
    assert out.stdout.split() == ["onnx", "False", "False"]
    listed = subprocess.run([sys.executable, "-m", "robustbench3d", "victims", "list", "--json", "my-*"],
                            capture_output=True, text=True, check=True, env=_env(cache))
    assert [r["name"] for r in json.loads(listed.stdout)] == ["my-onnx"]


def test_add_onnx_refuses_bad_names_and_directories(onnx_dir, cache, tmp_path, capsys):
    assert main(["victims", "add-onnx", str(onnx_dir), "--name", "fpointnet-v1"]) == 2
    assert "taken" in capsys.readouterr().err
    assert main(["victims", "add-onnx", str(onnx_dir), "--name", "My Victim"]) == 2
    assert "'my-victim'" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["victims", "add-onnx", str(tmp_path / "empty"), "--name", "empty"]) == 2
    assert f"{tmp_path / 'empty' / 'manifest.json'}: manifest not found" in capsys.readouterr().err
    assert main(["victims", "add-onnx", str(onnx_dir), "--name", "twice"]) == 0
    other = Path(str(onnx_dir) + "-copy")
    if not other.exists():
        import shutil

        shutil.copytree(onnx_dir, other)
    assert main(["victims", "add-onnx", str(other), "--name", "twice"]) == 2
    assert "--replace" in capsys.readouterr().err
    assert main(["victims", "add-onnx", str(other), "--name", "twice", "--replace"]) == 0
    assert json.loads(user_registry_file().read_text())["victims"]["twice"] == str(other.resolve())
    assert not user_registry_file().with_name("onnx.json.tmp").exists()


def test_a_broken_registry_file_does_not_break_other_victims(cache):
    path = cache / "victims" / "onnx.json"
    path.parent.mkdir(parents=True)
    path.write_text("{not json")
    proc = subprocess.run([sys.executable, "-m", "robustbench3d", "victims", "list", "fpointnet-v1"],
                          capture_output=True, text=True, env=_env(cache))
    assert proc.returncode == 0 and "fpointnet-v1" in proc.stdout
    assert f"ignoring the ONNX victim registry: {path}: not valid JSON" in proc.stderr


def test_victim_references_resolve_names_and_directories(onnx_dir, tmp_path):
    assert VICTIMS.resolve("fpointnet-v1") == "fpointnet-v1"
    assert sanitise_name("My_Export.v1") == "my_export.v1" and sanitise_name("  //") == ""
    name = VICTIMS.resolve(str(onnx_dir))
    assert name == "my_export.v1" and VICTIMS.resolve(str(onnx_dir) + os.sep) == name  # idempotent
    with pytest.raises(DataFormatError, match="not an ONNX victim directory"):
        VICTIMS.resolve(str(tmp_path))


def test_run_accepts_an_onnx_directory(onnx_dir, kitti_samples, tmp_path, capsys):
    data = link_frames(kitti_samples, tmp_path / "data", ["000002", "000003"])
    rc = main(["run", "--victims", str(onnx_dir), "--proposals", "gt", "--data", str(data), "--out",
               str(tmp_path / "out"), "--no-progress", "--victim-arg", f"{onnx_dir}:threads=1"])
    assert rc == 0, capsys.readouterr().err
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    cell = summary[0] if isinstance(summary, list) else summary["cells"][0]
    assert cell["victim"] == "my_export.v1" and cell["status"] == "ok"
    victim = cell["provenance"]["config"]["victim"]
    assert victim["capabilities"]["backend"] == "onnx" and victim["kwargs"] == {"threads": 1, "seed": 0}
    assert victim["weights_sha256"] == sha256_file(onnx_dir / "manifest.json")
    rows = (tmp_path / "out" / "cells" / "my_export.v1+none+gt" / "data" / "000003.txt").read_text().splitlines()
    assert len(rows) == 1 and rows[0].startswith("Car ")
