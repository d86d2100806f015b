"""Benchmark integrity: a victim never receives labels, GT proposals are exactly the 2D label
boxes (the frustum protocols': the GT box united with the object's projected box, or the GT box and the row
indices of the object's returns), a cheating plugin scores nothing -- on clean and attacked frames, whose
deferred images hold data, not closures over the harness, and on the frames ``attack train`` hands its
victim; the summary covers every comparable finished cell of the output directory; a rejected (NaN) result is reported
without naming a file that is gone."""

from __future__ import annotations

import copy
import csv
import dataclasses
import functools
import types
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from kitti_files import label_rows

from robustbench3d.attacks.roof import CameraRender, RoofObjectAttack
from robustbench3d.cli import main
from robustbench3d.eval import evaluate
from robustbench3d.kitti.dataset import FileImageFrame, KittiDataset, LazyImageFrame
from robustbench3d.kitti.labels import Labels
from robustbench3d.results import read_summary
from robustbench3d.runner import RunConfig, run_benchmark
from robustbench3d.victims import VICTIMS
from robustbench3d.victims.base import Proposals
from robustbench3d.victims.spec import Capabilities, EntryInfo, VictimSpec

FRAMES = 4
SNOOP = "test-trust-snoop"
ATTACKS = ("benign-sphere", "adv-object")  # a registry shape and a shipped object file
CAPS = Capabilities(modalities=("camera", "lidar"), backend="other", gradients=False, deterministic=True)
_OPAQUE = (type, types.ModuleType)
_LEAVES = (str, bytes, int, float, complex, Path, type(None), np.generic)


def _callable_parts(obj: Any) -> list[Any]:
    """What a callable carries besides its ``__dict__``: closure cells, defaults, a bound method's
    ``__self__`` and ``__func__``, a partial's function and arguments, ``__wrapped__`` (not ``__globals__``
    or ``__code__``: module namespaces and code are the library, not the frame)."""
    parts: list[Any] = []
    if isinstance(obj, types.FunctionType):
        parts += [*(obj.__closure__ or ()), obj.__defaults__, obj.__kwdefaults__]
    if isinstance(obj, types.MethodType | types.BuiltinMethodType | types.MethodWrapperType):
        parts += [obj.__self__, getattr(obj, "__func__", None)]
    if isinstance(obj, functools.partial):
        parts += [obj.func, obj.args, obj.keywords]
    if callable(obj):
        parts.append(getattr(obj, "__wrapped__", None))
    return parts


def reachable(*roots: Any) -> list[Any]:
    """Every object reachable from ``roots`` through containers, instance attributes (``__dict__``,
    slots, cached properties), object arrays and array bases, closure cells, ``__wrapped__``, bound
    methods, partials and functions' defaults and ``__dict__`` -- all a victim can get at from its
    arguments without leaving them (classes, modules and functions' globals are not followed)."""
    seen: set[int] = set()
    out: list[Any] = []
    stack = list(roots)
    while stack:
        obj = stack.pop()
        if id(obj) in seen or isinstance(obj, _OPAQUE):
            continue
        seen.add(id(obj))
        out.append(obj)
        if isinstance(obj, dict):
            stack += [*obj.keys(), *obj.values()]
        elif isinstance(obj, list | tuple | set | frozenset):
            stack += list(obj)
        elif isinstance(obj, np.ndarray):
            stack += [obj.base] if obj.base is not None else []
            stack += list(obj.ravel()) if obj.dtype == object else []
        elif isinstance(obj, types.CellType):
            stack += [obj.cell_contents] if _cell_full(obj) else []
        elif not isinstance(obj, _LEAVES):
            stack += _callable_parts(obj)
            stack += list(vars(obj).values()) if hasattr(obj, "__dict__") else []  # values, not attribute names
            stack += [getattr(obj, s) for s in getattr(type(obj), "__slots__", ()) if hasattr(obj, s)]
    return out


def _cell_full(cell: types.CellType) -> bool:
    try:
        cell.cell_contents  # noqa: B018 - an empty cell raises
    except ValueError:
        return False
    return True


RECORD: list[dict[str, Any]] = []


class SnoopingVictim:
    """TEST ONLY: a cheating plugin. Records what ``detect`` is given (after reading the images, in
    detector mode), hunts it for labels (the frames' ``labels``, any :class:`Labels` or file path
    reachable from its arguments) and returns whatever ground truth it found, as Cars with score 1."""

    supported_proposals = ("detector", "gt", "gt-object", "gt-append")

    def detect(self, frames, proposals="detector"):
        if proposals == "detector":
            for frame in frames:
                assert frame.image.shape[2] == 3  # renders an attacked frame's image: what it keeps is walked too
        everything = reachable(list(frames), proposals)
        paths = [Path(o) for o in everything if isinstance(o, str | Path) and ("/" in str(o) or "\\" in str(o))]
        RECORD.append({"frames": list(frames), "proposals": proposals, "reachable": everything, "paths": paths})
        out = []
        for frame in frames:
            found = [o for o in reachable(frame) if isinstance(o, Labels) and not o.has_score]
            found += [_read_labels(d, frame.frame_id) for d in _label_dirs(paths)
                      if (d / f"{frame.frame_id}.txt").is_file()]
            if found:
                cars = found[0].select(found[0].type == "Car")
                out.append(dataclasses.replace(cars, score=np.ones(len(cars))))
            else:
                out.append(Labels.empty(with_score=True))
        return out


def _label_dirs(paths: list[Path]) -> list[Path]:
    """Where labels may lie near ``paths``: each path and its ancestors, and their ``label_2`` folders."""
    near = [q for p in paths for q in (p, *p.parents)]
    return [d for q in near for d in (q, q / "label_2")]


def _read_labels(directory: Path, frame_id: str) -> Labels:
    from robustbench3d.kitti.labels import read_labels

    return read_labels(directory / f"{frame_id}.txt")


class NanVictim:
    """TEST ONLY: on frame 000000, a second detection whose score is NaN."""

    supported_proposals = ("detector",)

    def detect(self, frames, proposals="detector"):
        out = []
        for frame in frames:
            n = 2 if frame.frame_id == "000000" else 0
            out.append(Labels(type=np.array(["Car"] * n, dtype=object), truncated=np.zeros(n),
                              occluded=np.zeros(n, dtype=np.int64), alpha=np.zeros(n),
                              bbox=np.tile([100.0, 150.0, 200.0, 220.0], (n, 1)),
                              dimensions=np.tile([1.5, 1.6, 3.9], (n, 1)), location=np.tile([1.0, 1.7, 20.0], (n, 1)),
                              rotation_y=np.zeros(n), score=np.array([0.9, np.nan][:n])))
        return out


VICTIMS.register(SNOOP, VictimSpec(factory=SnoopingVictim, info=EntryInfo(CAPS, summary="TEST ONLY: cheats")))
VICTIMS.register("test-trust-nan", VictimSpec(factory=NanVictim, info=EntryInfo(CAPS, summary="TEST ONLY: NaN")))


@pytest.fixture(scope="module")
def dataset(shared_split) -> Path:
    """Four generated frames, all in the val split (Cars, Vans, Pedestrians, DontCare ...)."""
    return shared_split(FRAMES, seed=5, val_fraction=1.0)


def run(dataset: Path, out: Path, proposals: tuple[str, ...], victims: tuple[str, ...] = (SNOOP,),
        log: list[str] | None = None, attacks: tuple[str, ...] = ("none",), **kw: Any):
    config = RunConfig(victims=victims, attacks=attacks, proposals=proposals, out=out, data=dataset,
                       batch_size=3, progress=False, **kw)
    return run_benchmark(config, (log if log is not None else []).append)


def test_victims_never_receive_labels_and_gt_mode_gets_exactly_the_2d_boxes(dataset, tmp_path):
    RECORD.clear()
    run(dataset, tmp_path / "run", ("detector", "gt"))
    # 4 frames in batches of 3: two calls per cell; then the determinism flag's probe, two calls on the first
    # frame per cell (runner.flags), which must see no more than the cells' calls
    by_mode = {"detector": RECORD[:2], "gt": RECORD[2:4]}
    probes = {"detector": RECORD[4:6], "gt": RECORD[6:]}
    assert len(RECORD) == 8
    ids = [f"{i:06d}" for i in range(FRAMES)]
    for mode, calls in by_mode.items():
        assert [f.frame_id for c in calls for f in c["frames"]] == ids
        assert [f.frame_id for c in probes[mode] for f in c["frames"]] == [ids[0], ids[0]]
        for call in calls + probes[mode]:
            assert all(f.labels is None for f in call["frames"])
            assert not any(isinstance(o, Labels) for o in call["reachable"]), mode
            assert call["paths"] == [], mode
            strings = {str(o) for o in call["reachable"] if isinstance(o, str)}
            frame_strings = {str(o) for o in reachable(call["frames"]) if isinstance(o, str)}
            assert frame_strings == {f.frame_id for f in call["frames"]}  # nothing but the frame ids
            if mode == "detector":
                assert call["proposals"] == "detector" and strings == frame_strings | {"detector"}
    assert {f.name for f in dataclasses.fields(Proposals)} == {"boxes", "scores", "source", "types", "extra_points"}
    for call in by_mode["gt"] + probes["gt"]:
        props = call["proposals"]
        assert isinstance(props, list) and len(props) == len(call["frames"])
        for frame, p in zip(call["frames"], props, strict=True):
            rows = [r for r in label_rows(dataset, frame.frame_id) if r[0] != "DontCare"]
            assert p.source == "gt"
            assert list(p.types) == [r[0] for r in rows]
            assert np.array_equal(p.boxes, np.array([[float(v) for v in r[4:8]] for r in rows]).reshape(-1, 4))
            assert np.array_equal(p.scores, np.ones(len(rows)))
            # nothing else: every array reachable from the proposals is (K,) or (K, 4) -- no 3D data
            arrays = [o for o in reachable(p) if isinstance(o, np.ndarray)]
            assert {a.shape for a in arrays} <= {(len(rows),), (len(rows), 4)}
    kinds = {r[0] for fid in ids for r in label_rows(dataset, fid)}
    assert {"Car", "DontCare"} <= kinds and len(kinds) >= 3  # the check covers several types and DontCare


def test_a_cheating_victim_cannot_return_the_labels(dataset, tmp_path, monkeypatch):
    report = run(dataset, tmp_path / "run", ("detector", "gt"))
    for cell in report.cells:
        assert cell["status"] == "ok"
        assert sum(cell["metrics"]["meta"]["detections"].values()) == 0
        assert cell["metrics"]["Car"]["3d"]["R40"] == {"easy": 0.0, "moderate": 0.0, "hard": 0.0}
        data = tmp_path / "run" / "cells" / f"{SNOOP}+none+{cell['proposals']}" / "data"
        assert all(p.read_text() == "" for p in data.iterdir())

    # the probe is not vacuous: a harness that leaks the labels (as before) lets it score 100
    import robustbench3d.runner.cell as cell_module

    def leaky(frames, labels, source, objects=None):
        return [dataclasses.replace(f, labels=lab if source == "gt" else None)
                for f, lab in zip(frames, labels, strict=True)], source

    monkeypatch.setattr(cell_module, "victim_inputs", leaky)
    (cheated,) = run(dataset, tmp_path / "leaky", ("gt",)).cells
    # reference: the evaluator on the label files against their own Cars (score 1); with this few
    # ground-truth cars the 40 recall points cap a perfect R40 AP below 100
    gt = [_read_labels(dataset / "training" / "label_2", f"{i:06d}") for i in range(FRAMES)]
    perfect = evaluate(gt, [dataclasses.replace(g.select(g.type == "Car"), score=np.ones(int((g.type == "Car").sum())))
                            for g in gt])
    assert cheated["metrics"]["Car"]["3d"] == perfect["Car"]["3d"]
    assert perfect["Car"]["3d"]["R40"]["moderate"] > 40.0


def test_frustum_protocols_hand_the_victim_boxes_and_object_rows_only(dataset, tmp_path, cache):
    """``gt-object`` and ``gt-append``, clean and attacked: no label, path, 3D box or object record reachable;
    the proposals hold boxes, scores, source, types and extra points only; the union boxes are the label file's
    GT box united with the default object's projected box (computed here from the label and calib files)."""
    from object_boxes import nominal_boxes_from_files

    from robustbench3d.attacks.record import ObjectRecord

    RECORD.clear()
    report = run(dataset, tmp_path / "run", ("gt-object", "gt-append"), attacks=("none", "benign-sphere"))
    assert [(c["attack"], c["proposals"], c["status"]) for c in report.cells] == [
        (a, p, "ok") for a in ("none", "benign-sphere") for p in ("gt-object", "gt-append")]
    assert all(sum(c["metrics"]["meta"]["detections"].values()) == 0 for c in report.cells)
    boxes_2d, boxes_3d = gt_boxes(dataset)
    seen = {"gt-object": 0, "gt-append": 0}
    for call in RECORD:
        props = call["proposals"]
        assert isinstance(props, list) and len(props) == len(call["frames"])
        assert not any(isinstance(o, Labels | ObjectRecord) for o in call["reachable"])
        assert call["paths"] == []
        assert holding(reachable(call["frames"]), boxes_2d) == [] and holding(call["reachable"], boxes_3d) == []
        for frame, p in zip(call["frames"], props, strict=True):
            rows, gt, want = nominal_boxes_from_files(dataset, frame.frame_id)
            seen[p.source] += 1
            assert list(p.types) == [r[0] for r in rows] and np.array_equal(p.scores, np.ones(len(rows)))
            arrays = [o for o in reachable(p) if isinstance(o, np.ndarray)]
            floats = [a for a in arrays if a.dtype.kind == "f"]
            assert {a.shape for a in floats} <= {(len(rows),), (len(rows), 4)}  # boxes and scores: nothing 3D
            if p.source == "gt-object":
                assert p.extra_points is None and not [a for a in arrays if a.dtype.kind in "iu"]
                ok = ~np.isnan(want[:, 0])
                assert ok.sum() >= 1
                np.testing.assert_allclose(p.boxes[ok], want[ok], rtol=0, atol=1e-9)
            else:
                assert np.array_equal(p.boxes, gt) and len(p.extra_points) == len(rows)
                for extra in p.extra_points:  # row indices into the frame's own scan, nothing else
                    assert extra.dtype == np.int64 and extra.ndim == 1
                    assert len(extra) == 0 or (extra.min() >= 0 and extra.max() < len(frame.scan))
    assert seen["gt-object"] > 0 and seen["gt-append"] > 0


class _Holder:
    def __init__(self, secret: Any) -> None:
        self.secret = secret

    def method(self) -> None:
        pass


def _closure(secret: Any):
    def make():
        return secret
    return make


def _with_dict(secret: Any):
    def make():
        return None
    make.kept = secret
    return make


def _defaults(secret: Any):
    def make(x=secret):
        return x
    return make


def _kwdefaults(secret: Any):
    def make(*, x=secret):
        return x
    return make


@pytest.mark.parametrize("hide", [
    _closure, _with_dict, _defaults, _kwdefaults,
    lambda secret: functools.wraps(_closure(secret))(lambda: None),  # __wrapped__
    lambda secret: functools.cache(_closure(secret)),
    lambda secret: _Holder(secret).method,  # a bound method's __self__
    lambda secret: functools.partial(print, secret),
    lambda secret: functools.partial(print, sep=secret),
    lambda secret: [secret].append,  # a builtin bound method
], ids=["closure", "function-dict", "defaults", "kwdefaults", "wraps", "cache", "bound-method", "partial-args",
        "partial-keywords", "builtin-method"])
def test_the_walker_follows_what_a_callable_carries(hide):
    secret = Labels.empty()
    assert any(o is secret for o in reachable(hide(secret)))


def test_the_walker_does_not_follow_globals_or_modules():
    # module namespaces are the library, not what the frame holds (RECORD is this module's global)
    assert not any(o is RECORD for o in reachable(_closure(1), reachable, types))


def gt_boxes(dataset: Path) -> tuple[np.ndarray, np.ndarray]:
    """(the 2D boxes (K, 4), the 3D locations and dimensions (2K, 3)) of every labelled object but DontCare
    of the label files, read independently of the library."""
    rows = [r for i in range(FRAMES) for r in label_rows(dataset, f"{i:06d}") if r[0] != "DontCare"]
    two = np.array([[float(v) for v in r[4:8]] for r in rows])
    three = np.array([[float(v) for v in r[11:14]] for r in rows] + [[float(v) for v in r[8:11]] for r in rows])
    return two, three


def holding(objects: list[Any], boxes: np.ndarray) -> list[Any]:
    """The float arrays and number sequences among ``objects`` holding one of ``boxes`` (K, k) as a row or a
    column (the form a leaked box takes)."""
    k = boxes.shape[1]
    found = []
    for o in objects:
        if isinstance(o, list | tuple) and len(o) == k and all(isinstance(x, float | int) for x in o):
            candidates = [np.array(o, np.float64)[None]]
        elif isinstance(o, np.ndarray) and o.dtype.kind == "f" and o.ndim >= 1:
            candidates = [o.reshape(-1, k)] if o.shape[-1] == k else []
            candidates += [o.T] if o.ndim == 2 and o.shape[0] == k else []
        else:
            continue
        if any(len(c) and (c[:, None, :] == boxes[None]).all(axis=2).any() for c in candidates):
            found.append(o)
    return found


def test_a_cheating_victim_finds_no_ground_truth_in_attacked_frames(dataset, tmp_path, cache):
    RECORD.clear()
    report = run(dataset, tmp_path / "run", ("detector", "gt"), attacks=ATTACKS)
    assert {(c["attack"], c["proposals"]) for c in report.cells} == {
        (a, p) for a in ("none", *ATTACKS) for p in ("detector", "gt")}
    for cell in report.cells:
        assert cell["status"] == "ok" and sum(cell["metrics"]["meta"]["detections"].values()) == 0
    boxes_2d, boxes_3d = gt_boxes(dataset)
    assert holding([boxes_2d], boxes_2d) and holding([boxes_3d.T.copy()], boxes_3d)  # the probe finds a leak
    attacked = {"detector": 0, "gt": 0}
    for call in RECORD:
        mode = "detector" if call["proposals"] == "detector" else "gt"
        lazy = [f for f in call["frames"] if isinstance(f, LazyImageFrame) and not isinstance(f, FileImageFrame)]
        attacked[mode] += sum(isinstance(f.make_image.make, CameraRender) for f in lazy)
        assert not any(isinstance(o, Labels) for o in call["reachable"]), mode
        assert call["paths"] == [], mode
        # data, not closures: no function, partial or cell reachable at all
        assert not [o for o in call["reachable"] if isinstance(o, types.FunctionType | functools.partial
                                                                  | types.CellType | RoofObjectAttack)]
        assert holding(reachable(call["frames"]), boxes_2d) == [], mode  # gt mode's proposals hold the 2D boxes
        assert holding(call["reachable"], boxes_3d) == [], mode
    assert attacked["detector"] > 0 and attacked["gt"] > 0  # attacked frames were walked, rendered or not


def test_the_probe_catches_an_attacked_frame_whose_image_is_a_closure(dataset, tmp_path, cache, monkeypatch):
    """As attacked frames were made before: the deferred render a closure over the clean frame (with its
    labels), the targets and a copy of the attack (with the dataset's root); the snooping victim finds them."""
    real = RoofObjectAttack.apply

    def closure_apply(self, frame, targets, rng):
        out = real(self, frame, targets, rng)
        if out is frame:
            return out
        render, settings = out.make_image, copy.copy(self)

        def camera_image():
            return render() if (frame, targets, settings) else None

        return LazyImageFrame(frame.frame_id, out.scan, frame.calib, frame.labels, frame.image_size, camera_image)

    monkeypatch.setattr(RoofObjectAttack, "apply", closure_apply)
    RECORD.clear()
    cells = run(dataset, tmp_path / "leaky", ("gt",), attacks=("benign-sphere",)).cells
    cheated = next(c for c in cells if c["attack"] == "benign-sphere")
    clean = next(c for c in cells if c["attack"] == "none")
    assert sum(clean["metrics"]["meta"]["detections"].values()) == 0
    assert cheated["metrics"]["meta"]["detections"]["Car"] > 0
    assert cheated["metrics"]["Car"]["3d"]["R40"]["moderate"] > 40.0
    assert any(isinstance(o, Labels) for call in RECORD for o in call["reachable"])
    assert any(str(dataset) in str(p) for call in RECORD for p in call["paths"])


class RecordingCascade:
    """TEST ONLY: wraps a victim, recording (frames, everything reachable) of every ``detect`` and
    ``proposals`` call; the rest is the victim's."""

    def __init__(self, victim: Any, seen: list[tuple[list[Any], list[Any]]]) -> None:
        self._victim, self._seen = victim, seen

    def __getattr__(self, name: str) -> Any:
        return getattr(self._victim, name)

    def detect(self, frames, proposals="detector"):
        self._seen.append((reachable(list(frames)), reachable(list(frames), proposals)))
        return self._victim.detect(frames, proposals)

    def proposals(self, frames, source):
        self._seen.append((reachable(list(frames)), reachable(list(frames), source)))
        return self._victim.proposals(frames, source)


@pytest.mark.parametrize("lidar_boxes", ["gt", "detector"])
def test_attack_train_hands_its_victim_no_ground_truth(dataset, cache, lidar_boxes):
    from robustbench3d.attacks.train import UniversalTrainer
    from robustbench3d.attacks.train_config import TrainConfig
    from robustbench3d.victims import create_victim

    kitti = KittiDataset(dataset, split="val")
    seen: list[tuple[list[Any], list[Any]]] = []
    victim = RecordingCascade(create_victim("fpointnet-v1-lite"), seen)
    config = TrainConfig(mode="adv-object", steps=1, batch_cars=2, occlusion="none", supersample=1,
                         lidar_boxes=lidar_boxes)
    UniversalTrainer(victim, kitti, kitti.frame_ids, [kitti.labels(f) for f in kitti.frame_ids],
                     config).compute_step(0)
    assert len(seen) >= 2
    boxes_2d, boxes_3d = gt_boxes(dataset)
    for frames, everything in seen:
        assert not any(isinstance(o, Labels) for o in everything)
        assert not [o for o in everything if isinstance(o, Path) or (isinstance(o, str) and "/" in o)]
        assert not [o for o in everything if isinstance(o, types.FunctionType | functools.partial | types.CellType)]
        assert holding(frames, boxes_2d) == [] and holding(everything, boxes_3d) == []


def test_summary_lists_every_comparable_finished_cell_of_the_directory(dataset, tmp_path, capsys):
    out = tmp_path / "run"
    a = run(dataset, out, ("detector",))
    log: list[str] = []
    b = run(dataset, out, ("gt",), log=log)
    assert [c["proposals"] for c in b.cells] == ["gt"] and b.earlier == a.cells and b.left_out == []
    summary = read_summary(out / "summary.json")
    assert [(c["victim"], c["proposals"]) for c in summary] == [(SNOOP, "gt"), (SNOOP, "detector")]
    assert summary[1] == a.cells[0]
    assert any("also lists 1 finished cell(s) of earlier runs" in line for line in log)
    with open(out / "results.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert {r["proposals"] for r in rows} == {"detector", "gt"} and len(rows) == 2 * 4 * 2 * 3

    # another seed is another experiment: the earlier gt cell stays on disk but is left out, and said so
    # (the detector cell of seed 0 is replaced: --force, see tests/trust/test_trust_outputs_run.py)
    assert main(["run", "--victims", SNOOP, "--proposals", "detector", "--seed", "1", "--data", str(dataset),
                 "--out", str(out), "--no-progress", "--force"]) == 0
    captured = capsys.readouterr()
    assert f"left out of the summary: {SNOOP}+none+gt: seed 0 (this run: 1)" in captured.err
    assert "1 cell(s) there are left out" in captured.out
    summary = read_summary(out / "summary.json")
    assert [(c["proposals"], c["provenance"]["seed"]) for c in summary] == [("detector", 1)]
    assert (out / "cells" / f"{SNOOP}+none+gt" / "cell.json").is_file()

    # fewer frames are another dataset
    shorter = run(dataset, out, ("gt",), max_frames=2, seed=1, force=True)
    assert shorter.earlier == []
    assert shorter.left_out == [f"{SNOOP}+none+detector: another dataset: frames 4 (this run: 2); "
                                "last_frame '000003' (this run: '000001'); sha256 differs"]


def test_a_nan_result_is_reported_without_a_missing_file(dataset, tmp_path):
    out = tmp_path / "run"
    (cell,) = run(dataset, out, ("detector",), victims=("test-trust-nan",)).cells
    reason = cell["reason"]
    assert cell["status"] == "error"
    assert reason.startswith("victim 'test-trust-nan' returned an invalid result for frame 000000: detection 2 'Car ")
    assert reason.endswith(" nan', field 'score': expected a finite number, got 'nan'")
    assert "data.partial" not in reason and str(out) not in reason
    assert not (out / "cells" / "test-trust-nan+none+detector" / "data.partial").exists()
