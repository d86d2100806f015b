"""Shared fixtures, and ``tests/helpers`` on ``sys.path``: the helper modules are imported by their basename
(``from cell_builders import hand_provenance``) from every area folder. Real KITTI samples are read from
``../shared/kitti_samples`` (beside the repository) or from ``$ROBUSTBENCH3D_KITTI_SAMPLES``; tests needing
them skip with a message when they are absent. They are never copied into this repository (CC BY-NC-SA data)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

REPO = Path(__file__).resolve().parents[1]
HELPERS = Path(__file__).resolve().parent / "helpers"
if str(HELPERS) not in sys.path:
    sys.path.insert(0, str(HELPERS))


def _samples_dir() -> Path:
    env = os.environ.get("ROBUSTBENCH3D_KITTI_SAMPLES")
    return Path(env) if env else REPO.parent / "shared" / "kitti_samples"


@pytest.fixture(scope="session")
def kitti_samples() -> Path:
    """Root of the six real KITTI frames (KITTI layout), or skip."""
    root = _samples_dir()
    if not (root / "training" / "label_2").is_dir():
        pytest.skip(f"real KITTI samples not found at {root} (set ROBUSTBENCH3D_KITTI_SAMPLES)")
    return root


@pytest.fixture
def cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A fresh robustbench3d cache directory for the test (``$ROBUSTBENCH3D_CACHE``)."""
    monkeypatch.setenv("ROBUSTBENCH3D_CACHE", str(tmp_path / "cache"))
    return tmp_path / "cache"



@pytest.fixture
def fed_frustums(monkeypatch: pytest.MonkeyPatch) -> list[np.ndarray]:
    """Filled during the test with every frustum the F-PointNet pipeline feeds its segmentation stage (one
    (num_points, 4) array each, in order), recorded around ``pipeline.run_frustum_stages``."""
    from robustbench3d.victims.fpointnet import pipeline

    fed: list[np.ndarray] = []
    real = pipeline.run_frustum_stages

    def recording(stages, points, *args, **kwargs):
        fed.extend(np.array(p) for p in points)
        return real(stages, points, *args, **kwargs)

    monkeypatch.setattr(pipeline, "run_frustum_stages", recording)
    return fed
