"""AP regression gate for the shipped cascade (slow: generates 160 frames, runs the victim).

The first frames of the embedded dataset are regenerated (frame i and its split membership are
pure functions of (seed, i), so their val frames are val frames of the embedded dataset, never
trained on) and the shipped ``fpointnet-v1-lite`` is scored on them with both proposal sources.
Its BEV AP (R40, moderate) must stay within :data:`MARGIN` points of the accuracy the manifest
records for the full val split — a loose band, since 80-odd frames give a noisy AP.
"""

from __future__ import annotations

import json

import pytest

from robustbench3d.cli import main
from robustbench3d.datasets import EMBEDDED
from robustbench3d.synth.writer import generate_dataset
from robustbench3d.victims.shipped import shipped

MARGIN = 12.0
FRAMES = 160


@pytest.mark.slow
def test_shipped_cascade_keeps_its_recorded_accuracy(tmp_path):
    data = tmp_path / "data"
    generate_dataset(data, FRAMES, seed=EMBEDDED.seed, val_fraction=EMBEDDED.val_fraction, workers=2, progress=False)
    out = tmp_path / "run"
    assert main(["run", "--victims", "fpointnet-v1-lite", "--attacks", "none", "--proposals", "detector,gt",
                 "--data", str(data), "--out", str(out), "--no-progress"]) == 0
    recorded = shipped("fpointnet-v1-lite").record["accuracy"]["cells"]
    for cell in json.loads((out / "summary.json").read_text()):
        got = cell["metrics"]["Car"]["bev"]["R40"]["moderate"]
        want = recorded[cell["proposals"]]["bev"]["R40"]["moderate"]
        assert got >= want - MARGIN, (cell["proposals"], got, want)
