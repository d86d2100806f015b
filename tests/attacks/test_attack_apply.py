"""``attack apply`` / ``attack check`` / ``show --attack`` on a few generated frames, exact occlusion and its
disk cache, the runner's clean cell and attack effect, and the edge cases (a frame without cars, a malformed
object file, an interrupted run)."""

from __future__ import annotations

import importlib.util
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from robustbench3d.attacks import create_attack
from robustbench3d.attacks.apply import apply_dataset
from robustbench3d.attacks.base import target_cars
from robustbench3d.attacks.check import check_attacked_dataset
from robustbench3d.cli import main
from robustbench3d.kitti import KittiDataset, read_split, write_image, write_scan
from robustbench3d.runner.cell import attack_rng
from robustbench3d.sensors.camera_render import render_camera
from robustbench3d.synth.scene_depth import dataset_scene_depth
from robustbench3d.testing import synth_dataset

NO_CARS = "000003"


pytestmark = pytest.mark.usefixtures("cache")  # a fresh cache per test (conftest)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """Generated frames 0-5 (val: 0, 3, 5); frame 3's labels keep no Car (scan and image still show them)."""
    root = synth_dataset(tmp_path_factory.mktemp("synth"), 6, seed=0, val_fraction=0.5)
    label = root / "training" / "label_2" / f"{NO_CARS}.txt"
    label.write_text("".join(r + "\n" for r in label.read_text().splitlines() if not r.startswith("Car ")))
    return root


@pytest.fixture(scope="module")
def attacked(dataset, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("att") / "out"
    apply_dataset("random-shape", dataset, "val", out, seed=0, progress=False)
    return out


def files(root: Path, fid: str) -> dict[str, bytes]:
    t = root / "training"
    return {sub: (t / sub / f"{fid}{ext}").read_bytes()
            for sub, ext in (("velodyne", ".bin"), ("image_2", ".png"), ("calib", ".txt"), ("label_2", ".txt"))}


def test_attacked_dataset_layout_and_provenance(dataset, attacked):
    assert read_split(attacked / "ImageSets" / "val.txt") == read_split(dataset / "ImageSets" / "val.txt")
    manifest = json.loads((attacked / "attack_manifest.json").read_text())
    assert manifest["attack"] == "random-shape" and manifest["seed"] == 0 and manifest["exact_occlusion"] is True
    assert manifest["object_sha256"] == create_attack("random-shape").sha256
    assert manifest["dataset"]["root"] == str(dataset.resolve())
    clean = KittiDataset(dataset, split="val")
    for fid in ("000000", "000005"):
        n_cars = len(target_cars(clean.labels(fid)))
        ply = attacked / "training" / "objects" / f"{fid}.ply"
        import trimesh

        mesh = trimesh.load(ply, file_type="ply", process=False)
        assert len(mesh.vertices) == 162 * n_cars and len(mesh.faces) == 320 * n_cars
        a, c = files(attacked, fid), files(dataset, fid)
        assert a["calib"] == c["calib"] and a["label_2"] == c["label_2"]
        assert a["velodyne"] != c["velodyne"] and a["image_2"] != c["image_2"]


def test_frame_without_cars_passes_through_bit_for_bit(dataset, attacked):
    assert files(attacked, NO_CARS) == files(dataset, NO_CARS)
    assert not (attacked / "training" / "objects" / f"{NO_CARS}.ply").exists()


def test_geometric_check_passes_on_random_shape(attacked):
    report = check_attacked_dataset(attacked)
    assert report.ok, report.violations
    assert report.frames == 3 and report.frames_with_objects == 2
    assert report.added > 100 and report.removed > 100 and report.changed_pixels > 1000
    assert report.max_added_distance_m <= 1e-4


def tampered(attacked: Path, tmp_path: Path) -> Path:
    copy = tmp_path / "tampered"
    shutil.copytree(attacked, copy)
    return copy


def test_geometric_check_catches_broken_attacks(attacked, dataset, tmp_path):
    fid = "000000"
    clean = KittiDataset(dataset, split=None)
    bad = tampered(attacked, tmp_path)
    t = bad / "training"
    scan = KittiDataset(bad, split=None).scan(fid)
    # A point off every mesh, a clean point dropped in the open (index 0: near the car, not behind an object),
    # and a pixel changed far from every object.
    off_mesh = np.array([[5.0, 5.0, 0.0, 0.5]], np.float32)
    first = clean.scan(fid)[0]
    keep = ~np.all(scan == first, axis=1)
    write_scan(t / "velodyne" / f"{fid}.bin", np.concatenate([scan[keep], off_mesh]))
    image = KittiDataset(bad, split=None).image(fid).copy()
    image[0, 0] = 255 - image[0, 0]
    write_image(t / "image_2" / f"{fid}.png", image)
    report = check_attacked_dataset(bad)
    text = "\n".join(report.violations)
    assert "1 added point(s) farther than 0.0001 m" in text
    assert "1 removed point(s) not behind a mesh" in text
    assert "1 pixel(s) changed outside the objects' projected boxes" in text
    # A kept point that the object hides: put the clean scan back (every removed point comes back as kept).
    write_scan(t / "velodyne" / f"{fid}.bin", np.concatenate([clean.scan(fid), scan[len(clean.scan(fid)) - 0:]]))
    assert "kept point(s) lie behind a mesh" in "\n".join(check_attacked_dataset(bad).violations)


def test_interrupted_apply_resumes(dataset, attacked, tmp_path):
    out = tampered(attacked, tmp_path)
    fid = "000005"
    (out / "training" / ".done" / f"{fid}.json").unlink()
    (out / "training" / "image_2" / f"{fid}.png").unlink()  # as if killed between two files of the frame
    counts = apply_dataset("random-shape", dataset, "val", out, seed=0, progress=False)
    assert counts == {"written": 1, "kept": 2, "objects": len(target_cars(KittiDataset(dataset).labels(fid)))}
    for f in ("000000", NO_CARS, fid):
        assert files(out, f) == files(attacked, f)
    assert (out / "training" / "objects" / f"{fid}.ply").read_bytes() == (
        attacked / "training" / "objects" / f"{fid}.ply").read_bytes()
    # Another seed into the same directory is refused (exit 2, naming the manifest).
    assert main(["attack", "apply", "random-shape", "--data", str(dataset), "--out", str(out), "--seed", "1",
                 "--no-progress"]) == 2


def test_malformed_object_file_exits_2_naming_it(dataset, tmp_path, capsys):
    from robustbench3d.attacks.object import random_shape
    from robustbench3d.attacks.objectfile import save_object

    ply = save_object(tmp_path / "thing.ply", random_shape(3))
    ply.write_bytes(ply.read_bytes()[:-40])  # truncated: no longer matches its sidecar
    code = main(["attack", "apply", str(ply), "--data", str(dataset), "--out", str(tmp_path / "o"), "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2 and str(ply) in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()


def test_exact_occlusion_is_cached_and_equals_the_rebuilt_scene(dataset, cache, monkeypatch):
    fid = "000000"
    ds = KittiDataset(dataset, split="val")
    frame = ds.frame(fid)
    targets = target_cars(frame.labels)
    attack = create_attack("random-shape")
    attack.bind_dataset(ds)
    assert attack.exact_occlusion
    out = attack.apply(frame, targets, attack_rng(0, fid))
    placed = attack.place(targets, attack_rng(0, fid))
    ref = render_camera(frame.image, frame.calib, [(v, attack.obj.faces, attack.obj.colors) for v, _ in placed],
                        scene_depth=dataset_scene_depth(dataset, fid), supersample=attack.supersample)
    assert np.array_equal(out.image, ref.image)
    cached = list((cache / "scene_depth").glob(f"*/{fid}_s3_*.npz"))
    assert len(cached) == 1
    # From the cache: no scene is rebuilt, the result is the same.
    import robustbench3d.synth.scene_depth as sd

    monkeypatch.setattr(sd, "dataset_scene_depth", lambda *a: pytest.fail("scene rebuilt despite the cache"))
    again = create_attack("random-shape")
    again.bind_dataset(ds)
    assert np.array_equal(again.apply(frame, targets, attack_rng(0, fid)).image, out.image)
    # A dataset without the generator's manifest falls back to the scan's depth map.
    plain = dataset.parent / "plain"
    if not plain.exists():
        shutil.copytree(dataset, plain, ignore=shutil.ignore_patterns("synth_manifest.json"))
    other = create_attack("random-shape")
    other.bind_dataset(KittiDataset(plain, split="val"))
    assert not other.exact_occlusion


def test_show_attack_draws_clean_and_attacked(dataset, tmp_path):
    from robustbench3d.draw import OBJECT_POINT_COLOUR
    from robustbench3d.kitti.image import read_image

    png = tmp_path / "f.png"
    assert main(["show", str(dataset), "000000", "--out", str(png), "--attack", "random-shape"]) == 0
    picture = read_image(png)
    height, width = KittiDataset(dataset, split=None).image("000000").shape[:2]
    assert picture.shape[1] == 2 * width
    marked = np.all(picture[height:] == OBJECT_POINT_COLOUR, axis=2)  # the bird's-eye views
    assert marked[:, width:].sum() > 50 and marked[:, :width].sum() == 0


@pytest.mark.skipif(importlib.util.find_spec("rb3d_lidar_cluster") is None, reason="example plugin not installed")
def test_run_adds_the_clean_cell_and_records_the_effect(dataset, tmp_path, capsys):
    from robustbench3d.results import CellResult, read_summary

    out = tmp_path / "run"
    assert main(["run", "--victims", "lidar-cluster", "--attacks", "random-shape", "--data", str(dataset),
                 "--out", str(out), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    cells = {c["attack"]: CellResult(c) for c in read_summary(out / "summary.json")}
    assert set(cells) == {"none", "random-shape"}
    clean, attacked = cells["none"], cells["random-shape"]
    assert clean.effect is None and attacked.effect is not None
    for d in ("easy", "moderate", "hard"):
        assert attacked.drop("Car", "bev", "R40", d) == clean.ap("Car", "bev", "R40", d) - attacked.ap(
            "Car", "bev", "R40", d)
    on_disk = json.loads((out / "cells" / "lidar-cluster+random-shape+detector" / "cell.json").read_text())
    assert on_disk["attack_effect"] == attacked.effect
    assert "ASR %" in printed
