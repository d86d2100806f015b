"""The F-PN cascade victim end to end on real KITTI frames (untrained, seeded networks): result
rows, proposal sources, determinism, the white-box oracles' gradients, weights round trip."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from robustbench3d.geometry import alpha_from_rotation_y
from robustbench3d.kitti.dataset import KittiDataset
from robustbench3d.victims import create_victim
from robustbench3d.victims.base import Proposals
from robustbench3d.victims.cascade import CascadeSettings, FPointNetCascade
from robustbench3d.victims.fpointnet.frustum import extract_frustum, project_scan
from robustbench3d.victims.yolo.letterbox import image_to_tensor

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def frames(kitti_samples):
    ds = KittiDataset(kitti_samples, split=None)
    return [ds.frame(f) for f in ds.frame_ids]


@pytest.fixture(scope="module")
def victim():
    v = create_victim("fpointnet-v1-lite", allow_untrained=True, seed=3)
    v.yolo.cfg = replace(v.yolo.cfg, max_detections=8)  # keep the untrained detector's output small
    return v


def test_gt_proposals_give_one_row_per_usable_car(victim, frames):
    rows = victim.detect(frames, proposals="gt")
    assert len(rows) == len(frames)
    for frame, r in zip(frames, rows, strict=True):
        cars = frame.labels.select(frame.labels.type == "Car")
        proj = project_scan(frame.scan, frame.calib, frame.image_size)
        usable = [b for b in cars.bbox if b[3] - b[1] >= 25 and len(extract_frustum(proj, b, frame.calib)) >= 1]
        assert r.has_score and len(r) == len(usable)
        assert np.array_equal(r.bbox, np.array(usable).reshape(-1, 4))  # the 2D box is the proposal
        if len(r):
            assert set(r.type) == {"Car"} and (r.truncated == -1).all() and (r.occluded == -1).all()
            assert np.isfinite(r.location).all() and (r.dimensions > 0).all()
            assert (np.abs(r.rotation_y) <= np.pi).all()
            assert np.allclose(r.alpha, alpha_from_rotation_y(r.rotation_y, r.location))
            assert ((r.score > 0) & (r.score <= 1)).all()
    assert sum(len(r) for r in rows) == 3  # frames 2, 3, 4; the cars at 51 m and 58 m are < 25 px high


def test_detect_is_deterministic(victim, frames):
    a = victim.detect(frames, proposals="gt")
    b = victim.detect(list(reversed(frames)), proposals="gt")[::-1]  # order / batching does not matter
    assert [x.to_text(precision=6) for x in a] == [x.to_text(precision=6) for x in b]


def test_detector_proposals_carry_the_2d_score(victim, frames):
    frame = frames[3]
    dets = victim.yolo.detect([frame.image])[0]
    rows = victim.detect([frame], proposals="detector")[0]
    assert 0 < len(rows) <= len(dets.boxes)
    for box, score in zip(rows.bbox, rows.score, strict=True):
        k = int(np.argmin(np.abs(dets.boxes - box).sum(axis=1)))
        assert np.allclose(dets.boxes[k], box) and score == pytest.approx(dets.scores[k])


def test_given_proposals_and_filters(victim, frames):
    frame = frames[3]
    car = frame.labels.select(frame.labels.type == "Car")
    tiny = np.array([600.0, 200.0, 640.0, 210.0])       # 10 px high: skipped
    empty = np.array([0.0, 0.0, 30.0, 40.0])            # top-left corner: no LiDAR points
    rows = victim.detect([frame], [Proposals(np.stack([car.bbox[0], tiny, empty]), np.array([0.9, 0.8, 0.7]))])[0]
    assert len(rows) == 1 and rows.score[0] == 0.9
    with pytest.raises(ValueError, match="proposal sets"):
        victim.detect([frame, frame], [Proposals(car.bbox, np.ones(1))])


def test_objectness_oracle_is_differentiable(victim, frames):
    frame = frames[3]
    car = frame.labels.select(frame.labels.type == "Car")
    image = image_to_tensor(frame.image).requires_grad_(True)
    cand = victim.objectness(image, [car.bbox], iou_threshold=0.3)
    assert len(cand.objectness_logit) > 0
    assert (cand.image_index == 0).all() and (cand.target_index == 0).all()
    inside = ((cand.boxes[:, 0] + cand.boxes[:, 2]) / 2 >= car.bbox[0, 0]) & ((cand.boxes[:, 0] + cand.boxes[:, 2]) / 2
                                                                              <= car.bbox[0, 2])
    assert ((cand.iou >= 0.3) | inside).all()
    loss = -torch.nn.functional.logsigmoid(-cand.objectness_logit).mean()  # = mean -log(1 - o)
    loss.backward()
    assert torch.isfinite(image.grad).all() and image.grad.abs().sum() > 0


def test_frustum_oracle_is_differentiable(victim, frames):
    frame = frames[3]
    car = frame.labels.select(frame.labels.type == "Car")
    rect = np.concatenate([frame.calib.velo_to_rect_points(frame.scan[:, :3]), frame.scan[:, 3:4]], axis=1)
    pts = torch.tensor(rect, dtype=torch.float32, requires_grad=True)
    out = victim.frustum_logits(pts, frame.calib, frame.image_size, car.bbox[0], frame_id=frame.frame_id, proposal=0)
    assert out is not None and out.logits.shape == (victim.num_points, 2)
    fr = extract_frustum(project_scan(frame.scan, frame.calib, frame.image_size), car.bbox[0], frame.calib)
    assert np.isin(out.sample_index, fr.indices).all()
    again = victim.frustum_logits(pts, frame.calib, frame.image_size, car.bbox[0], frame_id=frame.frame_id, proposal=0)
    assert torch.equal(out.logits, again.logits)
    out.object_prob.max().backward()
    grad = pts.grad.abs().sum(dim=1)
    assert torch.isfinite(pts.grad).all() and grad.sum() > 0
    assert (grad[np.setdiff1d(np.arange(len(rect)), out.sample_index)] == 0).all()  # only sampled points
    assert victim.frustum_logits(pts, frame.calib, frame.image_size, np.array([0.0, 0, 20, 20]),
                                 frame_id=frame.frame_id, proposal=0) is None


def test_frustum_oracle_resamples_the_points_detect_scores(victim, frames, fed_frustums):
    """For every usable proposal of a frame, the oracle's network input is the one ``detect`` feeds
    the segmentation network (same resampled points, in the same order)."""
    fed = fed_frustums
    scored = frames[2:5]  # three usable cars (GT proposals need one frustum point)
    victim.detect(scored, "gt")
    oracle = []
    for frame in scored:
        (props,) = victim.proposals([frame], "gt")
        rect = np.concatenate([frame.calib.velo_to_rect_points(frame.scan[:, :3]), frame.scan[:, 3:4]], axis=1)
        pts = torch.tensor(rect, dtype=torch.float32)
        for k, box in enumerate(props.boxes):
            out = victim.frustum_logits(pts, frame.calib, frame.image_size, box, frame_id=frame.frame_id, proposal=k)
            if out is not None and box[3] - box[1] >= victim.settings.min_box_height:
                oracle.append((frame, k, box, rect, out))
    assert len(oracle) == len(fed) == 3
    for (_, _, _, rect, got), want in zip(oracle, fed, strict=True):
        assert np.allclose(got.points.detach().numpy(), want, atol=1e-4)
        assert np.array_equal(rect[got.sample_index, 3].astype(np.float32), want[:, 3])  # the very points fed
    # another proposal index (or frame) draws another resampling
    frame, k, box, rect, first = oracle[-1]
    pts = torch.tensor(rect, dtype=torch.float32)
    for frame_id, proposal in ((frame.frame_id, k + 1), (scored[0].frame_id, k)):
        other = victim.frustum_logits(pts, frame.calib, frame.image_size, box, frame_id=frame_id, proposal=proposal)
        assert not np.array_equal(other.sample_index, first.sample_index)


def test_weights_round_trip(victim, frames, tmp_path):
    path = tmp_path / "cascade.pt"
    victim.save(path)
    from robustbench3d.fileio import sha256_file

    loaded = FPointNetCascade.load(path, CascadeSettings(seed=3), sha256=sha256_file(path))
    a = victim.detect(frames[2:4], proposals="gt")
    b = loaded.detect(frames[2:4], proposals="gt")
    assert [x.to_text(precision=6) for x in a] == [x.to_text(precision=6) for x in b]
    from robustbench3d.errors import RobustBenchError

    with pytest.raises(RobustBenchError, match="sha256"):
        FPointNetCascade.load(path, sha256="0" * 64)


def _tta(victim) -> FPointNetCascade:
    tta = FPointNetCascade(victim.yolo.__class__(victim.yolo.net), victim.fpn, victim.settings)
    tta.yolo.cfg = replace(victim.yolo.cfg, flip_tta=True, nms_merge=True)
    return tta


def test_flip_tta_pools_both_views_and_is_mirror_equivariant(victim, frames):
    from robustbench3d.victims.yolo.postprocess import image_priors

    tta = _tta(victim)
    image = frames[3].image
    w = image.shape[1]
    mirrored = np.ascontiguousarray(image[:, ::-1])
    (b, o, _, geo), = image_priors([image], tta.yolo.run_heads, tta.yolo.cfg)
    (b1, o1, _, _), = image_priors([image], victim.yolo.run_heads, victim.yolo.cfg)
    (bm, om, _, _), = image_priors([mirrored], victim.yolo.run_heads, victim.yolo.cfg)
    p = len(o1)
    assert len(o) == 2 * p and np.array_equal(o[:p], o1) and np.array_equal(o[p:], om)
    assert np.array_equal(b[:p], b1)
    # the mirrored view's priors, mapped to the original image, are the mirror images of its boxes
    left = geo.to_image(np.stack([b[p:, 0] - b[p:, 2] / 2, b[p:, 1], b[p:, 0] + b[p:, 2] / 2, b[p:, 1]], 1))[:, 0]
    right_m = geo.to_image(np.stack([bm[:, 0] + bm[:, 2] / 2, bm[:, 1], bm[:, 0] + bm[:, 2] / 2, bm[:, 1]], 1))[:, 0]
    assert np.allclose(left, w - right_m, atol=1e-3)
    # detections of the mirrored image are the mirrored detections (both views are seen either way)
    d, dm = tta.yolo.detect([image])[0], tta.yolo.detect([mirrored])[0]
    assert len(d.boxes) == len(dm.boxes) > 0
    order, order_m = np.argsort(-d.scores, kind="stable"), np.argsort(-dm.scores, kind="stable")
    assert np.allclose(d.scores[order], dm.scores[order_m], rtol=0, atol=1e-7)
    flipped = np.stack([w - dm.boxes[:, 2], dm.boxes[:, 1], w - dm.boxes[:, 0], dm.boxes[:, 3]], axis=1)
    assert np.allclose(np.clip(flipped[order_m], 0, w - 1), d.boxes[order], atol=2e-3)


def test_objectness_with_flip_tta_covers_both_views(victim, frames):
    tta = _tta(victim)
    frame = frames[3]
    car = frame.labels.select(frame.labels.type == "Car").bbox[:1]
    w = frame.image.shape[1]
    image = image_to_tensor(frame.image).requires_grad_(True)
    plain = victim.objectness(image, [car])
    mirror_car = np.stack([w - car[:, 2], car[:, 1], w - car[:, 0], car[:, 3]], axis=1)
    seen_mirrored = victim.objectness(torch.flip(image, dims=[-1]), [mirror_car])
    both = tta.objectness(image, [car])
    n = len(plain.objectness_logit)
    assert len(both.objectness_logit) == n + len(seen_mirrored.objectness_logit)
    assert torch.equal(both.objectness_logit[n:], seen_mirrored.objectness_logit)
    back = seen_mirrored.boxes
    assert torch.allclose(both.boxes[n:], torch.stack([w - back[:, 2], back[:, 1], w - back[:, 0], back[:, 3]], 1))
    both.objectness_logit.sum().backward()
    assert torch.isfinite(image.grad).all() and image.grad.abs().sum() > 0


@pytest.mark.parametrize("trained", [False, True])
def test_frustum_box_oracle_is_the_box_detect_reports(trained, victim, frames):
    """For every usable GT proposal of three real frames, the box oracle's decoded box (rect frame) is
    the row ``detect`` writes: centre (location minus h/2), l/w/h and rotation_y; and it is differentiable
    in the points it was given (finite, non-zero gradient on sampled points only)."""
    from robustbench3d.geometry import wrap_angle

    v = create_victim("fpointnet-v1-lite") if trained else victim
    checked = 0
    for frame in frames[2:5]:
        rows = v.detect([frame], "gt")[0]
        (props,) = v.proposals([frame], "gt")
        rect = np.concatenate([frame.calib.velo_to_rect_points(frame.scan[:, :3]), frame.scan[:, 3:4]], axis=1)
        pts = torch.tensor(rect, dtype=torch.float64, requires_grad=True)
        for k, box in enumerate(props.boxes):
            row = np.flatnonzero(np.all(rows.bbox == box, axis=1))
            got = v.frustum_box(pts, frame.calib, frame.image_size, box, frame_id=frame.frame_id, proposal=k)
            if len(row) == 0:
                continue
            r = int(row[0])
            centre = rows.location[r] - np.array([0.0, rows.dimensions[r, 0] / 2, 0.0])
            assert np.allclose(got.center.detach().numpy(), centre, atol=2e-4)
            assert np.allclose(got.size_lwh.detach().numpy(), rows.dimensions[r, [2, 1, 0]], atol=2e-4)
            assert abs(wrap_angle(got.heading.item() - rows.rotation_y[r])) < 2e-4
            target = got.center[0] + got.center[2] + got.heading + got.size_lwh.sum()
            (grad,) = torch.autograd.grad(target, pts)
            assert torch.isfinite(grad).all() and grad.abs().sum() > 0
            checked += 1
    assert checked == 3
