"""Dataset resolution for ``run``: the embedded dataset is generated in the cache when missing and
recorded with its generator parameters; bad ``--data`` / ``--split`` arguments name the path."""

from __future__ import annotations

import pytest

from robustbench3d import datasets
from robustbench3d.datasets import EmbeddedParams, resolve_dataset
from robustbench3d.errors import DataFormatError
from robustbench3d.runner import RunConfig, run_benchmark
from robustbench3d.synth import DEFAULT_FRAMES, DEFAULT_SEED, DEFAULT_VAL_FRACTION
from robustbench3d.victims import VICTIMS
from robustbench3d.victims.spec import Capabilities, EntryInfo, VictimSpec

TINY = EmbeddedParams(frames=2, seed=4, val_fraction=1.0)


class NothingDetector:
    """TEST ONLY: detects nothing (keeps this test independent of any real victim)."""

    supported_proposals = ("detector",)

    def detect(self, frames, proposals="detector"):
        from robustbench3d.kitti.labels import Labels

        return [Labels.empty(with_score=True) for _ in frames]


VICTIMS.register("test-nothing", VictimSpec(
    factory=NothingDetector,
    info=EntryInfo(Capabilities(modalities=("lidar",), backend="other", gradients=False, deterministic=True))))


def test_embedded_defaults_are_the_data_synth_defaults():
    assert (datasets.EMBEDDED.frames, datasets.EMBEDDED.seed, datasets.EMBEDDED.val_fraction) == (
        DEFAULT_FRAMES, DEFAULT_SEED, DEFAULT_VAL_FRACTION)


def test_embedded_dataset_is_generated_once_in_the_cache_and_recorded(tmp_path, monkeypatch):
    monkeypatch.setenv("ROBUSTBENCH3D_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(datasets, "EMBEDDED", TINY)
    report = run_benchmark(RunConfig(victims=("test-nothing",), attacks=("none",), proposals=("detector",),
                                     out=tmp_path / "run", progress=False), lambda line: None)
    root = tmp_path / "cache" / "datasets" / "synth"
    cell = report.cells[0]
    assert cell["status"] == "ok" and cell["dataset"]["root"] == str(root.resolve())
    assert cell["dataset"]["embedded"] == {"generator": "robustbench3d.synth", "generator_version": 1,
                                           "frames": 2, "seed": 4, "val_fraction": 1.0}
    assert cell["dataset"]["frames"] == 2 and cell["metrics"]["meta"]["frames"] == 2
    scan = root / "training" / "velodyne" / "000001.bin"
    stamp = scan.stat().st_mtime_ns
    again = resolve_dataset(None, "val")
    assert again.root == root.resolve() and scan.stat().st_mtime_ns == stamp  # complete: not regenerated


def test_bad_data_arguments_name_the_path(tmp_path):
    with pytest.raises(DataFormatError, match="nowhere: dataset directory not found"):
        resolve_dataset(tmp_path / "nowhere")
    (tmp_path / "flat").mkdir()
    with pytest.raises(DataFormatError, match=r"flat/training: not a directory; expected the KITTI layout"):
        resolve_dataset(tmp_path / "flat")
    root = tmp_path / "kitti"
    (root / "training").mkdir(parents=True)
    (root / "ImageSets").mkdir()
    (root / "ImageSets" / "train.txt").write_text("000000\n")
    with pytest.raises(DataFormatError, match=r"ImageSets/val\.txt: split file not found \(available splits: train\)"):
        resolve_dataset(root, "val")
    assert resolve_dataset(root, "train").split_file == (root / "ImageSets" / "train.txt").resolve()


def test_embedded_completeness_needs_every_frame(tmp_path):
    root = tmp_path / "synth"
    datasets.ensure_embedded(root, TINY, progress=False)
    label = root / "training" / "label_2" / "000000.txt"
    label.unlink()  # an interrupted generation: the frame is incomplete
    datasets.ensure_embedded(root, TINY, progress=False)
    assert label.is_file()
