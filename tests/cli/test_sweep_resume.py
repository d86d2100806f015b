"""``robustbench3d sweep``: a sweep interrupted in its second point's training and resumed writes the same objects,
``sweep.json`` and ``sweep.csv`` as an uninterrupted one (apart from runtime provenance), reusing the first point's
object; the training is a deterministic fake written through the object-file writer (the real one is covered by
``attack train``'s tests), the scoring is the real benchmark run with the shipped cascade on a tiny dataset."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path
from typing import Any

import pytest

from robustbench3d.cli import main
from robustbench3d.testing import synth_dataset

#: JSON keys that describe the invocation's machine and time, not its results.
RUNTIME = {"provenance", "cost", "seconds", "cpu_seconds", "wall_time_s"}
CSV_RUNTIME = ("seconds", "cpu_seconds")


class FakeTraining:
    """A deterministic stand-in for ``train_universal``: writes the family's seeded random shape with a sidecar
    recording the configuration; raises on the call numbered ``fail_on`` (1-based) before writing anything."""

    def __init__(self, fail_on: int | None = None) -> None:
        self.calls: list[str] = []
        self.fail_on = fail_on

    def __call__(self, victim: Any, victim_info: dict, kitti: Any, frame_ids: list, labels: list, config: Any,
                 out: Any, *, data_identity: dict | None = None, resume: bool = False, force: bool = False,
                 progress: bool = True, log: Any = None, workers: int = 1, on_step: Any = None) -> dict:
        from robustbench3d.attacks.object import Family, random_shape
        from robustbench3d.attacks.objectfile import save_object

        self.calls.append(Path(out).name)
        if self.fail_on is not None and len(self.calls) == self.fail_on:
            raise KeyboardInterrupt  # as a user's Ctrl-C in the middle of a training
        family = Family(config.level, config.radius)
        made_by = {"attack": config.mode, "victim": victim_info, "training_data": data_identity or {},
                   "config": {**asdict(config), "eot": list(config.eot)}, "seed": config.seed,
                   "steps": config.steps, "object_step": config.steps, "cars": 1,
                   "stopped": {"reason": "steps", "step": config.steps, "line": "fake"}, "curve": None,
                   "wall_time_s": 0.0}
        save_object(out, random_shape(config.seed + family.level, family=family), made_by)
        return made_by


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return synth_dataset(tmp_path_factory.mktemp("sweepdata"), 8, seed=3, val_fraction=0.5)


def _args(data: Path, out: Path) -> list[str]:
    return ["sweep", "--victim", "fpointnet-v1-lite", "--mode", "adv-texture", "--levels", "2", "--radii", "0.2,0.4",
            "--out", str(out), "--data", str(data), "--proposals", "gt", "--steps", "3", "--eval-every", "0",
            "--bootstrap", "20", "--workers", "1", "--no-progress"]


def _strip(tree: Any) -> Any:
    if isinstance(tree, dict):
        return {k: _strip(v) for k, v in tree.items() if k not in RUNTIME}
    if isinstance(tree, list):
        return [_strip(v) for v in tree]
    return tree


def _csv(path: Path) -> list[dict[str, str]]:
    import csv

    with path.open(encoding="utf-8", newline="") as f:
        return [{k: v for k, v in row.items() if k not in CSV_RUNTIME} for row in csv.DictReader(f)]


def test_a_resumed_sweep_equals_an_uninterrupted_one(data, tmp_path, monkeypatch, capsys):
    from robustbench3d.attacks import train_run

    whole, cut = tmp_path / "whole", tmp_path / "cut"
    monkeypatch.setattr(train_run, "train_universal", FakeTraining())
    assert main(_args(data, whole)) == 0

    first = FakeTraining(fail_on=2)
    monkeypatch.setattr(train_run, "train_universal", first)
    assert main(_args(data, cut)) == 130  # interrupted in the second point's training
    assert first.calls == ["adv-texture-l2-r0.20.ply", "adv-texture-l2-r0.40.ply"]
    assert (cut / "objects" / "adv-texture-l2-r0.20.ply").is_file()
    assert not (cut / "objects" / "adv-texture-l2-r0.40.ply").exists() and not (cut / "sweep.json").exists()
    capsys.readouterr()

    second = FakeTraining()
    monkeypatch.setattr(train_run, "train_universal", second)
    assert main(_args(data, cut)) == 0
    assert second.calls == ["adv-texture-l2-r0.40.ply"]  # the first point's object is reused
    assert "keeping" in capsys.readouterr().err

    for name in ("adv-texture-l2-r0.20.ply", "adv-texture-l2-r0.40.ply"):
        assert (whole / "objects" / name).read_bytes() == (cut / "objects" / name).read_bytes()
    a = json.loads((whole / "sweep.json").read_text(encoding="utf-8"))
    b = json.loads((cut / "sweep.json").read_text(encoding="utf-8"))
    assert _strip(a) == _strip(b)
    assert _csv(whole / "sweep.csv") == _csv(cut / "sweep.csv")
    # every point, the clean control and both benign spheres were scored on the same frames
    assert {r["attack"] for r in a["scores"]} == {"adv-texture-l2-r0.20", "adv-texture-l2-r0.40", "benign-sphere",
                                                  "benign-sphere-r0.20"}
    assert [p["name"] for p in a["points"] if p["seed_point"]] == ["adv-texture-l2-r0.40"]
    assert (whole / "sweep.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
