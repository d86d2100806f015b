"""Ground truth scored against itself (score column added) gives AP 100 everywhere it can."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from robustbench3d.cli import main
from robustbench3d.eval import evaluate
from robustbench3d.kitti import Labels, read_labels, write_labels

CLASSES = ("Car", "Pedestrian", "Cyclist")
METRICS = ("2d", "aos", "bev", "3d")
TYPES = ("Car", "Van", "Truck", "Pedestrian", "Person_sitting", "Cyclist", "Misc", "DontCare")
DIMS = {"Car": (1.5, 1.6, 3.9), "Van": (2.2, 1.9, 5.0), "Truck": (3.0, 2.5, 9.0), "Pedestrian": (1.7, 0.6, 0.8),
        "Person_sitting": (1.2, 0.6, 0.8), "Cyclist": (1.7, 0.6, 1.8), "Misc": (1.8, 1.5, 3.5)}


def with_scores(labels: Labels, rng: np.random.Generator, keep_dontcare: bool = False) -> Labels:
    """The labels as detections: a score column added; DontCare lines dropped unless asked to keep.

    (DontCare lines carry alpha = -10, which, as in the devkit, switches AOS off.)
    """
    out = dataclasses.replace(labels, score=np.round(rng.random(len(labels)), 2))
    return out if keep_dontcare else out.select(out.type != "DontCare")


def generated_frames(rng: np.random.Generator, n_frames: int) -> list[Labels]:
    """Frames of disjoint objects (image slots 150 px apart, 3D slots 8 m apart) of mixed difficulty."""
    frames = []
    for _ in range(n_frames):
        n = int(rng.integers(2, 9))
        types = [TYPES[k] for k in rng.integers(0, len(TYPES), n)]
        slots = np.arange(n)
        left = slots * 150.0 + rng.uniform(0, 20, n)
        # Mostly random heights, some exactly at or next to the 25 / 40 px limits.
        height = np.where(rng.random(n) < 0.7, rng.uniform(12, 150, n), rng.choice([25.0, 40.0, 40.5, 60.0], n))
        top = rng.uniform(100, 200, n)
        dc = np.array([t == "DontCare" for t in types])
        scale = np.where(dc, 1.0, rng.uniform(0.9, 1.1, n))[:, None]
        dims = np.array([DIMS.get(t, (-1.0, -1.0, -1.0)) for t in types]) * scale
        loc = np.column_stack([slots * 8.0 - 30 + rng.uniform(-1, 1, n), rng.uniform(1.4, 2.0, n),
                               rng.uniform(10, 60, n)])
        loc[dc] = -1000.0
        ry = np.where(dc, -10.0, rng.uniform(-np.pi, np.pi, n))
        frames.append(Labels(
            type=np.array(types, dtype=object),
            truncated=np.where(dc, -1.0, np.where(rng.random(n) < 0.5, 0.0,
                                                  rng.choice([0.1, 0.15, 0.2, 0.3, 0.45, 0.5, 0.7], n))),
            occluded=np.where(dc, -1, np.where(rng.random(n) < 0.6, 0, rng.integers(0, 4, n))).astype(np.int64),
            alpha=np.where(dc, -10.0, rng.uniform(-np.pi, np.pi, n)),
            bbox=np.column_stack([left, top, left + rng.uniform(20, 120, n), top + height]),
            dimensions=dims, location=loc, rotation_y=ry,
        ))
    return frames


def assert_all_perfect(result: dict, classes: tuple[str, ...], metrics: tuple[str, ...] = METRICS) -> None:
    for cls in classes:
        counted = result["meta"]["gt_counted"][cls]
        assert min(counted.values()) >= 41, counted  # enough GT for AP to reach 100 at every level
        assert set(result[cls]) == set(metrics)
        for metric in metrics:
            for recall in ("R40", "R11"):
                assert result[cls][metric][recall] == pytest.approx(
                    {"easy": 100.0, "moderate": 100.0, "hard": 100.0}, abs=1e-9), (cls, metric, recall)


def test_generated_gt_against_itself_is_perfect() -> None:
    rng = np.random.default_rng(42)
    gt = generated_frames(rng, 400)
    result = evaluate(gt, [with_scores(g, rng) for g in gt], classes=CLASSES)
    assert_all_perfect(result, CLASSES)
    # Keeping the DontCare lines as "detections" switches AOS off (alpha = -10) and changes nothing else.
    result = evaluate(gt, [with_scores(g, rng, keep_dontcare=True) for g in gt], classes=CLASSES)
    assert_all_perfect(result, CLASSES, ("2d", "bev", "3d"))
    assert {s["metric"] for s in result["meta"]["skipped"]} == {"aos"}


def test_generated_gt_against_itself_through_files_and_cli(tmp_path: Path, capsys) -> None:
    rng = np.random.default_rng(43)
    gt = generated_frames(rng, 400)
    for i, g in enumerate(gt):
        write_labels(tmp_path / "gt" / f"{i:06d}.txt", g)
        write_labels(tmp_path / "pred" / f"{i:06d}.txt", with_scores(g, rng))
    out = tmp_path / "ap.json"
    rc = main(["eval", "--gt", str(tmp_path / "gt"), "--pred", str(tmp_path / "pred"), "--classes",
               "Car,Pedestrian,Cyclist", "--json", str(out)])
    assert rc == 0
    assert "Car BEV AP@0.70 R40" in capsys.readouterr().out
    assert_all_perfect(json.loads(out.read_text()), CLASSES)


def test_real_samples_against_themselves(kitti_samples: Path) -> None:
    rng = np.random.default_rng(44)
    gt = [read_labels(p, scored=False) for p in sorted((kitti_samples / "training/label_2").glob("*.txt"))]
    dt = [with_scores(g, rng) for g in gt]
    # Six frames hold too few objects for 41 thresholds; repeating them 41 times lifts every count.
    tiled = evaluate(gt * 41, dt * 41, classes=CLASSES)
    assert_all_perfect(tiled, ("Car", "Pedestrian"))
    # The only Cyclist has occlusion 3 (unknown): never counted, so AP 0 with a note.
    assert tiled["meta"]["gt_counted"]["Cyclist"] == {"easy": 0, "moderate": 0, "hard": 0}
    assert any("Cyclist easy: no counted GT" in n for n in tiled["meta"]["notes"])
    # Untiled: N counted GT, all found -> R40 = 100 (N - 1) / 40, R11 = 100 ceil(N / 4) / 11.
    once = evaluate(gt, dt, classes=("Car", "Pedestrian"))
    for cls in ("Car", "Pedestrian"):
        for diff, n in once["meta"]["gt_counted"][cls].items():
            for metric in METRICS:
                assert once[cls][metric]["R40"][diff] == pytest.approx(100 * max(n - 1, 0) / 40)
                assert once[cls][metric]["R11"][diff] == pytest.approx(100 * -(-n // 4) / 11)
