"""Sanity flags (robustbench3d.runner.flags): each flag triggered on purpose and left silent on the shipped
objects and honest cells; the runner writes them into cell.json and summary.json, prints them, and keeps
the determinism verdict of a reused cell; that verdict comes from the process that computed the cell
(the run's own with --jobs 1, a shard worker with --jobs 2), never from a victim created for it."""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
import os
from pathlib import Path

import numpy as np
import pytest

from robustbench3d.attacks import register_attack
from robustbench3d.attacks.base import Attack
from robustbench3d.attacks.object import NEUTRAL_GREY, RoofObject, template_vertices
from robustbench3d.attacks.objectfile import read_object_file, save_object
from robustbench3d.attacks.roof import RoofObjectAttack
from robustbench3d.kitti import Labels, write_split
from robustbench3d.kitti.labels import read_labels
from robustbench3d.results import read_summary, validate_summary
from robustbench3d.runner import RunConfig, run_benchmark
from robustbench3d.runner.config import CellKey
from robustbench3d.runner.executors import LocalExecutor
from robustbench3d.runner.flags import (
    CODES,
    attack_flags,
    attack_raises_ap,
    object_out_of_bounds,
    onnx_divergence,
    partial_split,
    training_gradients,
    twin_source,
)
from robustbench3d.runner.shards import CellJob, Shard, finished_shard
from robustbench3d.testing import write_kitti_frame
from robustbench3d.victims import VICTIMS
from robustbench3d.victims.spec import Capabilities, EntryInfo, VictimSpec

OBJECTS = Path(__file__).resolve().parents[2] / "attacks" / "objects"
SHA = "ab" * 32


# ---- hand-made cells ---------------------------------------------------------------------------------

def cell(victim: str = "v", attack: str = "a", frames: int = 10, split_frames: int = 10, bev_moderate: float = 50.0,
         backend: str = "torch", weights: str | None = SHA) -> dict:
    by = {"easy": 40.0, "moderate": bev_moderate, "hard": 30.0}
    return {
        "schema_version": 1, "victim": victim, "attack": attack, "proposals": "gt", "status": "ok", "reason": None,
        "dataset": {"root": "/d", "split": "val", "frames": frames, "split_frames": split_frames, "sha256": SHA,
                    "embedded": None, "manifest": None},
        "metrics": {"Car": {"bev": {"R40": dict(by), "R11": dict(by)}},
                    "meta": {"evaluator": "robustbench3d.eval", "version": "1", "ap_unit": "percent", "frames": frames,
                             "classes": ["Car"], "metrics": ["bev"], "min_overlap": {"Car": {"bev": 0.7}}}},
        "provenance": {"config": {"victim": {"name": victim, "capabilities": {"backend": backend},
                                             "weights_sha256": weights}}},
    }


def with_effect(c: dict, clean_moderate: float, drop_moderate: float) -> dict:
    def table(v: float) -> dict:
        return {"Car": {"bev": {"R40": {"easy": 0.0, "moderate": v, "hard": 0.0}}}}

    c["attack_effect"] = {"clean": table(clean_moderate), "drop": table(drop_moderate)}
    return c


def test_partial_split_only_below_the_split():
    assert partial_split(cell(frames=10, split_frames=10)) == []
    (f,) = partial_split(cell(frames=3, split_frames=10))
    assert f["code"] == "partial-split" and "3 of the 10 frames of split 'val'" in f["message"]


@pytest.mark.parametrize(("drop", "flagged"), [(-0.6, True), (-0.5, False), (0.0, False), (3.0, False)])
def test_attack_raises_ap_beyond_the_tolerance(drop, flagged):
    out = attack_raises_ap(with_effect(cell(), 60.0, drop))
    assert bool(out) == flagged
    if flagged:
        assert out[0]["code"] == "attack-raises-ap"
        assert "60.60 % under attack is 0.60 points above the clean cell's 60.00 %" in out[0]["message"]
    assert attack_raises_ap(cell()) == []  # the clean cell has no comparison


def test_object_out_of_bounds_counts_vertices_by_brute_force():
    assert object_out_of_bounds(template_vertices()) == []
    big = template_vertices() * 1.25
    (f,) = object_out_of_bounds(big)
    outside = sum(1 for v in big if any(abs(x) > 0.4 + 1e-6 for x in v))
    worst = max(max(abs(x) - 0.4 for x in v) for v in big)
    assert outside > 0 and f["message"].startswith(f"{outside} of 162 vertices leave")
    assert f"{worst:.4f} m outside" in f["message"]
    # an object whose own bounds allow it: flagged all the same (its bounds are not the sphere's)
    obj = RoofObject.from_vertices(big, bounds=(0.6, 0.6, 0.6))
    assert [f["code"] for f in attack_flags(RoofObjectAttack(obj))] == ["object-out-of-bounds"]


def test_shipped_objects_raise_no_flag():
    for name in ("adv-shape", "adv-texture", "adv-object"):
        loaded = read_object_file(OBJECTS / f"{name}.ply")
        attack = RoofObjectAttack(loaded.obj, identity=loaded.made_by, sha256=loaded.sha256)
        assert attack_flags(attack) == [], name


def shipped_made_by(name: str) -> dict:
    return read_object_file(OBJECTS / f"{name}.ply").made_by


def test_zero_attack_loss_means_zero_gradient():
    made_by = shipped_made_by("adv-shape")
    assert training_gradients(made_by) == []
    made_by["losses"]["mean_last_10"]["lidar"] = 0.0
    (f,) = training_gradients(made_by)
    assert f["code"] == "training-gradients" and "the lidar loss was exactly 0" in f["message"]
    # a term the mode does not weight is no attack gradient of this object
    made_by = shipped_made_by("adv-shape")
    made_by["losses"]["mean_last_10"]["image"] = 0.0
    assert training_gradients(made_by) == []


def test_non_finite_loss_means_nan_gradient():
    made_by = shipped_made_by("adv-object")
    made_by["losses"]["last_step"]["image"] = float("nan")
    (f,) = training_gradients(made_by)
    assert "non-finite training loss at losses.last_step.image" in f["message"]


def test_colours_that_never_moved_mean_all_zero_colour_gradients():
    made_by = shipped_made_by("adv-texture")
    grey = RoofObject(colors=np.full((162, 3), NEUTRAL_GREY))
    (f,) = training_gradients(made_by, grey.vertices(), grey.colors)
    assert "colours are all still the initial neutral grey" in f["message"]
    trained = read_object_file(OBJECTS / "adv-texture.ply").obj
    assert training_gradients(made_by, trained.vertices(), trained.colors) == []
    # a control that was never trained (benign sphere: grey by design) has no losses record: no flag
    assert training_gradients({"attack": "benign-sphere"}, grey.vertices(), grey.colors) == []


def test_onnx_divergence_against_the_torch_twin():
    source = {"victim": "torch-v", "weights_sha256": SHA}
    twin_of = {"onnx-v": source}.get
    for delta, flagged in ((0.03125, True), (0.0078125, False), (0.0, False)):  # exact in binary
        cells = [cell("torch-v", "a", bev_moderate=50.0), cell("onnx-v", "a", bev_moderate=50.0 + delta,
                                                             backend="onnx", weights="cd" * 32)]
        out = onnx_divergence(cells, twin_of)
        assert (1 in out) == flagged and 0 not in out
        if flagged:
            assert ("from its torch twin 'torch-v' by up to 0.0312 points (Car/bev/R40/moderate: 50.0312 vs 50.0000)"
                    in out[1][0]["message"])
    # a twin with other weights than the export's, or on another attack, is no twin
    cells = [cell("torch-v", "a", weights="ef" * 32), cell("onnx-v", "a", bev_moderate=80.0, backend="onnx")]
    assert onnx_divergence(cells, twin_of) == {}
    cells = [cell("torch-v", "b"), cell("onnx-v", "a", bev_moderate=80.0, backend="onnx")]
    assert onnx_divergence(cells, twin_of) == {}


def test_shipped_onnx_victim_names_its_torch_twin():
    source = twin_source("fpointnet-v1-lite-onnx")
    assert source is not None and source["victim"] == "fpointnet-v1-lite"
    from robustbench3d.victims.shipped import shipped_sha256

    assert source["weights_sha256"] == shipped_sha256("fpointnet-v1-lite")
    assert twin_source("fpointnet-v1-lite") is None


# ---- through the runner --------------------------------------------------------------------------------

N_FRAMES, CARS = 5, 4
MARKER_INTENSITY = 0.123


def toy_labels(rng: np.random.Generator) -> Labels:
    n = CARS
    left = np.arange(n) * 250.0 + rng.uniform(0, 20, n)
    top = rng.uniform(150, 180, n)
    return Labels(
        type=np.array(["Car"] * n, dtype=object), truncated=np.zeros(n), occluded=np.zeros(n, dtype=np.int64),
        alpha=np.zeros(n), bbox=np.column_stack([left, top, left + 100.0, top + 80.0]),
        dimensions=np.column_stack([np.full(n, 1.5), np.full(n, 1.6), np.full(n, 4.0)]),
        location=np.column_stack([np.arange(n) * 8.0 - 12, np.full(n, 1.7), np.full(n, 15.0)]),
        rotation_y=np.zeros(n))


@pytest.fixture(scope="module")
def toy(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("toy")
    rng = np.random.default_rng(3)
    ids = [f"{i:06d}" for i in range(N_FRAMES)]
    for fid in ids:
        write_kitti_frame(root, fid, labels=toy_labels(rng), scan=rng.normal(size=(32, 4)).astype(np.float32))
    write_split(root / "ImageSets" / "val.txt", ids)
    return root


class HalfOracle:
    """TEST ONLY: the ground-truth Cars (from ``labels_dir``, given openly by the test) as detections with
    GT proposals, but only the first half of them unless the scan carries a point of intensity
    :data:`MARKER_INTENSITY`; with ``jitter`` every call shifts the boxes (a nondeterministic victim)."""

    supported_proposals = ("gt",)

    def __init__(self, labels_dir: str, jitter: bool = False):
        self.labels_dir, self.jitter, self.calls = labels_dir, jitter, 0

    def detect(self, frames, proposals="gt"):
        self.calls += 1
        out = []
        for frame in frames:
            cars = read_labels(Path(self.labels_dir) / f"{frame.frame_id}.txt")
            if not np.any(np.isclose(frame.scan[:, 3], MARKER_INTENSITY)):
                cars = cars.select(np.arange(len(cars)) < len(cars) // 2)
            loc = cars.location + (0.05 * self.calls if self.jitter else 0.0)
            out.append(dataclasses.replace(cars, location=loc, score=np.linspace(0.9, 0.5, len(cars))))
        return out


#: Pids of the processes that created a jittery victim, as this process saw it (a spawned worker has its own).
created_in: list[int] = []


def half_oracle(labels_dir: str) -> HalfOracle:
    return HalfOracle(labels_dir)


def jittery_oracle(labels_dir: str) -> HalfOracle:
    created_in.append(os.getpid())
    return HalfOracle(labels_dir, jitter=True)


# module-level factories: a worker process unpickles the registry entry by reference to them
for _name, _factory in (("test-flags-half-oracle", half_oracle), ("test-flags-jittery", jittery_oracle)):
    VICTIMS.register(_name, VictimSpec(
        factory=_factory,
        info=EntryInfo(Capabilities(modalities=("lidar",), backend="other", gradients=False, deterministic=True),
                       summary="TEST ONLY: half the GT cars unless the scan is marked")))


@register_attack("test-flags-helpful", summary="TEST ONLY: marks the scan, which makes the test victim see all cars")
class HelpfulAttack(Attack):
    def apply(self, frame, targets, rng):
        marker = np.array([[50.0, 0.0, -5.0, MARKER_INTENSITY]], dtype=frame.scan.dtype)
        return dataclasses.replace(frame, scan=np.concatenate([frame.scan, marker]))

    def describe(self):
        return {"marker_intensity": MARKER_INTENSITY}


def test_runner_writes_prints_and_keeps_flags(toy, tmp_path):
    ply = tmp_path / "big.ply"
    save_object(ply, RoofObject.from_vertices(template_vertices() * 1.25, bounds=(0.6, 0.6, 0.6)),
                {"attack": "adv-shape", "losses": {"weights": {"lidar": 1.0}, "mean_last_10": {"lidar": 0.0}}})
    labels = {"labels_dir": str(toy / "training" / "label_2")}
    config = RunConfig(victims=("test-flags-half-oracle", "test-flags-jittery"),
                       attacks=("none", "test-flags-helpful", "object-file"), proposals=("gt",), out=tmp_path / "run",
                       data=toy, max_frames=3, batch_size=2, progress=False,
                       victim_args={"test-flags-half-oracle": labels, "test-flags-jittery": labels},
                       attack_args={"object-file": {"path": str(ply)}})
    lines: list[str] = []
    report = run_benchmark(config, lines.append)
    summary = read_summary(tmp_path / "run" / "summary.json")
    assert [c["status"] for c in summary] == ["ok"] * 6
    codes = {(c["victim"], c["attack"]): [f["code"] for f in c["flags"]] for c in summary}
    steady, jittery = "test-flags-half-oracle", "test-flags-jittery"
    assert codes[(steady, "none")] == ["partial-split"]
    assert codes[(steady, "test-flags-helpful")] == ["partial-split", "attack-raises-ap"]
    assert codes[(steady, "object-file")] == ["partial-split", "object-out-of-bounds", "training-gradients"]
    assert codes[(jittery, "none")] == ["partial-split", "victim-nondeterministic"]
    assert "victim-nondeterministic" in codes[(jittery, "test-flags-helpful")]  # a property of the victim
    helped = next(c for c in summary if (c["victim"], c["attack"]) == (steady, "test-flags-helpful"))
    # hand reference: 2 of 4 cars clean (every difficulty), all 4 attacked
    assert helped["attack_effect"]["drop"]["Car"]["bev"]["R40"]["moderate"] < -0.5
    for c in summary:  # cell files carry the same flags
        key = f"{c['victim']}+{c['attack']}+gt"
        assert json.loads((tmp_path / "run" / "cells" / key / "cell.json").read_text())["flags"] == c["flags"]
    assert any(line.startswith(f"flag victim-nondeterministic: {jittery} / none / gt: two detect calls on frame "
                               "000000") for line in lines)
    assert sum(line.startswith("flag ") for line in lines) == sum(len(c["flags"]) for c in summary)
    assert report.summary == summary
    # a resumed run reuses every cell; the determinism verdict stays, nothing is rewritten
    before = {p: p.stat().st_mtime_ns for p in (tmp_path / "run" / "cells").glob("*/cell.json")}
    again = run_benchmark(config, lambda line: None)
    assert all(o.reused for o in again.outcomes)
    assert read_summary(tmp_path / "run" / "summary.json") == summary
    assert {p: p.stat().st_mtime_ns for p in before} == before


@pytest.mark.parametrize("jobs", [1, 2])
def test_the_determinism_check_runs_where_the_victim_already_is(toy, tmp_path, jobs):
    labels = {"labels_dir": str(toy / "training" / "label_2")}
    config = RunConfig(victims=("test-flags-half-oracle", "test-flags-jittery"), attacks=("none",),
                       proposals=("gt",), out=tmp_path / "run", data=toy, max_frames=2, batch_size=1,
                       progress=False, victim_args={"test-flags-half-oracle": labels, "test-flags-jittery": labels})
    created_in.clear()
    lines: list[str] = []
    if jobs == 1:
        run_benchmark(config, lines.append)
    else:
        with LocalExecutor(2, shard_frames=1) as executor:  # two one-frame shards per cell
            run_benchmark(config, lines.append, executor=executor)
    summary = read_summary(tmp_path / "run" / "summary.json")
    codes = {c["victim"]: [f["code"] for f in c["flags"]] for c in summary}
    assert codes == {"test-flags-half-oracle": ["partial-split"],
                     "test-flags-jittery": ["partial-split", "victim-nondeterministic"]}
    (flag,) = [f for f in summary[1]["flags"] if f["code"] == "victim-nondeterministic"]
    # HalfOracle moves its 2 boxes (frame 000000, no marker) by 0.05 m per call: the two checks' files differ
    assert flag["message"].startswith("two detect calls on frame 000000 (clean, proposals gt) gave different "
                                      "detections (2 and 2 rows; first difference at row 1)")
    # --jobs 1: the one victim the cells used, created once; --jobs 2: none created in this process
    assert created_in == ([os.getpid()] if jobs == 1 else [])


def shard_with_mark(tmp_path: Path, index: int, mark_extra: dict) -> Shard:
    """A one-frame shard of a hand-made cell directory whose result file and record an earlier run left."""
    key = CellKey("v", "none", "gt")
    job = CellJob(key=key, cell_dir=str(tmp_path), fingerprint="fp", victim_spec=None, victim_kwargs={},
                  attack=b"", kitti=None, seed=0, batch_size=1)
    fid = f"{index:06d}"
    shard = Shard(job, index, index, ((fid, Labels.empty()),))
    text = "Car 0.00 0 0.00 1.00 2.00 3.00 4.00 1.50 1.60 4.00 1.00 1.70 15.00 0.00 0.90\n"
    (tmp_path / "data.partial").mkdir(parents=True, exist_ok=True)
    (tmp_path / "data.partial" / f"{fid}.txt").write_text(text)
    shard.mark_path.parent.mkdir(exist_ok=True)
    mark = {"fingerprint": "fp", "frames": [fid], "sha256": [hashlib.sha256(text.encode()).hexdigest()]}
    shard.mark_path.write_text(json.dumps({**mark, **mark_extra}))
    return shard


def test_a_resumed_first_shard_brings_its_determinism_verdict(tmp_path):
    nondet = {"code": "victim-nondeterministic", "message": "two detect calls differ"}
    got = finished_shard(shard_with_mark(tmp_path / "a", 0, {"victim_probe": [nondet]}))
    assert got is not None and got.reused and got.victim_probe == [nondet]
    got = finished_shard(shard_with_mark(tmp_path / "b", 0, {"victim_probe": []}))
    assert got is not None and got.victim_probe == []
    # a first shard without a (valid) verdict is computed again; a later shard needs none
    for bad in ({}, {"victim_probe": None}, {"victim_probe": [{"code": "partial-split", "message": "m"}]},
                {"victim_probe": [{"code": "victim-nondeterministic"}]}):
        assert finished_shard(shard_with_mark(tmp_path / "c", 0, bad)) is None, bad
    got = finished_shard(shard_with_mark(tmp_path / "d", 1, {}))
    assert got is not None and got.victim_probe is None


def test_flags_are_schema_checked():
    good = copy.deepcopy(json.loads(json.dumps(SCHEMA_CELL)))
    validate_summary([good])
    good["flags"] = [{"code": CODES[0], "message": "m"}]
    validate_summary([good])
    for bad in ([{"code": "x"}], [{"code": "Bad Code", "message": "m"}], [{"code": "x", "message": ""}],
                [{"code": "x", "message": "m", "extra": 1}], {"code": "x"}):
        good["flags"] = bad
        with pytest.raises(Exception, match="flags"):
            validate_summary([good], "s.json")


SCHEMA_CELL = {
    "schema_version": 1, "victim": "v", "attack": "none", "proposals": "gt", "status": "skipped", "reason": "r",
    "dataset": {"root": "/d", "split": "val", "frames": 1, "split_frames": 1, "sha256": SHA, "embedded": None,
                "manifest": None},
    "metrics": None,
    "provenance": {
        "fingerprint": SHA,
        "config": {"victim": {"name": "v", "origin": "x", "kwargs": {}, "capabilities": None, "weights_sha256": None,
                              "weight_files": {}},
                   "attack": {"name": "none", "origin": "x", "params": {}, "object": {},
                              "requirements": {"needs_gradients": False, "needs_camera": False, "needs_lidar": False}},
                   "proposals": "gt", "dataset": {}, "seed": 0, "batch_size": 1, "evaluation": {}},
        "run": {"victims": ["v"], "attacks": ["none"], "proposals": ["gt"]},
        "package": {"name": "robustbench3d", "version": "0"}, "git": {"commit": None, "dirty": None},
        "versions": {"python": "3", "numpy": "2", "torch": None, "onnxruntime": None},
        "platform": {"system": "Linux", "machine": "x", "cpu": None, "cpu_count": 2}, "seed": 0,
        "determinism": {}, "started": "2026-01-01T00:00:00Z", "finished": "2026-01-01T00:00:01Z", "seconds": 1.0},
}
