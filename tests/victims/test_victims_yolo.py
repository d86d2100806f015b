"""YOLO 2D stage (reference §2): layouts, decoding, IoU / NMS against brute force, target
assignment on hand-made boxes, loss stability, k-means anchors, letterboxing."""

from __future__ import annotations

import itertools
from dataclasses import replace

import numpy as np
import pytest
import torch

from robustbench3d.victims.yolo.anchors import kmeans_anchors
from robustbench3d.victims.yolo.boxes import batched_nms, box_iou, nms
from robustbench3d.victims.yolo.config import MINI, MINI3, TINY, V3
from robustbench3d.victims.yolo.detector import YoloDetector, candidates_for_targets
from robustbench3d.victims.yolo.letterbox import letterbox, letterbox_geometry
from robustbench3d.victims.yolo.loss import build_targets, yolo_loss
from robustbench3d.victims.yolo.model import build_model, conv_layer_count, flatten

torch.set_num_threads(1)


def test_mini_layout_heads_and_size():
    net = build_model("mini").eval()
    assert MINI.input_size == (640, 192) and net.head_strides == [16, 8]
    with torch.no_grad():
        heads = net(torch.zeros(1, 3, 192, 640))
    assert [tuple(h.shape) for h in heads] == [(1, 18, 12, 40), (1, 18, 24, 80)]  # 3·(5+1) channels
    n = sum(p.numel() for p in net.parameters())
    assert 0.6e6 <= n <= 1.2e6  # §2.3 budget


def test_mini3_is_mini_plus_a_stride_32_head():
    mini, mini3 = build_model("mini", seed=4), build_model("mini3", seed=4).eval()
    assert MINI3.input_size == (960, 288) and mini3.head_strides == [16, 8, 32]
    assert mini3.specs[: len(mini.specs)] == mini.specs
    assert all(torch.equal(v, mini3.state_dict()[k]) for k, v in mini.state_dict().items())  # same seeded init
    with torch.no_grad():
        heads = mini3(torch.zeros(1, 3, 288, 960))
    assert [tuple(h.shape) for h in heads] == [(1, 18, 18, 60), (1, 18, 36, 120), (1, 18, 9, 30)]
    assert sorted(a for m in mini3.head_masks for a in m) == list(range(9))


def test_tiny_and_v3_layouts_build_and_run():
    tiny80 = build_model(replace(TINY, class_names=tuple(f"c{i}" for i in range(80))))
    assert conv_layer_count(tiny80) == 13 and tiny80.head_strides == [32, 16]
    assert sum(p.numel() for p in tiny80.parameters()) == pytest.approx(8.85e6, rel=0.005)  # reference §2.2
    v3 = build_model("v3").eval()
    assert conv_layer_count(v3) == 75 and v3.head_strides == [32, 16, 8]  # reference §2.1
    with torch.no_grad():
        assert [tuple(h.shape) for h in build_model("tiny").eval()(torch.zeros(1, 3, 64, 64))] == [
            (1, 18, 2, 2), (1, 18, 4, 4)]
        assert [tuple(h.shape) for h in v3(torch.zeros(1, 3, 64, 64))] == [(1, 18, 2, 2), (1, 18, 4, 4), (1, 18, 8, 8)]
    assert TINY.anchors[0] == (10.0, 14.0) and V3.anchors[-1] == (373.0, 326.0)


def test_decoding_of_zero_outputs():
    """t = 0 everywhere: centre = (0.5 + cell)·stride, size = the anchor, probabilities 0.5."""
    net = build_model("mini")
    heads = [torch.zeros(1, 18, 12, 40), torch.zeros(1, 18, 24, 80)]
    pred = flatten(heads, net)
    assert pred.boxes.shape == (1, 3 * 12 * 40 + 3 * 24 * 80, 4)
    # prior (head 0, anchor slot 1 = anchor 4, row 3, column 6)
    p = (1 * 12 + 3) * 40 + 6
    assert pred.boxes[0, p].tolist() == pytest.approx([6.5 * 16, 3.5 * 16, *MINI.anchors[4]])
    assert int(pred.anchor[p]) == 4 and pred.grid[p].tolist() == [6, 3] and float(pred.stride[p]) == 16
    q = 3 * 12 * 40 + (2 * 24 + 10) * 80 + 7  # head 1, anchor slot 2 = anchor 2, row 10, column 7
    assert pred.boxes[0, q].tolist() == pytest.approx([7.5 * 8, 10.5 * 8, *MINI.anchors[2]])
    # channel layout: t_x of anchor slot 1 is channel 6 of the head
    heads[0][0, 6 + 0, 3, 6] = 2.0
    heads[0][0, 6 + 4, 3, 6] = -3.0
    pred = flatten(heads, net)
    assert float(pred.raw[0, p, 0]) == 2.0 and float(pred.obj_logit[0, p]) == -3.0


def brute_iou(a, b) -> float:
    iw = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    ih = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = iw * ih
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / union if union > 0 else 0.0


def brute_nms(boxes, scores, thr) -> list[int]:
    remaining = sorted(range(len(boxes)), key=lambda i: (-scores[i], i))
    keep = []
    while remaining:
        i = remaining.pop(0)
        keep.append(i)
        remaining = [j for j in remaining if brute_iou(boxes[i], boxes[j]) <= thr]
    return keep


def test_iou_hand_values():
    a = torch.tensor([[0.0, 0, 2, 2]])
    b = torch.tensor([[1.0, 1, 3, 3], [2.0, 2, 4, 4], [0, 0, 2, 2], [0.5, 0.5, 1.5, 1.5]])
    assert box_iou(a, b)[0].tolist() == pytest.approx([1 / 7, 0.0, 1.0, 0.25])
    assert float(box_iou(torch.tensor([[1.0, 1, 1, 1]]), torch.tensor([[1.0, 1, 1, 1]]))) == 0.0  # guarded


@pytest.mark.parametrize("seed", range(5))
def test_nms_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 100, (60, 2))
    wh = rng.uniform(5, 40, (60, 2))
    boxes = np.concatenate([xy, xy + wh], axis=1)
    scores = rng.integers(0, 10, 60) / 10.0  # many ties
    for thr in (0.0, 0.3, 0.5, 0.9):
        got = nms(torch.tensor(boxes), torch.tensor(scores), thr).tolist()
        assert got == brute_nms(boxes.tolist(), scores.tolist(), thr)
    classes = rng.integers(0, 3, 60)
    got = batched_nms(torch.tensor(boxes), torch.tensor(scores), torch.tensor(classes), 0.4).tolist()
    expect = list(itertools.chain.from_iterable(
        [int(np.flatnonzero(classes == c)[k]) for k in brute_nms(boxes[classes == c].tolist(),
                                                                   scores[classes == c].tolist(), 0.4)]
        for c in range(3)))
    assert sorted(got) == sorted(expect)
    assert np.all(np.diff(scores[got]) <= 0)


def test_assignment_hand_made():
    """Two cars: one shaped like anchor 3 (stride-16 head), one like anchor 0 (stride-8 head);
    a Van as an ignore box. Network outputs are zero, so every prior decodes to its anchor box
    at its cell centre."""
    net = build_model("mini")
    pred = flatten([torch.zeros(1, 18, 12, 40), torch.zeros(1, 18, 24, 80)], net)
    car_a = torch.tensor([[100.0 - 30, 50 - 20, 100 + 30, 50 + 20]])  # 60x40 = anchor 3, centre (100, 50)
    car_b = torch.tensor([[300.0 - 7, 120 - 5, 300 + 7, 120 + 5]])   # 14x10 = anchor 0, centre (300, 120)
    van = torch.tensor([[500.0, 20, 596, 82]])                        # 96x62 = anchor 4 shape
    t = build_targets(pred, MINI, [torch.cat([car_a, car_b])], [torch.tensor([0, 0])], [van])
    assert MINI.anchors[3] == (60.0, 40.0) and MINI.anchors[0] == (14.0, 10.0) and MINI.anchors[4] == (96.0, 62.0)
    p_a = (0 * 12 + 3) * 40 + 6                       # anchor slot 0 of head 0, row 50//16=3, col 100//16=6
    p_b = 3 * 12 * 40 + (0 * 24 + 15) * 80 + 37       # anchor slot 0 of head 1, row 120//8=15, col 300//8=37
    assert t.obj_index.tolist() == [p_a, p_b]
    assert np.allclose(t.txy.numpy(), [[100 / 16 - 6, 50 / 16 - 3], [300 / 8 - 37, 120 / 8 - 15]])
    assert np.allclose(t.twh.numpy(), 0.0, atol=1e-6)  # GT size == anchor size
    assert t.cls.tolist() == [[1.0], [1.0]]
    # no-object set: everything except assigned priors and priors overlapping a GT / ignore box > 0.5
    boxes = pred.boxes[0]
    xyxy = torch.cat([boxes[:, :2] - boxes[:, 2:] / 2, boxes[:, :2] + boxes[:, 2:] / 2], dim=1).tolist()
    gts = [car_a[0].tolist(), car_b[0].tolist(), van[0].tolist()]
    ignored = {i for i, b in enumerate(xyxy) if max(brute_iou(b, g) for g in gts) > MINI.ignore_thresh}
    p_van = (1 * 12 + 51 // 16) * 40 + 548 // 16    # the Van's best prior (anchor 4, slot 1 of head 0)
    expect_noobj = set(range(len(xyxy))) - ignored - {p_a, p_b, p_van}
    assert set(torch.nonzero(t.noobj[0]).reshape(-1).tolist()) == expect_noobj
    assert p_van not in t.obj_index.tolist()


def test_loss_is_stable_and_zero_safe():
    net = build_model("mini")
    heads = [torch.zeros(2, 18, 12, 40, requires_grad=True), torch.zeros(2, 18, 24, 80, requires_grad=True)]
    with torch.no_grad():
        heads[0][:, 4::6] = 1e4     # saturated objectness logits
        heads[1][:, 4::6] = -1e4
    pred = flatten(heads, net)
    gt = [torch.tensor([[100.0, 30, 160, 70]]), torch.zeros(0, 4)]  # second image: no objects
    t = build_targets(pred, MINI, gt, [torch.tensor([0]), torch.zeros(0, dtype=torch.int64)])
    total, terms = yolo_loss(pred, t, MINI)
    total.backward()
    assert torch.isfinite(total) and all(torch.isfinite(v) for v in terms.values())
    assert all(torch.isfinite(h.grad).all() for h in heads)
    assert terms["noobj"].item() > 1e3  # the saturated wrong logits are penalised linearly, not log(0)
    # no targets anywhere: coordinate / class terms are exactly zero
    t0 = build_targets(pred, MINI, [torch.zeros(0, 4)] * 2, [torch.zeros(0, dtype=torch.int64)] * 2)
    _, terms0 = yolo_loss(pred, t0, MINI)
    assert terms0["xy"].item() == terms0["wh"].item() == terms0["cls"].item() == terms0["obj"].item() == 0.0


def test_kmeans_recovers_known_shapes():
    rng = np.random.default_rng(0)
    centres = np.array([[20.0, 12.0], [60.0, 40.0], [150.0, 90.0]])
    wh = np.concatenate([c * rng.uniform(0.95, 1.05, (200, 2)) for c in centres])
    anchors, mean_iou = kmeans_anchors(wh, 3, np.random.default_rng(1))
    assert np.allclose(anchors, centres, rtol=0.05)
    assert mean_iou > 0.85
    again, _ = kmeans_anchors(wh, 3, np.random.default_rng(1))
    assert np.array_equal(anchors, again)
    with pytest.raises(ValueError):
        kmeans_anchors(wh[:2], 3, np.random.default_rng(0))


def test_letterbox_geometry_and_gradient():
    geo = letterbox_geometry((1242, 375), (640, 192))
    assert geo.resized == (636, 192) and geo.pad == (2, 0)  # s = min(640/1242, 192/375) = 0.512
    boxes = np.array([[100.0, 50.0, 300.0, 200.0]])
    assert np.allclose(geo.to_image(geo.to_input(boxes)), boxes)
    assert np.allclose(geo.to_input(boxes)[0, :2], [100 * 636 / 1242 + 2, 50 * 192 / 375])
    img = torch.rand(1, 3, 375, 1242, requires_grad=True)
    x, _ = letterbox(img, (640, 192))
    assert x.shape == (1, 3, 192, 640) and x[0, 0, 0, 0].item() == 0.5  # padding column
    x[..., 100:120, 200:260].sum().backward()
    g = img.grad
    assert torch.isfinite(g).all() and g[..., 190:240, 380:510].abs().sum() > 0 and g[..., :100, :].abs().sum() == 0


def test_detector_postprocess_maps_to_original_pixels():
    net = build_model("mini")
    det = YoloDetector(net)
    heads = [torch.full((1, 18, 12, 40), -10.0), torch.full((1, 18, 24, 80), -10.0)]
    p = (1 * 12 + 3) * 40 + 6
    heads[0][0, 6:12, 3, 6] = torch.tensor([0.0, 0.0, 0.0, 0.0, 5.0, 5.0])  # one confident prior
    pred = flatten(heads, net)
    geo = letterbox_geometry((1242, 375), (640, 192))
    out = det.postprocess(pred, geo)[0]
    assert len(out.boxes) == 1
    cx, cy, w, h = pred.boxes[0, p].tolist()
    expect = geo.to_image(np.array([[cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2]]))
    assert np.allclose(out.boxes, expect)
    assert out.scores[0] == pytest.approx(float(torch.sigmoid(torch.tensor(5.0)) ** 2))
    c = candidates_for_targets(pred, geo, torch.tensor(expect), 0.9, 0)
    assert p in c["prior"].tolist() and float(c["iou"][c["prior"].tolist().index(p)]) == pytest.approx(1.0)


def test_multi_assignment_by_hand():
    """A 60x40 car with ``assign="multi"``: every anchor whose w and h ratios are < 4 trains, each
    in its own head's cell; anchor 0 (14x10: ratio 60/14 = 4.29) does not."""
    from robustbench3d.victims.yolo.config import LOSSES

    cfg = replace(MINI, **LOSSES["iou"])
    net = build_model(cfg)
    pred = flatten([torch.zeros(1, 18, 12, 40), torch.zeros(1, 18, 24, 80)], net)
    car = torch.tensor([[100.0 - 30, 50 - 20, 100 + 30, 50 + 20]])
    t = build_targets(pred, cfg, [car], [torch.tensor([0])])

    def prior(a: int) -> int:
        if a >= 3:   # head 0: stride 16, 12x40, anchors 3, 4, 5
            return ((a - 3) * 12 + 50 // 16) * 40 + 100 // 16
        return 3 * 12 * 40 + (a * 24 + 50 // 8) * 80 + 100 // 8

    assert t.obj_index.tolist() == sorted(prior(a) for a in (1, 2, 3, 4, 5))
    assert np.allclose(t.box.numpy(), car.numpy().repeat(5, axis=0))
    anchors = np.array(MINI.anchors)
    order = np.argsort([prior(a) for a in (1, 2, 3, 4, 5)])
    expect_twh = np.log(np.array([60.0, 40.0]) / anchors[[1, 2, 3, 4, 5]])[order]
    assert np.allclose(t.twh.numpy(), expect_twh, atol=1e-6)
    # the faithful mode keeps only the best-shaped anchor
    assert build_targets(pred, MINI, [car], [torch.tensor([0])]).obj_index.tolist() == [prior(3)]


def test_multi_assignment_conflict_keeps_better_shape():
    """Two cars centred in the same cells: a prior both claim goes to the better-shaped car."""
    from robustbench3d.victims.yolo.config import LOSSES

    cfg = replace(MINI, **LOSSES["iou"])
    pred = flatten([torch.zeros(1, 18, 12, 40), torch.zeros(1, 18, 24, 80)], build_model(cfg))
    a = torch.tensor([[100.0 - 30, 50 - 20, 100 + 30, 50 + 20]])   # 60x40: anchor 3 exactly
    b = torch.tensor([[100.0 - 48, 50 - 31, 100 + 48, 50 + 31]])   # 96x62: anchor 4 exactly
    t = build_targets(pred, cfg, [torch.cat([a, b])], [torch.tensor([0, 0])])
    p3 = (0 * 12 + 3) * 40 + 6
    p4 = (1 * 12 + 3) * 40 + 6
    rows = {k: i for i, k in enumerate(t.obj_index.tolist())}
    assert torch.equal(t.box[rows[p3]], a[0]) and torch.equal(t.box[rows[p4]], b[0])


def test_giou_hand_values_and_degenerate_gradients():
    from robustbench3d.victims.yolo.loss import giou

    a = torch.tensor([[0.0, 0, 2, 2], [0, 0, 1, 1], [0, 0, 1, 1]])
    b = torch.tensor([[1.0, 1, 3, 3], [2, 0, 3, 1], [0, 0, 1, 1]])
    iou, g = giou(a, b)
    assert np.allclose(iou.numpy(), [1 / 7, 0, 1])
    assert np.allclose(g.numpy(), [1 / 7 - 2 / 9, -1 / 3, 1])
    for k in range(3):
        assert iou[k].item() == pytest.approx(brute_iou(a[k].tolist(), b[k].tolist()))
    # zero-size and coincident zero-size boxes: finite values and gradients
    z = torch.tensor([[5.0, 5, 5, 5], [1, 1, 1, 1]], requires_grad=True)
    iou, g = giou(z, torch.tensor([[5.0, 5, 5, 5], [0, 0, 2, 2]]))
    (g.sum() + iou.sum()).backward()
    assert torch.isfinite(g).all() and torch.isfinite(z.grad).all()


def test_iou_objectness_target_is_the_decoded_iou():
    """With ``obj_target="iou"`` the assigned prior's objectness BCE target is the IoU of its
    decoded box (here its anchor box at the cell centre) with the GT."""
    from robustbench3d.victims.yolo.config import LOSSES

    cfg = replace(MINI, **{**LOSSES["iou"], "assign": "best"})
    heads = [torch.zeros(1, 18, 12, 40), torch.zeros(1, 18, 24, 80)]
    pred = flatten(heads, build_model(cfg))
    car = torch.tensor([[100.0 - 20, 50 - 20, 100 + 40, 50 + 20]])  # 60x40, centre (110, 50)
    t = build_targets(pred, cfg, [car], [torch.tensor([0])])
    _, terms = yolo_loss(pred, t, cfg)
    decoded = [6 * 16 + 8 - 30, 3 * 16 + 8 - 20, 6 * 16 + 8 + 30, 3 * 16 + 8 + 20]  # anchor 3 at cell (6, 3)
    target = brute_iou(decoded, car[0].tolist())
    expect = -(target * np.log(0.5) + (1 - target) * np.log(0.5))  # logit 0 -> p = 0.5
    assert terms["obj"].item() == pytest.approx(expect, rel=1e-6)
    assert terms["box"].item() > 0 and terms["xy"].item() == terms["wh"].item() == 0.0


def test_nms_clusters_and_merge_by_hand():
    from robustbench3d.victims.yolo.postprocess import merge_clusters, nms_clusters

    boxes = np.array([[0.0, 0, 10, 10], [1, 0, 11, 10], [50, 50, 60, 60], [0, 1, 10, 11], [100, 0, 101, 1]])
    scores = np.array([0.9, 0.6, 0.8, 0.3, 0.7])
    clusters = nms_clusters(boxes, scores, 0.5)
    assert [c.tolist() for c in clusters] == [[0, 1, 3], [2], [4]]
    merged = merge_clusters(boxes, scores, clusters)
    assert np.allclose(merged[0], (0.9 * boxes[0] + 0.6 * boxes[1] + 0.3 * boxes[3]) / 1.8)
    assert np.allclose(merged[1:], boxes[[2, 4]], rtol=0, atol=1e-12)
    # the kept boxes are those of plain NMS, which matches brute force
    assert [c[0] for c in clusters] == brute_nms(boxes.tolist(), scores.tolist(), 0.5)
