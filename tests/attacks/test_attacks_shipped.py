"""Shipped universal objects: the package's manifest and reproduce script, the writer
(``tools/ship_object.py``), hash checks, and their registration as attacks.

Objects here come from one real ``attack train`` run (one step on one generated frame) or from
:func:`random_shape` written by :func:`save_object`, shipped into ``tmp_path`` with a temporary manifest.
Hashes are recomputed with hashlib, independently of :func:`robustbench3d.fileio.sha256_file`.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib.util
import json
import re
import shlex
import subprocess
import sys
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from robustbench3d.attacks import ATTACKS, AttackSpec
from robustbench3d.attacks.base import target_cars
from robustbench3d.attacks.object import random_shape
from robustbench3d.attacks.objectfile import load_object, save_object
from robustbench3d.attacks.roof import RoofObjectAttack
from robustbench3d.attacks.shipped import (
    MANIFEST_FORMAT,
    ORIGIN,
    manifest_path,
    objects_dir,
    read_manifest,
    register_shipped_objects,
    shipped_object,
    shipped_objects,
)
from robustbench3d.errors import DataFormatError, RobustBenchError
from robustbench3d.registry import Registry

REPO = Path(__file__).resolve().parents[2]
MODES = ("adv-shape", "adv-texture", "adv-object")

pytestmark = pytest.mark.usefixtures("cache")  # a fresh cache per test (conftest)


def _tool() -> Any:
    spec = importlib.util.spec_from_file_location("ship_object", REPO / "tools" / "ship_object.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


ship_object = _tool()


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _fresh_registry() -> Registry[AttackSpec]:
    return Registry("attack", base=AttackSpec, key=lambda spec: spec.key)


def _train_config(command: str) -> dict[str, Any]:
    """The TrainConfig an ``attack train`` command line builds (``attack_train.config_from_args``, as
    ``attack_train.run`` builds it), as a dict without the fields that do not change the object."""
    from robustbench3d.commands.attack_train import add_arguments, config_from_args

    words = shlex.split(command)
    assert words[:3] == ["robustbench3d", "attack", "train"], command
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    config = config_from_args(parser.parse_args(words[3:]))
    d = {**asdict(config), "eot": list(config.eot)}
    d.pop("checkpoint_every")
    return d


def _without_checkpoint(config: dict[str, Any]) -> dict[str, Any]:
    """A recorded config as the TrainConfig it describes: without checkpoint_every, fields added since (absent
    from older records) at the value the record implies (train_config.RECORD_DEFAULTS)."""
    from robustbench3d.attacks.train_config import RECORD_DEFAULTS

    return {**RECORD_DEFAULTS, **{k: v for k, v in config.items() if k != "checkpoint_every"}}


@pytest.fixture(scope="module")
def trained(tmp_path_factory, shared_split) -> tuple[Path, Path]:
    """(object file, dataset) of a one-step ``attack train adv-object`` run on one generated frame."""
    from robustbench3d.cli import main

    root = tmp_path_factory.mktemp("trained")
    dataset = shared_split(2, seed=0, val_fraction=0.5)
    out = root / "trained-object.ply"
    code = main(["attack", "train", "adv-object", "--victim", "fpointnet-v1-lite", "--victim-arg", "seed=0",
                 "--data", str(dataset), "--out", str(out), "--steps", "1", "--batch-cars", "1", "--seed", "2",
                 "--eot", "jitter", "--no-class-prob", "--lambda-lap", "0.02", "--occlusion", "none",
                 "--no-progress"])
    assert code == 0
    return out, dataset


@pytest.fixture
def shipped_dir(trained, tmp_path) -> Path:
    """A temporary objects directory with the trained object shipped as adv-object."""
    directory = tmp_path / "objects"
    assert ship_object.main(["adv-object", str(trained[0]), "--objects-dir", str(directory)]) == 0
    return directory


# ---- the package's own manifest and reproduce script ------------------------------------------------------


def test_package_manifest_entries_verify_and_are_registered():
    data = read_manifest()
    assert manifest_path().is_file() and data["format"] == MANIFEST_FORMAT
    names = []
    for entry in shipped_objects():
        entry.verify()
        assert entry.path.parent == objects_dir()
        assert entry.path.stat().st_size == entry.size_bytes and _sha256(entry.path) == entry.sha256
        assert _sha256(entry.sidecar_path) == entry.sidecar_sha256
        mode = entry.record["training"]["attack"]  # adv-shape-gt-object: an adv-shape trained for a protocol
        assert mode in MODES and (entry.name == mode or entry.name.startswith(f"{mode}-"))
        assert _train_config(entry.record["training"]["command"]) == _without_checkpoint(
            entry.record["training"]["config"])
        spec = ATTACKS.get(entry.name)
        assert spec.summary == entry.summary and ATTACKS.entry(entry.name).origin == ORIGIN
        names.append(entry.name)
    # an empty manifest registers no adv-* attack; a filled one exactly its entries
    assert ATTACKS.names("adv-*") == sorted(names)


def test_reproduce_script_trains_each_object_with_its_manifest_config():
    script = objects_dir() / "reproduce.sh"
    text = script.read_text(encoding="utf-8")
    lines = [ln for ln in text.splitlines() if ln.startswith("robustbench3d attack train")]
    configs, victims = {}, {}
    for line in lines:
        words = shlex.split(line)
        out = words[words.index("--out") + 1]
        name = out.removeprefix("$OUT/").removesuffix(".ply")
        assert out == f"$OUT/{name}.ply" and (name == words[3] or name.startswith(f"{words[3]}-"))
        configs[name] = _train_config(line)
        victims[name] = words[words.index("--victim") + 1]
    assert sorted(configs) == sorted(e.name for e in shipped_objects()) and len(lines) == len(configs)
    assert set(MODES) <= set(configs)
    for entry in shipped_objects():
        assert configs[entry.name] == _without_checkpoint(entry.record["training"]["config"]), entry.name
        assert victims[entry.name] == entry.record["training"]["victim"]["name"], entry.name
    weights_script = (REPO / "victims" / "weights" / "reproduce.sh").read_text(encoding="utf-8")
    synth = next(ln for ln in weights_script.splitlines() if ln.startswith("robustbench3d data synth"))
    assert synth in text  # the same dataset as the shipped victim's
    subprocess.run(["bash", "-n", str(script)], check=True)


def test_package_data_ships_the_objects_directory():
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib

    data = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))
    globs = data["tool"]["setuptools"]["package-data"]["robustbench3d.attacks"]
    assert {"objects/*.ply", "objects/*.json", "objects/*.sh"} <= set(globs)


def test_listing_attacks_imports_no_torch():
    code = ("import sys; from robustbench3d.attacks import ATTACKS; names = ATTACKS.names(); "
            "[ATTACKS.get(n).summary for n in names]; print('torch' in sys.modules, 'none' in names)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out == "False True\n"


# ---- writer and manifest round trip --------------------------------------------------------------------------


def test_ship_copies_the_pair_and_writes_the_entry_from_the_sidecar(trained, shipped_dir):
    source, _ = trained
    side = source.with_suffix(".json")
    ply, sidecar = shipped_dir / "adv-object.ply", shipped_dir / "adv-object.json"
    assert ply.read_bytes() == source.read_bytes() and sidecar.read_bytes() == side.read_bytes()
    made_by = json.loads(side.read_text(encoding="utf-8"))["made_by"]
    manifest = json.loads((shipped_dir / "manifest.json").read_text(encoding="utf-8"))
    assert manifest["format"] == MANIFEST_FORMAT and [e["name"] for e in manifest["objects"]] == ["adv-object"]
    rec = manifest["objects"][0]
    assert (rec["file"], rec["sha256"], rec["size_bytes"]) == ("adv-object.ply", _sha256(source), source.stat().st_size)
    assert rec["sidecar"] == {"file": "adv-object.json", "sha256": _sha256(side), "size_bytes": side.stat().st_size}
    training = rec["training"]
    for key in ("config", "seed", "steps", "victim", "training_data", "wall_time_s", "attack"):
        assert training[key] == made_by[key], key
    from robustbench3d.victims import VICTIMS

    assert training["victim"]["name"] == "fpointnet-v1-lite"
    assert training["victim"]["weights_sha256"] == VICTIMS.get("fpointnet-v1-lite").info.weights_sha256
    assert training["steps"] == 1 and training["seed"] == 2 and training["wall_time_s"] > 0
    assert "evaluation" not in rec and rec["summary"].startswith("universal adv-object object trained against")
    # the rebuilt command builds the very config the run recorded
    assert _train_config(training["command"]) == _without_checkpoint(made_by["config"])
    words = shlex.split(training["command"])
    assert words[words.index("--victim-arg") + 1] == "seed=0"
    assert words[words.index("--data") + 1] == made_by["training_data"]["root"]
    # read back through the module: the same record
    assert read_manifest(shipped_dir / "manifest.json") == manifest
    entry = shipped_object("adv-object", shipped_dir / "manifest.json")
    assert entry is not None and entry.record == rec
    entry.verify()


def test_reshipping_replaces_the_entry_and_keeps_the_others(trained, shipped_dir, tmp_path):
    other = save_object(tmp_path / "other.ply", random_shape(3),
                        {**load_sidecar(trained[0])["made_by"], "attack": "adv-shape"})
    assert ship_object.main(["adv-shape", str(other), "--objects-dir", str(shipped_dir),
                             "--command", "robustbench3d attack train adv-shape --victim v --out x.ply"]) == 0
    assert ship_object.main(["adv-object", str(other), "--objects-dir", str(shipped_dir)]) == 0
    data = read_manifest(shipped_dir / "manifest.json")
    assert [e["name"] for e in data["objects"]] == ["adv-object", "adv-shape"]
    assert {e["sha256"] for e in data["objects"]} == {_sha256(other)}
    assert data["objects"][1]["training"]["command"] == "robustbench3d attack train adv-shape --victim v --out x.ply"
    assert (shipped_dir / "adv-object.ply").read_bytes() == other.read_bytes()


def load_sidecar(ply: Path) -> dict[str, Any]:
    return json.loads(ply.with_suffix(".json").read_text(encoding="utf-8"))


def test_ship_refuses_an_object_not_made_by_attack_train(tmp_path, capsys):
    path = save_object(tmp_path / "rand.ply", random_shape(1), {"attack": "random-shape", "seed": 1})
    assert ship_object.main(["adv-shape", str(path), "--objects-dir", str(tmp_path / "objects")]) == 1
    err = capsys.readouterr().err
    assert "rand.json" in err and "made_by.tool" in err
    assert not (tmp_path / "objects").exists()


def test_ship_refuses_a_bad_name_before_writing(trained, tmp_path, capsys):
    assert ship_object.main(["Adv Shape", str(trained[0]), "--objects-dir", str(tmp_path / "objects")]) == 1
    assert "field 'objects[0].name'" in capsys.readouterr().err
    assert not (tmp_path / "objects").exists()


def test_evaluation_from_a_run_summary_keeps_the_cells_of_this_object(trained, tmp_path):
    sha = _sha256(trained[0])

    def cell(attack: str, ply_sha: str | None, status: str = "ok") -> dict[str, Any]:
        car = {"bev": {"R40": {"easy": 50.0, "moderate": 40.0, "hard": 30.0}}, "aos": {}}
        return {"victim": "v", "attack": attack, "proposals": "gt", "status": status, "dataset": {"split": "val"},
                "metrics": {"Car": car, "meta": {}}, "attack_effect": {"drop": 1.0},
                # the runner's attack record: its "object" is Attack.describe(), whose "object" names the PLY
                "provenance": {"config": {"attack": {
                    "params": {"eot": True},
                    "object": None if ply_sha is None else {"object": {"ply_sha256": ply_sha}}}}}}

    summary = tmp_path / "summary.json"
    summary.write_text(json.dumps([cell("none", None), cell("x", sha), cell("y", "0" * 64), cell("z", sha, "error")]))
    rec = ship_object.evaluation_record(summary, sha)
    assert list(rec["cells"]) == ["v+x+gt"] and rec["dataset"] == {"split": "val"}
    assert rec["cells"]["v+x+gt"]["metrics"] == {"bev": {"R40": {"easy": 50.0, "moderate": 40.0, "hard": 30.0}}}
    assert rec["cells"]["v+x+gt"]["params"] == {"eot": True}
    assert rec["cells"]["v+x+gt"]["attack_effect"] == {"drop": 1.0}
    with pytest.raises(RobustBenchError, match="no finished cell ran the object"):
        ship_object.evaluation_record(summary, "1" * 64)
    free = tmp_path / "eval.json"
    free.write_text(json.dumps({"bev_moderate_drop": 12.5}))
    directory = tmp_path / "objects"
    assert ship_object.main(["adv-object", str(trained[0]), "--objects-dir", str(directory), "--eval", str(free)]) == 0
    entry = shipped_object("adv-object", directory / "manifest.json")
    assert entry.record["evaluation"] == {"source": "eval.json", "bev_moderate_drop": 12.5}
    # reshipping the same bytes without --eval keeps it; other bytes drop it
    assert ship_object.main(["adv-object", str(trained[0]), "--objects-dir", str(directory)]) == 0
    assert shipped_object("adv-object", directory / "manifest.json").record["evaluation"]["bev_moderate_drop"] == 12.5
    other = save_object(tmp_path / "other.ply", random_shape(4), load_sidecar(trained[0])["made_by"])
    assert ship_object.main(["adv-object", str(other), "--objects-dir", str(directory)]) == 0
    assert "evaluation" not in shipped_object("adv-object", directory / "manifest.json").record


def test_training_command_spells_out_options_only_an_option_sets(trained):
    made_by = load_sidecar(trained[0])["made_by"]
    embedded = {**made_by, "training_data": {**made_by["training_data"], "embedded": {"seed": 0}, "frames": 5,
                                             "split_frames": 991}}
    cmd = ship_object.training_command("adv-object", embedded)
    assert '--data "$DATA"' in cmd and "--max-frames 5" in cmd and '--out "$OUT/adv-object.ply"' in cmd
    assert cmd.index("--steps 1 --seed 2") < cmd.index("--eot jitter")
    odd = {**made_by, "config": {**made_by["config"], "supersample": 1}}
    with pytest.raises(RobustBenchError, match=r"'supersample'.*give --command"):
        ship_object.training_command("adv-object", odd)


# ---- manifest checks: tampered, missing, malformed -----------------------------------------------------------


def test_tampered_or_missing_files_are_refused_naming_the_file(shipped_dir):
    manifest = shipped_dir / "manifest.json"
    ply, side = shipped_dir / "adv-object.ply", shipped_dir / "adv-object.json"
    registry = _fresh_registry()
    register_shipped_objects(manifest, registry)
    original = ply.read_bytes()
    tampered = bytearray(original)
    tampered[-5] ^= 1  # a face index byte: same size, another hash
    ply.write_bytes(bytes(tampered))
    p, m = re.escape(str(ply)), re.escape(str(manifest))
    with pytest.raises(RobustBenchError, match=rf"{p}: sha256 [0-9a-f]{{64}} does not match .*{m}"):
        registry.get("adv-object").create()
    ply.write_bytes(original + b"\0")
    with pytest.raises(RobustBenchError, match=rf"{p}: {len(original) + 1} bytes, but {m} records"):
        registry.get("adv-object").create()
    ply.unlink()
    with pytest.raises(RobustBenchError, match=rf"{p}: object file of the shipped attack 'adv-object' is missing"):
        registry.get("adv-object").create(eot=True)
    ply.write_bytes(original)
    side.write_text(side.read_text(encoding="utf-8").replace('"steps": 1', '"steps": 2'), encoding="utf-8")
    with pytest.raises(RobustBenchError, match=rf"{re.escape(str(side))}: sha256 .* sidecar of 'adv-object'"):
        registry.get("adv-object").create()


@pytest.mark.parametrize(("edit", "field"), [
    (lambda d: d.update(format="robustbench3d.shipped_weights/1"), "format"),
    (lambda d: d.update(objects={}), "objects"),
    (lambda d: d["objects"][0].update(name="Adv"), "objects[0].name"),
    (lambda d: d["objects"][0].update(file="../adv-object.ply"), "objects[0].file"),
    (lambda d: d["objects"][0].update(sha256="ABC"), "objects[0].sha256"),
    (lambda d: d["objects"][0].update(size_bytes=True), "objects[0].size_bytes"),
    (lambda d: d["objects"][0]["sidecar"].update(file="other.json"), "objects[0].sidecar.file"),
    (lambda d: d["objects"][0].pop("summary"), "objects[0].summary"),
    (lambda d: d["objects"][0]["training"].pop("command"), "objects[0].training.command"),
    (lambda d: d["objects"][0]["training"].update(seed="0"), "objects[0].training.seed"),
    (lambda d: d["objects"][0]["training"]["victim"].update(weights_sha256="x"),
     "objects[0].training.victim.weights_sha256"),
    (lambda d: d["objects"][0].update(evaluation=[1]), "objects[0].evaluation"),
    (lambda d: d["objects"].append(dict(d["objects"][0])), "objects[1].name"),
])
def test_malformed_manifest_is_refused_naming_file_and_field(shipped_dir, edit, field):
    manifest = shipped_dir / "manifest.json"
    data = json.loads(manifest.read_text(encoding="utf-8"))
    edit(data)
    manifest.write_text(json.dumps(data), encoding="utf-8")
    with pytest.raises(DataFormatError) as info:
        register_shipped_objects(manifest, _fresh_registry())
    assert info.value.path == manifest and info.value.field == field
    assert str(info.value).startswith(f"{manifest}: field '{field}': ")


def test_manifest_that_is_not_json_is_refused_naming_it(tmp_path):
    manifest = tmp_path / "manifest.json"
    manifest.write_text("{", encoding="utf-8")
    with pytest.raises(DataFormatError, match=rf"^{re.escape(str(manifest))}: not valid JSON"):
        read_manifest(manifest)


# ---- registration ------------------------------------------------------------------------------------------


def test_empty_or_absent_manifest_registers_nothing(tmp_path):
    registry = _fresh_registry()
    assert register_shipped_objects(tmp_path / "absent.json", registry) == []
    (tmp_path / "manifest.json").write_text(json.dumps({"format": MANIFEST_FORMAT, "objects": []}))
    assert register_shipped_objects(tmp_path / "manifest.json", registry) == []
    assert registry.names() == []


def test_shipped_attack_places_the_objects_of_its_ply(trained, shipped_dir):
    source, dataset = trained
    manifest = shipped_dir / "manifest.json"
    registry = _fresh_registry()
    assert register_shipped_objects(manifest, registry) == ["adv-object"]
    assert register_shipped_objects(manifest, registry) == ["adv-object"]  # the same entry again: a no-op
    spec = registry.get("adv-object")
    assert registry.entry("adv-object").origin == ORIGIN
    assert spec.summary == read_manifest(manifest)["objects"][0]["summary"]

    from robustbench3d.datasets import load_ground_truth, resolve_dataset

    gt = load_ground_truth(resolve_dataset(dataset, "train", progress=False))
    targets = target_cars(gt.labels[0])
    assert len(targets) > 0
    reference_obj = load_object(source)  # the trained PLY itself, read directly
    for eot in (False, True):
        attack = spec.create(eot=eot)
        reference = RoofObjectAttack(reference_obj, eot=eot)
        assert attack.sha256 == _sha256(source) and attack.eot is eot
        assert attack.obj.colors.tobytes() == reference_obj.colors.tobytes()
        placed = attack.place(targets, np.random.default_rng(7))
        expected = reference.place(targets, np.random.default_rng(7))
        assert len(placed) == len(expected) == len(targets)
        for (v, pose), (w, ref_pose) in zip(placed, expected, strict=True):
            assert v.dtype == w.dtype and v.tobytes() == w.tobytes()
            assert pose.yaw == ref_pose.yaw
            for name in ("centre", "rotation", "roof_centre"):
                assert getattr(pose, name).tobytes() == getattr(ref_pose, name).tobytes(), name
    # the object-file attack of the same PLY describes the same object
    from robustbench3d.attacks import create_attack

    assert spec.create().describe() == create_attack("object-file", path=str(source)).describe()


def test_shipped_attack_collides_with_a_control_name(shipped_dir):
    registry = _fresh_registry()
    registry.register("adv-object", AttackSpec(factory=lambda: None, summary="another"))
    from robustbench3d.registry import RegistryError

    with pytest.raises(RegistryError, match="'adv-object' is already registered"):
        register_shipped_objects(shipped_dir / "manifest.json", registry)
