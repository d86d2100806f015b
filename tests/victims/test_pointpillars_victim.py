"""The PointPillars victim: detect's output format (KITTI rows in the camera FOV, 2D boxes inside the image,
scores, determinism), target_scores against detect (the top detection's score, and with the shipped weights
the matched ground-truth cars of a real frame), gradients w.r.t. appended points against finite differences
(tiny float64 network), and bad victim arguments refused with one line."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from robustbench3d.errors import RobustBenchError
from robustbench3d.eval.iou import bev_iou
from robustbench3d.kitti import KittiDataset
from robustbench3d.testing import synth_dataset
from robustbench3d.victims import create_victim
from robustbench3d.victims.base import AttackedScene, AttackTargets, TargetScoreOracle, check_victim
from robustbench3d.victims.pointpillars.config import PointPillarsConfig
from robustbench3d.victims.pointpillars.detector import PointPillarsDetector
from robustbench3d.victims.pointpillars.model import build_model
from robustbench3d.victims.shipped import shipped
from robustbench3d.victims.zoo import POINTPILLARS_CAPABILITIES

torch.set_num_threads(1)
TINY = PointPillarsConfig(pillar_channels=8, block_channels=(8, 8, 8), block_layers=(1, 1, 1), up_channels=8,
                          head_channels=8)


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    root = synth_dataset(tmp_path_factory.mktemp("pp"), 2, seed=3, val_fraction=1.0)
    ds = KittiDataset(root, split="val")
    return [ds.frame(f) for f in ds.frame_ids]


def _victim(dtype=torch.float32, seed=0) -> PointPillarsDetector:
    return PointPillarsDetector(build_model(TINY, seed).eval(), dtype=dtype)


def _scene(frame, extra_rect: np.ndarray | None = None, grad: bool = False):
    rect = np.concatenate([frame.calib.velo_to_rect_points(frame.scan[:, :3]), frame.scan[:, 3:4]], axis=1)
    base = torch.from_numpy(rect)
    if extra_rect is None:
        return AttackedScene(frame=replace(frame, labels=None), points_rect=base), None
    extra = torch.tensor(extra_rect, dtype=torch.float64, requires_grad=grad)
    return AttackedScene(frame=replace(frame, labels=None), points_rect=torch.cat([base, extra])), extra


def _targets_of(labels) -> AttackTargets:
    b3 = np.concatenate([labels.location, labels.dimensions, labels.rotation_y[:, None]], axis=1)
    return AttackTargets(boxes2d=labels.bbox, boxes3d=b3, proposal=np.full(len(labels), -1))


def _iou_rows(labels) -> np.ndarray:
    """(N, 7) h, w, l, x, y, z, ry rows (the evaluator's box layout)."""
    return np.concatenate([labels.dimensions, labels.location, labels.rotation_y[:, None]], axis=1)


def test_contract_and_format(frames):
    victim = _victim()
    check_victim(victim, POINTPILLARS_CAPABILITIES)
    assert isinstance(victim, TargetScoreOracle) and victim.supported_proposals == ("detector",)
    for frame in frames:
        det = victim.detect([replace(frame, labels=None)])[0]
        assert len(det) > 0 and set(det.type) == {"Car"}
        w, h = frame.image_size
        assert np.all(det.bbox[:, [0, 1]] >= 0) and np.all(det.bbox[:, 2] <= w - 1) and np.all(det.bbox[:, 3] <= h - 1)
        assert np.all(det.bbox[:, 2] >= det.bbox[:, 0]) and np.all(det.bbox[:, 3] >= det.bbox[:, 1])
        centre = det.location - np.stack([np.zeros(len(det)), det.dimensions[:, 0] / 2, np.zeros(len(det))], axis=1)
        uv, depth = frame.calib.rect_to_image(centre)
        assert np.all(depth > 0) and np.all((uv[:, 0] >= 0) & (uv[:, 0] < w))
        assert np.all((det.score >= 0.05) & (det.score < 1)) and np.all(np.diff(det.score) <= 0)
        again = victim.detect([frame])[0]
        assert again.to_text() == det.to_text() and np.array_equal(again.score, det.score)


def test_detect_refuses_proposal_lists(frames):
    with pytest.raises(ValueError, match="proposals must be 'detector'"):
        _victim().detect(frames[:1], "gt")


def test_top_detection_score_is_sigmoid_of_its_logit(frames):
    """The frame's best detection sits on the map's largest heatmap logit, so the largest logit over its
    footprint is that one: sigmoid(logit) equals the reported score; its box decodes back too."""
    victim = _victim()
    frame = frames[0]
    det = victim.detect([frame])[0]
    out = victim.output(frame.scan, frame.calib, frame.image_size)
    assert det.score[0] == pytest.approx(1 / (1 + np.exp(-float(out[0].max()))), abs=1e-12)  # precondition
    scene, _ = _scene(frame)
    got = victim.target_scores(scene, _targets_of(det.select(slice(0, 1))), with_box=True)
    assert got.present.tolist() == [True]
    assert torch.sigmoid(got.logit[0]).item() == pytest.approx(det.score[0], abs=1e-5)
    box = got.box[0].detach().numpy()
    centre = det.location[0] - np.array([0, det.dimensions[0, 0] / 2, 0])
    np.testing.assert_allclose(box[:3], centre, atol=1e-3)
    np.testing.assert_allclose(box[3:6], det.dimensions[0, [2, 1, 0]], atol=1e-4)
    assert abs((box[6] - det.rotation_y[0] + np.pi) % (2 * np.pi) - np.pi) < 1e-4


def test_target_off_the_grid_is_absent(frames):
    """A car behind the sensor (rect z -20 m) has no output cell: present False."""
    victim = _victim()
    scene, _ = _scene(frames[0])
    t = AttackTargets(boxes2d=np.zeros((1, 4)), boxes3d=np.array([[0.0, 1.6, -20.0, 1.5, 1.6, 4.0, 0.0]]),
                      proposal=np.array([-1]))
    assert victim.target_scores(scene, t).present.tolist() == [False]


def test_gradients_match_finite_differences(frames):
    """d logit / d (appended points) of a tiny float64 network against central differences (the points stay
    in their pillars: 1e-6 m steps from positions away from pillar edges)."""
    victim = _victim(torch.float64, seed=1)
    frame = frames[0]
    velo = np.array([[12.05, 1.05, -0.5], [12.13, 1.11, -0.2], [12.45, 0.73, -0.9]])
    rect = np.concatenate([frame.calib.velo_to_rect_points(velo), np.full((3, 1), 0.4)], axis=1)
    car = np.array([[*frame.calib.velo_to_rect_points(np.array([[12.2, 1.0, -1.6]]))[0], 1.5, 1.7, 4.0, -1.5]])
    targets = AttackTargets(boxes2d=np.zeros((1, 4)), boxes3d=car, proposal=np.array([-1]))
    scene, extra = _scene(frame, rect, grad=True)
    got = victim.target_scores(scene, targets, with_box=True)
    (grad,) = torch.autograd.grad(got.logit[0] + got.box[0].sum(), extra)
    assert torch.isfinite(grad).all() and grad[:, :3].abs().sum() > 0
    eps = 1e-6
    for i in range(3):
        for j in range(3):
            vals = []
            for sign in (1, -1):
                moved = rect.copy()
                moved[i, j] += sign * eps
                s, _ = _scene(frame, moved)
                r = victim.target_scores(s, targets, with_box=True)
                vals.append((r.logit[0] + r.box[0].sum()).item())
            fd = (vals[0] - vals[1]) / (2 * eps)
            assert fd == pytest.approx(grad[i, j].item(), rel=1e-4, abs=1e-6)


@pytest.mark.skipif(shipped("pointpillars") is None, reason="no shipped pointpillars weights")
def test_shipped_target_scores_agree_with_detect(frames):
    """Shipped weights on a real frame: every ground-truth car that detect finds (BEV IoU >= 0.7) gets
    sigmoid(logit) equal to the matched detection's score."""
    victim = create_victim("pointpillars")
    checked = 0
    for frame in frames:
        gt = frame.labels.of_types(["Car"])
        det = victim.detect([replace(frame, labels=None)])[0]
        scene, _ = _scene(frame)
        got = victim.target_scores(scene, _targets_of(gt))
        iou = bev_iou(_iou_rows(gt), _iou_rows(det))
        for k in range(len(gt)):
            j = int(np.argmax(iou[k])) if len(det) else -1
            if j < 0 or iou[k, j] < 0.7:
                continue
            assert got.present[k]
            assert torch.sigmoid(got.logit[k]).item() == pytest.approx(det.score[j], abs=1e-5)
            checked += 1
    assert checked > 0


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"score_threshold": 0.0}, "victim argument 'score_threshold': 0.0 is not a number in [0.001, 0.99]"),
    ({"score_threshold": "high"}, "victim argument 'score_threshold'"),
    ({"max_detections": 0}, "victim argument 'max_detections': 0 is not an integer in [1, 1000]"),
    ({"max_detections": True}, "victim argument 'max_detections'"),
    ({"seed": -1}, "victim argument 'seed'"),
])
def test_bad_arguments_refused(kwargs, message):
    with pytest.raises(RobustBenchError) as err:
        create_victim("pointpillars", allow_untrained=True, **kwargs)
    assert message in str(err.value) and "\n" not in str(err.value)


def test_weights_file_refused_with_one_line(tmp_path):
    bad = tmp_path / "model.pt"
    torch.save({"config": {"nonsense": 1}, "state_dict": {}}, bad)
    with pytest.raises(RobustBenchError) as err:
        create_victim("pointpillars", weights=bad)
    assert str(bad) in str(err.value) and "\n" not in str(err.value)
