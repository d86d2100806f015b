"""Issue #33's frustum protocols on the harness side: the object record (the placed bounds box's image box,
each car's object returns, its label row), ``Attack.apply_recorded`` (the same frames as ``apply``; the clean
control's nominal record), the runner's ``gt-object`` / ``gt-append`` cells (the boxes and rows a victim gets,
the clean pairing, skips, the CLI), the seed table's LiDAR-only row per protocol, the tradeoff's decimated
record and the pytest plugin's ``proposals=``.

References are independent of the code under test: hand-computed projections, the label and calib files read
with plain numpy, the renderer's own ``LidarRenderResult`` and brute force over the mesh's vertices."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from object_boxes import NEAR, cube_corners, extent_box, nominal_boxes_from_files, project, ry_matrix

from robustbench3d.attacks import create_attack
from robustbench3d.attacks.base import target_cars
from robustbench3d.attacks.object import BOUNDS, RoofObject, random_shape, template_vertices
from robustbench3d.attacks.placement import Pose
from robustbench3d.attacks.record import EMPTY_BOX, ObjectRecord, nominal_record, placed_object_boxes, union_box
from robustbench3d.attacks.roof import RoofObjectAttack
from robustbench3d.kitti.dataset import Frame
from robustbench3d.testing import IMAGE_SIZE, SIMPLE_CALIB

W, H = IMAGE_SIZE


# ---------------------------------------------------------------- independent geometry

P2_SIMPLE = np.array([[700.0, 0.0, 600.0, 0.0], [0.0, 700.0, 180.0, 0.0], [0.0, 0.0, 1.0, 0.0]])


def pose(centre: tuple[float, float, float], yaw: float = 0.0) -> Pose:
    c = np.array(centre, dtype=np.float64)
    return Pose(centre=c, yaw=yaw, rotation=ry_matrix(yaw), roof_centre=c)


# ---------------------------------------------------------------- the record's image box

def test_bounds_box_projection_by_hand():
    calib = dataclasses.replace(SIMPLE_CALIB, P2=P2_SIMPLE)
    bounds = (0.5, 0.4, 0.3)
    # axis-aligned at (1, 0.5, 10): x in [0.5, 1.5], y in [0.1, 0.9], z in [9.7, 10.3]
    # yawed by 90 degrees the box's length runs along rect z: x in [0.7, 1.3], z in [9.5, 10.5]
    boxes = placed_object_boxes(bounds, [pose((1.0, 0.5, 10.0)), pose((1.0, 0.5, 10.0), math.pi / 2)], calib,
                                IMAGE_SIZE)
    assert boxes.dtype == np.float64 and boxes.shape == (2, 4)
    np.testing.assert_allclose(boxes[0], [600 + 700 * 0.5 / 10.3, 180 + 700 * 0.1 / 10.3,
                                          600 + 700 * 1.5 / 9.7, 180 + 700 * 0.9 / 9.7], rtol=0, atol=1e-9)
    np.testing.assert_allclose(boxes[1], [600 + 700 * 0.7 / 10.5, 180 + 700 * 0.1 / 10.5,
                                          600 + 700 * 1.3 / 9.5, 180 + 700 * 0.9 / 9.5], rtol=0, atol=1e-9)


def test_bounds_box_is_clipped_to_the_image_and_empty_when_unseen():
    calib = dataclasses.replace(SIMPLE_CALIB, P2=P2_SIMPLE)
    # x in [-9.5, -8.5] at z 9.7..10.3: u from 600 - 700 * 9.5 / 9.7 < 0 (clipped) to 600 - 700 * 8.5 / 10.3
    # y in [3.1, 3.9]: v from 180 + 700 * 3.1 / 10.3 = 390.7 > H - 1, so the box misses the image
    left, below, behind, right = placed_object_boxes(
        (0.5, 0.4, 0.3), [pose((-9.0, 0.5, 10.0)), pose((0.0, 3.5, 10.0)), pose((0.0, 0.5, -5.0)),
                          pose((9.0, 0.5, 10.0))], calib, IMAGE_SIZE)
    np.testing.assert_allclose(left, [0.0, 180 + 700 * 0.1 / 10.3, 600 - 700 * 8.5 / 10.3, 180 + 700 * 0.9 / 9.7],
                               atol=1e-9)
    # x in [8.5, 9.5]: u up to 600 + 700 * 9.5 / 9.7 = 1285.6 > W - 1 (clipped)
    np.testing.assert_allclose(right, [600 + 700 * 8.5 / 10.3, 180 + 700 * 0.1 / 10.3, W - 1, 180 + 700 * 0.9 / 9.7],
                               atol=1e-9)
    for unseen in (below, behind):
        np.testing.assert_array_equal(unseen, EMPTY_BOX)
    gt = np.array([10.0, 20.0, 30.0, 40.0])
    np.testing.assert_array_equal(union_box(gt, below), gt)  # the empty box leaves the GT box alone
    np.testing.assert_array_equal(union_box(gt, np.array([5.0, 25.0, 35.0, 38.0])), [5.0, 20.0, 35.0, 40.0])


def test_object_record_checks_its_fields():
    ok = ObjectRecord(np.zeros((1, 4)), (np.array([3, 5]),), np.array([0]))
    assert len(ok) == 1 and not ok.boxes.flags.writeable and ok.returns[0].dtype == np.int64
    for bad in (dict(boxes=np.zeros((1, 3))), dict(returns=()), dict(returns=(np.array([5, 3]),)),
                dict(returns=(np.array([-1]),)), dict(returns=(np.array([1.0]),)), dict(target_index=np.array([0, 1]))):
        fields = {"boxes": np.zeros((1, 4)), "returns": (np.array([3]),), "target_index": np.array([0]), **bad}
        with pytest.raises(ValueError, match=f"field '{next(iter(bad))}'"):
            ObjectRecord(**fields)


# ---------------------------------------------------------------- the record of a roof object on a generated frame

@pytest.fixture(scope="module")
def frame() -> Frame:
    from robustbench3d.synth.frame import generate_frame

    f = generate_frame(0, 0)
    return Frame("000000", f.image, f.scan, f.calib, f.labels)


@pytest.fixture(scope="module")
def targets(frame):
    return target_cars(frame.labels).select(slice(0, 6))  # six cars, the first one's object out of the image


def test_record_boxes_hold_every_vertex_of_the_placed_object(frame, targets):
    """Brute force: every vertex of each placed mesh (EOT on, a non-default box) projects into its car's box
    (clipped to the image like the box), and a car whose box is empty shows no vertex in the image."""
    bounds = np.array([0.30, 0.20, 0.50])
    obj = RoofObject.from_vertices(random_shape(3).vertices() * bounds / 0.4, bounds=bounds)
    attack = RoofObjectAttack(obj, eot=True, occlusion="none", supersample=1)
    _, record = attack.apply_recorded(frame, targets, np.random.default_rng(7))
    placed = attack.place(targets, np.random.default_rng(7))  # the placements apply drew first
    w, h = frame.image_size
    seen_empty = seen_box = 0
    for (vertices, _), box in zip(placed, record.boxes, strict=True):
        front = vertices[vertices[:, 2] > NEAR]
        uv = project(frame.calib.P2, front)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
        if np.array_equal(box, EMPTY_BOX):
            assert not inside.any()
            seen_empty += 1
            continue
        seen_box += 1
        c = np.clip(uv, 0, [w - 1, h - 1])
        assert np.all((c[:, 0] >= box[0] - 1e-9) & (c[:, 0] <= box[2] + 1e-9))
        assert np.all((c[:, 1] >= box[1] - 1e-9) & (c[:, 1] <= box[3] + 1e-9))
        assert box[2] - box[0] > 1 and box[3] - box[1] > 1
    assert seen_empty >= 1 and seen_box >= 4


def test_record_returns_are_the_rows_the_render_added_for_each_car(frame, targets):
    from robustbench3d.sensors.lidar_render import render_lidar
    from robustbench3d.sensors.pattern_cache import default_pattern_cache

    attack = create_attack("random-shape", seed=2, eot=True, range_noise_m=0.02, dropout=0.1, occlusion="none",
                           supersample=1)
    out, record = attack.apply_recorded(frame, targets, np.random.default_rng(11))
    # the reference: the renderer's own result for the same placements and draws
    rng = np.random.default_rng(11)
    placed = attack.place(targets, rng)
    meshes = [(frame.calib.rect_to_velo_points(v), attack.obj.faces.copy(), attack.obj.colors.copy())
              for v, _ in placed]
    result = render_lidar(frame.scan, meshes, rng=rng, range_noise_m=0.02, dropout=0.1,
                          patterns=default_pattern_cache())
    assert np.array_equal(out.scan, result.scan)
    first = len(frame.scan) - len(result.removed_index)
    assert [len(r) for r in record.returns] == [int((result.object_index == k).sum()) for k in range(len(targets))]
    for k, rows in enumerate(record.returns):
        assert np.array_equal(rows, first + np.flatnonzero(result.object_index == k))
        assert out.scan[rows].tobytes() == result.added[result.object_index == k].tobytes()
    assert sum(len(r) for r in record.returns) == len(result.added) > 0
    clean = {row.tobytes() for row in frame.scan}
    new_rows = [i for i, row in enumerate(out.scan) if row.tobytes() not in clean]
    assert sorted(np.concatenate(record.returns).tolist()) == new_rows


def test_each_cars_returns_lie_on_its_own_object(frame, targets):
    attack = create_attack("benign-sphere", occlusion="none", supersample=1)
    out, record = attack.apply_recorded(frame, targets, np.random.default_rng(0))
    rect = frame.calib.velo_to_rect_points(out.scan[:, :3].astype(np.float64))
    for k, car in enumerate(target_cars(targets).location):
        roof = car - np.array([0.0, targets.dimensions[k, 0], 0.0])
        centre = roof - np.array([0.0, template_vertices()[:, 1].max(), 0.0])
        near = np.linalg.norm(rect[record.returns[k]] - centre, axis=1)
        assert np.all(near <= 0.40 + 1e-3)  # on the sphere of radius 0.4 m around its own roof centre


def test_target_index_is_each_targets_label_row(frame, targets):
    _, record = create_attack("none").apply_recorded(frame, targets, np.random.default_rng(0))
    car_rows = [i for i, t in enumerate(frame.labels.type) if str(t) == "Car"]
    assert record.target_index.tolist() == car_rows[:6]
    assert np.array_equal(frame.labels.bbox[record.target_index], targets.bbox)
    unlabelled = dataclasses.replace(frame, labels=None)
    assert nominal_record(unlabelled, targets).target_index.tolist() == [-1] * 6


def test_apply_is_apply_recorded_without_the_record(frame, targets):
    attack = create_attack("random-shape", seed=4, eot=True, dropout=0.05, occlusion="none", supersample=1)
    plain = attack.apply(frame, targets, np.random.default_rng(3))
    recorded, record = attack.apply_recorded(frame, targets, np.random.default_rng(3))
    assert plain.scan.tobytes() == recorded.scan.tobytes() and plain.image.tobytes() == recorded.image.tobytes()
    assert len(record) == len(targets)
    nothing = attack.apply_recorded(frame, targets.select(slice(0, 0)), np.random.default_rng(3))
    assert nothing[0] is frame and len(nothing[1]) == 0


def test_the_clean_control_records_the_nominal_box_and_no_returns(frame, targets):
    out, record = create_attack("none").apply_recorded(frame, targets, np.random.default_rng(0))
    assert out is frame and all(len(r) == 0 for r in record.returns)
    # by hand: the +-0.40 m cube on the roof centre, its centre raised by the template's lowest point, yawed
    y_low = template_vertices()[:, 1].max()
    for k in range(len(targets)):
        roof = targets.location[k] - np.array([0.0, targets.dimensions[k, 0], 0.0])
        corners = cube_corners(roof - [0.0, y_low, 0.0], ry_matrix(float(targets.rotation_y[k])), np.array(BOUNDS))
        assert np.all(corners[:, 2] > NEAR)
        np.testing.assert_allclose(record.boxes[k], extent_box(project(frame.calib.P2, corners), frame.image_size),
                                   rtol=0, atol=1e-9)
    # the same boxes as the grey sphere without EOT: the clean gt-object cell and that cell share union boxes
    _, sphere = create_attack("benign-sphere", occlusion="none").apply_recorded(frame, targets,
                                                                                np.random.default_rng(0))
    assert np.array_equal(sphere.boxes, record.boxes) and np.array_equal(sphere.target_index, record.target_index)


# ---------------------------------------------------------------- the runner's cells

FRAMES = 3
RECORDING = "test-frustum-recording"
DETECTOR_ONLY = "test-frustum-detector-only"
SEEN: list[dict[str, Any]] = []


class RecordingVictim:
    """TEST ONLY: records what ``detect`` is given per call; detects nothing."""

    supported_proposals = ("detector", "gt", "gt-object", "gt-append")

    def detect(self, frames, proposals="detector"):
        SEEN.append({"frames": list(frames), "proposals": proposals})
        from robustbench3d.kitti.labels import Labels

        return [Labels.empty(with_score=True) for _ in frames]


class DetectorOnlyVictim(RecordingVictim):
    supported_proposals = ("detector", "gt")


def _register() -> None:
    from robustbench3d.victims import VICTIMS
    from robustbench3d.victims.spec import Capabilities, EntryInfo, VictimSpec

    caps = Capabilities(modalities=("camera", "lidar"), backend="other", gradients=False, deterministic=True)
    for name, factory in ((RECORDING, RecordingVictim), (DETECTOR_ONLY, DetectorOnlyVictim)):
        VICTIMS.register(name, VictimSpec(factory=factory, info=EntryInfo(caps, summary="TEST ONLY")))


_register()


@pytest.fixture(scope="module")
def dataset(shared_split) -> Path:
    return shared_split(FRAMES, seed=5, val_fraction=1.0)


def run(dataset: Path, out: Path, proposals: tuple[str, ...], attacks: tuple[str, ...] = ("none",),
        victims: tuple[str, ...] = (RECORDING,), **kw: Any):
    from robustbench3d.runner import RunConfig, run_benchmark

    config = RunConfig(victims=victims, attacks=attacks, proposals=proposals, out=out, data=dataset, batch_size=2,
                       progress=False, bootstrap=0,
                       attack_args={a: {"occlusion": "none", "supersample": 1} for a in attacks if a != "none"}, **kw)
    return run_benchmark(config, [].append)


def test_gt_object_cells_get_the_union_boxes_and_gt_append_cells_the_object_rows(dataset, tmp_path):
    SEEN.clear()
    report = run(dataset, tmp_path / "run", ("gt-object", "gt-append"), attacks=("none", "benign-sphere"))
    assert [(c["attack"], c["proposals"], c["status"]) for c in report.cells] == [
        (a, p, "ok") for a in ("none", "benign-sphere") for p in ("gt-object", "gt-append")]
    cells = [c for c in SEEN if isinstance(c["proposals"], list)]
    assert len(cells) == 4 * 2 + 2 * 2  # two batches per cell, then two determinism probes per source
    ids = [f"{i:06d}" for i in range(FRAMES)]
    checked = appended = 0
    for call in cells:
        for frame, props in zip(call["frames"], call["proposals"], strict=True):
            rows, gt, want = nominal_boxes_from_files(dataset, frame.frame_id)
            assert frame.labels is None and props.source in ("gt-object", "gt-append")
            assert list(props.types) == [r[0] for r in rows] and np.array_equal(props.scores, np.ones(len(rows)))
            if props.source == "gt-object":  # the grey sphere without EOT has the nominal boxes, like the clean cell
                ok = ~np.isnan(want[:, 0])
                np.testing.assert_allclose(props.boxes[ok], want[ok], rtol=0, atol=1e-9)
                checked += int(ok.sum())
                assert props.extra_points is None
                continue
            assert np.array_equal(props.boxes, gt)
            assert len(props.extra_points) == len(rows)
            clean = np.fromfile(dataset / "training" / "velodyne" / f"{frame.frame_id}.bin", np.float32).reshape(-1, 4)
            is_clean = frame.scan.tobytes() == clean.tobytes()
            before = {row.tobytes() for row in clean}
            for r, extra in zip(rows, props.extra_points, strict=True):
                assert extra.dtype == np.int64 and np.all(np.diff(extra) > 0)
                if r[0] != "Car" or is_clean:
                    assert len(extra) == 0  # other types, and the clean control: the bare GT frustums
                    continue
                assert all(frame.scan[i].tobytes() not in before for i in extra)  # the object's own returns
                appended += len(extra)
    assert checked > 10 and appended > 50
    assert {fid for c in cells for f in c["frames"] for fid in [f.frame_id]} == set(ids)


def test_attacked_protocol_cells_pair_with_the_clean_cell_of_their_source(dataset, tmp_path):
    report = run(dataset, tmp_path / "run", ("gt", "gt-object", "gt-append"), attacks=("benign-sphere",))
    by = {(c["attack"], c["proposals"]): c for c in report.cells}
    for source in ("gt", "gt-object", "gt-append"):
        effect = by[("benign-sphere", source)]["attack_effect"]
        assert effect is not None and effect["clean_cell"] == f"{RECORDING}+none+{source}"
        assert by[("none", source)]["provenance"]["config"]["proposals"] == source
    fingerprints = {c["provenance"]["fingerprint"] for c in report.cells}
    assert len(fingerprints) == len(report.cells)  # the source is part of every cell's identity
    import csv

    with open(tmp_path / "run" / "results.csv", newline="") as f:
        assert {r["proposals"] for r in csv.DictReader(f)} == {"gt", "gt-object", "gt-append"}
    assert not any(fl.get("kind") == "victim-nondeterministic" for c in report.cells for fl in c.get("flags") or [])


def test_a_victim_without_the_protocols_gets_skipped_cells(dataset, tmp_path):
    report = run(dataset, tmp_path / "run", ("gt", "gt-object", "gt-append"), victims=(DETECTOR_ONLY,))
    status = {c["proposals"]: (c["status"], c["reason"]) for c in report.cells}
    assert status["gt"] == ("ok", None)
    for source in ("gt-object", "gt-append"):
        assert status[source] == ("skipped", f"victim {DETECTOR_ONLY!r} supports proposals detector, gt only "
                                             f"(not {source!r})")


def test_run_cli_accepts_and_describes_the_sources(dataset, tmp_path, capsys):
    from robustbench3d.cli import main
    from robustbench3d.victims.spec import PROTOCOL_LABELS

    assert main(["run", "--victims", RECORDING, "--proposals", "detector,gt,gt-object,gt-append", "--data",
                 str(dataset), "--out", str(tmp_path / "run"), "--no-progress", "--bootstrap", "0"]) == 0
    assert len(list((tmp_path / "run" / "cells").iterdir())) == 4
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_help:
        main(["run", "--help"])
    assert exit_help.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    for source, label in PROTOCOL_LABELS.items():
        assert f"{source}: {label}" in text
    assert PROTOCOL_LABELS["gt"] == "GT 2D boxes (object outside the frustum)"
    assert main(["run", "--victims", RECORDING, "--proposals", "gt,gt-box", "--data", str(dataset),
                 "--out", str(tmp_path / "bad"), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("robustbench3d: error: --proposals: unknown source 'gt-box'")
    assert all(f"{s}: {label}" in err[0] for s, label in PROTOCOL_LABELS.items())
    assert not (tmp_path / "bad").exists()


@pytest.fixture
def one_thread():
    """This process as a shard worker: one intra-op thread (restored afterwards), so float32 sums agree."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def test_parallel_shards_write_the_same_protocol_files(dataset, tmp_path, one_thread):
    from robustbench3d.runner import RunConfig, run_benchmark
    from robustbench3d.runner.executors import LocalExecutor

    def files(out: Path) -> dict[str, bytes]:
        return {str(p.relative_to(out)): p.read_bytes() for p in sorted((out / "cells").rglob("data/*.txt"))}

    serial = tmp_path / "serial"
    run(dataset, serial, ("gt-append", "gt-object"), attacks=("benign-sphere",), victims=("fpointnet-v1-lite",))
    config = RunConfig(victims=("fpointnet-v1-lite",), attacks=("benign-sphere",), proposals=("gt-append", "gt-object"),
                       out=tmp_path / "shards", data=dataset, batch_size=2, progress=False, bootstrap=0,
                       attack_args={"benign-sphere": {"occlusion": "none", "supersample": 1}})
    with LocalExecutor(2, shard_frames=2) as executor:  # two shards per cell
        report = run_benchmark(config, [].append, executor=executor)
    assert all(c["status"] == "ok" for c in report.cells), [c["reason"] for c in report.cells]
    assert files(serial) == files(tmp_path / "shards") and len(files(serial)) == 4 * FRAMES


# ---------------------------------------------------------------- the seed table

def test_the_lidar_only_row_appears_for_each_protocol_with_its_control():
    from seed_cells import attacked, cell

    from robustbench3d.seed_table import PAPER_LIDAR, SeedRow, layout_rows, seed_table_markdown

    def hit(attack: str, source: str) -> dict:
        return attacked("fp", attack, source, (50.0, 40.0, 30.0), (51.0, 41.0, 31.0), (80.0, 80.0, 80.0),
                        (81.0, 81.0, 81.0), (30.0, 40.0, 50.0), (30.0, 40.0, 50.0), (0.375, 0.5, 0.625),
                        (0.37, 0.49, 0.62), 10, 4)

    sources = ("gt", "gt-object", "gt-append")
    cells = [cell("fp", "none", s, (80.0, 80.0, 80.0), (81.0, 81.0, 81.0)) for s in sources]
    cells += [hit("benign-sphere", s) for s in sources]
    cells += [hit("adv-shape", "gt"), hit("adv-shape-gt-object", "gt-object"), hit("adv-shape-gt-append", "gt-append")]
    md = seed_table_markdown(cells)
    rows = [line.split(" | ") for line in md.splitlines() if line.startswith("| ") and "---" not in line][1:]
    named = [(r[0].lstrip("| "), r[1]) for r in rows]
    assert named == [("clean", "gt"), ("clean", "gt-object"), ("clean", "gt-append"), ("benign-sphere", "gt"),
                     ("benign-sphere", "gt-object"), ("benign-sphere", "gt-append"), ("adv-shape", "gt"),
                     ("adv-shape-gt-object", "gt-object"), ("adv-shape-gt-append", "gt-append")]
    for r in rows[-3:]:
        assert r[7] == "LiDAR-only" and r[5] == "50.0 49.0"  # beside the seed's row, relative drop at moderate
    assert "gt-object = GT 2D box united with the object's projected box" in md
    assert "gt = GT 2D boxes (object outside the frustum)" in md
    assert SeedRow("adv-shape-gt-append", "adv-shape-gt-append", "gt-append", PAPER_LIDAR) in layout_rows(sources)
    notes = [line for line in md.splitlines() if line.startswith("- not in this run: ")]
    assert len(notes) == 1 and "adv-shape / gt-object, adv-shape / gt-append" in notes[0]  # the gt shape, absent


# ---------------------------------------------------------------- the tradeoff and the pytest plugin

def test_decimated_scan_renumbers_the_object_returns(frame, targets):
    from robustbench3d.tradeoff.measure import DecimatedScan

    inner = create_attack("benign-sphere", occlusion="none", supersample=1)
    full, full_rec = inner.apply_recorded(frame, targets, np.random.default_rng(0))
    sparse, rec = DecimatedScan(inner, 2).apply_recorded(frame, targets, np.random.default_rng(0))
    assert sparse.scan.tobytes() == DecimatedScan(inner, 2).apply(frame, targets,
                                                                   np.random.default_rng(0)).scan.tobytes()
    kept = {row.tobytes() for row in sparse.scan}
    for k, rows in enumerate(rec.returns):
        want = [full.scan[i].tobytes() for i in full_rec.returns[k] if full.scan[i].tobytes() in kept]
        assert [sparse.scan[i].tobytes() for i in rows] == want
    assert 0 < sum(map(len, rec.returns)) < sum(map(len, full_rec.returns))
    assert np.array_equal(rec.boxes, full_rec.boxes)


def test_tradeoff_accepts_the_protocols():
    import argparse

    from robustbench3d.commands.tradeoff import add_arguments

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    for source in ("detector", "gt", "gt-object", "gt-append"):
        assert parser.parse_args(["--out", "x", "--proposals", source]).proposals == source
    assert "GT 2D box united with the object's projected box" in " ".join(parser.format_help().split())


def test_pytest_marker_takes_the_protocols(tmp_path):
    from robustbench3d.pytest_plugin import _config_from_marker

    mark = pytest.mark.robustbench3d(victim="v", proposals=("gt-object", "gt-append")).mark
    assert _config_from_marker(mark, tmp_path).proposals == ("gt-object", "gt-append")
    with pytest.raises(pytest.UsageError, match=r"proposals='gt-box' is not a proposal source; choose from .*"
                                                r"gt-object: GT 2D box united"):
        _config_from_marker(pytest.mark.robustbench3d(victim="v", proposals="gt-box").mark, tmp_path)
