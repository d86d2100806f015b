"""Hand-computed cases for the 2D stage's numpy inference path (no real data needed): letterbox
geometry and resampling, head decoding, scores, IoU / NMS and the mapping of detections back to
original pixels (:mod:`robustbench3d.victims.yolo.preprocess`, :mod:`.postprocess`)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from robustbench3d.victims.yolo.config import MINI
from robustbench3d.victims.yolo.postprocess import (
    box_iou,
    decode_heads,
    head_masks,
    nms,
    prior_scores,
    select_detections,
    sigmoid,
)
from robustbench3d.victims.yolo.preprocess import letterbox_geometry, letterbox_image, resize_taps

L3 = math.log(3.0)  # sigmoid(L3) = 3/4


def test_letterbox_geometry_by_hand():
    geo = letterbox_geometry((1242, 375), (960, 288))
    # s = min(960/1242, 288/375) = 0.768: 1242·0.768 = 953.856 -> 954 wide, 288 high, pad (960-954)//2 = 3
    assert geo.resized == (954, 288) and geo.pad == (3, 0) and geo.image_size == (1242, 375)
    assert geo.scale == pytest.approx((954 / 1242, 288 / 375))
    tall = letterbox_geometry((100, 400), (960, 288))  # s = 0.72: 72 x 288, pad (960-72)//2 = 444
    assert tall.resized == (72, 288) and tall.pad == (444, 0)
    odd = letterbox_geometry((10, 10), (15, 10))        # s = 1: no resize, pad 5//2 = 2 left, 0 top
    assert odd.resized == (10, 10) and odd.pad == (2, 0)
    wide = letterbox_geometry((400, 100), (100, 100))   # s = 0.25: 100 x 25, pad (0, 37)
    assert wide.resized == (100, 25) and wide.pad == (0, 37)


def test_letterbox_box_mapping_and_mirror_by_hand():
    geo = letterbox_geometry((1242, 375), (960, 288))
    box = np.array([[100.0, 50.0, 300.0, 200.0]])
    sx, sy = 954 / 1242, 288 / 375
    expect = np.array([[100 * sx + 3, 50 * sy, 300 * sx + 3, 200 * sy]])
    assert geo.to_input(box) == pytest.approx(expect)
    assert geo.to_image(expect) == pytest.approx(box)
    # x = 100 in the image is x = 1142 in the mirrored image; its input x mirrored back is 100's input x
    assert geo.mirror_x((1242 - 100) * sx + 3) == pytest.approx(100 * sx + 3)
    assert geo.mirror_x(0.0) == 960.0  # resized width + both pads


def test_resize_taps_by_hand():
    # upsampling 2 -> 4: bilinear with clamped edges, weights (1), (3/4, 1/4), (1/4, 3/4), (1)
    index, weight = resize_taps(2, 4)
    dense = np.zeros((4, 2))
    np.add.at(dense, (np.repeat(np.arange(4), index.shape[1]), index.ravel()), weight.ravel())
    assert dense == pytest.approx(np.array([[1, 0], [0.75, 0.25], [0.25, 0.75], [0, 1]]))
    # downsampling 4 -> 2 (antialiased: the triangle is twice as wide): (3, 3, 1)/7 and (1, 3, 3)/7
    index, weight = resize_taps(4, 2)
    dense = np.zeros((2, 4))
    np.add.at(dense, (np.repeat(np.arange(2), index.shape[1]), index.ravel()), weight.ravel())
    assert dense == pytest.approx(np.array([[3, 3, 1, 0], [0, 1, 3, 3]]) / 7, rel=1e-6)
    assert weight.dtype == np.float32 and index.dtype == np.int64


def test_letterbox_image_by_hand():
    img = np.zeros((1, 4, 3), dtype=np.uint8)
    img[0, :, 0] = [0, 70, 140, 210]
    img[0, :, 1] = 255
    x, geo = letterbox_image(img, (2, 3))  # s = min(2/4, 3/1) = 0.5: 2 x 1 (rounded), pad (0, 1)
    assert geo.resized == (2, 1) and geo.pad == (0, 1) and x.shape == (3, 3, 2) and x.dtype == np.float32
    assert x[0, 1] == pytest.approx(np.array([50, 160]) / 255, rel=1e-6)   # (0·3 + 70·3 + 140) / 7, ...
    assert x[1, 1].tolist() == [1.0, 1.0] and x[2, 1].tolist() == [0.0, 0.0]
    assert (x[:, 0] == 0.5).all() and (x[:, 2] == 0.5).all()               # fill rows above and below
    same, g = letterbox_image(img, (6, 1), fill=0.25)                     # no resize: exact /255, pad x 1
    assert g.resized == (4, 1) and g.pad == (1, 0)
    assert same[0, 0].tolist() == pytest.approx([0.25, 0, 70 / 255, 140 / 255, 210 / 255, 0.25])
    with pytest.raises(ValueError, match="uint8"):
        letterbox_image(img.astype(np.float32), (6, 1))


def test_sigmoid_and_prior_scores_by_hand():
    x = np.array([0.0, L3, -L3, 1000.0, -1000.0], dtype=np.float32)
    assert sigmoid(x) == pytest.approx([0.5, 0.75, 0.25, 1.0, 0.0]) and sigmoid(x).dtype == np.float32
    score, cls = prior_scores(np.array([L3, -L3]), np.array([[0.0, L3], [L3, 0.0]]))
    # 3/4 · (1/2, 3/4) -> class 1, 9/16; 1/4 · (3/4, 1/2) -> class 0, 3/16
    assert score == pytest.approx([9 / 16, 3 / 16]) and cls.tolist() == [1, 0]


def test_decode_heads_by_hand():
    heads = [np.zeros((1, 18, 12, 40), np.float32), np.zeros((1, 18, 24, 80), np.float32)]
    # head 0 (stride 16), anchor slot 1 (anchor 4 = 96 x 62), row 3, column 6: channels 6..11
    heads[0][0, 6:12, 3, 6] = [0.0, L3, math.log(2.0), 9.0, 1.5, -2.0]
    boxes, obj, cls = decode_heads(heads, MINI)
    assert boxes.shape == (1, 3 * 12 * 40 + 3 * 24 * 80, 4) and cls.shape == (1, boxes.shape[1], 1)
    p = (1 * 12 + 3) * 40 + 6
    assert head_masks(MINI)[0][1] == 4 and MINI.anchors[4] == (96.0, 62.0)
    # centre (σ(0) + 6)·16 = 104, (σ(ln 3) + 3)·16 = 60; size 96·2 and 62·e^8 (t_h clamped at 8)
    assert boxes[0, p] == pytest.approx([104.0, 60.0, 192.0, 62.0 * math.exp(8.0)], rel=1e-6)
    assert obj[0, p] == 1.5 and cls[0, p, 0] == -2.0
    # head 1 (stride 8), anchor slot 2 (anchor 2 = 38 x 26), row 10, column 7, all zero
    q = 3 * 12 * 40 + (2 * 24 + 10) * 80 + 7
    assert boxes[0, q] == pytest.approx([7.5 * 8, 10.5 * 8, 38.0, 26.0])
    with pytest.raises(ValueError, match="head tensors"):
        decode_heads(heads[:1], MINI)
    with pytest.raises(ValueError, match="does not fit"):
        decode_heads([heads[0], np.zeros((1, 18, 24, 79), np.float32)], MINI)


def test_numpy_iou_and_nms_by_hand():
    a = np.array([[0.0, 0, 2, 2]])
    b = np.array([[1.0, 1, 3, 3], [2.0, 2, 4, 4], [0, 0, 2, 2], [0.5, 0.5, 1.5, 1.5], [0, 1, 2, 4]])
    assert box_iou(a, b)[0] == pytest.approx([1 / 7, 0.0, 1.0, 0.25, 2 / 8])
    assert box_iou(np.array([[1.0, 1, 1, 1]]), np.array([[1.0, 1, 1, 1]]))[0, 0] == 0.0
    boxes = np.array([[0.0, 0, 10, 10], [0, 0, 10, 16], [0, 0, 10, 17]])  # IoU with box 0: 10/16, 10/17
    assert nms(boxes, np.array([0.9, 0.8, 0.7]), 0.6).tolist() == [0, 2]      # 0.625 > 0.6 >= 0.588
    assert nms(boxes, np.array([0.9, 0.8, 0.7]), 0.625).tolist() == [0, 1]  # IoU must exceed; 1 vs 2: 16/17
    assert nms(boxes, np.array([0.7, 0.8, 0.8]), 0.95).tolist() == [1, 2, 0]  # ties by lower index
    assert nms(np.zeros((0, 4)), np.zeros(0), 0.5).tolist() == []


def test_select_detections_maps_back_and_clips_by_hand():
    geo = letterbox_geometry((1242, 375), (960, 288))
    cfg = replace(MINI, input_size=(960, 288), conf_threshold=0.1, nms_threshold=0.4)
    boxes = np.array([[480.0, 144.0, 100.0, 50.0],     # score 9/16, kept
                      [482.0, 144.0, 100.0, 50.0],     # score 3/16, overlaps the first (IoU 98/102): dropped
                      [940.0, 20.0, 60.0, 60.0],       # score 9/16, right edge beyond the image: clipped
                      [100.0, 100.0, 20.0, 20.0]],     # score 1/16 < 0.1: dropped
                     dtype=np.float32)
    obj = np.array([L3, -L3, L3, -L3])
    cls = np.array([[L3], [L3], [L3], [-L3]])
    det = select_detections(boxes, obj, cls, geo, cfg)
    s = 1242 / 954
    expect = np.array([[(430 - 3) * s, 119 * 375 / 288, (530 - 3) * s, 169 * 375 / 288],
                       [(910 - 3) * s, 0.0, 1241.0, 50 * 375 / 288]])
    assert det.boxes == pytest.approx(expect)
    assert det.scores == pytest.approx([9 / 16, 9 / 16]) and det.classes.tolist() == [0, 0]
    merged = select_detections(boxes, obj, cls, geo, replace(cfg, nms_merge=True))
    # the kept box becomes the score-weighted mean of its cluster: x shifted by 2·(3/16)/(12/16) = 0.5 px
    assert merged.boxes[0] == pytest.approx(expect[0] + np.array([0.5 * s, 0, 0.5 * s, 0]))
    assert len(select_detections(boxes, obj, cls, geo, replace(cfg, max_detections=1)).boxes) == 1


# ---- kills of surviving mutants: edge inputs, dtypes, the torch twins ----------------------------
def test_letterbox_geometry_keeps_one_pixel_and_maps_lists_and_tensors():
    import torch

    assert letterbox_geometry((1, 1000), (10, 10)).resized == (1, 10)   # 0.01 px wide -> 1 px, not 0
    geo = letterbox_geometry((1242, 375), (960, 288))
    box = [[100.0, 50.0, 300.0, 200.0]]
    assert geo.to_input(box) == pytest.approx(geo.to_input(np.array(box)))
    t = torch.tensor(box, dtype=torch.float64)
    assert geo.to_input(t).numpy() == pytest.approx(geo.to_input(np.array(box)))
    assert geo.to_image(t).numpy() == pytest.approx(geo.to_image(np.array(box)))
    assert geo.mirror_x(torch.tensor([10.0])).tolist() == [950.0]
    f32 = np.array(box, dtype=np.float32) + np.float32(0.1)              # mapped in float64
    assert geo.to_input(f32).dtype == geo.to_image(f32).dtype == np.float64
    assert geo.to_image(geo.to_input(f32)) == pytest.approx(f32.astype(np.float64), abs=1e-12)
    with pytest.raises(ValueError, match="uint8"):
        letterbox_image(np.zeros((4, 4), np.uint8), (8, 8))                # a grey image is refused
    with pytest.raises(ValueError, match="uint8"):
        letterbox_image(np.zeros((4, 4, 4), np.uint8), (8, 8))             # so is RGBA


def test_numpy_letterbox_equals_the_differentiable_one():
    """The numpy resize (inference) and torch's antialiased bilinear (training, attacks) agree to
    float32 rounding on the KITTI image size, downscaled, and on a padded upscale."""
    import torch

    from robustbench3d.victims.yolo.letterbox import image_to_tensor, letterbox

    rng = np.random.default_rng(0)
    for shape, size in (((375, 1242, 3), (960, 288)), ((5, 7, 3), (16, 20))):
        img = rng.integers(0, 256, shape, dtype=np.uint8)
        ours, geo = letterbox_image(img, size)
        theirs, geo_t = letterbox(image_to_tensor(img), size)
        assert geo == geo_t and theirs.shape == (1, 3, size[1], size[0])
        assert np.abs(ours - theirs[0].numpy()).max() <= 1e-5  # 3.7e-6 seen at 960 x 288 on this CPU
    same, _ = letterbox(torch.full((1, 3, 2, 4), 0.25), (4, 6), fill=0.75)  # no resize: rows of fill
    assert same[0, 0, :, 0].tolist() == [0.75, 0.75, 0.25, 0.25, 0.75, 0.75]


def test_image_to_tensor_by_hand():
    from robustbench3d.victims.yolo.letterbox import image_to_tensor

    img = np.array([[[0, 51, 255], [102, 204, 1]]], dtype=np.uint8)   # (H 1, W 2, 3)
    t = image_to_tensor(img)
    assert t.shape == (1, 3, 1, 2) and t.dtype.is_floating_point
    assert t[0, :, 0, 0].tolist() == pytest.approx([0.0, 0.2, 1.0]) and t[0, 0, 0, 1].item() == pytest.approx(0.4)
    img[0, 0, 0] = 255                                                 # a copy: later edits do not leak
    assert t[0, 0, 0, 0].item() == 0.0


def test_image_to_tensor_takes_read_only_images_silently():
    """read_image gives np.asarray of a PIL image, which is read-only; torch warns (once per
    process, so every time under set_warn_always) when handed one, which the copy avoids."""
    import warnings

    import torch

    from robustbench3d.victims.yolo.letterbox import image_to_tensor

    img = np.array([[[0, 51, 255]]], dtype=np.uint8)
    img.flags.writeable = False
    was = torch.is_warn_always_enabled()
    torch.set_warn_always(True)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            t = image_to_tensor(img)
    finally:
        torch.set_warn_always(was)
    assert t[0, :, 0, 0].tolist() == pytest.approx([0.0, 0.2, 1.0])


def test_box_conversions_and_torch_iou_by_hand():
    import torch

    from robustbench3d.victims.yolo.boxes import box_iou as torch_iou
    from robustbench3d.victims.yolo.boxes import box_iou_np, cxcywh_to_xyxy, wh_iou, xyxy_to_cxcywh

    xyxy = torch.tensor([[[10.0, 20.0, 40.0, 60.0]]])
    assert xyxy_to_cxcywh(xyxy).tolist() == [[[25.0, 40.0, 30.0, 40.0]]]
    assert cxcywh_to_xyxy(xyxy_to_cxcywh(xyxy)).tolist() == xyxy.tolist()
    a = torch.tensor([[0.0, 0.0, 0.5, 0.5]])
    b = torch.tensor([[0.0, 0.0, 0.5, 0.25], [2.0, 2.0, 3.0, 3.0]])
    assert torch_iou(a, b)[0].tolist() == pytest.approx([0.5, 0.0])        # sub-pixel areas, disjoint boxes
    assert torch_iou(torch.tensor([[0.0, 0, 2, 2]]), torch.tensor([[1.0, 0, 0, 1]]))[0, 0].item() == 0.0
    assert box_iou_np(a.numpy(), b.numpy()) == pytest.approx(torch_iou(a, b).numpy())
    # same-centre IoU of shapes: 2x8 vs 4x4: intersection 2x4 = 8, union 16 + 16 - 8 = 24
    assert wh_iou(torch.tensor([[2.0, 8.0]]), torch.tensor([[4.0, 4.0], [2.0, 8.0]]))[0].tolist() == pytest.approx(
        [1 / 3, 1.0])
    # 4x2 vs 2x8: intersection min(4, 2)·min(2, 8) = 4, union 8 + 16 - 4 = 20
    assert wh_iou(torch.tensor([[4.0, 2.0]]), torch.tensor([[2.0, 8.0]]))[0, 0].item() == pytest.approx(0.2)


def test_numpy_iou_of_disjoint_and_tiny_boxes():
    a = np.array([[0.0, 0.0, 1.0, 1.0]], dtype=np.float32)
    b = np.array([[2.0, 2.0, 3.0, 3.0], [0.0, 0.0, 0.5, 0.25], [0.0, 0.0, -1.0, 1.0]], dtype=np.float32)
    iou = box_iou(a, b)
    assert iou[0].tolist() == pytest.approx([0.0, 0.125, 0.0]) and iou.dtype == np.float64
    assert box_iou(b[2:], b[2:])[0, 0] == 0.0    # a box with negative width has no area
    assert box_iou(np.array([[0.0, 0, 0.5, 1]]), np.array([[0.0, 0, 0.5, 1]]))[0, 0] == 1.0
    # overlapping columns, disjoint rows: the negative height is clipped too (IoU 0, not negative)
    assert box_iou(np.array([[0.0, 0, 2, 1]]), np.array([[0.0, 2, 2, 3]]))[0, 0] == 0.0


def test_nms_outputs_are_int64_even_when_empty_and_ties_across_classes_are_stable():
    from robustbench3d.victims.yolo.postprocess import batched_nms, batched_nms_clusters

    assert nms(np.zeros((0, 4)), np.zeros(0), 0.5).dtype == np.int64
    assert batched_nms(np.zeros((0, 4)), np.zeros(0), np.zeros(0, np.int64), 0.5).dtype == np.int64
    n = 40                                  # disjoint boxes, two classes, pairwise tied scores
    boxes = np.stack([np.arange(n) * 10.0, np.zeros(n), np.arange(n) * 10.0 + 5, np.ones(n) * 5], axis=1)
    scores = np.repeat(np.arange(n // 2, 0, -1) / 100.0, 2)
    classes = np.tile([1, 0], n // 2)
    kept = [int(c[0]) for c in batched_nms_clusters(boxes, scores, classes, 0.5)]
    # clusters come per class (class 0 first), then a stable sort by score keeps that order in ties
    assert kept == [j for pair in zip(range(1, n, 2), range(0, n, 2), strict=True) for j in pair]


def test_prior_scores_and_heads_are_float32():
    score, cls = prior_scores(np.array([0.0]), np.array([[0.0, 1.0]]))  # float64 logits
    assert score.dtype == np.float32 and cls.dtype == np.int64
    heads = [np.zeros((1, 18, 12, 40)), np.zeros((1, 18, 24, 80))]         # float64 heads
    boxes, obj, cls_logit = decode_heads(heads, MINI)
    assert boxes.dtype == obj.dtype == cls_logit.dtype == np.float32
    with pytest.raises(ValueError, match="does not fit"):               # stride 32 across, 16 down
        decode_heads([np.zeros((1, 18, 12, 20), np.float32), heads[1]], MINI)


def test_select_detections_threshold_top_k_and_clipping():
    from robustbench3d.victims.yolo.postprocess import PRE_NMS_TOP_K

    geo = letterbox_geometry((1242, 375), (960, 288))
    cfg = replace(MINI, input_size=(960, 288), conf_threshold=0.25, nms_threshold=0.4, max_detections=2000)
    # a score of exactly the threshold is kept: σ(0)·σ(0) = 1/4
    one = select_detections(np.array([[480.0, 144.0, 10.0, 10.0]]), np.zeros(1), np.zeros((1, 1)), geo, cfg)
    assert len(one.boxes) == 1 and one.scores[0] == 0.25
    none = select_detections(np.array([[480.0, 144.0, 10.0, 10.0]]), np.full(1, -5.0), np.zeros((1, 1)), geo, cfg)
    assert none.boxes.shape == (0, 4) and none.classes.dtype == np.int64
    # boxes beyond every image edge are clipped to [0, W-1] x [0, H-1]
    edge = select_detections(np.array([[2.0, 280.0, 10.0, 30.0]]), np.zeros(1), np.zeros((1, 1)), geo, cfg)
    assert edge.boxes[0].tolist() == pytest.approx([0.0, (265 * 375 / 288), (7 - 3) * 1242 / 954, 374.0])
    # more than PRE_NMS_TOP_K priors above the threshold: the top-scoring ones enter NMS
    n = PRE_NMS_TOP_K + 1
    cx = 3 + (np.arange(n) % 100) * 9.0
    cy = (np.arange(n) // 100) * 20.0 + 10
    many = np.stack([cx, cy, np.full(n, 4.0), np.full(n, 4.0)], axis=1)
    obj = np.linspace(0.0, 3.0, n)[::-1].copy()        # prior 0 scores highest, prior n-1 lowest
    det = select_detections(many, obj, np.full((n, 1), 5.0), geo, cfg)
    assert len(det.boxes) == PRE_NMS_TOP_K
    assert det.scores.min() > prior_scores(obj[-1:], np.full((1, 1), 5.0))[0][0]   # the lowest was cut


def test_detect_images_with_a_stub_network():
    """Letterbox -> network -> decoding -> detections, with a network whose output is known: one
    confident prior (head 0, anchor 4 = 96 x 62, row 3) at column 6 for a dark image, 10 for a bright one."""
    from robustbench3d.victims.yolo.postprocess import detect_images, image_priors

    calls = []

    def run_heads(x):
        calls.append(x.shape)
        heads = [np.full((len(x), 18, 12, 40), -10.0, np.float32), np.full((len(x), 18, 24, 80), -10.0, np.float32)]
        for b in range(len(x)):
            col = 10 if x[b].mean() > 0.5 else 6
            heads[0][b, 6:12, 3, col] = [0.0, 0.0, 0.0, 0.0, 5.0, 5.0]
        return heads

    dark, bright = np.zeros((96, 320, 3), np.uint8), np.full((96, 320, 3), 255, np.uint8)   # scale 2, no pad
    cfg = replace(MINI, conf_threshold=0.5)
    dets = detect_images([dark, bright], run_heads, cfg)
    assert calls == [(1, 3, 192, 640), (1, 3, 192, 640)]        # batch_size 1 by default
    # centre ((0.5 + col)·16, 3.5·16) = (104 or 168, 56), size 96 x 62, halved back to the image
    assert dets[0].boxes == pytest.approx(np.array([[28.0, 12.5, 76.0, 43.5]]))
    assert dets[1].boxes == pytest.approx(np.array([[60.0, 12.5, 108.0, 43.5]]))
    assert dets[0].scores == pytest.approx([float(sigmoid(np.float32(5.0))) ** 2])
    calls.clear()
    again = detect_images([dark, bright], run_heads, cfg, batch_size=2)
    assert calls == [(2, 3, 192, 640)]
    assert all(np.array_equal(a.boxes, b.boxes) for a, b in zip(again, dets, strict=True))
    # flip TTA: the mirrored view's priors are mirrored back (x -> 640 - x) and pooled with the plain ones
    tta = replace(cfg, flip_tta=True)
    (boxes, obj, _, geo), = image_priors([dark], run_heads, tta)
    p = 3 * 12 * 40 + 3 * 24 * 80
    assert len(obj) == 2 * p and geo.resized == (640, 192)
    assert boxes[(12 + 3) * 40 + 6, 0] == pytest.approx(104.0)
    assert boxes[p + (12 + 3) * 40 + 6, 0] == pytest.approx(640 - 104.0)
    both = detect_images([dark], run_heads, tta)[0]
    assert sorted(both.boxes[:, 0].tolist()) == pytest.approx([28.0, 320 - 76.0])


def test_flip_tta_sees_the_mirrored_image_and_padding_uses_the_fill():
    """A network that puts its one confident prior at the brightest input column: the mirrored
    view of a left-bright image answers on the right, and maps back there."""
    from robustbench3d.victims.yolo.postprocess import image_priors

    seen = []

    def run_heads(x):
        seen.append(x)
        heads = [np.full((len(x), 18, 12, 40), -10.0, np.float32), np.full((len(x), 18, 24, 80), -10.0, np.float32)]
        for b in range(len(x)):
            col = int(np.argmax(x[b].mean(axis=(0, 1)))) // 16
            heads[0][b, 6:12, 3, col] = [0.0, 0.0, 0.0, 0.0, 5.0, 5.0]
        return heads

    img = np.zeros((96, 320, 3), np.uint8)
    img[:, :100] = 255                                      # bright left: input columns 0..199
    cfg = replace(MINI, conf_threshold=0.5, flip_tta=True)
    (boxes, obj, _, _), = image_priors([img], run_heads, cfg)
    p = 3 * 12 * 40 + 3 * 24 * 80
    top = int(np.argmax(obj[p:]))
    assert top == (12 + 3) * 40 + 27                        # mirrored: bright columns 440..639 -> cell 27
    assert boxes[p + top, 0] == pytest.approx(640 - 27.5 * 16)
    seen.clear()
    narrow = np.zeros((96, 300, 3), np.uint8)               # scale 2 -> 600 px wide, padded 20 px a side
    image_priors([narrow], run_heads, replace(cfg, fill=0.25))             # plain and mirrored views
    assert len(seen) == 2 and all(v[0, :, :, :20].min() == v[0, :, :, :20].max() == 0.25 for v in seen)


def test_pre_nms_top_k_breaks_score_ties_by_index():
    from robustbench3d.victims.yolo.postprocess import PRE_NMS_TOP_K

    geo = letterbox_geometry((1242, 375), (960, 288))
    cfg = replace(MINI, input_size=(960, 288), conf_threshold=0.01, nms_threshold=0.4, max_detections=2000)
    n = PRE_NMS_TOP_K + 50
    cx = 3 + (np.arange(n) % 100) * 9.0
    cy = (np.arange(n) // 100) * 20.0 + 10
    many = np.stack([cx, cy, np.full(n, 4.0), np.full(n, 4.0)], axis=1)
    obj = np.random.default_rng(0).integers(0, 3, n).astype(np.float64)   # three score levels, many ties
    det = select_detections(many, obj, np.full((n, 1), 5.0), geo, cfg)
    order = sorted(range(n), key=lambda j: (-obj[j], j))[:PRE_NMS_TOP_K]   # stable: lower index first
    want = geo.to_image(np.stack([cx - 2, cy - 2, cx + 2, cy + 2], axis=1)[sorted(order)])
    want = np.clip(want, 0, [1241, 374, 1241, 374])
    got = det.boxes[np.lexsort((det.boxes[:, 0], det.boxes[:, 1]))]
    assert got == pytest.approx(want[np.lexsort((want[:, 0], want[:, 1]))])
