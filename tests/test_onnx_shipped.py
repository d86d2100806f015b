"""The shipped ONNX export of the shipped cascade: registered, pinned to the shipped torch weights,
reproducible byte for byte by its recorded command, and at parity with the torch victim."""

from __future__ import annotations

import hashlib
import shlex

import pytest
import torch

from robustbench3d.cli import main
from robustbench3d.kitti.dataset import KittiDataset
from robustbench3d.victims import VICTIMS, create_victim
from robustbench3d.victims.onnx.manifest import read_manifest
from robustbench3d.victims.onnx.parity import run_parity
from robustbench3d.victims.onnx.registration import SHIPPED
from robustbench3d.victims.onnx.runtime import OnnxCascade
from robustbench3d.victims.shipped import shipped, weights_dir

torch.set_num_threads(1)
NAME = "fpointnet-v1-lite-onnx"


@pytest.fixture(scope="module")
def onnx_dir():
    return weights_dir() / SHIPPED[NAME]


def test_shipped_export_is_registered_and_pinned_to_the_shipped_weights(onnx_dir):
    manifest = read_manifest(onnx_dir)
    manifest_sha = hashlib.sha256((onnx_dir / "manifest.json").read_bytes()).hexdigest()
    assert VICTIMS.get(NAME).info.weights_sha256 == manifest_sha
    assert VICTIMS.get(NAME).info.capabilities.backend == "onnx"
    assert manifest.source["victim"] == "fpointnet-v1-lite" and manifest.source["kwargs"] == {}
    assert manifest.source["weights_sha256"] == shipped("fpointnet-v1-lite").sha256
    for stage in manifest.stages:
        assert hashlib.sha256((onnx_dir / stage.file).read_bytes()).hexdigest() == stage.sha256


def test_shipped_export_is_reproduced_by_its_command(onnx_dir, tmp_path):
    import onnx
    import onnxscript

    manifest = read_manifest(onnx_dir)
    ex = manifest.exporter
    here = {"torch": torch.__version__, "onnx": onnx.__version__, "onnxscript": onnxscript.__version__}
    if any(ex[k] != v for k, v in here.items() if ex.get(k) is not None):
        pytest.skip(f"installed exporter versions {here} differ from the recorded {ex}; "
                    "byte-reproduction holds only for the recorded versions")
    argv = shlex.split(manifest.reproduce["command"].replace("DIR", str(tmp_path / "again")))
    assert argv[:2] == ["robustbench3d", "export-onnx"]
    assert main(argv[1:]) == 0
    again = read_manifest(tmp_path / "again")
    assert [(s.name, s.sha256) for s in again.stages] == [(s.name, s.sha256) for s in manifest.stages]


def test_shipped_export_matches_the_torch_victim(onnx_dir, tmp_path):
    from robustbench3d.testing import synth_dataset

    synth_dataset(tmp_path / "synth", 3, seed=0)
    ds = KittiDataset(tmp_path / "synth", split=None)
    frames = [ds.frame(f) for f in ds.frame_ids]
    victim = create_victim("fpointnet-v1-lite")
    onnx_victim = OnnxCascade(onnx_dir, seed=victim.settings.seed, gather=victim.settings.gather)
    report = run_parity(victim, onnx_victim, frames)
    assert report.ok, report.to_dict()
    assert all(b.rows_torch > 0 for b in report.boxes)  # the trained detector finds the cars
