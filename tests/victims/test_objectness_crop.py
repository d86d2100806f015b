"""The objectness oracle on crops (issue #33): the 2D network run only on the slices of the letterboxed input
that the targets' candidates read gives the candidates, logits, boxes, IoUs and image gradients of the whole
input, bit for bit -- on the shipped lite cascade (mini3 at 960x288) over generated frames, for single cars,
several cars, far-apart cars (separate crops), flip TTA, a batch, a smaller input size, and for every
layout's windowed forward on random windows. The reference is the whole-input path built here from its parts
(letterbox, the network, decoding, candidate selection)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from robustbench3d.attacks.base import target_cars
from robustbench3d.attacks.losses import SUM_MIN_IOU, best_candidate_scores, image_target_losses
from robustbench3d.kitti.dataset import KittiDataset
from robustbench3d.victims import create_victim
from robustbench3d.victims.yolo.boxes import box_iou
from robustbench3d.victims.yolo.detector import candidate_region, candidates_for_targets
from robustbench3d.victims.yolo.letterbox import image_to_tensor, letterbox, letterbox_window, resize_for_letterbox
from robustbench3d.victims.yolo.model import build_model

torch.set_num_threads(1)

FIELDS = ("objectness_logit", "class_logit", "boxes", "iou", "image_index", "target_index")


@pytest.fixture(scope="module")
def frames(shared_split):
    root = shared_split(2, seed=5, val_fraction=1.0)
    ds = KittiDataset(root, split="val")
    return [ds.frame(f) for f in ds.frame_ids]


@pytest.fixture(scope="module")
def victim(lite_victim):
    v = lite_victim  # the session's shared one (conftest): read only
    assert v.yolo.cfg.layout == "mini3" and tuple(v.yolo.cfg.input_size) == (960, 288)
    return v


def whole_input(victim, images, targets, iou_threshold):
    """The candidates of the whole input, from the parts (today's oracle), and their image gradient."""
    x = images.clone().requires_grad_(True)
    yolo = victim.yolo
    rows = {k: [] for k in FIELDS}
    for mirrored in (False, True) if yolo.cfg.flip_tta else (False,):
        pred, geo = yolo.predictions(torch.flip(x, dims=[-1]) if mirrored else x)
        if mirrored:
            pred = replace(pred, boxes=torch.cat([geo.mirror_x(pred.boxes[..., :1]), pred.boxes[..., 1:]], -1))
        for b, tgt in enumerate(targets):
            c = candidates_for_targets(pred, geo, torch.as_tensor(np.asarray(tgt, dtype=np.float64)), iou_threshold, b)
            rows["objectness_logit"].append(pred.obj_logit[b, c["prior"]])
            rows["class_logit"].append(pred.cls_logit[b, c["prior"], victim.car_class])
            rows["boxes"].append(c["boxes"].float())
            rows["iou"].append(c["iou"].float())
            rows["image_index"].append(torch.full_like(c["prior"], b))
            rows["target_index"].append(c["target"])
    out = {k: torch.cat(v) for k, v in rows.items()}
    return out, _grad(out["objectness_logit"], out["class_logit"], x)


def _grad(obj, cls, x):
    w = torch.linspace(0.5, 1.5, len(obj))
    loss = (obj * w).sum() + (cls * w.flip(0)).sum()
    (g,) = torch.autograd.grad(loss, x, allow_unused=True)
    return torch.zeros_like(x) if g is None else g


def assert_crop_matches(victim, images, targets, iou_threshold=0.3):
    ref, ref_grad = whole_input(victim, images, targets, iou_threshold)
    x = images.clone().requires_grad_(True)
    got = victim.objectness(x, targets, iou_threshold=iou_threshold, crop=True)
    for name in FIELDS:
        assert torch.equal(getattr(got, name), ref[name]), name
    assert torch.equal(_grad(got.objectness_logit, got.class_logit, x), ref_grad)
    return got


def spread(boxes):
    """Leftmost, rightmost, widest and narrowest of (T, 4) boxes (indices, unique)."""
    cx, w = (boxes[:, 0] + boxes[:, 2]) / 2, boxes[:, 2] - boxes[:, 0]
    return sorted({int(np.argmin(cx)), int(np.argmax(cx)), int(np.argmax(w)), int(np.argmin(w))})


def test_crop_equals_whole_input_for_single_cars_bit_for_bit(victim, frames):
    checked = 0
    for frame in frames:
        image = image_to_tensor(frame.image)
        cars = target_cars(frame.labels).bbox
        for k in spread(cars):
            for thr in (0.3, SUM_MIN_IOU):
                got = assert_crop_matches(victim, image, [cars[k:k + 1]], thr)
                checked += len(got.iou)
    assert checked > 500  # the comparisons were not vacuous


def test_crop_equals_whole_input_for_several_and_far_apart_cars(victim, frames, monkeypatch):
    frame = frames[0]
    image = image_to_tensor(frame.image)
    cars = target_cars(frame.labels).bbox
    assert len(cars) >= 3
    assert_crop_matches(victim, image, [cars])  # every car of the frame
    w = frame.image.shape[1]
    far = np.array([[w - 150.0, 150.0, w - 60.0, 210.0], [40.0, 160.0, 120.0, 200.0]])  # right one first
    calls = []
    forward = victim.yolo.net.forward_window
    monkeypatch.setattr(victim.yolo.net, "forward_window", lambda *a, **k: calls.append(1) or forward(*a, **k))
    got = assert_crop_matches(victim, image, [far], SUM_MIN_IOU)
    assert len(calls) == 2 and set(got.target_index.tolist()) == {0, 1}  # one crop per car, merged in order


def test_crop_with_flip_tta_batch_and_odd_targets(victim, frames):
    tta = create_victim("fpointnet-v1-lite")
    tta.yolo.cfg = replace(tta.yolo.cfg, flip_tta=True)
    frame = frames[1]
    image = image_to_tensor(frame.image)
    cars = target_cars(frame.labels).bbox
    got = assert_crop_matches(tta, image, [cars[spread(cars)[:2]]])
    assert len(got.iou) > 0
    w = frame.image.shape[1]
    batch = torch.cat([image, torch.flip(image, dims=[-1])])
    odd = np.array([[np.nan, 10.0, 50.0, 60.0], [w - 40.0, 100.0, w + 80.0, 180.0]])  # NaN; beyond the right edge
    assert_crop_matches(victim, batch, [cars[:1], np.concatenate([cars[1:2], odd])], 0.4)
    none = victim.objectness(image, [np.zeros((0, 4))], crop=True)
    assert len(none.iou) == 0 and none.class_logit.shape == (0,)


def test_crop_at_a_smaller_input_size_and_batch_kernel_choice(frames):
    """At 320x96 a batch of two makes PyTorch pick oneDNN for small convolutions that one image would not get:
    the crops (one image each) follow the batch's choice."""
    small = create_victim("fpointnet-v1-lite", input_size="320x96")
    images = [image_to_tensor(f.image) for f in frames]
    if images[0].shape != images[1].shape:
        images[1] = torch.nn.functional.interpolate(images[1], size=images[0].shape[-2:])
    targets = [target_cars(f.labels).bbox[:2] for f in frames]
    assert_crop_matches(small, torch.cat(images), targets)


def test_sum_loss_and_scores_are_the_same_at_threshold_one_half(victim, frames):
    """The training call asks for IoU >= 0.5 candidates under the sum loss: its terms and detection scores
    are those of the default threshold's candidates."""
    frame = frames[0]
    image = image_to_tensor(frame.image)
    cars = target_cars(frame.labels).bbox[:3]
    wide, narrow = (victim.objectness(image, [cars], iou_threshold=t) for t in (0.3, SUM_MIN_IOU))
    assert len(narrow.iou) < len(wide.iou)
    assert torch.equal(image_target_losses(wide, 3, 0, True, "sum"), image_target_losses(narrow, 3, 0, True, "sum"))
    assert np.array_equal(best_candidate_scores(wide, 3), best_candidate_scores(narrow, 3))


@pytest.mark.parametrize("t", [0.1, 0.3, 0.45, 0.5, 0.7])
def test_candidate_region_holds_every_candidate_centre(t):
    """Random boxes against a 100 x 50 target: every box with IoU >= t or its centre inside has its centre in
    the region; the extremal box (the target's height, width 100 / t, left edges together: IoU = t) sits on
    the region's bound (minus its margin), so the bound k = 1/(2t) - 1 is tight."""
    target = np.array([200.0, 100.0, 300.0, 150.0])
    rng = np.random.default_rng(int(t * 100))
    centre = rng.uniform([-200, -200], [700, 450], (20000, 2))
    size = np.exp(rng.uniform(np.log(5), np.log(2000), (20000, 2)))
    boxes = np.concatenate([centre - size / 2, centre + size / 2], axis=1)
    iou = box_iou(torch.tensor(boxes), torch.tensor(target[None]))[:, 0].numpy()
    inside = ((centre >= target[:2]) & (centre <= target[2:])).all(axis=1)
    cand = (iou >= t) | inside
    region = candidate_region(target, t)
    assert cand.sum() > 50
    assert ((centre[cand] >= region[:2]) & (centre[cand] <= region[2:])).all()
    k = max(0.0, 1 / (2 * t) - 1)
    assert region[2] - (300 + k * 100) == pytest.approx(2.0)  # REGION_MARGIN_PX
    if t < 0.5:
        extremal = np.array([[200.0, 100.0, 200 + 100 / t, 150.0]])
        assert box_iou(torch.tensor(extremal), torch.tensor(target[None]))[0, 0].item() == pytest.approx(t)
        assert (extremal[0, 0] + extremal[0, 2]) / 2 == pytest.approx(300 + k * 100)
    assert candidate_region(target, 0.0) is None


@pytest.mark.parametrize("layout,hw", [("mini", (96, 320)), ("mini3", (96, 320)), ("tiny", (64, 128)),
                                       ("v3", (64, 96))])
def test_forward_window_equals_forward_for_every_layout(layout, hw):
    """Random head windows on an input with flat areas (ties in the max-pools): the windowed head outputs
    and the input gradients equal the whole forward's (stride-2 convolutions and shortcuts: v3; stride-1
    max-pool: tiny)."""
    net = build_model(layout, seed=1).eval()
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.2, 0.2)
                m.running_var.uniform_(0.5, 2.0)
    gen = torch.Generator().manual_seed(0)
    x0 = torch.rand(1, 3, *hw, generator=gen)
    x0[..., :, : hw[1] // 5] = 0.5
    xf = x0.clone().requires_grad_(True)
    full = net(xf)
    rng = np.random.default_rng(2)
    for _ in range(6):
        wins = []
        for f in full:
            gh, gw = f.shape[-2:]
            r0, c0 = int(rng.integers(0, gh)), int(rng.integers(0, gw))
            wins.append(((r0, int(rng.integers(r0 + 1, gh + 1))), (c0, int(rng.integers(c0 + 1, gw + 1)))))
        wins[int(rng.integers(0, len(wins)))] = None if len(wins) > 1 else wins[0]
        weights = [None if w is None else torch.randn(1, f.shape[1], w[0][1] - w[0][0], w[1][1] - w[1][0],
                                                      generator=gen) for f, w in zip(full, wins, strict=True)]
        ref = [None if w is None else f[..., w[0][0]:w[0][1], w[1][0]:w[1][1]] for f, w in zip(full, wins, strict=True)]
        (g_ref,) = torch.autograd.grad(sum((r * m).sum() for r, m in zip(ref, weights, strict=True) if r is not None),
                                       xf, retain_graph=True)
        x = x0.clone().requires_grad_(True)
        heads = net.forward_window(x, wins)
        for h, r, w in zip(heads, ref, wins, strict=True):
            assert (h is None) == (r is None)
            if h is not None:
                assert (h.row0, h.col0) == (w[0][0], w[1][0]) and torch.equal(h.values, r)
        (g,) = torch.autograd.grad(sum((h.values * m).sum() for h, m in zip(heads, weights, strict=True)
                                       if h is not None), x)
        assert torch.equal(g, g_ref)


def test_letterbox_window_is_that_part_of_the_letterbox():
    """Windows inside the image, inside the padding (above, below, beside) and across both."""
    image = torch.rand(2, 3, 100, 400, generator=torch.Generator().manual_seed(3))
    whole, geo = letterbox(image, (320, 160), fill=0.25)
    assert geo.pad == (0, 40) and geo.resized == (320, 80)
    resized, _ = resize_for_letterbox(image, (320, 160))
    for (r0, r1), (c0, c1) in [((0, 160), (0, 320)), ((0, 10), (5, 50)), ((150, 160), (0, 320)),
                               ((30, 90), (100, 200)), ((35, 125), (310, 320))]:
        got = letterbox_window(resized, geo, ((r0, r1), (c0, c1)), fill=0.25)
        assert torch.equal(got, whole[..., r0:r1, c0:c1])
