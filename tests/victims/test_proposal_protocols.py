"""The frustum protocols ``gt-object`` and ``gt-append`` on the victim side (issue #33): the protocols' words,
:class:`Proposals` with ``extra_points``, the proposals :func:`victim_inputs` builds from the labels and an
attack's record of its objects, and the F-PN cascades (torch and ONNX, one glue) and their white-box oracles
on those proposals, checked against hand-built references (projection, box test and union done here in
numpy), against ``gt`` (bit for bit with no extra points) and torch against ONNX."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import pytest
import torch

from robustbench3d.kitti.dataset import Frame, KittiDataset
from robustbench3d.kitti.labels import Labels
from robustbench3d.victims.base import PlacementRecord, Proposals, gt_proposals, victim_inputs
from robustbench3d.victims.fpointnet.frustum import ProjectedScan, extract_frustum
from robustbench3d.victims.onnx.parity import Tolerances, box_parity
from robustbench3d.victims.spec import PROPOSAL_SOURCES, PROTOCOL_LABELS

torch.set_num_threads(1)
EMPTY = (np.inf, np.inf, -np.inf, -np.inf)


@dataclass(frozen=True)
class Record:
    """A placement record as the harness hands it to ``victim_inputs`` (duck-typed, no attacks import)."""

    boxes: np.ndarray
    returns: tuple[np.ndarray, ...]
    target_index: np.ndarray


def labels_of(types: list[str], boxes: list[list[float]]) -> Labels:
    n = len(types)
    return Labels(type=np.array(types, dtype=object), truncated=np.zeros(n), occluded=np.zeros(n, dtype=np.int64),
                  alpha=np.zeros(n), bbox=np.array(boxes, dtype=np.float64).reshape(n, 4),
                  dimensions=np.ones((n, 3)), location=np.tile([0.0, 1.6, 20.0], (n, 1)), rotation_y=np.zeros(n))


def hand_frame(scan_points: int = 10) -> Frame:
    from robustbench3d.testing import SIMPLE_CALIB

    return Frame("000007", np.zeros((100, 200, 3), dtype=np.uint8), np.zeros((scan_points, 4), dtype=np.float32),
                 SIMPLE_CALIB, None)


HAND_LABELS = labels_of(["Car", "DontCare", "Pedestrian", "Car", "Car"],
                        [[10, 20, 50, 60], [0, 0, 5, 5], [60, 10, 70, 40], [100, 30, 150, 90], [20, 70, 40, 95]])


# ---- words and Proposals -------------------------------------------------------------------------------
def test_every_source_has_the_agreed_words():
    assert set(PROPOSAL_SOURCES) == {"detector", "gt", "gt-object", "gt-append"}
    assert PROTOCOL_LABELS == {
        "detector": "the victim's own 2D detector",
        "gt": "GT 2D boxes (object outside the frustum)",
        "gt-object": "GT 2D box united with the object's projected box",
        "gt-append": "GT-box frustum plus the car's object returns",
    }
    from robustbench3d.victims import base

    assert base.PROTOCOL_LABELS is PROTOCOL_LABELS and "PROTOCOL_LABELS" in base.__all__


@pytest.mark.parametrize("extra, why", [
    ((np.array([1, 2]),), "2 boxes but 1"),
    ((np.array([3, 1]), np.array([], dtype=np.int64)), "sorted"),
    ((np.array([1, 1]), np.array([], dtype=np.int64)), "unique"),
    ((np.array([-1, 2]), np.array([], dtype=np.int64)), ">= 0"),
    ((np.array([0.5]), np.array([], dtype=np.int64)), "integer"),
    ((np.array([[1, 2]]), np.array([], dtype=np.int64)), "1-D"),
    (np.array([[1], [2]]), "sequence"),
])
def test_proposals_refuse_bad_extra_points(extra, why):
    with pytest.raises(ValueError, match=why):
        Proposals(np.zeros((2, 4)), np.ones(2), "gt-append", np.array(["Car", "Car"]), extra)


def test_proposals_of_the_new_sources_need_types_and_gt_append_its_extra_points():
    for source in ("gt-object", "gt-append"):
        with pytest.raises(ValueError, match="type of each box"):
            Proposals(np.zeros((1, 4)), np.ones(1), source, None, (np.zeros(0, dtype=np.int64),))
    with pytest.raises(ValueError, match="needs extra_points"):
        Proposals(np.zeros((1, 4)), np.ones(1), "gt-append", np.array(["Car"]))
    ok = Proposals(np.zeros((1, 4)), np.ones(1), "gt-object", np.array(["Car"]))
    assert ok.extra_points is None


def test_select_and_of_types_keep_extra_points_with_their_boxes():
    p = Proposals(np.arange(16.0).reshape(4, 4), np.ones(4), "gt-append", np.array(["Car", "Van", "Car", "Car"]),
                  (np.array([1, 5]), np.array([2]), np.array([], dtype=np.int64), np.array([0, 9, 11])))
    cars = p.of_types(["Car"])
    assert cars.boxes[:, 0].tolist() == [0.0, 8.0, 12.0]
    assert [e.tolist() for e in cars.extra_points] == [[1, 5], [], [0, 9, 11]]
    assert all(e.dtype == np.int64 for e in cars.extra_points)
    picked = p.select(np.array([False, True, False, True]))
    assert [e.tolist() for e in picked.extra_points] == [[2], [0, 9, 11]]
    gt = Proposals(np.zeros((1, 4)), np.ones(1), "gt", np.array(["Car"]))
    assert gt.select(np.array([True])).extra_points is None


# ---- victim_inputs -----------------------------------------------------------------------------------
def test_gt_object_unites_each_targets_box_with_its_objects_box_clipped_to_the_image():
    frame = replace(hand_frame(), labels=HAND_LABELS)  # image 200 x 100 px
    # targets: label rows 0, 3, 4 (Cars); row 4's object shows nowhere; a fourth target is no labels row
    record = Record(np.array([[25, 5, 45, 30], [140, -20, 260, 40], EMPTY, [0, 0, 199, 99]], dtype=np.float64),
                    tuple(np.zeros(0, dtype=np.int64) for _ in range(4)), np.array([0, 3, 4, -1]))
    bare, (props,) = victim_inputs([frame], [HAND_LABELS], "gt-object", objects=[record])
    assert bare[0].labels is None and bare[0].scan is frame.scan
    assert props.source == "gt-object" and props.extra_points is None
    assert props.types.tolist() == ["Car", "Pedestrian", "Car", "Car"]  # DontCare dropped, label order
    assert props.scores.tolist() == [1.0] * 4
    assert props.boxes.tolist() == [
        [10, 5, 50, 60],      # row 0: top raised to the object's
        [60, 10, 70, 40],     # the pedestrian: no target, unchanged
        [100, 0, 199, 90],    # row 3: object clipped to [0, 199] x [0, 99] first
        [20, 70, 40, 95],     # row 4: empty object box
    ]
    assert set(vars(props)) == {"boxes", "scores", "source", "types", "extra_points"}  # nothing else reaches it


def test_gt_append_gives_each_target_its_object_returns_and_the_others_none():
    frame = replace(hand_frame(scan_points=10), labels=HAND_LABELS)
    record = Record(np.array([EMPTY, EMPTY]), (np.array([7, 8, 9]), np.array([2])), np.array([3, 0]))
    _, (props,) = victim_inputs([frame], [HAND_LABELS], "gt-append", objects=[record])
    assert props.source == "gt-append"
    assert props.boxes.tolist() == gt_proposals(HAND_LABELS).boxes.tolist()  # the GT boxes
    assert [e.tolist() for e in props.extra_points] == [[2], [], [7, 8, 9], []]
    # a frame without a record: no object anywhere
    _, (none,) = victim_inputs([frame], [HAND_LABELS], "gt-append", objects=[None])
    assert [e.tolist() for e in none.extra_points] == [[], [], [], []]


def test_object_records_are_checked_against_the_frames_and_modes():
    frame = replace(hand_frame(scan_points=10), labels=HAND_LABELS)
    good = Record(np.array([EMPTY]), (np.array([1]),), np.array([0]))
    cases = [
        ("gt-append", None, "one object record per frame"),
        ("gt-object", [good, good], "one object record per frame"),
        ("gt", [good], "take no object records"),
        ("detector", [good], "take no object records"),
        ("gt-append", [Record(np.array([EMPTY]), (np.array([10]),), np.array([0]))], "rows of the attacked scan"),
        ("gt-object", [Record(np.array([EMPTY]), (np.array([1]),), np.array([1]))], "non-DontCare"),
        ("gt-object", [Record(np.array([EMPTY]), (np.array([1]),), np.array([5]))], "non-DontCare"),
        ("gt-object", [Record(np.array([EMPTY, EMPTY]), (np.array([1]),) * 2, np.array([0, 0]))], "distinct"),
        ("gt-object", [Record(np.array([EMPTY]), (), np.array([0]))], "1 targets"),
        ("gt-object", [Record(np.array([[np.nan, 0, 1, 1]]), (np.array([1]),), np.array([0]))], "NaN"),
    ]
    for source, objects, why in cases:
        with pytest.raises(ValueError, match=why):
            victim_inputs([frame], [HAND_LABELS], source, objects=objects)


def test_the_attack_sides_record_is_a_placement_record():
    from robustbench3d.attacks.record import ObjectRecord

    frame = replace(hand_frame(scan_points=10), labels=HAND_LABELS)
    record = ObjectRecord(np.array([[25.0, 5, 45, 30]]), (np.array([4, 6]),), np.array([0]))
    assert isinstance(record, PlacementRecord)
    _, (obj,) = victim_inputs([frame], [HAND_LABELS], "gt-object", objects=[record])
    _, (app,) = victim_inputs([frame], [HAND_LABELS], "gt-append", objects=[record])
    assert obj.boxes[0].tolist() == [10, 5, 50, 60] and app.extra_points[0].tolist() == [4, 6]


# ---- frustum extraction --------------------------------------------------------------------------------
def test_extract_frustum_adds_the_extra_rows_in_front_of_the_camera_once_in_scan_order():
    from robustbench3d.testing import SIMPLE_CALIB

    uv = np.array([[5, 5], [50, 50], [15, 15], [500, 5], [12, 12], [-40, 3], [18, 18]], dtype=np.float64)
    in_fov = np.array([True, True, True, False, True, False, False])
    in_front = np.array([True, True, True, True, True, True, False])
    points = np.arange(28.0).reshape(7, 4)
    proj = ProjectedScan(points, uv, in_fov, in_front)
    box = np.array([10.0, 10.0, 20.0, 20.0])  # rows 2 and 4 project inside (row 6 too, but behind the camera)
    assert extract_frustum(proj, box, SIMPLE_CALIB).indices.tolist() == [2, 4]
    fr = extract_frustum(proj, box, SIMPLE_CALIB, np.array([0, 3, 4, 5, 6]))
    assert fr.indices.tolist() == [0, 2, 3, 4, 5]  # 0, 3, 5 added (3, 5 outside the image), 4 once, 6 behind
    assert np.array_equal(fr.points, points[[0, 2, 3, 4, 5]])
    assert extract_frustum(proj, box, SIMPLE_CALIB, np.zeros(0, dtype=np.int64)).indices.tolist() == [2, 4]
    with pytest.raises(ValueError, match="rows of the 7-point scan"):
        extract_frustum(proj, box, SIMPLE_CALIB, np.array([7]))
    with pytest.raises(ValueError, match="in_front"):
        extract_frustum(ProjectedScan(points, uv, in_fov), box, SIMPLE_CALIB, np.array([1]))


# ---- the shipped lite cascade, torch and ONNX ----------------------------------------------------------
@pytest.fixture(scope="module")
def frames(shared_split) -> list[Frame]:
    """Three generated val frames, each scan with three rows appended: in front of the camera but left of
    the image (velodyne (10, 40, 0)), behind it ((-5, 0, 0)) and inside the clip distance ((1.5, 0, -1))."""
    root = shared_split(3, seed=0, val_fraction=1.0)
    ds = KittiDataset(root, split="val")
    added = np.array([[10, 40, 0, 0.5], [-5, 0, 0, 0.5], [1.5, 0, -1, 0.5]], dtype=np.float32)
    return [replace(f, scan=np.concatenate([f.scan, added])) for f in (ds.frame(i) for i in ds.frame_ids)]


@pytest.fixture(scope="module")
def lite(lite_victim):
    return lite_victim  # the session's shared one (conftest): read only


@pytest.fixture(scope="module")
def lite_onnx(lite):
    from robustbench3d.victims.onnx.registration import SHIPPED
    from robustbench3d.victims.onnx.runtime import OnnxCascade
    from robustbench3d.victims.shipped import weights_dir

    return OnnxCascade(weights_dir() / SHIPPED["fpointnet-v1-lite-onnx"], seed=lite.settings.seed,
                       gather=lite.settings.gather)


def reference_projection(frame: Frame) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Hand projection of ``frame.scan``: rect xyz + reflectance (P, 4), pixel uv (P, 2), in the image and
    velodyne x > 2 m (P,), velodyne x > 2 m (P,)."""
    c = frame.calib
    velo_h = np.concatenate([frame.scan[:, :3].astype(np.float64), np.ones((len(frame.scan), 1))], axis=1)
    rect = (c.R0_rect @ (c.Tr_velo_to_cam @ velo_h.T)).T
    img = (c.P2 @ np.concatenate([rect, np.ones((len(rect), 1))], axis=1).T).T
    uv = img[:, :2] / img[:, 2:3]
    w, h = frame.image_size
    front = frame.scan[:, 0] > 2.0
    fov = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h) & front
    return np.concatenate([rect, frame.scan[:, 3:4]], axis=1), uv, fov, front


def hand_extra_rows(frame: Frame) -> list[np.ndarray]:
    """Per Car of ``frame`` (label order): rows to append: some FOV rows projecting right of its box, two rows
    inside it, and the three rows the fixture appended (one in front outside the image, two not in front)."""
    _, uv, fov, _ = reference_projection(frame)
    n = len(frame.scan)
    out = []
    for box in frame.labels.bbox[frame.labels.type == "Car"]:
        outside = np.flatnonzero(fov & (uv[:, 0] >= box[2]) & (uv[:, 0] < box[2] + 80))[:40]
        inside = np.flatnonzero(fov & (uv[:, 0] >= box[0]) & (uv[:, 0] < box[2])
                                & (uv[:, 1] >= box[1]) & (uv[:, 1] < box[3]))[:2]
        out.append(np.unique(np.concatenate([outside, inside, [n - 3, n - 2, n - 1]])).astype(np.int64))
    return out


def append_record(frame: Frame, rows: list[np.ndarray] | None = None) -> Record:
    cars = np.flatnonzero(frame.labels.type == "Car")
    rows = rows if rows is not None else [np.zeros(0, dtype=np.int64)] * len(cars)
    return Record(np.tile(EMPTY, (len(cars), 1)), tuple(rows), cars)


def assert_same_rows(a: Labels, b: Labels) -> None:
    for field in ("type", "truncated", "occluded", "alpha", "bbox", "dimensions", "location", "rotation_y", "score"):
        assert np.array_equal(getattr(a, field), getattr(b, field)), field


@pytest.mark.parametrize("which", ["torch", "onnx"])
def test_empty_extra_points_and_empty_object_boxes_give_the_gt_result_bit_for_bit(which, frames, lite, lite_onnx):
    victim = lite if which == "torch" else lite_onnx
    labels = [f.labels for f in frames]
    records = [append_record(f) for f in frames]
    want = victim.detect(*victim_inputs(frames, labels, "gt"))
    assert sum(len(d) for d in want) > 5
    for source in ("gt-append", "gt-object"):
        got = victim.detect(*victim_inputs(frames, labels, source, objects=records))
        for a, b in zip(want, got, strict=True):
            assert_same_rows(a, b)


def test_gt_append_feeds_segmentation_the_hand_built_frustums(frames, lite, fed_frustums):
    """The points the pipeline feeds the segmentation stage are, per usable Car, the hand-built frustum (scan
    points projecting into the GT box, in the image and 2 m ahead, united with the given rows 2 m ahead, in scan
    order) resampled with the frustum's generator and rotated by hand about rect y."""
    fed = fed_frustums
    rows = [hand_extra_rows(f) for f in frames]
    records = [append_record(f, r) for f, r in zip(frames, rows, strict=True)]
    lite.detect(*victim_inputs(frames, [f.labels for f in frames], "gt-append", objects=records))
    expected, grew = [], 0
    for frame, extra in zip(frames, rows, strict=True):
        rect, uv, fov, front = reference_projection(frame)
        for k, box in enumerate(frame.labels.bbox[frame.labels.type == "Car"]):
            inside = fov & (uv[:, 0] >= box[0]) & (uv[:, 0] < box[2]) & (uv[:, 1] >= box[1]) & (uv[:, 1] < box[3])
            added = np.zeros(len(rect), dtype=bool)
            added[extra[k]] = True
            members = np.flatnonzero(inside | (added & front))
            assert len(rows) and frame.scan.shape[0] - 3 in members and frame.scan.shape[0] - 2 not in members
            grew += len(members) > inside.sum()
            if box[3] - box[1] < 25 or len(members) == 0:
                continue
            rng = np.random.default_rng([lite.settings.seed, int(frame.frame_id), k])
            pts = rect[members[rng.integers(0, len(members), lite.num_points)]]
            fu, cu = frame.calib.P2[0, 0], frame.calib.P2[0, 2]
            x = ((box[0] + box[2]) / 2 - cu) * 20.0 / fu - frame.calib.P2[0, 3] / fu
            a = np.pi / 2 - np.arctan2(20.0, x)
            rotated = pts.copy()
            rotated[:, 0] = np.cos(a) * pts[:, 0] - np.sin(a) * pts[:, 2]
            rotated[:, 2] = np.sin(a) * pts[:, 0] + np.cos(a) * pts[:, 2]
            expected.append(rotated)
    assert grew > 5 and len(fed) == len(expected) > 5
    for got, want in zip(fed, expected, strict=True):
        assert np.allclose(got[:, :3], want[:, :3], atol=1e-4)
        assert np.array_equal(got[:, 3], want[:, 3].astype(np.float32))


def object_boxes(frame: Frame) -> Record:
    """Per Car: a box over its roof (upper middle of its GT box, reaching 50 % of its height above it)."""
    cars = np.flatnonzero(frame.labels.type == "Car")
    b = frame.labels.bbox[cars]
    w, h = b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]
    boxes = np.column_stack([b[:, 0] + 0.3 * w, b[:, 1] - 0.5 * h, b[:, 2] - 0.3 * w, b[:, 1] + 0.2 * h])
    return Record(boxes, tuple(np.zeros(0, dtype=np.int64) for _ in cars), cars)


def test_gt_object_is_gt_with_the_union_boxes(frames, lite):
    """A ``gt-object`` set gives what a ``gt`` set with the same (union) boxes gives: GT filters and 3D scores."""
    labels = [f.labels for f in frames]
    bare, given = victim_inputs(frames, labels, "gt-object", objects=[object_boxes(f) for f in frames])
    as_gt = [Proposals(p.boxes, p.scores, "gt", p.types) for p in given]
    plain = victim_inputs(frames, labels, "gt")[1]
    assert any(not np.array_equal(a.boxes, b.boxes) for a, b in zip(given, plain, strict=True))
    got, want = lite.detect(bare, given), lite.detect(bare, as_gt)
    for a, b in zip(got, want, strict=True):
        assert_same_rows(a, b)


@pytest.mark.parametrize("source", ["gt-append", "gt-object"])
def test_torch_and_onnx_agree_on_the_new_sources(source, frames, lite, lite_onnx):
    labels = [f.labels for f in frames]
    records = [append_record(f, hand_extra_rows(f)) if source == "gt-append" else object_boxes(f) for f in frames]
    bare, given = victim_inputs(frames, labels, source, objects=records)
    dets_t, dets_o = lite.detect(bare, given), lite_onnx.detect(bare, given)
    parity = box_parity(bare, source, dets_t, dets_o, Tolerances())
    assert parity.ok and parity.rows_torch > 5, parity


# ---- the white-box oracles ---------------------------------------------------------------------------
def scan_rect(frame: Frame, dtype: torch.dtype) -> torch.Tensor:
    rect = np.concatenate([frame.calib.velo_to_rect_points(frame.scan[:, :3]), frame.scan[:, 3:4]], axis=1)
    return torch.tensor(rect, dtype=dtype, requires_grad=True)


def test_oracles_build_the_gt_append_frustum_detect_scores(frames, lite, fed_frustums):
    """With a box's extra points, ``frustum_logits`` samples the very rows ``detect`` feeds (the hand-built
    union), ``frustum_box`` is the row ``detect`` writes, and gradients reach the appended points; with empty
    extra points both are today's oracles."""
    from robustbench3d.geometry import wrap_angle

    fed = fed_frustums
    frame = frames[0]
    extra = hand_extra_rows(frame)
    bare, given = victim_inputs([frame], [frame.labels], "gt-append", objects=[append_record(frame, extra)])
    rows = lite.detect(bare, given)[0]
    (props,) = lite.proposals(bare, given)
    pts = scan_rect(frame, torch.float64)
    rect, uv, fov, front = reference_projection(frame)
    checked = 0
    for k, box in enumerate(props.boxes):
        where = dict(frame_id=frame.frame_id, proposal=k)
        fl = lite.frustum_logits(pts, frame.calib, frame.image_size, box, extra_points=props.extra_points[k], **where)
        if fl is None or box[3] - box[1] < 25:
            continue
        inside = fov & (uv[:, 0] >= box[0]) & (uv[:, 0] < box[2]) & (uv[:, 1] >= box[1]) & (uv[:, 1] < box[3])
        added = np.zeros(len(rect), dtype=bool)
        added[extra[k]] = True
        assert set(fl.sample_index.tolist()) <= set(np.flatnonzero(inside | (added & front)).tolist())
        assert np.allclose(fl.points.detach().numpy(), fed[checked], atol=1e-4)
        fb = lite.frustum_box(pts, frame.calib, frame.image_size, box, extra_points=props.extra_points[k], **where)
        r = int(np.flatnonzero(np.all(rows.bbox == box, axis=1))[0])
        centre = rows.location[r] - np.array([0.0, rows.dimensions[r, 0] / 2, 0.0])
        assert np.allclose(fb.center.detach().numpy(), centre, atol=2e-4)
        assert np.allclose(fb.size_lwh.detach().numpy(), rows.dimensions[r, [2, 1, 0]], atol=2e-4)
        assert abs(wrap_angle(fb.heading.item() - rows.rotation_y[r])) < 2e-4
        outside = [i for i in np.unique(fl.sample_index) if not inside[i]]
        assert outside  # appended points were sampled ...
        (grad,) = torch.autograd.grad(fl.logits[:, 1].sum(), pts)
        assert grad[outside].abs().sum() > 0  # ... and the loss reaches them
        plain = lite.frustum_logits(pts, frame.calib, frame.image_size, box, **where)
        empty = lite.frustum_logits(pts, frame.calib, frame.image_size, box, extra_points=np.zeros(0, np.int64),
                                    **where)
        assert np.array_equal(plain.sample_index, empty.sample_index) and torch.equal(plain.logits, empty.logits)
        checked += 1
    assert checked == len(fed) >= 3


def test_a_gt_append_name_alone_is_refused(frames, lite):
    with pytest.raises(ValueError, match="built by victim_inputs"):
        lite.detect(frames[:1], "gt-append")
    frame = frames[0]
    bad = Proposals(np.array([[0.0, 0, 100, 100]]), np.ones(1), "gt-append", np.array(["Car"]),
                    (np.array([len(frame.scan)]),))
    with pytest.raises(ValueError, match=f"scan has {len(frame.scan)} points"):
        lite.detect([frame], [bad])


def test_shipped_victims_list_the_new_sources(lite, lite_onnx):
    for victim in (lite, lite_onnx):
        assert {"gt-object", "gt-append"} <= set(victim.supported_proposals)
