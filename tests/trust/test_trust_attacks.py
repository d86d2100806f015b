"""Trust in the attack inputs and outputs (issue #32, second pass): object-file sidecar ranges, the roof-object
attack's setting ranges, the written-once rule of ``show``, ``attack train`` and ``attack apply``, the numeric
ranges of their options and of ``attack check``, and ``attack check`` on a damaged attacked dataset: one error
line naming the file/option and the field, exit 2, checked before any work, nothing half-written."""

from __future__ import annotations

import hashlib
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh
from cli_checks import fails_cleanly

from robustbench3d.attacks import create_attack
from robustbench3d.attacks.apply import apply_dataset
from robustbench3d.attacks.object import RoofObject, random_shape
from robustbench3d.attacks.objectfile import read_object_file, save_object
from robustbench3d.attacks.shipped import shipped_objects
from robustbench3d.attacks.spec import AttackSpecError
from robustbench3d.attacks.train_config import TrainConfig, TrainingError
from robustbench3d.cli import main
from robustbench3d.errors import DataFormatError
from robustbench3d.sensors.mesh import icosphere
from robustbench3d.testing import synth_dataset

OBJECTS = Path(__file__).resolve().parents[2] / "attacks" / "objects"


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """Two generated frames, both in val."""
    return synth_dataset(tmp_path_factory.mktemp("synth"), 2, seed=0, val_fraction=1.0)


# ---- 1. object files: every sidecar field has a range ------------------------------------------------------


def _object_pair(directory: Path, name: str, vertices: np.ndarray, bounds: list, **sidecar) -> Path:
    """A PLY written by trimesh (162 vertices, the icosphere's faces, grey) and a sidecar written here, by hand,
    with the PLY's sha256: the reader's checks after the hash are reached whatever ``bounds`` says."""
    _, faces = icosphere(2, 0.4)
    ply = directory / f"{name}.ply"
    colours = np.full((len(vertices), 4), 128, np.uint8)
    ply.write_bytes(trimesh.Trimesh(vertices, faces, vertex_colors=colours, process=False).export(file_type="ply"))
    data = {"format": "robustbench3d.roof_object/1", "ply": ply.name,
            "ply_sha256": hashlib.sha256(ply.read_bytes()).hexdigest(),
            "template": {"kind": "icosphere", "level": 2, "radius": 0.4, "vertices": 162, "faces": 320},
            "frame": "object frame", "placement": {"rule": "roof-centre", "description": "on the roof"},
            "bounds": bounds, "box_constraint": "|v_i| <= bounds_i", "made_by": {"attack": "test"}}
    data.update(sidecar)
    ply.with_suffix(".json").write_text(json.dumps(data))
    return ply


def _refused(ply: Path, field: str, *words: str) -> str:
    with pytest.raises(DataFormatError) as info:
        read_object_file(ply)
    message = str(info.value)
    assert info.value.field == field, message
    assert str(info.value.path) in message
    for word in words:
        assert word in message, message
    return message


@pytest.mark.parametrize("half_extent", [1e6, 3e38, 1.0001])
def test_an_object_larger_than_a_car_roof_is_refused_naming_the_sidecar_field(tmp_path, half_extent):
    """The filed case: a 1e6 m object (and a 3e38 m one), its vertices inside its own bounds."""
    sphere, _ = icosphere(2, 0.4)
    ply = _object_pair(tmp_path, "big", sphere / 0.4 * half_extent, [half_extent] * 3)
    message = _refused(ply, "bounds", "[0.001, 1] m")
    assert message.startswith(str(tmp_path / "big.json"))


def test_the_largest_and_smallest_bounds_load(tmp_path):
    sphere, _ = icosphere(2, 0.4)
    for name, half in (("largest", 1.0), ("smallest", 1e-3)):
        ply = _object_pair(tmp_path, name, sphere / 0.4 * half * 0.999, [half] * 3)
        obj = read_object_file(ply).obj
        assert np.all(obj.bounds == half) and np.abs(obj.vertices()).max() <= half


SIDECAR_CASES = [
    ("bounds", {"bounds": [0.4, 0.4, 1e-4]}, "[0.001, 1] m"),
    ("bounds", {"bounds": [True, True, True]}, "three numbers"),
    ("bounds", {"bounds": [0.4, 0.4, math.nan]}, "[0.001, 1] m"),
    ("bounds", {"bounds": "0.4"}, "three numbers"),
    ("ply", {"ply": 7}, "ending in .ply"),
    ("ply", {"ply": "object.obj"}, "ending in .ply"),
    ("ply_sha256", {"ply_sha256": "Z" * 64}, "hex"),
    ("template", {"template": {"kind": "cube", "level": 2, "radius": 0.4}}, "icosphere"),
    ("template", {"template": {"level": 2, "radius": 0.4, "vertices": 163}}, "icosphere"),
    ("placement", {"placement": {"rule": "roof-centre", "description": 5}}, "roof-centre"),
    ("frame", {"frame": 5}, "a string"),
    ("box_constraint", {"box_constraint": ["x"]}, "a string"),
]


@pytest.mark.parametrize(("field", "change", "words"), SIDECAR_CASES, ids=[f"{c[0]}-{i}" for i, c in
                                                                           enumerate(SIDECAR_CASES)])
def test_sidecar_fields_outside_their_range_are_refused(tmp_path, field, change, words):
    sphere, _ = icosphere(2, 0.4)
    ply = _object_pair(tmp_path, "obj", sphere * 0.999, **{"bounds": [0.4, 0.4, 0.4], **change})
    _refused(ply, field, words)


def test_oversized_files_are_refused_before_they_are_parsed(tmp_path):
    sphere, _ = icosphere(2, 0.4)
    ply = _object_pair(tmp_path, "padded", sphere * 0.999, [0.4] * 3)
    side = ply.with_suffix(".json")
    data = json.loads(side.read_text())
    data["made_by"] = {"notes": "x" * (1 << 20)}  # a valid sidecar, 1 MiB of notes
    side.write_text(json.dumps(data))
    with pytest.raises(DataFormatError, match="at most 1048576 bytes") as info:
        read_object_file(ply)
    assert info.value.path == side
    ply2 = _object_pair(tmp_path, "long", sphere * 0.999, [0.4] * 3)
    ply2.write_bytes(ply2.read_bytes() + b"\0" * (1 << 20))  # 1 MiB of trailing bytes, the hash updated
    data = json.loads(ply2.with_suffix(".json").read_text())
    data["ply_sha256"] = hashlib.sha256(ply2.read_bytes()).hexdigest()
    ply2.with_suffix(".json").write_text(json.dumps(data))
    with pytest.raises(DataFormatError, match="at most 1048576 bytes") as info:
        read_object_file(ply2)
    assert info.value.path == ply2


def test_an_object_cannot_be_built_with_bounds_beyond_the_range():
    for bounds in ((1.5, 0.4, 0.4), (0.4, 0.4, 1e-4), (0.4, math.inf, 0.4)):
        with pytest.raises(ValueError, match=r"field 'bounds'.*\[0.001, 1\] m"):
            RoofObject(bounds=bounds)


def test_shipped_objects_and_saved_objects_still_load(tmp_path):
    entries = shipped_objects()
    assert {"adv-shape", "adv-texture", "adv-object", "adv-shape-gt-object", "adv-shape-gt-append"} <= {
        e.name for e in entries}
    for entry in entries:
        side = json.loads(entry.sidecar_path.read_text())
        assert read_object_file(entry.path).obj.bounds.tolist() == side["bounds"]
    obj = random_shape(5)
    assert read_object_file(save_object(tmp_path / "r.ply", obj, {"attack": "random-shape"})).obj == obj


def test_a_too_large_object_file_stops_attack_apply_before_the_dataset(tmp_path, capsys):
    sphere, _ = icosphere(2, 0.4)
    ply = _object_pair(tmp_path, "huge", sphere / 0.4 * 1e6, [1e6] * 3)
    fails_cleanly(tmp_path, capsys, ["attack", "apply", str(ply), "--data", str(tmp_path / "no-data"),
                                     "--out", str(tmp_path / "out"), "--no-progress"], "huge.json", "'bounds'")


# ---- 2. the roof-object attack's settings have ranges ------------------------------------------------------

SETTING_CASES = [("position_jitter_m", 1e9, "[0, 0.5] m"), ("position_jitter_m", 0.51, "[0, 0.5] m"),
                 ("yaw_jitter_rad", 3.2, "[0, pi] rad"), ("range_noise_m", 0.25, "[0, 0.2] m"),
                 ("supersample", 100000, "[1, 16]"), ("supersample", 17, "[1, 16]")]


@pytest.mark.parametrize(("name", "value", "span"), SETTING_CASES)
def test_settings_beyond_their_range_are_refused_naming_setting_and_range(name, value, span):
    for attack in ("benign-sphere", "adv-object"):
        with pytest.raises(AttackSpecError) as info:
            create_attack(attack, **{name: value})
        assert f"field '{name}'" in str(info.value) and span in str(info.value) and repr(value) in str(info.value)


def test_settings_at_the_ends_of_their_ranges_are_accepted():
    attack = create_attack("benign-sphere", eot=True, position_jitter_m=0.5, yaw_jitter_rad=math.pi,
                           range_noise_m=0.2, dropout=0.0, supersample=16)
    assert (attack.position_jitter_m, attack.yaw_jitter_rad, attack.range_noise_m, attack.supersample) == (
        0.5, math.pi, 0.2, 16)
    zero = create_attack("benign-sphere", position_jitter_m=0, yaw_jitter_rad=0, supersample=1)
    assert (zero.position_jitter_m, zero.yaw_jitter_rad, zero.supersample) == (0.0, 0.0, 1)


def test_random_shape_seed_has_a_range():
    """As run --seed: 32-bit."""
    with pytest.raises(AttackSpecError, match=r"field 'seed': expected an integer in \[0, 2\*\*32 - 1\]"):
        create_attack("random-shape", seed=2**32)
    assert create_attack("random-shape", seed=2**32 - 1).identity == {"attack": "random-shape", "seed": 2**32 - 1}


def test_run_refuses_a_setting_before_the_dataset_is_read(tmp_path, capsys):
    """The filed case: position_jitter_m=1e9 made a cell of zero drop; now run stops first (the dataset does not
    even exist, so the refusal cannot come from rendering)."""
    fails_cleanly(tmp_path, capsys, ["run", "--victims", "fpointnet-v1-lite", "--attacks", "benign-sphere",
                                     "--attack-arg", "benign-sphere:position_jitter_m=1e9",
                                     "--data", str(tmp_path / "no-data"), "--out", str(tmp_path / "run"),
                                     "--no-progress"], "position_jitter_m", "[0, 0.5] m")


# ---- 3. written once: show, attack train, attack apply -----------------------------------------------------


def test_show_refuses_an_existing_out_and_replaces_it_with_force(dataset, tmp_path, capsys):
    png = tmp_path / "f.png"
    png.write_bytes(b"someone else's picture")
    fails_cleanly(tmp_path, capsys, ["show", str(dataset), "000000", "--out", str(png)], str(png), "--force")
    assert main(["show", str(dataset), "000000", "--out", str(png), "--force"]) == 0
    printed = capsys.readouterr().out
    assert f"replacing {png} (--force)" in printed
    assert png.read_bytes().startswith(b"\x89PNG")


def _train_argv(out: Path, data: Path, *extra: str) -> list[str]:
    return ["attack", "train", "adv-shape", "--victim", "fpointnet-v1-lite", "--data", str(data), "--split", "val",
            "--out", str(out), "--steps", "1", "--batch-cars", "1", "--no-progress", *extra]


def test_attack_train_refuses_an_existing_object_sidecar_or_checkpoint_up_front(tmp_path, capsys):
    """Each refusal comes before the dataset is read (it does not exist)."""
    no_data = tmp_path / "no-data"
    ply = save_object(tmp_path / "obj.ply", random_shape(2), {"attack": "random-shape", "seed": 2})
    fails_cleanly(tmp_path, capsys, _train_argv(ply, no_data), str(ply), "--force")
    ply.unlink()  # the sidecar alone
    fails_cleanly(tmp_path, capsys, _train_argv(ply, no_data), "obj.json", "--force")
    ply.with_suffix(".json").unlink()
    (tmp_path / "obj.train.pt").write_bytes(b"an interrupted training's checkpoint")
    fails_cleanly(tmp_path, capsys, _train_argv(ply, no_data), "obj.train.pt", "--resume")


def test_attack_train_force_and_the_resume_rule(dataset, tmp_path, capsys):
    out = tmp_path / "o.ply"
    side, ckpt = tmp_path / "o.json", tmp_path / "o.train.pt"
    assert main(_train_argv(out, dataset)) == 0
    capsys.readouterr()
    assert out.is_file() and side.is_file() and ckpt.is_file()
    fails_cleanly(tmp_path, capsys, _train_argv(out, dataset), str(out), "--force")
    # --resume continues the training that wrote o.ply and o.json: they are its to replace (and it says so)
    assert main(_train_argv(out, dataset, "--resume", "--steps", "2")) == 0
    printed = capsys.readouterr().out
    assert f"replacing {out} and o.json" in printed and "(--resume)" in printed
    assert json.loads(side.read_text())["made_by"]["steps"] == 2
    # another object under that name is not the checkpoint's to replace
    shutil.copyfile(OBJECTS / "adv-texture.ply", out)
    shutil.copyfile(OBJECTS / "adv-texture.json", side)
    fails_cleanly(tmp_path, capsys, _train_argv(out, dataset, "--resume", "--steps", "3"), str(out), "--force")
    assert main(_train_argv(out, dataset, "--force")) == 0
    printed = capsys.readouterr().out
    for path in (out, side, ckpt):
        assert f"replacing {path} (--force)" in printed
    assert json.loads(side.read_text())["made_by"]["attack"] == "adv-shape"


def test_attack_apply_refuses_a_dangling_symlink_out(tmp_path, capsys):
    link = tmp_path / "out"
    link.symlink_to(tmp_path / "nowhere")
    fails_cleanly(tmp_path, capsys, ["attack", "apply", "benign-sphere", "--data", str(tmp_path / "no-data"),
                                     "--out", str(link), "--no-progress"], str(link), "broken symbolic link")


def test_attack_apply_refuses_a_directory_of_another_tool(tmp_path, capsys):
    other = tmp_path / "other"
    other.mkdir()
    (other / "attack_manifest.json").write_text(json.dumps({"tool": "someone else", "frames": []}))
    fails_cleanly(tmp_path, capsys, ["attack", "apply", "benign-sphere", "--data", str(tmp_path / "no-data"),
                                     "--out", str(other), "--no-progress"], "attack_manifest.json", "'tool'")


# ---- 4. attack check on a damaged attacked dataset; show's options -----------------------------------------


@pytest.fixture(scope="module")
def attacked(dataset, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("att") / "out"
    apply_dataset("benign-sphere", dataset, "val", out, seed=0, progress=False)
    return out


def _damage_ply_missing(t: Path) -> None:
    (t / "objects" / "000000.ply").unlink()


def _damage_ply_garbage(t: Path) -> None:
    (t / "objects" / "000000.ply").write_bytes(b"not a mesh")


def _damage_ply_truncated(t: Path) -> None:
    path = t / "objects" / "000000.ply"
    path.write_bytes(path.read_bytes()[:1000])


def _damage_marker(text: str):
    def damage(t: Path) -> None:
        (t / ".done" / "000000.json").write_text(text)
    return damage


def _damage_calib_missing(t: Path) -> None:
    (t / "calib" / "000000.txt").unlink()


DAMAGE = {
    "ply-missing": (_damage_ply_missing, ["objects/000000.ply", "not found"]),
    "ply-garbage": (_damage_ply_garbage, ["objects/000000.ply", "not a readable PLY"]),
    "ply-truncated": (_damage_ply_truncated, ["objects/000000.ply", "not a readable PLY"]),
    "marker-not-json": (_damage_marker("{"), [".done/000000.json", "not valid JSON"]),
    "marker-a-list": (_damage_marker("[]"), [".done/000000.json", "JSON object"]),
    "marker-objects-text": (_damage_marker('{"frame": "000000", "objects": "x"}'),
                            [".done/000000.json", "'objects'"]),
    "marker-other-frame": (_damage_marker('{"frame": "000001", "objects": 0, "vertices_per_object": 0, '
                                          '"faces_per_object": 0}'), [".done/000000.json", "'frame'"]),
    "marker-count-mismatch": (_damage_marker('{"frame": "000000", "objects": 1, "vertices_per_object": 162, '
                                             '"faces_per_object": 320}'), ["objects/000000.ply", "'vertices'"]),
    "calib-missing": (_damage_calib_missing, ["calib/000000.txt", "not found"]),
}


@pytest.mark.parametrize("case", list(DAMAGE))
def test_attack_check_on_a_damaged_attacked_dataset_is_one_line(attacked, tmp_path, capsys, case):
    damage, names = DAMAGE[case]
    copy = tmp_path / "attacked"
    shutil.copytree(attacked, copy)
    damage(copy / "training")
    fails_cleanly(tmp_path, capsys, ["attack", "check", str(copy)], *names)


def test_attack_check_on_a_manifest_without_its_dataset(attacked, tmp_path, capsys):
    copy = tmp_path / "attacked"
    shutil.copytree(attacked, copy)
    (copy / "attack_manifest.json").write_text("{}")
    fails_cleanly(tmp_path, capsys, ["attack", "check", str(copy)], "attack_manifest.json", "'dataset'")


def test_attack_check_max_frames_must_be_positive(attacked, tmp_path, capsys):
    """--max-frames 0 checked no frame and printed PASS."""
    fails_cleanly(tmp_path, capsys, ["attack", "check", str(attacked), "--max-frames", "0"], "--max-frames 0",
                  "[1, 1000000]")
    assert main(["attack", "check", str(attacked), "--max-frames", "1"]) == 0
    assert capsys.readouterr().out.startswith("1 frames (1 with objects)")


@pytest.mark.parametrize(("option", "value", "words"), [
    ("--seed", "-1", ["--seed -1", "2**32 - 1"]), ("--seed", str(2**32), ["--seed 4294967296", "2**32 - 1"]),
    ("--bev-range", "nan", ["--bev-range nan", "[5, 200] m"]), ("--bev-range", "1e9", ["--bev-range", "[5, 200] m"]),
    ("--bev-range", "0", ["--bev-range 0", "[5, 200] m"]), ("--bev-range", "-5", ["--bev-range -5", "[5, 200] m"])])
def test_show_numeric_options_are_checked_before_the_dataset(tmp_path, capsys, option, value, words):
    """The dataset does not exist: the refusal comes first (1e9 used to hang drawing 1e8 range rings)."""
    fails_cleanly(tmp_path, capsys, ["show", str(tmp_path / "no-data"), "000000", "--out", str(tmp_path / "f.png"),
                                     "--attack", "benign-sphere", option, value], *words)


# ---- 5. numeric options of attack train and attack apply ---------------------------------------------------

TRAIN_CASES = [("--steps", "10000000", "'steps'", "[1, 1000000]"),
               ("--batch-cars", "100000", "'batch_cars'", "[1, 1024]"),
               ("--lr-shape", "1000", "'lr_shape'", "(0, 10]"), ("--lr-color", "inf", "'lr_color'", "(0, 10]"),
               ("--lambda-lap", "1e9", "'lambda_lap'", "[0, 1000]"),
               ("--lambda-img", "nan", "'lambda_img'", "[0, 1000]"),
               ("--lambda-box", "nan", "'lambda_box'", "[0, 1000]"),
               ("--lambda-box", "-1", "'lambda_box'", "[0, 1000]"),
               ("--seed", str(2**32), "'seed'", "[0, 4294967295]"),
               ("--checkpoint-every", "10000000", "'checkpoint_every'", "[1, 1000000]"),
               ("--max-frames", "0", "--max-frames 0", "[1, 1000000]")]


@pytest.mark.parametrize(("option", "value", "field", "span"), TRAIN_CASES)
def test_attack_train_options_out_of_range_are_refused_up_front(tmp_path, capsys, option, value, field, span):
    fails_cleanly(tmp_path, capsys, _train_argv(tmp_path / "o.ply", tmp_path / "no-data", option, value), field, span)


@pytest.mark.parametrize(("field", "value"), [("iou_floor", 1.5), ("zero_grad_patience", 10**6), ("supersample", 17),
                                              ("lambda_box", math.inf)])
def test_train_config_fields_without_an_option_have_ranges(field, value):
    with pytest.raises(TrainingError, match=rf"field '{field}'.*got {value!r} \(range "):
        TrainConfig(mode="adv-object", **{field: value})


@pytest.mark.parametrize(("option", "value", "words"), [("--seed", str(2**32), ["--seed 4294967296", "2**32 - 1"]),
                                                        ("--max-frames", "0", ["--max-frames 0", "[1, 1000000]"]),
                                                        ("--max-frames", "1000001", ["--max-frames", "[1, 1000000]"])])
def test_attack_apply_options_out_of_range_are_refused_up_front(tmp_path, capsys, option, value, words):
    fails_cleanly(tmp_path, capsys, ["attack", "apply", "benign-sphere", "--data", str(tmp_path / "no-data"),
                                     "--out", str(tmp_path / "out"), "--no-progress", option, value], *words)

