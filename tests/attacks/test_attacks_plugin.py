"""The example attack plugin (examples/lidar_dropout_attack), found through its entry point.

The entry point its ``pyproject.toml`` declares is discovered from a distribution written to a temporary
``sys.path`` entry, and its attack is checked on a hand-made frame, whether or not the package is installed.
The tests of the installed plugin (the registry's ``lidar-dropout``, a benchmark cell) need
``pip install -c constraints.txt -e examples/lidar_dropout_attack`` and skip with that hint otherwise.
"""

from __future__ import annotations

import importlib
import importlib.util
import json
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from robustbench3d.attacks import ATTACKS, ENTRY_POINT_GROUP, create_attack
from robustbench3d.attacks.base import Attack, target_cars
from robustbench3d.attacks.spec import AttackRequirements, AttackSpec, AttackSpecError
from robustbench3d.kitti.dataset import Frame
from robustbench3d.kitti.labels import Labels
from robustbench3d.registry import NO_PLUGINS_ENV, Registry
from robustbench3d.testing import SIMPLE_CALIB, synth_dataset

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10: the dev extra installs tomli
    import tomli as tomllib

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "lidar_dropout_attack"
INSTALL = "pip install -c constraints.txt -e examples/lidar_dropout_attack"
installed = pytest.mark.skipif(importlib.util.find_spec("rb3d_lidar_dropout") is None,
                               reason=f"example attack plugin not installed: {INSTALL}")

# One car, rect frame, rotation_y 0: its box spans x in [1.0, 5.2] m, y in [0.1, 1.6] m (up is -y), z in
# [14.15, 15.85] m (KITTI: l along x, h up from the bottom centre, w along z).
DIMS, LOC = np.array([1.5, 1.7, 4.2]), np.array([3.1, 1.6, 15.0])


def project() -> dict:
    return tomllib.loads((EXAMPLE / "pyproject.toml").read_text(encoding="utf-8"))["project"]


def example_module(monkeypatch: pytest.MonkeyPatch) -> ModuleType:
    """``rb3d_lidar_dropout.attack`` imported from the example folder (the same file an editable install uses)."""
    monkeypatch.syspath_prepend(str(EXAMPLE))
    return importlib.import_module("rb3d_lidar_dropout.attack")


def scene(rng: np.random.Generator) -> tuple[Frame, int]:
    """A frame whose scan holds 2000 returns well inside the car's box (its first rows, at most 90 % of each
    half-extent from the centre) and 1000 ground returns at least 3 m from it; returns it and the inside count."""
    half = np.array([4.2, 1.5, 1.7]) / 2
    centre = LOC - [0.0, 0.75, 0.0]
    inside = centre + rng.uniform(-0.9, 0.9, (2000, 3)) * half
    ground = np.stack([rng.uniform(-10, -2, 1000), np.full(1000, 1.6), rng.uniform(5, 40, 1000)], axis=1)
    rect = np.concatenate([inside, ground])
    scan = np.concatenate([SIMPLE_CALIB.rect_to_velo_points(rect), np.full((len(rect), 1), 0.3)], axis=1)
    labels = Labels(type=np.array(["Car"], dtype=object), truncated=np.zeros(1), occluded=np.zeros(1, np.int64),
                    alpha=np.zeros(1), bbox=np.array([[500.0, 150.0, 700.0, 250.0]]), dimensions=DIMS[None],
                    location=LOC[None], rotation_y=np.zeros(1))
    image = np.zeros((375, 1242, 3), np.uint8)
    return Frame("000000", image, scan.astype(np.float32), SIMPLE_CALIB, labels), len(inside)


def test_the_examples_entry_point_registers_its_attack(tmp_path, monkeypatch):
    ATTACKS.names()  # the package's registry is discovered before the fake distribution is on sys.path
    meta = project()
    entry_points = meta["entry-points"][ENTRY_POINT_GROUP]
    assert entry_points == {"lidar-dropout": "rb3d_lidar_dropout:SPEC"}
    site = tmp_path / "site" / f"{meta['name'].replace('-', '_')}-{meta['version']}.dist-info"
    site.mkdir(parents=True)
    (site / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {meta['name']}\nVersion: {meta['version']}\n")
    (site / "entry_points.txt").write_text(f"[{ENTRY_POINT_GROUP}]\nlidar-dropout = rb3d_lidar_dropout:SPEC\n")
    monkeypatch.syspath_prepend(str(EXAMPLE))
    monkeypatch.syspath_prepend(str(site.parent))
    monkeypatch.delenv(NO_PLUGINS_ENV, raising=False)
    registry: Registry[AttackSpec] = Registry("attack", group=ENTRY_POINT_GROUP, base=AttackSpec,
                                              key=lambda spec: spec.key)  # as ATTACKS discovers plugins
    assert registry.entry("lidar-dropout").origin == "plugin rb3d-lidar-dropout 0.1.0"
    spec = registry.get("lidar-dropout")
    assert spec.requirements == AttackRequirements(needs_lidar=True) and spec.summary
    assert isinstance(spec.create(fraction=0.25), Attack)
    with pytest.raises(AttackSpecError, match="invalid parameters"):
        spec.create(ratio=0.25)


def test_the_example_attack_removes_returns_inside_the_target_boxes_only(monkeypatch):
    attack_module = example_module(monkeypatch)
    frame, n_inside = scene(np.random.default_rng(0))
    targets = target_cars(frame.labels)
    before = frame.scan.copy()

    def rng() -> np.random.Generator:  # a fresh generator of one seed per call
        return np.random.default_rng([7, 0])

    everything = attack_module.build(fraction=1.0).apply(frame, targets, rng())
    np.testing.assert_array_equal(everything.scan, before[n_inside:])  # every box return gone, the rest kept
    assert attack_module.build(fraction=0.0).apply(frame, targets, rng()) is frame
    assert attack_module.build().apply(frame, target_cars(None), rng()) is frame  # no target: unchanged

    half = attack_module.build(fraction=0.5).apply(frame, targets, rng())
    np.testing.assert_array_equal(half.scan[-1000:], before[n_inside:])  # the ground returns all kept, in order
    kept = half.scan[:-1000]
    assert 0.4 * n_inside < len(kept) < 0.6 * n_inside  # Binomial(2000, 0.5): 0.1 is 9 standard deviations
    rows = {r.tobytes() for r in before[:n_inside]}
    assert all(r.tobytes() in rows for r in kept)  # only removals, no new or moved returns
    np.testing.assert_array_equal(attack_module.build(fraction=0.5).apply(frame, targets, rng()).scan, half.scan)
    np.testing.assert_array_equal(frame.scan, before)  # the input frame is untouched
    assert half.image is frame.image and half.calib is frame.calib and half.labels is frame.labels
    assert attack_module.build(0.5).describe() == {"attack": "lidar-dropout", "fraction": 0.5}


@pytest.mark.parametrize("bad", [-0.1, 1.5, float("nan"), True, "half", None])
def test_the_example_attack_refuses_a_fraction_outside_its_range(monkeypatch, bad):
    attack_module = example_module(monkeypatch)
    with pytest.raises(AttackSpecError, match=r"field 'fraction': expected a number in \[0, 1\], got "):
        attack_module.build(fraction=bad)


@installed
def test_the_installed_plugin_is_an_attack_of_the_registry():
    entry = ATTACKS.entry("lidar-dropout")
    assert entry.origin.startswith("plugin rb3d-lidar-dropout")
    assert ATTACKS.get("lidar-dropout").requirements.needs_lidar
    with pytest.raises(AttackSpecError, match=r"^attack 'lidar-dropout': field 'fraction': expected a number in "
                                              r"\[0, 1\], got 2$"):
        create_attack("lidar-dropout", fraction=2)


@installed
def test_the_installed_plugin_attacks_a_benchmark_cell(tmp_path, capsys):
    from robustbench3d.cli import main

    data = synth_dataset(tmp_path / "synth", 1, seed=3, val_fraction=1.0)
    out = tmp_path / "run"
    assert main(["run", "--victims", "fpointnet-v1-lite", "--attacks", "none,lidar-dropout", "--proposals", "gt",
                 "--attack-arg", "lidar-dropout:fraction=1", "--data", str(data), "--out", str(out),
                 "--no-progress"]) == 0, capsys.readouterr().err
    cell = json.loads((out / "cells" / "fpointnet-v1-lite+lidar-dropout+gt" / "cell.json").read_text())
    assert cell["status"] == "ok"
    attack = cell["provenance"]["config"]["attack"]
    assert attack["origin"].startswith("plugin rb3d-lidar-dropout") and attack["params"] == {"fraction": 1}
    assert attack["object"] == {"attack": "lidar-dropout", "fraction": 1.0}
