"""Black-box training (``attack train --optimizer cma``): the optimiser reaches the known optimum of a synthetic
victim, the query count is the budget, a resumed run ends with an uninterrupted run's bytes, the refusals, the
white-box trainer's output files, and the proposals of the queries (a victim only ever gets a mode it lists)."""

from __future__ import annotations

import importlib.util
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from robustbench3d.attacks.base import attack_rng, target_cars
from robustbench3d.attacks.blackbox import BlackBoxSettings, ParamSpace, QueryObjective
from robustbench3d.attacks.blackbox_run import cma_checkpoint_path, query_proposals, train_blackbox
from robustbench3d.attacks.objectfile import load_object, read_object_file
from robustbench3d.attacks.roof import RoofObjectAttack
from robustbench3d.attacks.train_config import TrainConfig, TrainingError
from robustbench3d.cli import main
from robustbench3d.datasets import load_ground_truth, resolve_dataset
from robustbench3d.kitti import write_image
from robustbench3d.kitti.labels import Labels
from robustbench3d.testing import box_car_dataset, synth_dataset
from robustbench3d.victims import VICTIMS
from robustbench3d.victims.base import PROPOSAL_SOURCES

REPO = Path(__file__).resolve().parents[2]
FAST = {"occlusion": "none", "supersample": 1}


def flat_box_cars(root: Path, n_train: int) -> Path:
    """``n_train`` training frames of 1-2 box cars (9-22 m ahead) on a flat grey image (fast to decode)."""
    box_car_dataset(root, n_train=n_train, n_val=1)
    for png in (root / "training" / "image_2").glob("*.png"):
        write_image(png, np.full((375, 1242, 3), 170, np.uint8))
    return root


def resolved(root: Path):
    split = resolve_dataset(root, "train", progress=False)
    return split, load_ground_truth(split)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return flat_box_cars(tmp_path_factory.mktemp("boxcars") / "d", 5)


@pytest.fixture(scope="module")
def data(dataset):
    return resolved(dataset)


@pytest.fixture(scope="module")
def one_frame(tmp_path_factory):
    return resolved(flat_box_cars(tmp_path_factory.mktemp("boxcar") / "d", 1))


class RedVictim:
    """A numpy Detector whose score of every target car of a frame is the mean red value (0-1) of the pixels
    the object changed in the frame's image; it reports each car at its own box (its table of the cars, kept
    from the label files by the test, stands for a perfect 3D detector), so the harness matches every car.
    The score falls as the object's red channels fall: the optimum is red 0 on every vertex (any green, blue).
    It counts the frames it is queried with and checks it never sees labels."""

    supported_proposals = ("detector",)

    def __init__(self, kitti, frame_ids, labels) -> None:
        self.clean = {f: np.asarray(kitti.image(f)) for f in frame_ids}
        self.cars = {f: target_cars(lab) for f, lab in zip(frame_ids, labels, strict=True)}
        self.frames = 0

    def detect(self, frames, proposals="detector"):
        assert proposals == "detector"
        out = []
        for frame in frames:
            assert frame.labels is None
            self.frames += 1
            image = np.asarray(frame.image)
            diff = image != self.clean[frame.frame_id]
            changed = diff[..., 0] | diff[..., 1] | diff[..., 2]
            red = image[changed][:, 0].mean() / 255.0 if changed.any() else 1.0
            c = self.cars[frame.frame_id]
            out.append(Labels(type=c.type, truncated=c.truncated, occluded=c.occluded, alpha=c.alpha, bbox=c.bbox,
                              dimensions=c.dimensions, location=c.location, rotation_y=c.rotation_y,
                              score=np.full(len(c), red)))
        return out


def red_victim(data) -> RedVictim:
    resolved, gt = data
    return RedVictim(resolved.kitti(), gt.frame_ids, gt.labels)


def mean_red(victim: RedVictim, data, obj) -> float:
    """The victim's mean car score over every training frame attacked with ``obj`` as a benchmark cell attacks
    it (the fitness the optimiser never sees whole)."""
    resolved, gt = data
    kitti = resolved.kitti()
    attack = RoofObjectAttack(obj, occlusion="none", supersample=1)
    scores = []
    for fid, lab in zip(gt.frame_ids, gt.labels, strict=True):
        frame = attack.apply(kitti.lazy_frame(fid, lab), target_cars(lab), attack_rng(0, fid))
        scores.append(victim.detect([replace(frame, labels=None)])[0].score)
    return float(np.concatenate(scores).mean())


def train(victim, data, out: Path, *, budget: int, population: int = 4, frames: int = 1, **kw):
    resolved, gt = data
    hooks = {k: kw.pop(k) for k in ("resume", "on_generation", "force") if k in kw}
    config = TrainConfig(mode=kw.pop("mode", "adv-texture"), **{**FAST, **kw})
    return train_blackbox(victim, {"name": "red"}, resolved.kitti(), gt.frame_ids, gt.labels, config,
                          BlackBoxSettings(budget, population, frames), out, data_identity={"split": "train"},
                          progress=False, **hooks)


def test_cma_reaches_the_known_optimum_of_a_synthetic_victim(one_frame, tmp_path):
    """The optimum is known by hand (red 0 on every vertex); from the grey start, 240 queries of one frame bring
    the car score to within a third of the way from the optimum back to the start (486 parameters, 162 of which
    matter, about half of those seen)."""
    data = one_frame
    victim = red_victim(data)
    space = ParamSpace(TrainConfig(mode="adv-texture"))
    start = space.object_at(space.start())
    best_x = space.start().reshape(-1, 3).copy()
    best_x[:, 0] = -30.0  # red 0 at file precision
    f0, f_opt = mean_red(victim, data, start), mean_red(victim, data, space.object_at(best_x.reshape(-1)))
    assert f_opt < 0.2 < 0.5 < f0  # shading and haze keep the red of a black object above 0
    train(victim, data, tmp_path / "o.ply", budget=240, population=8, eval_every=0)
    obj = load_object(tmp_path / "o.ply")
    assert mean_red(victim, data, obj) <= f_opt + (f0 - f_opt) / 3
    assert np.median(obj.colors[:, 0]) < 0.2  # most red channels went dark; green and blue were free


def test_queries_equal_the_budget_and_the_curve_counts_apart(data, tmp_path):
    victim = red_victim(data)
    made_by = train(victim, data, tmp_path / "a.ply", budget=24, population=4, frames=2, eval_every=0)
    assert victim.frames == 24 and made_by["queries"]["used"] == 24 and made_by["steps"] == 3
    # a budget that is not a multiple of a generation (8 queries) leaves the remainder unused
    victim = red_victim(data)
    made_by = train(victim, data, tmp_path / "b.ply", budget=31, population=4, frames=2, eval_every=0)
    assert victim.frames == 24 and made_by["queries"] == {**made_by["queries"], "budget": 31, "used": 24}
    # with the held-out curve (the last frame of five), its queries are counted apart: the clean frame once, then
    # one per evaluation (generations 0, 2, 3)
    victim = red_victim(data)
    made_by = train(victim, data, tmp_path / "c.ply", budget=24, population=4, frames=2, eval_every=2, eval_frames=1)
    assert made_by["queries"]["used"] == 24 and made_by["queries"]["held_out"] == 1 + 3
    assert victim.frames == 24 + 4


class Stop(Exception):
    pass


def runtime_free(path: Path) -> dict:
    """The sidecar's made_by without the fields that measure the run rather than describe it."""
    made_by = read_object_file(path).made_by
    made_by.pop("wall_time_s")
    made_by["curve"].pop("eval_time_s")
    made_by["curve"].pop("files")
    made_by["queries"].pop("held_out")  # a resumed run queries the clean held-out frame again
    return made_by


def test_resume_equals_uninterrupted(data, tmp_path):
    kw = {"budget": 32, "population": 4, "frames": 2, "eval_every": 1, "eval_frames": 1, "checkpoint_every": 2,
          "eot": ("jitter", "range-noise", "dropout")}
    train(red_victim(data), data, tmp_path / "full.ply", **kw)

    def interrupt(run):
        if run.state.generation == 3:  # after the checkpoint of generation 2, before that of 4
            raise Stop

    with pytest.raises(Stop):
        train(red_victim(data), data, tmp_path / "part.ply", **kw, on_generation=interrupt)
    assert not (tmp_path / "part.ply").exists()
    saved = json.loads(cma_checkpoint_path(tmp_path / "part.ply").read_text())  # plain JSON, no pickle
    assert saved["generation"] == 2 and saved["queries"] == 16 and len(saved["fitness"]) == 2
    victim = red_victim(data)
    train(victim, data, tmp_path / "part.ply", **kw, resume=True)
    assert victim.frames == 16 + 1 + 2  # only the remaining generations, the clean frame, 2 evaluations
    assert (tmp_path / "part.ply").read_bytes() == (tmp_path / "full.ply").read_bytes()
    assert (tmp_path / "part.curve.csv").read_bytes() == (tmp_path / "full.curve.csv").read_bytes()
    assert runtime_free(tmp_path / "part.ply") == runtime_free(tmp_path / "full.ply")
    # a smaller budget first, then --resume with the larger one: the same object as the larger budget at once
    train(red_victim(data), data, tmp_path / "grow.ply", **{**kw, "budget": 16})
    train(red_victim(data), data, tmp_path / "grow.ply", **kw, resume=True)
    assert (tmp_path / "grow.ply").read_bytes() == (tmp_path / "full.ply").read_bytes()
    # a checkpoint of another configuration is refused, nothing replaced
    before = (tmp_path / "part.ply").read_bytes()
    with pytest.raises(TrainingError, match=r"another training.*optimizer\.population"):
        train(red_victim(data), data, tmp_path / "part.ply", **{**kw, "population": 5}, resume=True)
    assert (tmp_path / "part.ply").read_bytes() == before


def test_output_files_and_sidecar_are_the_white_box_trainers(data, tmp_path):
    made_by = train(red_victim(data), data, tmp_path / "o.ply", budget=16, population=4, frames=2, eval_every=1,
                    eval_frames=1, mode="adv-object", seed=3)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o.cma.json", "o.curve.csv", "o.curve.png", "o.json",
                                                          "o.ply"]
    side = read_object_file(tmp_path / "o.ply").made_by
    assert side == json.loads(json.dumps(made_by))
    shipped = json.loads((REPO / "attacks" / "objects" / "adv-texture.json").read_text())["made_by"]
    assert set(shipped) <= set(side)  # every field the white-box trainer writes
    assert side["tool"] == "robustbench3d attack train" and side["attack"] == "adv-object" and side["seed"] == 3
    assert side["config"]["optimizer"] == "cma" and side["config"]["population"] == 4
    assert "lr_shape" not in side["config"] and "steps" not in side["config"]  # the Adam settings do not apply
    assert side["queries"]["budget"] == 16 and side["queries"]["used"] == 16 and side["steps"] == 2
    assert side["optimizer"]["dimension"] == 2 * 162 * 3 and side["optimizer"]["package"].startswith("cma ")
    assert side["curve"]["files"] == {"csv": "o.curve.csv", "png": "o.curve.png"}
    assert side["losses"]["weights"] == {"car_score": 1.0, "laplacian": 0.01}
    obj = load_object(tmp_path / "o.ply")
    assert np.all(np.abs(obj.vertices()) <= obj.bounds)  # the tanh box holds every candidate
    rows = (tmp_path / "o.curve.csv").read_text().splitlines()
    assert rows[0].startswith("step,") and [r.split(",")[0] for r in rows[1:]] == ["0", "1", "2"]


def cli(dataset, out, *extra):
    return main(["attack", "train", "adv-texture", "--victim", "lidar-cluster", "--data", str(dataset), "--out",
                 str(out), "--no-progress", "--workers", "1", *extra])


@pytest.mark.parametrize(("extra", "message"), [
    (["--query-budget", "10"], "--query-budget: only with --optimizer cma"),
    (["--optimizer", "adam", "--population", "8"], "--population: only with --optimizer cma"),
    (["--optimizer", "cma"], "--optimizer cma: --query-budget N is required"),
    (["--optimizer", "cma", "--query-budget", "0"], "--query-budget: must be an integer in [1, 100000000], got 0"),
    (["--optimizer", "cma", "--query-budget", "100", "--population", "3"],
     "--population: must be an integer in [4, 4096], got 3"),
    (["--optimizer", "cma", "--query-budget", "100", "--frames-per-candidate", "1025"],
     "--frames-per-candidate: must be an integer in [1, 1024], got 1025"),
])
def test_refusals_of_the_options(dataset, tmp_path, capsys, extra, message):
    assert cli(dataset, tmp_path / "o.ply", *extra) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1
    assert list(tmp_path.iterdir()) == []


def test_refusals_with_the_data_and_the_victim(data, dataset, tmp_path, capsys, monkeypatch):
    with pytest.raises(TrainingError, match=r"--query-budget 7: one generation takes 8 queries"):
        train(red_victim(data), data, tmp_path / "o.ply", budget=7, population=4, frames=2)
    with pytest.raises(TrainingError, match=r"--frames-per-candidate 5: the training frames have only 4"):
        train(red_victim(data), data, tmp_path / "o.ply", budget=100, population=4, frames=5)  # one is held out
    with pytest.raises(TrainingError, match=r"does not take the proposals 'gt-object'.*--lidar-boxes"):
        train(red_victim(data), data, tmp_path / "o.ply", budget=8, mode="adv-shape", lidar_boxes="gt-object")
    gt_only = red_victim(data)
    gt_only.supported_proposals = ("gt",)
    with pytest.raises(TrainingError, match=r"does not take the proposals 'detector' the queries need \(it takes gt\)"):
        train(gt_only, data, tmp_path / "o.ply", budget=8, mode="adv-texture")
    assert list(tmp_path.iterdir()) == []
    monkeypatch.setitem(sys.modules, "cma", None)  # the package missing
    assert cli(dataset, tmp_path / "o.ply", "--optimizer", "cma", "--query-budget", "8") == 2
    err = capsys.readouterr().err
    assert "needs the package cma (pycma)" in err and "robustbench3d[blackbox]" in err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.skipif(importlib.util.find_spec("rb3d_lidar_cluster") is None, reason="example plugin not installed")
def test_cli_trains_the_lidar_plugin_and_the_onnx_victim(dataset, tmp_path, capsys):
    """Victims without gradients: the LiDAR-only plugin (adv-shape on its own detections) and the ONNX cascade."""
    out = tmp_path / "shape.ply"
    assert main(["attack", "train", "adv-shape", "--victim", "lidar-cluster", "--lidar-boxes", "detector",
                 "--data", str(dataset), "--out", str(out), "--optimizer", "cma", "--query-budget", "8",
                 "--population", "4", "--frames-per-candidate", "2", "--occlusion", "none", "--no-progress",
                 "--workers", "1"]) == 0
    printed = capsys.readouterr().out
    assert f"{out}: adv-shape (cma) after 1 generations, 8 of 8 queries" in printed
    assert read_object_file(out).made_by["queries"]["proposals"] == "detector"
    out = tmp_path / "tex.ply"
    assert main(["attack", "train", "adv-texture", "--victim", "fpointnet-v1-lite-onnx", "--data", str(dataset),
                 "--out", str(out), "--optimizer", "cma", "--query-budget", "4", "--population", "4",
                 "--frames-per-candidate", "1", "--eval-every", "0", "--no-progress", "--workers", "1"]) == 0
    side = read_object_file(out).made_by
    assert side["victim"]["name"] == "fpointnet-v1-lite-onnx" and side["queries"]["used"] == 4


@pytest.fixture
def lidar_cluster(monkeypatch):
    """The example plugin ``lidar-cluster`` (LiDAR only, gradients False, supported_proposals ("detector",)):
    the installed one, else registered for this test from examples/lidar_cluster_victim."""
    if "lidar-cluster" in VICTIMS.names():
        yield
        return
    monkeypatch.syspath_prepend(str(REPO / "examples" / "lidar_cluster_victim"))
    before = set(sys.modules)
    import rb3d_lidar_cluster

    VICTIMS.register("lidar-cluster", rb3d_lidar_cluster.SPEC)
    try:
        yield
    finally:
        VICTIMS.unregister("lidar-cluster")
        for name in set(sys.modules) - before:
            if name.startswith("rb3d_lidar_cluster"):
                del sys.modules[name]


def test_cli_refuses_a_victim_without_the_queries_proposals_before_the_data(tmp_path, capsys, lidar_cluster):
    code = main(["attack", "train", "adv-shape", "--victim", "lidar-cluster", "--lidar-boxes", "gt-object",
                 "--data", str(tmp_path / "none"), "--out", str(tmp_path / "o.ply"), "--optimizer", "cma",
                 "--query-budget", "8", "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2 and "does not take the proposals 'gt-object' the queries need (it takes detector)" in err
    assert len(err.strip().splitlines()) == 1 and list(tmp_path.iterdir()) == []


class TakesEveryMode:
    """A black-box victim that takes every proposal mode and has no white-box oracle (as an ONNX cascade)."""

    supported_proposals = PROPOSAL_SOURCES


def test_query_proposals_are_a_mode_the_victim_lists(data):
    """The default --lidar-boxes gt becomes detector for a victim that finds its own objects and stays gt for one
    that takes proposals (decided by supported_proposals, not by the white-box oracles); the fitness refuses a
    mode its victim does not list."""
    red, every = red_victim(data), TakesEveryMode()
    shape = TrainConfig(mode="adv-shape", **FAST)
    assert query_proposals(shape, red) == "detector" and query_proposals(shape, every) == "gt"
    assert query_proposals(replace(shape, lidar_boxes="gt-object"), every) == "gt-object"
    assert query_proposals(replace(shape, lidar_boxes="gt-object"), red) == "gt-object"  # refused by check_victim
    assert query_proposals(TrainConfig(mode="adv-texture", **FAST), every) == "detector"
    resolved_split, gt = data
    with pytest.raises(TrainingError, match=r"proposals 'gt' are not among the victim's supported_proposals"):
        QueryObjective(red, resolved_split.kitti(), gt.frame_ids, gt.labels, shape, "gt")


@pytest.fixture(scope="module")
def synth5(tmp_path_factory) -> Path:
    """Five generated training frames (one of them held out by the curve)."""
    return synth_dataset(tmp_path_factory.mktemp("synth5") / "d", 5, seed=3, val_fraction=0.0)


@pytest.mark.parametrize("name", ["pointpillars", "lidar-cluster"])
def test_cli_trains_a_victim_that_finds_its_own_objects_with_the_default_lidar_boxes(
        name, synth5, tmp_path, capsys, monkeypatch, request):
    """`attack train adv-shape --victim V --optimizer cma` with the default --lidar-boxes gt, V listing only
    "detector" (pointpillars; the lidar-cluster plugin): it runs, and every detect of the fitness and of the
    held-out curve gets "detector" (was: refused, the queries asking for "gt")."""
    if name == "lidar-cluster":
        request.getfixturevalue("lidar_cluster")
    seen: list[object] = []
    victim_class = type(VICTIMS.get(name).create())
    original = victim_class.detect

    def spy(self, frames, proposals="detector"):
        seen.extend([proposals] * len(frames))
        return original(self, frames, proposals)

    monkeypatch.setattr(victim_class, "detect", spy)
    out = tmp_path / "o.ply"
    assert main(["attack", "train", "adv-shape", "--victim", name, "--data", str(synth5), "--out", str(out),
                 "--optimizer", "cma", "--query-budget", "4", "--population", "4", "--frames-per-candidate", "1",
                 "--eval-every", "1", "--eval-frames", "1", "--occlusion", "none", "--no-progress",
                 "--workers", "1"]) == 0
    assert f"{out}: adv-shape (cma) after 1 generations, 4 of 4 queries" in capsys.readouterr().out
    queries = read_object_file(out).made_by["queries"]
    assert queries["proposals"] == "detector" and queries["held_out"] > 0
    assert len(seen) == queries["used"] + queries["held_out"] and set(seen) == {"detector"}
