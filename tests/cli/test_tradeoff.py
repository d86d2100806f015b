"""``robustbench3d tradeoff``: sweeps around the default, Pareto fronts and pro-rata times by hand, scores
against the evaluator run directly on the same detections, and a tiny real run end to end (files, resume,
the report's section in a real headless browser)."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from browser import chromium_page

from robustbench3d.cli import main
from robustbench3d.errors import DataFormatError, RobustBenchError
from robustbench3d.eval.kitti_eval import evaluate
from robustbench3d.kitti.labels import parse_labels
from robustbench3d.tradeoff.analysis import Scorer, pareto_front, score
from robustbench3d.tradeoff.measure import CellMeasure
from robustbench3d.tradeoff.output import read_doc
from robustbench3d.tradeoff.sweeps import (
    CLEAN,
    FrameSweep,
    Point,
    Setting,
    Sweep,
    VictimDefaults,
    build_sweeps,
)

V = "fpointnet-v1-lite"


def test_pareto_front_by_hand():
    pts = [(1.0, 5.0), (2.0, 1.0), (3.0, 1.0), (4.0, 0.0), (1.0, 5.0), (0.5, 9.0), (2.0, 2.0)]
    # (3, 1) is dominated by (2, 1); (2, 2) by (2, 1); equal points do not dominate each other
    assert pareto_front(pts) == [True, True, False, True, True, True, False]
    assert pareto_front([]) == []
    assert pareto_front([(1.0, 0.0)]) == [True]


def test_sweeps_hold_the_default_once_and_reference_the_highest_fidelity():
    default = Setting(V)
    sweeps = build_sweeps(V, frames=50, defaults=VictimDefaults(512, (960, 288), True))
    assert [s.name for s in sweeps] == ["frames", "points", "azimuth", "input", "supersample", "precision",
                                        "backend", "render"]
    assert sweeps[0].counts == (10, 25, 50)
    refs = {s.name: s.points[s.reference] for s in sweeps if isinstance(s, Sweep)}
    assert dict(refs["points"].setting.victim_args) == {"num_points": 2048}
    assert refs["azimuth"].setting == default and refs["azimuth"].value == "1"
    assert dict(refs["input"].setting.victim_args) == {"input_size": "1280x384"}
    assert dict(refs["supersample"].setting.attack_args) == {"supersample": 4}
    assert dict(refs["precision"].setting.victim_args) == {"precision": "float64"}
    assert refs["backend"].setting == default
    assert dict(refs["render"].setting.attack_args) == {"cull": False}
    render = next(s for s in sweeps if s.name == "render")
    assert render.frames == 4  # the full-scene reference is slow: the first 4 frames only
    full = refs["render"].setting
    # the default's cells are the run's (all frames); the full-scene cells cover the sweep's 4 frames
    assert render.cells("adv", default) == [default.cell(CLEAN), default.cell("adv"), full.cell(CLEAN, 4),
                                            full.cell("adv", 4)]
    assert full.cell(CLEAN, 4) != full.cell(CLEAN) and '"frames":4' in full.cell(CLEAN, 4).key
    assert '"frames"' not in default.cell(CLEAN).key  # keys of whole-run cells are unchanged
    for s in sweeps:
        if isinstance(s, Sweep):
            assert sum(p.setting == default for p in s.points) == 1, s.name
            assert len({p.setting for p in s.points}) == len(s.points), s.name
    inputs = next(s for s in sweeps if s.name == "input")
    assert [p.value for p in inputs.points] == ["640x192", "960x288 (trained)", "1280x384"]
    # the clean control takes no attack arguments: render settings share the default's clean cell
    assert refs["supersample"].setting.cell(CLEAN) == default.cell(CLEAN)
    assert refs["supersample"].setting.cell("adv-object") != default.cell("adv-object")
    # knobs the victim lacks are left out; counts never exceed the run's frames
    bare = build_sweeps("lidar-cluster", frames=30, defaults=VictimDefaults())
    assert [s.name for s in bare] == ["frames", "azimuth", "supersample", "render"]
    assert bare[0].counts == (10, 25, 30)
    with pytest.raises(RobustBenchError, match="unknown sweep 'pointz'"):
        build_sweeps(V, ["pointz"])


def _measure(spec_setting: Setting, attack: str, dets, batches=(2, 2, 2), wall=(1.0, 2.0, 3.0)) -> CellMeasure:
    return CellMeasure(spec_setting.cell(attack), dets, list(batches), list(wall), [w / 2 for w in wall], False, {})


def test_time_of_takes_whole_batches_and_a_partial_one_pro_rata():
    m = _measure(Setting(V), CLEAN, [], batches=(4, 4, 2), wall=(4.0, 8.0, 1.0))
    assert m.time_of(4) == 4.0
    assert m.time_of(6) == 4.0 + 8.0 * 2 / 4
    assert m.time_of(10) == 13.0
    assert m.time_of(10, "cpu") == 6.5


CAR = "Car 0.00 0 -1.57 {l} 150.00 {r} 250.00 1.50 1.60 3.90 {x} 1.70 {z} -1.57"


def _labels(rows: list[tuple[float, float]], score: float | None = None):
    text = "\n".join(CAR.format(l=600 + 10 * i, r=700 + 10 * i, x=x, z=z) + ("" if score is None else f" {score}")
                     for i, (x, z) in enumerate(rows))
    return parse_labels(text, Path("<hand>"), scored=score is not None)


def test_scores_equal_the_evaluator_on_the_same_detections():
    # 6 frames, one easy car each; clean finds all, "worse" misses frames 0-2, "shifted" misses frame 5
    gt = [_labels([(1.0 + f, 12.0)]) for f in range(6)]
    found = [_labels([(1.0 + f, 12.0)], 0.9) for f in range(6)]
    empty = _labels([], 0.9)
    worse = [empty] * 3 + found[3:]
    shifted = [*found[:5], empty]
    base, other = Setting(V), Setting(V, victim_args=(("num_points", 256),))
    measures = {m.spec.key: m for m in (
        _measure(base, CLEAN, found), _measure(base, "adv", worse),
        _measure(other, CLEAN, found, wall=(0.5, 0.5, 0.5)), _measure(other, "adv", shifted, wall=(0.5, 0.5, 0.5)))}
    sweeps = [FrameSweep((3, 6)), Sweep("points", "points", (Point("256", other), Point("512", base)), reference=1)]
    rows = score(sweeps, measures, "adv", Scorer(gt, 200, 0), base)
    key = ("Car", "bev", "R40", "moderate")

    def ap(dets, n):
        return evaluate(gt[:n], dets[:n])["Car"]["bev"]["R40"]["moderate"]

    f3, f6, p256, p512 = rows
    assert f3["ap_clean"] == pytest.approx(ap(found, 3)) and f3["ap_attacked"] == pytest.approx(ap(worse, 3))
    assert f6["ap_attacked"] == pytest.approx(ap(worse, 6))
    assert f3["d_attacked"] == pytest.approx(ap(worse, 3) - ap(worse, 6))
    assert f3["d_attacked_lo"] is None  # a subset is not a paired difference
    assert f3["wall_s"] == pytest.approx(2 * (1.0 + 2.0 / 2))  # frames 0-2: batch 1, half of batch 2; 2 cells
    assert p256["d_attacked"] == pytest.approx(ap(shifted, 6) - ap(worse, 6))
    assert p256["d_clean"] == 0.0 and p256["d_clean_lo"] == 0.0 and p256["d_clean_hi"] == 0.0
    assert p512["reference"] and p512["default"] and p512["error"] == 0.0 and p512["d_attacked_hi"] == 0.0
    assert p256["error"] == pytest.approx(abs(p256["d_attacked"]))
    assert p256["drop"] == pytest.approx(ap(found, 6) - ap(shifted, 6))
    # the paired interval is the percentile interval of the resampled differences, recomputed here
    from robustbench3d.eval.bootstrap import FrameBootstrap, resample_weights

    w = resample_weights(6, 200, 0)
    diff = FrameBootstrap(gt, shifted).resampled(w)[key] - FrameBootstrap(gt, worse).resampled(w)[key]
    assert [p256["d_attacked_lo"], p256["d_attacked_hi"]] == pytest.approx(list(np.percentile(diff, [2.5, 97.5])))
    assert p256["wall_s"] == 3.0 and p512["wall_s"] == 12.0
    assert p256["time_vs_default"] == 0.25 and p512["time_vs_default"] == 1.0
    assert f3["time_vs_default"] == pytest.approx(4.0 / 12.0)  # the frames sweep: over all frames
    assert p256["pareto_sweep"] and p512["pareto_sweep"]  # 256 faster but wrong, 512 exact but slow: both
    assert p256["pareto_all"] and p512["pareto_all"] and f3["pareto_all"] is None


# ------------------------------------------------------------------------------ a tiny real run, end to end

@pytest.fixture(scope="module")
def tiny_tradeoff(tmp_path_factory, shared_split) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("tradeoff")
    ds = shared_split(3, seed=5, val_fraction=1.0)
    out = root / "out"
    assert main(["tradeoff", "--out", str(out), "--data", str(ds), "--frames", "3", "--attack", "random-shape",
                 "--sweeps", "frames,azimuth,backend", "--resamples", "50", "--no-progress"]) == 0
    return ds, out


def test_tiny_run_writes_consistent_files_and_resumes(tiny_tradeoff, capsys):
    ds, out = tiny_tradeoff
    doc = read_doc(out)
    assert [p["sweep"] for p in doc["points"]] == ["frames", "azimuth", "azimuth", "azimuth", "backend", "backend"]
    assert doc["dataset"]["frames"] == 3 and doc["machine"]["cpu_count"] >= 1
    assert len(doc["cells"]) == 8 and doc["reused_cells"] == 0
    with open(out / "tradeoff.csv", newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 6
    for row, p in zip(rows, doc["points"], strict=True):
        assert float(row["wall_s"]) == pytest.approx(p["wall_s"]) and row["value"] == p["value"]
        assert float(row["ap_attacked"]) == pytest.approx(p["ap_attacked"])
    md = (out / "tradeoff.md").read_text(encoding="utf-8")
    assert md.count("## ") == 4 and "| torch (ref) |" in md and "| 1 (ref) |" in md
    assert (out / "tradeoff.png").read_bytes()[:4] == b"\x89PNG"
    # the ONNX twin gives the torch cascade's AP (parity), so its |ΔAP| is 0
    onnx = doc["points"][5]
    assert onnx["value"] == "onnxruntime" and onnx["error"] == 0.0
    # the default point's cells are the frames sweep's; its time is their sum
    cells = [c for c in doc["cells"].values() if c["victim"]["name"] == V and c["spec"]["decimation"] == 1]
    assert doc["points"][0]["wall_s"] == pytest.approx(sum(c["wall_s_total"] for c in cells))
    # a sparser scan: each decimated cell's result files differ from the full scan's, and they are its own
    dec = [c for c in doc["cells"].values() if c["spec"]["decimation"] == 4]
    assert len(dec) == 2 and all(c["attack"]["object"]["scan_decimation"] == 4 for c in dec
                                 if c["attack"]["name"] != "none")
    # a rerun reuses every cell and scores the same
    again = out.parent / "again"
    shutil.copytree(out, again)
    assert main(["tradeoff", "--out", str(again), "--data", str(ds), "--frames", "3", "--attack", "random-shape",
                 "--sweeps", "frames,azimuth,backend", "--resamples", "50", "--no-progress"]) == 0
    doc2 = read_doc(again)
    assert doc2["reused_cells"] == 8
    for a, b in zip(doc["points"], doc2["points"], strict=True):
        assert {k: v for k, v in a.items()} == {k: v for k, v in b.items()}


def test_bad_inputs_are_refused(tmp_path, capsys):
    assert main(["tradeoff", "--out", str(tmp_path / "o"), "--frames", "0"]) == 2
    assert "--frames must be an integer in 1..1000000 (frames), got 0" in capsys.readouterr().err
    assert main(["tradeoff", "--out", str(tmp_path / "o"), "--attack", "none"]) == 2
    assert "--attack" in capsys.readouterr().err
    (tmp_path / "t").mkdir()
    (tmp_path / "t" / "tradeoff.json").write_text('{"points": []}', encoding="utf-8")
    with pytest.raises(DataFormatError, match="field 'config'"):
        read_doc(tmp_path / "t")
    assert main(["report", "--tradeoff", str(tmp_path / "t"), "--out", str(tmp_path / "r")]) == 2
    assert main(["report", "--out", str(tmp_path / "r")]) == 2
    assert "at least one RUN_DIR, --tradeoff DIR or --sweep DIR" in capsys.readouterr().err


def test_report_section_in_headless_chromium(tiny_tradeoff, tmp_path):
    _, out = tiny_tradeoff
    rep = tmp_path / "rep"
    assert main(["report", "--tradeoff", str(out), "--out", str(rep)]) == 0
    md = (rep / "leaderboard.md").read_text(encoding="utf-8")
    assert "## Speed/accuracy trade: fpointnet-v1-lite / random-shape (3 frames)" in md
    assert (rep / "figures" / "tradeoff_out.png").read_bytes()[:4] == b"\x89PNG"
    doc = json.loads((out / "tradeoff.json").read_text(encoding="utf-8"))
    with chromium_page() as (page, errors):
        page.goto((rep / "leaderboard.html").as_uri())
        img = page.locator("#tradeoff-0 img")
        img.scroll_into_view_if_needed()
        assert img.is_visible() and img.evaluate("e => e.complete && e.naturalWidth > 0")
        rows = "#tradeoff-table-0 tbody tr"
        assert page.locator(rows).count() == len(doc["points"])
        page.locator('#tradeoff-table-0 th[data-key="wall_s"]').click()
        got = page.eval_on_selector_all(rows, "rs => rs.map(r => Number(r.dataset.i))")
        want = sorted(range(len(doc["points"])), key=lambda i: (doc["points"][i]["wall_s"], i))
        assert got == want
        page.locator("#tradeoff-prov-0 summary").click()
        assert page.locator("#tradeoff-prov-0").evaluate("d => d.open") is True
    assert errors == []


def test_a_sweep_on_fewer_frames_scores_only_those():
    gt = [_labels([(1.0 + f, 12.0)]) for f in range(6)]
    found = [_labels([(1.0 + f, 12.0)], 0.9 - 0.1 * f) for f in range(6)]
    empty = _labels([], 0.9)
    base, full = Setting(V), Setting(V, attack_args=(("cull", False),))
    miss1 = [found[0], empty, found[2]]
    measures = {m.spec.key: m for m in (
        _measure(base, CLEAN, found), _measure(base, "adv", found),
        CellMeasure(full.cell(CLEAN, 3), found[:3], [2, 1], [10.0, 5.0], [10.0, 5.0], False, {}),
        CellMeasure(full.cell("adv", 3), miss1, [2, 1], [10.0, 5.0], [10.0, 5.0], False, {}))}
    sweep = Sweep("render", "r", (Point("culled", base), Point("full", full)), reference=1, frames=3)
    culled, ref = score([sweep], measures, "adv", Scorer(gt, 50, 0), base)

    def ap(dets):
        return evaluate(gt[:3], dets)["Car"]["bev"]["R40"]["moderate"]

    assert culled["frames"] == ref["frames"] == 3
    assert ap(found[:3]) > ap(miss1) > 0
    assert culled["d_attacked"] == pytest.approx(ap(found[:3]) - ap(miss1)) and ref["error"] == 0.0
    assert culled["wall_s"] == pytest.approx(2 * (1.0 + 2.0 / 2)) and ref["wall_s"] == 30.0
    assert culled["time_vs_default"] == 1.0 and ref["time_vs_default"] == pytest.approx(30.0 / 4.0)  # same frames
