"""Shared fixtures, and ``tests/helpers`` on ``sys.path``: the helper modules are imported by their basename
(``from cell_builders import hand_provenance``) from every area folder. Real KITTI samples are read from
``../shared/kitti_samples`` (beside the repository) or from ``$ROBUSTBENCH3D_KITTI_SAMPLES``; tests needing
them skip with a message when they are absent. They are never copied into this repository (CC BY-NC-SA data)."""

from __future__ import annotations

import hashlib
import os
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

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


def _file_digests(root: Path) -> dict[str, str]:
    """sha256 of every file under ``root``, by relative path."""
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="session")
def shared_split(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Callable[..., Path]]:
    """``shared_split(frames, seed=..., val_fraction=...)``: the generated dataset of
    :func:`robustbench3d.testing.synth_dataset` with those parameters, generated once per test run and shared by
    every test that asks for the same parameters. Read only: a test that writes into its dataset generates (or
    copies) its own. Every shared dataset is checked byte for byte unchanged when the run ends."""
    from robustbench3d.testing import synth_dataset

    made: dict[tuple[int, int, float], tuple[Path, dict[str, str]]] = {}

    def split(frames: int, *, seed: int, val_fraction: float) -> Path:
        key = (frames, seed, val_fraction)
        if key not in made:
            root = synth_dataset(tmp_path_factory.mktemp(f"split_{frames}f_seed{seed}_val{val_fraction:g}_"), frames,
                                 seed=seed, val_fraction=val_fraction)
            made[key] = root, _file_digests(root)
        return made[key][0]

    yield split
    changed = [str(root) for root, digests in made.values() if _file_digests(root) != digests]
    assert not changed, f"a test wrote into a shared dataset (give it its own): {changed}"


def _victim_state(victim: Any) -> tuple[str, ...]:
    """The weights (sha256 over every tensor's bytes) and settings of an F-PN cascade."""
    import torch

    digest = hashlib.sha256()
    for net in (victim.yolo.net, victim.fpn):
        for name, tensor in net.state_dict().items():
            digest.update(name.encode())
            digest.update(tensor.detach().cpu().contiguous().reshape(-1).view(torch.uint8).numpy().tobytes())
    modes = (victim.yolo.net.training, victim.fpn.training)
    return (digest.hexdigest(), repr(victim.yolo.cfg), repr(victim.fpn.cfg), repr(victim.settings),
            repr(victim.fidelity()), repr(victim.objectness_crop), repr(modes))


@pytest.fixture(scope="session")
def lite_victim() -> Iterator[Any]:
    """The registry's ``fpointnet-v1-lite`` (shipped weights, default arguments), built once per test run for the
    tests that only read from it; a test that changes its victim builds its own. Its weights and settings are
    checked unchanged when the run ends."""
    from robustbench3d.victims import create_victim

    victim = create_victim("fpointnet-v1-lite")
    before = _victim_state(victim)
    yield victim
    assert _victim_state(victim) == before, "a test changed the shared fpointnet-v1-lite (give it its own)"


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
