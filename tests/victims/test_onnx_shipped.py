"""The shipped ONNX exports of the shipped cascades: registered, pinned to the shipped torch weights,
reproducible byte for byte by their recorded commands, and at parity with the torch victims.
``fpointnet-v1-onnx`` shares its 2D-stage graph with ``fpointnet-v1-lite-onnx`` (one copy ships)."""

from __future__ import annotations

import hashlib
import shlex
import shutil

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
#: shipped ONNX twin -> the torch victim it was exported from
TWINS = {"fpointnet-v1-lite-onnx": "fpointnet-v1-lite", "fpointnet-v1-onnx": "fpointnet-v1"}


@pytest.fixture(scope="module", params=sorted(TWINS))
def twin(request):
    """(ONNX victim name, its directory, the torch victim name)."""
    return request.param, weights_dir() / SHIPPED[request.param], TWINS[request.param]


def test_every_shipped_twin_is_tested():
    assert set(SHIPPED) == set(TWINS)


def test_shipped_export_is_registered_and_pinned_to_the_shipped_weights(twin):
    name, onnx_dir, torch_name = twin
    manifest = read_manifest(onnx_dir)
    manifest_sha = hashlib.sha256((onnx_dir / "manifest.json").read_bytes()).hexdigest()
    assert VICTIMS.get(name).info.weights_sha256 == manifest_sha
    assert VICTIMS.get(name).info.capabilities.backend == "onnx"
    assert manifest.source["victim"] == torch_name and manifest.source["kwargs"] == {}
    assert manifest.source["weights_sha256"] == shipped(torch_name).sha256
    for stage in manifest.stages:
        assert hashlib.sha256((onnx_dir / stage.file).read_bytes()).hexdigest() == stage.sha256


def test_the_full_twin_ships_no_second_copy_of_the_2d_stage():
    full, lite = (weights_dir() / SHIPPED[n] for n in ("fpointnet-v1-onnx", "fpointnet-v1-lite-onnx"))
    detector = read_manifest(full).stage("detector_2d")
    assert detector.file == "../fpointnet-v1-lite-onnx/detector_2d.onnx"
    assert detector.sha256 == read_manifest(lite).stage("detector_2d").sha256
    assert not (full / "detector_2d.onnx").exists()
    assert shipped("fpointnet-v1").record["shared"]["yolo"] == {
        "file": "fpointnet-v1-lite.pt", "sha256": shipped("fpointnet-v1-lite").sha256}


def test_shipped_export_is_reproduced_by_its_command(twin, tmp_path):
    import onnx
    import onnxscript

    onnx_dir = twin[1]
    manifest = read_manifest(onnx_dir)
    ex = manifest.exporter
    here = {"torch": torch.__version__, "onnx": onnx.__version__, "onnxscript": onnxscript.__version__}
    if any(ex[k] != v for k, v in here.items() if ex.get(k) is not None):
        pytest.skip(f"installed exporter versions {here} differ from the recorded {ex}; "
                    "byte-reproduction holds only for the recorded versions")
    for stage in manifest.stages:  # a shared graph's sibling directory, beside the output as shipped
        if stage.file.startswith("../"):
            sibling = (onnx_dir / stage.file).parent
            if not (tmp_path / sibling.name).exists():
                shutil.copytree(sibling, tmp_path / sibling.name)
    argv = shlex.split(manifest.reproduce["command"].replace("DIR", str(tmp_path / "again")))
    assert argv[:2] == ["robustbench3d", "export-onnx"]
    assert main(argv[1:]) == 0
    again = read_manifest(tmp_path / "again")
    assert [(s.name, s.file, s.sha256) for s in again.stages] == [(s.name, s.file, s.sha256) for s in manifest.stages]


def test_shipped_export_matches_the_torch_victim(twin, shared_split):
    # every frame, whatever the split: a frame's files depend on (seed, index) only, not on val_fraction
    ds = KittiDataset(shared_split(3, seed=0, val_fraction=1.0), split=None)
    frames = [ds.frame(f) for f in ds.frame_ids]
    _, onnx_dir, torch_name = twin
    victim = create_victim(torch_name)
    onnx_victim = OnnxCascade(onnx_dir, seed=victim.settings.seed, gather=victim.settings.gather)
    report = run_parity(victim, onnx_victim, frames)
    assert report.ok, report.to_dict()
    assert all(b.rows_torch > 0 for b in report.boxes)  # the trained detector finds the cars
