"""A test-only oracle victim (ground-truth boxes as detections) through the whole runner path
must score AP 100, as the evaluator does for GT against GT. The harness never hands a victim
labels (see tests/trust/test_trust_integrity.py), so the oracle is given the label directory by the
test, openly, as a factory argument."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from robustbench3d.eval import evaluate
from robustbench3d.kitti import Labels, write_split
from robustbench3d.kitti.labels import read_labels
from robustbench3d.results import read_summary
from robustbench3d.runner import RunConfig, run_benchmark
from robustbench3d.testing import write_kitti_frame
from robustbench3d.victims import VICTIMS
from robustbench3d.victims.spec import Capabilities, EntryInfo, VictimSpec

N_FRAMES, CARS_PER_FRAME = 6, 8


def toy_labels(rng: np.random.Generator) -> Labels:
    """Eight easy cars (tall unoccluded untruncated boxes, 150 px / 8 m apart), one Van, one DontCare."""
    n = CARS_PER_FRAME
    left = np.arange(n) * 150.0 + rng.uniform(0, 20, n)
    top = rng.uniform(150, 200, n)
    cars = Labels(
        type=np.array(["Car"] * n, dtype=object), truncated=np.zeros(n), occluded=np.zeros(n, dtype=np.int64),
        alpha=rng.uniform(-3, 3, n), bbox=np.column_stack([left, top, left + rng.uniform(60, 120, n),
                                                           top + rng.uniform(45, 150, n)]),
        dimensions=np.column_stack([rng.uniform(1.4, 1.7, n), rng.uniform(1.5, 1.8, n), rng.uniform(3.6, 4.6, n)]),
        location=np.column_stack([np.arange(n) * 8.0 - 30, rng.uniform(1.5, 1.9, n), rng.uniform(10, 50, n)]),
        rotation_y=rng.uniform(-3, 3, n))
    van = Labels(type=np.array(["Van"], dtype=object), truncated=np.zeros(1), occluded=np.zeros(1, dtype=np.int64),
                 alpha=np.zeros(1), bbox=np.array([[1200.0, 150.0, 1240.0, 250.0]]),
                 dimensions=np.array([[2.2, 1.9, 5.0]]), location=np.array([[40.0, 1.7, 30.0]]), rotation_y=np.zeros(1))
    dontcare = Labels(type=np.array(["DontCare"], dtype=object), truncated=-np.ones(1),
                      occluded=-np.ones(1, dtype=np.int64), alpha=np.full(1, -10.0),
                      bbox=np.array([[5.0, 100.0, 30.0, 120.0]]), dimensions=-np.ones((1, 3)),
                      location=np.full((1, 3), -1000.0), rotation_y=np.full(1, -10.0))
    return Labels.concatenate([cars, van, dontcare])


@pytest.fixture(scope="module")
def toy_dataset(tmp_path_factory) -> Path:
    """KITTI layout written with the data layer: toy labels, blank images, a few scan points."""
    root = tmp_path_factory.mktemp("toy")
    rng = np.random.default_rng(11)
    ids = [f"{i:06d}" for i in range(N_FRAMES)]
    for fid in ids:
        write_kitti_frame(root, fid, labels=toy_labels(rng), scan=rng.normal(size=(64, 4)).astype(np.float32))
    write_split(root / "ImageSets" / "val.txt", ids)
    return root


class OracleFromLabels:
    """TEST ONLY: with proposals="gt" returns the ground-truth Cars read from ``labels_dir`` (given
    by the test) as detections; with "detector" it returns none. Fails if the harness hands it labels."""

    supported_proposals = ("detector", "gt")

    def __init__(self, labels_dir: str | None = None):
        self.labels_dir = labels_dir

    def detect(self, frames, proposals="detector"):
        out = []
        for i, frame in enumerate(frames):
            if frame.labels is not None:
                raise RuntimeError(f"labels of frame {frame.frame_id} leaked to the victim")
            if isinstance(proposals, str):
                out.append(Labels.empty(with_score=True))
            else:
                assert proposals[i].source == "gt"
                labels = read_labels(Path(self.labels_dir) / f"{frame.frame_id}.txt")
                cars = labels.select(labels.type == "Car")
                out.append(dataclasses.replace(cars, score=np.linspace(0.99, 0.5, len(cars))))
        return out


VICTIMS.register("test-oracle-from-labels", VictimSpec(
    factory=OracleFromLabels,
    info=EntryInfo(Capabilities(modalities=("camera", "lidar"), backend="other", gradients=False, deterministic=True),
                   summary="TEST ONLY: ground truth as detections")))


def test_ground_truth_against_itself_is_100(toy_dataset):
    """The independent reference: the evaluator on GT vs GT (no runner involved)."""
    gt = [read_labels(p) for p in sorted((toy_dataset / "training" / "label_2").glob("*.txt"))]
    dt = [dataclasses.replace(g, score=np.ones(len(g))).select(g.type == "Car") for g in gt]
    result = evaluate(gt, dt)
    assert min(result["meta"]["gt_counted"]["Car"].values()) >= 41
    for metric in ("2d", "aos", "bev", "3d"):
        for recall in ("R40", "R11"):
            assert result["Car"][metric][recall] == pytest.approx({"easy": 100, "moderate": 100, "hard": 100})


def test_oracle_victim_scores_100_through_the_runner(toy_dataset, tmp_path):
    answers = {"labels_dir": str(toy_dataset / "training" / "label_2")}
    report = run_benchmark(RunConfig(victims=("test-oracle-from-labels",), attacks=("none",),
                                     proposals=("detector", "gt"), out=tmp_path / "run", data=toy_dataset,
                                     batch_size=4, progress=False, victim_args={"test-oracle-from-labels": answers}),
                           lambda line: None)
    detector, gt = read_summary(tmp_path / "run" / "summary.json")
    assert report.cells == [detector, gt]
    assert detector["status"] == "ok" and gt["status"] == "ok"
    assert gt["metrics"]["meta"]["gt_counted"]["Car"]["easy"] == N_FRAMES * CARS_PER_FRAME
    for metric in ("2d", "aos", "bev", "3d"):
        for recall in ("R40", "R11"):
            assert gt["metrics"]["Car"][metric][recall] == pytest.approx(
                {"easy": 100, "moderate": 100, "hard": 100}, abs=1e-9), (metric, recall)
            assert detector["metrics"]["Car"][metric][recall] == {"easy": 0.0, "moderate": 0.0, "hard": 0.0}
    written = read_labels(tmp_path / "run" / "cells" / "test-oracle-from-labels+none+gt" / "data" / "000000.txt")
    assert len(written) == CARS_PER_FRAME and set(written.type) == {"Car"}
