"""Benchmark integrity: a victim never receives labels, GT proposals are exactly the 2D label
boxes, a cheating plugin scores nothing; the summary covers every comparable finished cell of
the output directory; a rejected (NaN) result is reported without naming a file that is gone."""

from __future__ import annotations

import csv
import dataclasses
import types
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from robustbench3d.cli import main
from robustbench3d.eval import evaluate
from robustbench3d.kitti.labels import Labels
from robustbench3d.results import read_summary
from robustbench3d.runner import RunConfig, run_benchmark
from robustbench3d.testing import synth_dataset
from robustbench3d.victims import VICTIMS
from robustbench3d.victims.base import Proposals
from robustbench3d.victims.spec import Capabilities, EntryInfo, VictimSpec

FRAMES = 4
SNOOP = "test-trust-snoop"
CAPS = Capabilities(modalities=("camera", "lidar"), backend="other", gradients=False, deterministic=True)
_OPAQUE = (type, types.ModuleType, types.FunctionType, types.BuiltinFunctionType, types.MethodType)


def reachable(*roots: Any) -> list[Any]:
    """Every object reachable from ``roots`` through containers, instance attributes (``__dict__``,
    slots, cached properties), object arrays and array bases -- all a victim can get at from its
    arguments without leaving them (classes, modules and functions are not followed)."""
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
        elif not isinstance(obj, str | bytes | int | float | complex | Path | type(None) | np.generic):
            stack += list(vars(obj).values()) if hasattr(obj, "__dict__") else []  # values, not attribute names
            stack += [getattr(obj, s) for s in getattr(type(obj), "__slots__", ()) if hasattr(obj, s)]
    return out


RECORD: list[dict[str, Any]] = []


class SnoopingVictim:
    """TEST ONLY: a cheating plugin. Records what ``detect`` is given, hunts it for labels (the
    frames' ``labels``, any :class:`Labels` or file path reachable from its arguments) and returns
    whatever ground truth it found, as Cars with score 1."""

    supported_proposals = ("detector", "gt")

    def detect(self, frames, proposals="detector"):
        everything = reachable(list(frames), proposals)
        paths = [Path(o) for o in everything if isinstance(o, str | Path) and ("/" in str(o) or "\\" in str(o))]
        RECORD.append({"frames": list(frames), "proposals": proposals, "reachable": everything, "paths": paths})
        out = []
        for frame in frames:
            found = [o for o in reachable(frame) if isinstance(o, Labels) and not o.has_score]
            found += [_read_labels(p, frame.frame_id) for p in paths if (p / f"{frame.frame_id}.txt").is_file()]
            if found:
                cars = found[0].select(found[0].type == "Car")
                out.append(dataclasses.replace(cars, score=np.ones(len(cars))))
            else:
                out.append(Labels.empty(with_score=True))
        return out


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
def dataset(tmp_path_factory) -> Path:
    """Four generated frames, all in the val split (Cars, Vans, Pedestrians, DontCare ...)."""
    return synth_dataset(tmp_path_factory.mktemp("synth"), FRAMES, seed=5, val_fraction=1.0)


def label_rows(dataset: Path, frame_id: str) -> list[list[str]]:
    """The label file's rows as tokens, read independently of the library."""
    text = (dataset / "training" / "label_2" / f"{frame_id}.txt").read_text()
    return [line.split() for line in text.splitlines() if line.strip()]


def run(dataset: Path, out: Path, proposals: tuple[str, ...], victims: tuple[str, ...] = (SNOOP,),
        log: list[str] | None = None, **kw: Any):
    config = RunConfig(victims=victims, attacks=("none",), proposals=proposals, out=out, data=dataset,
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
    assert {f.name for f in dataclasses.fields(Proposals)} == {"boxes", "scores", "source", "types"}
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

    def leaky(frames, labels, source):
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
    assert main(["run", "--victims", SNOOP, "--proposals", "detector", "--seed", "1", "--data", str(dataset),
                 "--out", str(out), "--no-progress"]) == 0
    captured = capsys.readouterr()
    assert f"left out of the summary: {SNOOP}+none+gt: seed 0 (this run: 1)" in captured.err
    assert "1 cell(s) there are left out" in captured.out
    summary = read_summary(out / "summary.json")
    assert [(c["proposals"], c["provenance"]["seed"]) for c in summary] == [("detector", 1)]
    assert (out / "cells" / f"{SNOOP}+none+gt" / "cell.json").is_file()

    # fewer frames are another dataset
    shorter = run(dataset, out, ("gt",), max_frames=2, seed=1)
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
