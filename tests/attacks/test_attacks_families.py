"""Object families (issue #36, the dose-response sweep): icosphere level 2 / 3 / 4 and radius 0.2-0.6 m, named
by their parameters, written and read as object files, placed on the roof, trained by ``attack train`` and
checked by ``attack check``. Counts, names and the roof height are computed by hand here."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from robustbench3d.attacks import create_attack
from robustbench3d.attacks.object import (
    DEFAULT_FAMILY,
    LEVELS,
    RADIUS_RANGE,
    Family,
    RoofObject,
    benign_sphere,
    check_family,
    random_shape,
    template_faces,
    template_vertices,
)
from robustbench3d.attacks.objectfile import read_object_file, save_object, sidecar_path
from robustbench3d.attacks.placement import Car, place_on_roof
from robustbench3d.attacks.spec import AttackSpecError
from robustbench3d.attacks.train_config import TrainConfig, TrainingError
from robustbench3d.cli import main
from robustbench3d.errors import DataFormatError
from robustbench3d.runner.flags import attack_flags
from robustbench3d.testing import synth_dataset

pytestmark = pytest.mark.usefixtures("cache")  # a fresh cache per test (conftest)

SHIPPED = Path(__file__).resolve().parents[2] / "attacks" / "objects"


# ---- names, bounds, counts --------------------------------------------------------------------

@pytest.mark.parametrize(("level", "radius", "name"), [
    (4, 0.4, "l4-r0.40"), (2, 0.2, "l2-r0.20"), (3, 0.3, "l3-r0.30"), (2, 0.6, "l2-r0.60"), (4, 0.5, "l4-r0.50"),
    (3, 0.25, "l3-r0.25"), (2, 0.30000000000000004, "l2-r0.30")])
def test_family_name_and_bounds_by_hand(level, radius, name):
    family = Family(level, radius)
    assert family.name == name
    r = float(name[-4:])
    assert family.bounds == (r, r, r)
    assert family.radius == r


def test_default_family_is_todays_object():
    assert DEFAULT_FAMILY == Family() == Family(2, 0.40)
    assert DEFAULT_FAMILY.name == "l2-r0.40"
    assert LEVELS == (2, 3, 4) and RADIUS_RANGE == (0.2, 0.6)
    assert benign_sphere().family == DEFAULT_FAMILY and benign_sphere().vertices().shape == (162, 3)


@pytest.mark.parametrize(("level", "vertices", "faces"), [(2, 162, 320), (3, 642, 1280), (4, 2562, 5120)])
def test_vertex_and_face_counts_by_hand(level, vertices, faces):
    """V = 10 * 4^L + 2, F = 20 * 4^L: 162 / 642 / 2562 and 320 / 1280 / 5120."""
    for radius in (0.2, 0.6):
        family = Family(level, radius)
        assert (family.n_vertices, family.n_faces) == (vertices, faces)
        v, f = template_vertices(family), template_faces(family)
        assert v.shape == (vertices, 3) and f.shape == (faces, 3)
        # every template vertex on the sphere of that radius (float32 file precision), inside the box
        assert np.allclose(np.linalg.norm(v, axis=1), radius, atol=1e-6)
        assert np.all(np.abs(v) <= radius)
        # a closed mesh: Euler characteristic 2, every edge shared by two faces
        edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        _, counts = np.unique(edges, axis=0, return_counts=True)
        assert vertices - len(counts) + faces == 2 and np.all(counts == 2)
        assert not v.flags.writeable and not f.flags.writeable


@pytest.mark.parametrize(("level", "radius", "field"), [
    (1, 0.4, "level"), (5, 0.4, "level"), (True, 0.4, "level"), (2.0, 0.4, "level"), ("3", 0.4, "level"),
    (2, 0.1, "radius"), (2, 0.65, "radius"), (2, float("nan"), "radius"), (2, 0.255, "radius"),
    (2, True, "radius"), (2, "0.4", "radius")])
def test_out_of_range_family_refused_naming_the_field(level, radius, field):
    rng = r"\{2, 3, 4\}" if field == "level" else r"\[0\.2, 0\.6\] m"
    with pytest.raises(ValueError, match=rf"^field '{field}': expected .*{rng}.*got") as info:
        Family(level, radius)
    assert "\n" not in str(info.value)
    with pytest.raises(ValueError, match=rf"^field '{field}'"):
        check_family(level, radius)
    with pytest.raises(TrainingError, match=rf"^field '{field}' \(--{field}\): .*{rng}"):
        TrainConfig(mode="adv-texture", level=level, radius=radius)
    with pytest.raises(AttackSpecError, match=rf"field '{field}'.*{rng}"):
        create_attack("benign-sphere", level=level, radius=radius)


def test_cli_refuses_a_bad_family_before_any_work(tmp_path, capsys):
    out = tmp_path / "o.ply"
    code = main(["attack", "train", "adv-texture", "--victim", "fpointnet-v1-lite", "--data", str(tmp_path / "none"),
                 "--out", str(out), "--radius", "0.7", "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1
    assert "field 'radius' (--radius)" in err[0] and "[0.2, 0.6] m" in err[0]
    assert not any(tmp_path.iterdir())


# ---- the object and its file ------------------------------------------------------------------

def test_family_object_round_trips_through_its_file(tmp_path):
    family = Family(4, 0.6)
    obj = random_shape(3, family=family)
    assert obj.family == family and obj.vertices().shape == (2562, 3) and obj.faces.shape == (5120, 3)
    assert np.all(np.abs(obj.vertices()) <= 0.6) and np.abs(obj.vertices()).max() > 0.4  # uses the larger box
    path = save_object(tmp_path / "big.ply", obj, {"attack": "test"})
    side = json.loads(sidecar_path(path).read_text())
    assert side["template"] == {"kind": "icosphere", "level": 4, "radius": 0.6, "vertices": 2562, "faces": 5120}
    assert side["bounds"] == [0.6, 0.6, 0.6]
    mesh = trimesh.load(path, process=False)  # read independently
    assert len(mesh.vertices) == 2562 and len(mesh.faces) == 5120
    assert np.array_equal(np.asarray(mesh.vertices, np.float32), obj.vertices().astype(np.float32))
    back = read_object_file(path)
    assert back.obj == obj and back.obj.family == family
    assert save_object(tmp_path / "again.ply", back.obj, {"attack": "test"}).read_bytes() == path.read_bytes()


def test_reading_validates_against_the_recorded_family(tmp_path):
    path = save_object(tmp_path / "a.ply", benign_sphere(Family(3, 0.3)))
    side = sidecar_path(path)
    good = json.loads(side.read_text())
    for template, field in (({"level": 4, "radius": 0.3}, "vertices"), ({"level": 3, "radius": 0.7}, "template"),
                            ({**good["template"], "vertices": 162}, "template")):
        side.write_text(json.dumps({**good, "template": template}))
        with pytest.raises(DataFormatError, match=f"field '{field}'"):
            read_object_file(path)
    # the radius is the family's: a level-3 sphere of radius 0.3 recorded as radius 0.2 has its vertices outside
    side.write_text(json.dumps({**good, "template": {"level": 3, "radius": 0.2}, "bounds": [0.2, 0.2, 0.2]}))
    with pytest.raises(DataFormatError, match=r"field 'vertices'.*outside the box"):
        read_object_file(path)


@pytest.mark.parametrize("name", ["adv-texture", "adv-shape", "adv-object"])
def test_default_object_files_are_byte_identical_to_the_shipped_ones(tmp_path, name):
    """A shipped (default-family) object loads unchanged and re-writing it gives the same PLY and sidecar bytes
    (under the PLY name its sidecar records)."""
    side = json.loads((SHIPPED / f"{name}.json").read_text())
    loaded = read_object_file(SHIPPED / f"{name}.ply")
    assert loaded.obj.family == DEFAULT_FAMILY
    out = save_object(tmp_path / side["ply"], loaded.obj, loaded.made_by)
    assert out.read_bytes() == (SHIPPED / f"{name}.ply").read_bytes()
    assert sidecar_path(out).read_bytes() == (SHIPPED / f"{name}.json").read_bytes()


# ---- placement, controls, flags ---------------------------------------------------------------

@pytest.mark.parametrize(("level", "radius"), [(4, 0.6), (2, 0.2), (3, 0.5)])
def test_family_object_rests_on_the_roof(level, radius):
    """The lowest point of the placed object is at the roof height of the label's box (location y - h in rect,
    y down) and its centre above the roof centre, for every radius."""
    family = Family(level, radius)
    car = Car(location=(2.5, 1.7, 14.0), dimensions=(1.45, 1.65, 4.1), rotation_y=0.4)
    roof_y = 1.7 - 1.45
    obj = random_shape(1, family=family)
    placed, _ = place_on_roof(obj.vertices(), car)
    assert placed[:, 1].max() == pytest.approx(roof_y, abs=1e-12)
    # the undeformed sphere: its centre one radius above the roof centre, its top two radii above the roof
    sphere, _ = place_on_roof(benign_sphere(family).vertices(), car)
    centre = sphere.mean(axis=0)
    assert centre == pytest.approx([2.5, roof_y - family.radius, 14.0], abs=1e-6)
    assert sphere[:, 1].min() == pytest.approx(roof_y - 2 * family.radius, abs=1e-6)
    assert np.all(np.linalg.norm(sphere[:, [0, 2]] - [2.5, 14.0], axis=1) <= family.radius + 1e-6)


def test_controls_take_level_and_radius_with_todays_defaults():
    default = create_attack("benign-sphere")
    assert default.obj == benign_sphere() and default.identity == {"attack": "benign-sphere"}
    assert "template" not in default.describe()["object"]
    big = create_attack("benign-sphere", radius=0.6)
    assert big.obj.family == Family(2, 0.6) and list(big.obj.bounds) == [0.6] * 3
    assert big.identity == {"attack": "benign-sphere", "level": 2, "radius": 0.6, "family": "l2-r0.60"}
    assert big.describe()["object"]["template"]["name"] == "l2-r0.60"
    fine = create_attack("random-shape", seed=2, level=3, radius=0.3)
    assert fine.obj.vertices().shape == (642, 3) and fine.obj.family == Family(3, 0.3)
    assert create_attack("random-shape", seed=2).obj == random_shape(2)


def test_out_of_bounds_flag_uses_the_objects_own_family_bounds():
    """A radius-0.6 object reaching 0.55 m is within its family's box (no flag); the same vertices in a default
    family object whose box was widened to 0.6 m leave the default sphere's +-0.40 m box (flagged)."""
    big = benign_sphere(Family(2, 0.6))
    assert attack_flags(create_attack("benign-sphere", radius=0.6)) == []
    widened = RoofObject.from_vertices(big.vertices() * 0.55 / 0.6, bounds=(0.6, 0.6, 0.6))
    attack = create_attack("benign-sphere")
    attack.obj = widened
    flags = attack_flags(attack)
    assert [f["code"] for f in flags] == ["object-out-of-bounds"] and "+-0.40 m" in flags[0]["message"]


# ---- training ---------------------------------------------------------------------------------

def test_config_records_the_family_only_when_not_the_default():
    default = TrainConfig(mode="adv-texture")
    assert (default.level, default.radius, default.name) == (2, 0.4, "adv-texture")
    assert "level" not in default.record() and "radius" not in default.identity()
    l4 = TrainConfig(mode="adv-texture", level=4, radius=0.4)
    assert l4.name == "adv-texture-l4-r0.40" and l4.family == Family(4, 0.4)
    assert (l4.record()["level"], l4.record()["radius"]) == (4, 0.4) and l4.identity()["level"] == 4


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    """Generated frames 0-2, all in val (and train: the same frames)."""
    root = synth_dataset(tmp_path_factory.mktemp("synth"), 3, seed=0, val_fraction=1.0)
    shutil.copyfile(root / "ImageSets" / "val.txt", root / "ImageSets" / "train.txt")
    return root


def test_level3_training_run_writes_its_family_with_finite_gradients(tiny, tmp_path, capsys):
    from robustbench3d.attacks.train import UniversalTrainer
    from robustbench3d.datasets import load_ground_truth, resolve_dataset
    from robustbench3d.victims import create_victim

    out = tmp_path / "l3.ply"
    code = main(["attack", "train", "adv-object", "--victim", "fpointnet-v1-lite", "--data", str(tiny),
                 "--out", str(out), "--steps", "1", "--batch-cars", "2", "--eval-every", "0", "--level", "3",
                 "--radius", "0.3", "--occlusion", "none", "--no-progress", "--workers", "1"])
    assert code == 0
    assert f"{out}: adv-object-l3-r0.30 after 1 steps" in capsys.readouterr().out
    side = json.loads(sidecar_path(out).read_text())
    assert side["template"]["level"] == 3 and side["template"]["radius"] == 0.3 and side["bounds"] == [0.3] * 3
    assert (side["made_by"]["config"]["level"], side["made_by"]["config"]["radius"]) == (3, 0.3)
    mesh = trimesh.load(out, process=False)
    assert len(mesh.vertices) == 642 and np.abs(mesh.vertices).max() <= 0.3 + 1e-6
    assert read_object_file(out).obj.family == Family(3, 0.3)
    # the step's gradients: finite, of the family's shape, and not all zero
    resolved = resolve_dataset(tiny, "train", progress=False)
    gt = load_ground_truth(resolved)
    trainer = UniversalTrainer(create_victim("fpointnet-v1-lite"), resolved.kitti(), gt.frame_ids, gt.labels,
                               TrainConfig(mode="adv-object", batch_cars=2, occlusion="none", supersample=1,
                                           level=3, radius=0.3))
    result = trainer.compute_step(0)
    assert [tuple(g.shape) for g in result.grads] == [(642, 3), (642, 3)]
    assert all(bool(torch.isfinite(g).all()) and bool(g.any()) for g in result.grads)
    assert all(math.isfinite(v) for v in result.losses.values())


def test_attack_check_passes_on_a_level4_family_attack(tiny, tmp_path):
    from robustbench3d.attacks.apply import apply_dataset
    from robustbench3d.attacks.check import check_attacked_dataset

    path = save_object(tmp_path / "l4big.ply", random_shape(5, family=Family(4, 0.6)), {"attack": "test"})
    out = tmp_path / "attacked"
    counts = apply_dataset(str(path), tiny, "val", out, seed=0, max_frames=2, progress=False)
    assert counts["objects"] > 0
    markers = [json.loads(p.read_text()) for p in sorted((out / "training" / ".done").glob("*.json"))]
    assert {(m["vertices_per_object"], m["faces_per_object"]) for m in markers if m["objects"]} == {(2562, 5120)}
    report = check_attacked_dataset(out)
    assert report.ok, report.violations
    assert report.frames == 2 and report.added > 0


def test_check_surface_distance_equals_the_brute_force_on_a_level4_mesh():
    """attack check's point-to-mesh distance prefilters the triangles; it must give the brute force's values."""
    from robustbench3d.attacks.check import surface_distance, surface_distance_brute

    obj = random_shape(1, family=Family(4, 0.6))
    tri = obj.vertices()[obj.faces]
    rng = np.random.default_rng(0)
    k = rng.integers(0, len(tri), 300)
    on = np.einsum("kj,kjd->kd", rng.dirichlet([1, 1, 1], 300), tri[k])
    points = np.concatenate([on, rng.normal(0, 0.5, (100, 3)), on[:100] + rng.normal(0, 1e-3, (100, 3))])
    got = surface_distance(points, tri)
    assert np.array_equal(got, surface_distance_brute(points, tri))
    assert got[:300].max() < 1e-9 and got[300:].min() > 0
