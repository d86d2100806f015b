"""The F-PN cascades' fidelity knobs (issue 15): ``num_points``, ``input_size`` and
``precision="float64"``. Defaults reproduce the pre-existing pipeline exactly; the knobs change
the frustum size, the letterbox geometry and the frustum stages' dtype as hand-computed."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from robustbench3d.errors import RobustBenchError
from robustbench3d.geometry import wrap_angle
from robustbench3d.kitti.dataset import KittiDataset
from robustbench3d.victims import create_victim
from robustbench3d.victims.cascade import Float64FrustumStages
from robustbench3d.victims.fpointnet import pipeline
from robustbench3d.victims.fpointnet.frustum import extract_frustum, project_scan
from robustbench3d.victims.fpointnet.model import TorchFrustumStages
from robustbench3d.victims.yolo.letterbox import image_to_tensor

torch.set_num_threads(1)
LITE = "fpointnet-v1-lite"


@pytest.fixture(scope="module")
def frames(kitti_samples):
    ds = KittiDataset(kitti_samples, split=None)
    return [ds.frame(f) for f in ds.frame_ids]


def untrained(**kwargs):
    """The untrained lite cascade (2D stage ``mini``, 640x192, largest stride 16), few detections."""
    v = create_victim(LITE, allow_untrained=True, seed=3, **kwargs)
    v.yolo.cfg = replace(v.yolo.cfg, max_detections=8)
    return v


def columns(labels):
    return [labels.bbox, labels.location, labels.dimensions, labels.rotation_y, labels.alpha, labels.score]


def assert_same_rows(a, b):
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        assert len(x) == len(y)
        for cx, cy in zip(columns(x), columns(y), strict=True):
            assert np.array_equal(cx, cy)


def rect_points(frame):
    return np.concatenate([frame.calib.velo_to_rect_points(frame.scan[:, :3]), frame.scan[:, 3:4]], axis=1)


# ---- defaults -----------------------------------------------------------------------------------
@pytest.mark.parametrize("source", ["gt", "detector"])
def test_defaults_and_explicit_trained_values_equal_the_plain_pipeline(frames, source):
    """Not passing the knobs, or passing the trained values, gives exactly the rows of the numpy
    pipeline run with the float32 stages at the network's N (the code path before the knobs)."""
    plain = untrained()
    explicit = untrained(num_points=512, input_size="640x192", precision="float32")
    assert plain.fidelity() == explicit.fidelity() == {"num_points": 512, "input_size": [640, 192],
                                                       "precision": "float32"}
    frames = frames if source == "gt" else frames[2:4]  # detector proposals: 8 per frame, two frames
    reference = pipeline.detect_frames(frames, source, detect_2d=plain.yolo.detect, car_class=plain.car_class,
                                       stages=TorchFrustumStages(plain.fpn), settings=plain.settings,
                                       num_points=plain.fpn.cfg.num_points,
                                       num_object_points=plain.fpn.cfg.num_object_points)
    got_plain, got_explicit = plain.detect(frames, source), explicit.detect(frames, source)
    assert_same_rows(got_plain, reference)
    assert_same_rows(got_explicit, reference)
    if source == "gt":
        assert sum(len(r) for r in reference) == 3  # the three usable cars of the samples


# ---- num_points ---------------------------------------------------------------------------------
def test_num_points_resamples_every_frustum_to_n(frames, monkeypatch):
    """detect feeds (B, 200, 4) frustums (200 < M = 512 object points: the gather repeats), and the
    segmentation oracle draws the same 200 indices: fr.indices[default_rng([seed, frame, k]).integers]."""
    v = untrained(num_points=200)
    assert v.num_points == 200 and v.fpn.cfg.num_points == 512
    fed: list[np.ndarray] = []
    real = pipeline.run_frustum_stages

    def recording(stages, points, *args, **kwargs):
        assert points.shape[1:] == (200, 4)
        fed.extend(np.array(p) for p in points)
        return real(stages, points, *args, **kwargs)

    monkeypatch.setattr(pipeline, "run_frustum_stages", recording)
    rows = v.detect(frames[2:5], "gt")
    assert sum(len(r) for r in rows) == len(fed) == 3
    assert all(np.isfinite(r.location).all() and (r.dimensions > 0).all() for r in rows)
    oracle = []
    for frame in frames[2:5]:
        (props,) = v.proposals([frame], "gt")
        rect = rect_points(frame)
        fr_all = project_scan(frame.scan, frame.calib, frame.image_size)
        for k, box in enumerate(props.boxes):
            fr = extract_frustum(fr_all, box, frame.calib)
            if box[3] - box[1] < 25 or len(fr) == 0:
                continue
            out = v.frustum_logits(torch.tensor(rect, dtype=torch.float32), frame.calib, frame.image_size, box,
                                   frame_id=frame.frame_id, proposal=k)
            draw = np.random.default_rng([3, int(frame.frame_id), k]).integers(0, len(fr), size=200)
            assert out.logits.shape == (200, 2) and np.array_equal(out.sample_index, fr.indices[draw])
            oracle.append((rect, out))
    assert len(oracle) == 3
    for (rect, out), want in zip(oracle, fed, strict=True):
        assert np.allclose(out.points.detach().numpy(), want, atol=1e-4)
        assert np.array_equal(rect[out.sample_index, 3].astype(np.float32), want[:, 3])


@pytest.mark.parametrize("n", [1, 2048])
def test_box_oracle_follows_num_points(frames, n):
    """With the shipped weights at N = 1 and N = 2048 the box oracle regresses the box detect reports."""
    v = create_victim(LITE, num_points=n)
    checked = 0
    for frame in frames[2:5]:
        rows = v.detect([frame], "gt")[0]
        (props,) = v.proposals([frame], "gt")
        pts = torch.tensor(rect_points(frame), dtype=torch.float64)
        for k, box in enumerate(props.boxes):
            row = np.flatnonzero(np.all(rows.bbox == box, axis=1))
            if len(row) == 0:
                continue
            got = v.frustum_box(pts, frame.calib, frame.image_size, box, frame_id=frame.frame_id, proposal=k)
            r = int(row[0])
            centre = rows.location[r] - np.array([0.0, rows.dimensions[r, 0] / 2, 0.0])
            assert got.logits.shape == (n, 2)
            assert np.allclose(got.center.detach().numpy(), centre, atol=2e-4)
            assert np.allclose(got.size_lwh.detach().numpy(), rows.dimensions[r, [2, 1, 0]], atol=2e-4)
            assert abs(wrap_angle(got.heading.item() - rows.rotation_y[r])) < 2e-4
            checked += 1
    assert checked == 3


# ---- input_size ---------------------------------------------------------------------------------
def test_input_size_sets_the_letterbox_by_hand():
    """A 1242x375 image into 320x96: s = min(320/1242, 96/375) = 0.256 -> 318x96 (1242·0.256 =
    317.95), pads ((320 - 318) // 2, 0) = (1, 0); the network sees (1, 3, 96, 320) and the
    differentiable letterbox of the objectness oracle agrees."""
    v = untrained(input_size="320x96")
    assert v.fidelity()["input_size"] == [320, 96] and v.yolo.net.cfg.input_size == (640, 192)
    image = np.random.default_rng(0).integers(0, 256, size=(375, 1242, 3), dtype=np.uint8)
    seen: list[tuple[int, ...]] = []
    real = v.yolo.run_heads

    def spy(x):
        seen.append(x.shape)
        return real(x)

    v.yolo.run_heads = spy
    (det,) = v.yolo.detect([image])
    assert seen == [(1, 3, 96, 320)]
    assert (det.boxes[:, 0::2] >= 0).all() and (det.boxes[:, 0::2] <= 1241).all()
    assert (det.boxes[:, 1::2] >= 0).all() and (det.boxes[:, 1::2] <= 374).all()
    pred, geo = v.yolo.predictions(image_to_tensor(image))
    assert geo.resized == (318, 96) and geo.pad == (1, 0)
    assert pred.boxes.shape == (1, 3 * (6 * 20 + 12 * 40), 4)  # strides 16 and 8 on 96x320


def test_input_size_decodes_a_prior_to_original_pixels_by_hand():
    """One confident prior on crafted head tensors at 320x96: head 0 (stride 96/6 = 16), anchor 3
    (60 x 40 px), cell (column 10, row 2), t = 0 -> centre (10.5·16, 2.5·16) = (168, 40), box
    [138, 20, 198, 60] input px -> x = (x_in - 1)·1242/318, y = y_in·375/96 in the image."""
    v = untrained(input_size="320x96")
    image = np.zeros((375, 1242, 3), dtype=np.uint8)

    def heads(x):
        h0 = np.zeros((1, 18, 6, 20), np.float32)
        h1 = np.zeros((1, 18, 12, 40), np.float32)
        for h in (h0, h1):
            h[:, 4::6] = -20.0  # objectness
            h[:, 5::6] = -20.0  # class
        h0[0, 4, 2, 10] = h0[0, 5, 2, 10] = 10.0
        return [h0, h1]

    v.yolo.run_heads = heads
    (det,) = v.yolo.detect([image])
    assert len(det.boxes) == 1
    want = [137 * 1242 / 318, 20 * 375 / 96, 197 * 1242 / 318, 60 * 375 / 96]
    assert np.allclose(det.boxes[0], want, atol=1e-4)
    assert det.scores[0] == pytest.approx((1 / (1 + np.exp(-10.0))) ** 2, rel=1e-6)


def test_input_size_runs_the_cascade(frames):
    """The shipped lite cascade (mini3, largest stride 32) at 640x192: proposals in original pixels,
    rows for them."""
    v = create_victim(LITE, input_size=[640, 192])
    assert max(v.yolo.net.head_strides) == 32 and v.yolo.cfg.input_size == (640, 192)
    frame = frames[3]
    (props,) = v.proposals([frame], "detector")
    w, h = frame.image_size
    assert len(props.boxes) > 0
    assert (props.boxes[:, [0, 2]] <= w - 1).all() and (props.boxes[:, [1, 3]] <= h - 1).all()
    assert (props.boxes >= 0).all()
    assert create_victim(LITE).proposals([frame], "detector")[0].boxes.tolist() != props.boxes.tolist()
    v.yolo.cfg = replace(v.yolo.cfg, max_detections=6)  # a few frustums suffice
    rows = v.detect([frame])[0]
    assert 0 < len(rows) <= 6 and np.isfinite(rows.location).all()


# ---- bad values ---------------------------------------------------------------------------------
@pytest.mark.parametrize(("field", "value"), [
    ("num_points", 0), ("num_points", -8), ("num_points", 65537), ("num_points", 512.0), ("num_points", True),
    ("num_points", "512"),
    ("input_size", "640x200"), ("input_size", "648x192"), ("input_size", "640"), ("input_size", "0x192"),
    ("input_size", "-640x192"), ("input_size", "axb"), ("input_size", [640]), ("input_size", [640.0, 192]),
    ("input_size", 640), ("precision", "float16"),
])
def test_bad_values_raise_naming_the_field(field, value):
    with pytest.raises(RobustBenchError, match=f"'{field}'"):
        create_victim(LITE, allow_untrained=True, **{field: value})


# ---- precision ----------------------------------------------------------------------------------
def test_float64_agrees_with_float32(frames):
    """The float64 copy's stage outputs are within 1e-4 of float32 on the same frustums (and not
    identical: it does run in float64); detect's rows agree to 1e-4; the float32 network is untouched."""
    v32 = create_victim(LITE)
    v64 = create_victim(LITE, precision="float64")
    assert v64.fidelity()["precision"] == "float64"
    assert next(v64.fpn.parameters()).dtype == torch.float32
    assert all(p.dtype == torch.float64 for p in v64._fpn64.parameters())
    scored = frames[2:5]
    props = v32.proposals(scored, "gt")
    inputs = pipeline.frustum_inputs(scored, props, v32.settings, v32.num_points)
    pts = np.stack([j.points for j in inputs])
    one_hot = np.tile(np.array([[1.0, 0.0, 0.0]], np.float32), (len(pts), 1))
    s32, s64 = TorchFrustumStages(v32.fpn), Float64FrustumStages(v64._fpn64)
    obj = pts[:, :512, :3]
    for name in ("segmentation", "center_delta", "box_output"):
        a = getattr(s32, name)(pts if name == "segmentation" else obj, one_hot)
        b = getattr(s64, name)(pts if name == "segmentation" else obj, one_hot)
        assert b.dtype == np.float64
        assert np.abs(a - b).max() <= 1e-4 * max(1.0, np.abs(b).max())
        assert not np.array_equal(a, b.astype(np.float32))
    r32, r64 = v32.detect(scored, "gt"), v64.detect(scored, "gt")
    assert [len(r) for r in r32] == [len(r) for r in r64] and sum(len(r) for r in r32) == 3
    for a, b in zip(r32, r64, strict=True):
        assert np.allclose(a.location, b.location, atol=1e-4) and np.allclose(a.dimensions, b.dimensions, atol=1e-4)
        assert np.allclose(a.rotation_y, b.rotation_y, atol=1e-4)
