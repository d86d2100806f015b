"""Numerics at the extremes: never NaN or inf, a clear error where the input is invalid.

IoU of the evaluator (eval/iou.py) and of the attack's box term (attacks/box_iou.py) on degenerate, huge,
far (1e4 m) and tiny (1e-6 m) boxes and yaw at +-pi; Moller-Trumbore (sensors/raycast.py) on grazing rays,
edges, vertices, zero-area faces and rays from inside a closed mesh; the attack losses at p -> 0 and 1,
with every / no point masked and for a car without object return; the victim heads' sigmoid and softmax
at overflowing logits; AP without ground truth, without detections and with tied scores. Expected values
are hand-computed (areas of rectangles, distances to a cube's faces, AP of constant precision).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from robustbench3d.attacks.box_iou import bev_iou_torch
from robustbench3d.attacks.losses import (
    box_car_loss,
    image_target_losses,
    lidar_car_loss,
    max_object_margin,
    neg_log_one_minus_product,
)
from robustbench3d.errors import DataFormatError
from robustbench3d.eval.bootstrap import FrameBootstrap, ap_intervals
from robustbench3d.eval.iou import bev_iou, bev_overlap, box3d_iou
from robustbench3d.eval.kitti_eval import evaluate
from robustbench3d.kitti import Labels
from robustbench3d.kitti.labels import parse_labels
from robustbench3d.sensors.raycast import cast_rays
from robustbench3d.victims.base import ObjectnessCandidates
from robustbench3d.victims.fpointnet.glue import mask_centroid
from robustbench3d.victims.fpointnet.model import build_model
from robustbench3d.victims.fpointnet.to_kitti import _softmax
from robustbench3d.victims.yolo.postprocess import sigmoid

torch.set_num_threads(1)


# ---- IoU -------------------------------------------------------------------------------------------
def box7(x: float, z: float, length: float, width: float, ry: float, h: float = 1.5, y: float = 1.6) -> np.ndarray:
    """Evaluator layout h, w, l, x, y, z, ry."""
    return np.array([[h, width, length, x, y, z, ry]], dtype=np.float64)


def box5(b7: np.ndarray) -> torch.Tensor:
    """attacks.box_iou layout x, z, l, w, ry."""
    _h, w, length, x, _y, z, ry = b7[0]
    return torch.tensor([x, z, length, w, ry], dtype=torch.float64)


def both_ious(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    return float(bev_iou(a, b)[0, 0]), float(bev_iou_torch(box5(a), box5(b)))


# Two 4 x 2 m boxes, the second shifted by half its length: intersection 2 x 2 = 4, union 8 + 8 - 4 = 12.
@pytest.mark.parametrize(("scale", "offset"), [(1.0, 0.0), (1.0, 1e4), (1e-6, 0.0), (1e-6, 1e4), (1e5, 0.0),
                                               (1e5, 1e4)])
@pytest.mark.parametrize("ry", [0.0, math.pi, -math.pi, math.pi / 2, -math.pi / 2 + 1e-12])
def test_half_shifted_boxes_give_one_third_at_any_scale_place_and_yaw(scale: float, offset: float, ry: float) -> None:
    c, s = math.cos(ry), math.sin(ry)
    shift = 2.0 * scale  # half the length, along the box's own length axis (x = c u, z = -s u)
    a = box7(offset, offset, 4 * scale, 2 * scale, ry)
    b = box7(offset + c * shift, offset - s * shift, 4 * scale, 2 * scale, ry)
    tol = 1e-9 if offset == 0 or scale >= 1 else 1e-4  # 1e-6 m boxes at 1e4 m: centres carry ~2e-12 m error
    for got in both_ious(a, b):
        assert got == pytest.approx(1 / 3, abs=tol)
    assert both_ious(a, a) == (pytest.approx(1.0, abs=1e-12), pytest.approx(1.0, abs=1e-12))


def test_yaw_plus_and_minus_pi_are_the_same_box_and_a_quarter_turn_is_not() -> None:
    for got in both_ious(box7(3, 20, 4, 2, math.pi), box7(3, 20, 4, 2, -math.pi)):
        assert got == pytest.approx(1.0, abs=1e-12)
    for got in both_ious(box7(3, 20, 4, 2, math.pi), box7(3, 20, 4, 2, 0.0)):  # 180 deg: same footprint
        assert got == pytest.approx(1.0, abs=1e-12)
    for got in both_ious(box7(3, 20, 4, 2, math.pi / 2), box7(3, 20, 4, 2, -math.pi)):  # cross: 2x2 / (8+8-4)
        assert got == pytest.approx(4 / 12, abs=1e-12)


@pytest.mark.parametrize("degenerate", [(0.0, 2.0), (4.0, 0.0), (0.0, 0.0), (-4.0, 2.0)])
def test_degenerate_boxes_are_finite(degenerate: tuple[float, float]) -> None:
    length, width = degenerate
    a, b = box7(0, 10, length, width, 0.3), box7(0, 10, 4, 2, 0.3)
    for got in both_ious(a, b) + both_ious(a, a):
        assert math.isfinite(got) and 0.0 <= got <= 1.0
    if length == 0 or width == 0:  # zero area: nothing overlaps
        assert max(both_ious(a, b)) == 0.0
    else:  # negative sizes are taken by magnitude (DontCare lines carry -1)
        assert min(both_ious(a, b)) == pytest.approx(1.0)
    assert box3d_iou(box7(0, 10, 4, 2, 0, h=0.0), box7(0, 10, 4, 2, 0))[0, 0] == 0.0  # zero height: no volume


def test_touching_and_far_apart_boxes_overlap_zero() -> None:
    for got in both_ious(box7(0, 10, 4, 2, 0), box7(4, 10, 4, 2, 0)):  # share an edge
        assert got == pytest.approx(0.0, abs=1e-15)
    for got in both_ious(box7(-1e4, -1e4, 4, 2, 0), box7(1e4, 1e4, 4, 2, 0)):
        assert got == 0.0


def test_non_finite_boxes_never_leak_nan_and_label_files_refuse_them() -> None:
    bad = box7(np.nan, 10, 4, 2, 0)
    assert bev_overlap(bad, box7(0, 10, 4, 2, 0))[0] == 0.0
    for value in ("nan", "inf", "-inf"):  # what reaches the evaluator is finite: label files are checked
        with pytest.raises(DataFormatError, match=r"000007\.txt"):
            parse_labels(f"Car 0.00 0 0.00 100 100 200 180 1.5 1.6 {value} 0.0 1.6 10.0 0.0\n", "000007.txt",
                         scored=False)
    with pytest.raises(ValueError, match="boxes must be"):
        bev_iou_torch(torch.zeros(4, dtype=torch.float64), torch.zeros(5, dtype=torch.float64))


finite = st.floats(allow_nan=False, allow_infinity=False)
sizes = st.floats(min_value=1e-6, max_value=1e4)
places = st.floats(min_value=-1e4, max_value=1e4)
yaws = st.floats(min_value=-math.pi, max_value=math.pi)


@settings(max_examples=200, deadline=None, derandomize=True)  # the same examples on every run (a seeded search)
@given(x=places, z=places, la=sizes, wa=sizes, ry_a=yaws, dx=st.floats(-2, 2), dz=st.floats(-2, 2),
       lb_ratio=st.floats(0.25, 4), wb_ratio=st.floats(0.25, 4), ry_b=yaws, turn=yaws)
def test_iou_properties(x, z, la, wa, ry_a, dx, dz, lb_ratio, wb_ratio, ry_b, turn) -> None:
    """In [0, 1], symmetric, torch = evaluator, invariant under rotating the whole scene about the origin."""
    scale = max(la, wa)
    a = box7(x, z, la, wa, ry_a)
    b = box7(x + dx * scale, z + dz * scale, la * lb_ratio, wa * wb_ratio, ry_b)
    ab, ba = float(bev_iou(a, b)[0, 0]), float(bev_iou(b, a)[0, 0])
    t = float(bev_iou_torch(box5(a), box5(b)))
    assert 0.0 <= ab <= 1.0 and 0.0 <= t <= 1.0
    # areas from corners: rounding ~ eps x (long side)^2, relative to the area l w: eps x aspect (1902 m x 1e-6 m
    # boxes differ by 1e-7 between two correct implementations)
    tol = 1e-7 + 64 * np.finfo(np.float64).eps * scale / min(la, wa)
    assert ab == pytest.approx(ba, abs=tol) and t == pytest.approx(ab, abs=tol)
    c, s = math.cos(turn), math.sin(turn)  # rotating (x, z) like a yaw increase: x' = c x + s z, z' = -s x + c z

    def rot(bx: np.ndarray) -> np.ndarray:
        h, w, length, px, y, pz, ry = bx[0]
        return box7(c * px + s * pz, -s * px + c * pz, length, w, ry + turn, h, y)

    assert float(bev_iou(rot(a), rot(b))[0, 0]) == pytest.approx(ab, abs=1e-6)


@pytest.mark.parametrize("case", ["identical", "zero-size", "touching", "pi", "far", "tiny"])
def test_box_term_gradients_are_finite(case: str) -> None:
    gt = {"identical": [3.0, 20.0, 4.0, 2.0, 0.5], "zero-size": [3.0, 20.0, 4.0, 2.0, 0.5],
          "touching": [7.0, 20.0, 4.0, 2.0, 0.0], "pi": [3.0, 20.0, 4.0, 2.0, -math.pi],
          "far": [1e4 + 0.5, 1e4, 4.0, 2.0, 0.0], "tiny": [3.0 + 5e-7, 20.0, 1e-6, 1e-6, 0.0]}[case]
    center = torch.tensor([3.0, 1.6, 20.0] if case not in ("far",) else [1e4, 1.6, 1e4], dtype=torch.float64,
                          requires_grad=True)
    lwh = torch.tensor({"zero-size": [0.0, 0.0, 1.5], "tiny": [1e-6, 1e-6, 1.5]}.get(case, [4.0, 2.0, 1.5]),
                       dtype=torch.float64, requires_grad=True)
    heading = torch.tensor(math.pi if case == "pi" else (0.5 if case in ("identical", "zero-size") else 0.0),
                           dtype=torch.float64, requires_grad=True)
    loss = box_car_loss(center, lwh, heading, np.array(gt))
    loss.backward()
    assert torch.isfinite(loss)
    for g in (center.grad, lwh.grad, heading.grad):
        assert torch.isfinite(g).all()
    want = {"identical": 1.0, "zero-size": 0.0, "touching": 0.0, "pi": 1.0, "far": 3.5 * 2 / (8 + 8 - 7),
            "tiny": 0.5e-12 / (2e-12 - 0.5e-12)}[case]
    assert loss.item() == pytest.approx(want, abs=1e-9)


# ---- Moller-Trumbore ---------------------------------------------------------------------------------
CUBE_V = torch.tensor([[2 * ((i >> 2) & 1) - 1, 2 * ((i >> 1) & 1) - 1, 2 * (i & 1) - 1] for i in range(8)],
                      dtype=torch.float64)
CUBE_F = torch.tensor([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                       [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])


def unit(*rows: tuple[float, float, float]) -> torch.Tensor:
    d = torch.tensor(rows, dtype=torch.float64)
    return d / d.norm(dim=1, keepdim=True)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_rays_from_inside_a_closed_mesh_hit_faces_edges_and_vertices(dtype: torch.dtype) -> None:
    rng = np.random.default_rng(0)
    random = rng.normal(size=(200, 3))
    special = np.array([[1, 1, 1], [-1, 1, -1], [1, 1, 0], [0, -1, 1], [1, 0.3, 0.3], [1, 0, 0], [0, 0, -1],
                        [1, 1e-9, 1e-9]], dtype=np.float64)  # vertices, cube edges, a face diagonal, face centres
    d = torch.from_numpy(np.concatenate([special, random]))
    d = d / d.norm(dim=1, keepdim=True)
    verts = CUBE_V.to(dtype).clone().requires_grad_(True)
    hits = cast_rays(verts, CUBE_F, d.to(dtype), torch.zeros(3, dtype=dtype))
    assert hits.hit.all()  # nothing leaks through an edge or a vertex
    want = 1.0 / d.abs().max(dim=1).values  # distance to the cube's surface along d
    tol = 1e-9 if dtype == torch.float64 else 1e-5
    np.testing.assert_allclose(hits.t.detach().double().numpy(), want.numpy(), rtol=tol)
    hits.t.sum().backward()
    assert torch.isfinite(verts.grad).all()


def test_grazing_rays_and_zero_area_faces() -> None:
    tri = torch.tensor([[0.0, 0.0, 5.0], [4.0, 0.0, 5.0], [0.0, 4.0, 5.0],  # a face in the plane z = 5
                        [1.0, 1.0, 3.0], [2.0, 2.0, 3.0], [3.0, 3.0, 3.0]],  # a zero-area face (collinear) at z = 3
                       dtype=torch.float64, requires_grad=True)
    faces = torch.tensor([[0, 1, 2], [3, 4, 5]])
    target = torch.tensor([1.0, 1.0, 5.0], dtype=torch.float64)
    cases = [  # (direction, origin, hit face or -1, t)
        ((1.0, 0.0, 0.0), torch.tensor([-1.0, 1.0, 5.0]), -1, 0.0),  # in the face's plane: det = 0
        ((1.0, 0.0, 5e-4), None, -1, 0.0),  # |cos| = 5e-4 <= cos_min = 1e-3: grazing, rejected
        ((1.0, 0.0, 2e-3), None, 0, 100.0),  # |cos| = 2e-3: a hit 100 m away, bounded gradient
        ((0.0, 0.0, 1.0), torch.tensor([1.5, 1.5, 2.0]), 0, 3.0),  # through the sliver's segment, on to the face
        ((0.0, 0.0, -1.0), torch.tensor([1.0, 1.0, 4.0]), -1, 0.0),  # through the sliver's vertex, then nothing
    ]
    total = tri.new_zeros(())
    for direction, origin, face, t in cases:
        d = unit(direction)
        o = target - 100.0 * d[0] if origin is None else origin.to(torch.float64)
        hits = cast_rays(tri, faces, d, o)
        assert hits.face.tolist() == [face] and hits.hit.tolist() == [face >= 0]
        assert hits.t.item() == pytest.approx(t, rel=1e-9)
        assert torch.isfinite(hits.t).all() and torch.isfinite(hits.u).all() and torch.isfinite(hits.v).all()
        total = total + hits.t.sum() + hits.u.sum() + hits.v.sum()
    total.backward()
    assert torch.isfinite(tri.grad).all() and tri.grad[3:].abs().sum() == 0  # the sliver takes no part
    assert tri.grad[:3].abs().max() < 1e6  # the accepted grazing ray's gradient stays bounded (~1 / cos)


def test_rays_starting_on_a_face_and_invalid_meshes() -> None:
    tri = torch.tensor([[0.0, 0.0, 5.0], [4.0, 0.0, 5.0], [0.0, 4.0, 5.0]], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2]])
    on_face = cast_rays(tri, faces, unit((0.0, 0.0, 1.0)), torch.tensor([1.0, 1.0, 5.0], dtype=torch.float64))
    assert not on_face.hit.any()  # t <= t_min is no hit
    nan = tri.clone()
    nan[1, 0] = float("nan")
    with pytest.raises(ValueError, match="vertices"):
        cast_rays(nan, faces, unit((0.0, 0.0, 1.0)), torch.zeros(3, dtype=torch.float64))
    with pytest.raises(ValueError, match="faces"):
        cast_rays(tri, torch.tensor([[0, 1, 3]]), unit((0.0, 0.0, 1.0)), torch.zeros(3, dtype=torch.float64))


# ---- attack losses -----------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("margin", [-1e30, -1e4, -50.0, 0.0, 50.0, 1e4, 1e30])
def test_lidar_loss_from_p_to_0_to_p_to_1(dtype: torch.dtype, margin: float) -> None:
    logits = torch.tensor([[0.0, margin], [0.0, margin - 1.0]], dtype=dtype, requires_grad=True)
    loss = lidar_car_loss(logits, 0.5)
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(logits.grad).all()
    want = 0.5 * (margin if margin > 30 else math.log1p(math.exp(margin)))  # softplus(margin)
    assert loss.item() == pytest.approx(want, rel=1e-6, abs=1e-30)


def test_lidar_loss_refuses_non_finite_logits() -> None:
    for bad in (float("inf"), float("-inf"), float("nan")):
        with pytest.raises(ValueError, match="logits"):
            lidar_car_loss(torch.tensor([[0.0, bad], [0.0, 1.0]], dtype=torch.float64), 0.5)
    with pytest.raises(ValueError, match="logits"):  # an empty frustum has no logits to take a maximum of
        max_object_margin(torch.zeros(0, 2, dtype=torch.float64))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_image_term_at_overflowing_logits(dtype: torch.dtype) -> None:
    a = torch.tensor([1e4, 1e4, -1e4, -1e4, 80.0, 1e30], dtype=dtype, requires_grad=True)
    b = torch.tensor([1e4, -1e4, 1e4, -1e4, 80.0, 1e30], dtype=dtype, requires_grad=True)
    out = neg_log_one_minus_product(a, b)
    out.sum().backward()
    assert torch.isfinite(out).all() and torch.isfinite(a.grad).all() and torch.isfinite(b.grad).all()
    # o, c -> 1: 1 - oc ~ e^-a + e^-b, so -log(1 - oc) ~ a - log 2 for a = b; one of them -> 0: -log(1 - 0) = 0
    tol = 1e-3 if dtype == torch.float32 else 1e-9
    assert out[0].item() == pytest.approx(1e4 - math.log(2), abs=tol * 1e4)
    assert out[1].item() == pytest.approx(0.0, abs=tol) and out[2].item() == pytest.approx(0.0, abs=tol)
    assert out[3].item() == pytest.approx(0.0, abs=tol) and out[4].item() == pytest.approx(80 - math.log(2), abs=1e-4)
    assert (out >= -tol).all()


def test_image_losses_without_candidates_are_zero() -> None:
    empty = ObjectnessCandidates(objectness_logit=torch.zeros(0), class_logit=torch.zeros(0),
                                 boxes=torch.zeros(0, 4), iou=torch.zeros(0),
                                 image_index=torch.zeros(0, dtype=torch.int64),
                                 target_index=torch.zeros(0, dtype=torch.int64))
    out = image_target_losses(empty, 3)
    assert out.tolist() == [0.0, 0.0, 0.0]


@pytest.mark.parametrize("bias", [(50.0, -50.0), (-50.0, 50.0)], ids=["no-point-masked", "every-point-masked"])
def test_frustum_network_with_an_empty_or_full_mask_is_finite(bias: tuple[float, float]) -> None:
    """A frustum whose segmentation finds no object (a car with no object return) or only object points."""
    model = build_model("lite", seed=0).eval()
    with torch.no_grad():
        model.seg.classifier.weight.zero_()
        model.seg.classifier.bias.copy_(torch.tensor(bias))
    pts = torch.randn(1, model.cfg.num_points, 4, dtype=torch.float32, generator=torch.Generator().manual_seed(0))
    pts.requires_grad_(True)
    one_hot = torch.tensor([[1.0, 0.0, 0.0]])
    out = model(pts, one_hot, straight_through=1.0)
    assert int(out.mask_count[0]) == (0 if bias[0] > 0 else model.cfg.num_points)
    loss = lidar_car_loss(out.seg_logits[0].double(), 0.0) + out.center.sum() + out.size_residuals.sum()
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(pts.grad).all()
    _, count, centroid = mask_centroid(out.seg_logits.detach().numpy(), pts.detach().numpy()[..., :3])
    assert np.isfinite(centroid).all() and count[0] == int(out.mask_count[0])


# ---- victim heads ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_sigmoid_and_softmax_heads_do_not_overflow(dtype: type) -> None:
    big = np.finfo(dtype).max
    x = np.array([-big, -1e4, -88.8, 0.0, 88.8, 1e4, big], dtype=dtype)
    s = sigmoid(x)  # RuntimeWarnings are errors in this suite: an overflowing exp would fail here
    assert s.dtype == dtype and np.isfinite(s).all() and (s >= 0).all() and (s <= 1).all()
    assert s[0] == 0 and s[-1] == 1 and s[3] == 0.5
    logits = np.array([[big, -big], [1e4, -1e4], [-1e4, 1e4], [0.0, 0.0]], dtype=dtype)
    p = _softmax(logits, axis=-1)
    assert np.isfinite(p).all()
    np.testing.assert_allclose(p, [[1, 0], [1, 0], [0, 1], [0.5, 0.5]])
    np.testing.assert_allclose(p.sum(axis=-1), 1.0, rtol=1e-6)


# ---- AP at the extremes ------------------------------------------------------------------------------
def car_row(x: float, z: float, score: float | None = None) -> str:
    row = f"Car 0.00 0 0.00 100 100 200 180 1.50 1.60 4.00 {x} 1.60 {z} 0.00"
    return row + ("" if score is None else f" {score}")


def frames_of(rows: list[list[str]], scored: bool) -> list[Labels]:
    return [parse_labels("".join(r + "\n" for r in fr), f"{i:06d}.txt", scored=scored) for i, fr in enumerate(rows)]


def moderate_r40(res: dict, metric: str = "bev") -> float:
    return res["Car"][metric]["R40"]["moderate"]


def test_ap_without_ground_truth_without_detections_and_with_tied_scores() -> None:
    n = 50
    gt = frames_of([[car_row(-4 + 8 * (i % 2), 20 + 10 * (i // 2))] for i in range(n)], False)
    no_gt = frames_of([[] for _ in range(n)], False)
    dets = frames_of([[car_row(-4 + 8 * (i % 2), 20 + 10 * (i // 2), 0.5)] for i in range(n)], True)
    none = frames_of([[] for _ in range(n)], True)
    # No ground truth: every AP 0, finite, with a note.
    res = evaluate(no_gt, dets)
    assert all(v == 0.0 for m in res["Car"].values() for r in m.values() for v in r.values())
    assert any("no counted GT" in note for note in res["meta"]["notes"])
    # No detections: AP 0.
    assert moderate_r40(evaluate(gt, none)) == 0.0
    # Neither: AP 0.
    assert moderate_r40(evaluate(no_gt, none)) == 0.0
    # All scores tied, all correct: precision 1 at every sampled threshold: AP 100.
    assert moderate_r40(evaluate(gt, dets)) == pytest.approx(100.0)
    # All tied, half of them false positives far away: precision 1/2 at the one threshold: AP 50.
    mixed = frames_of([[car_row(-4 + 8 * (i % 2), 20 + 10 * (i // 2), 0.5), car_row(30, 70 + i, 0.5)]
                       for i in range(n)], True)
    assert moderate_r40(evaluate(gt, mixed)) == pytest.approx(50.0)
    # Bootstrap intervals of these degenerate sets are finite and contain the point estimates.
    for g, d, want in ((no_gt, dets, 0.0), (gt, none, 0.0), (gt, dets, 100.0), (gt, mixed, 50.0)):
        lo, hi = ap_intervals(FrameBootstrap(g, d), 200, seed=1)["Car"]["bev"]["R40"]["moderate"]
        assert math.isfinite(lo) and math.isfinite(hi) and lo <= want + 1e-9 and hi >= want - 1e-9


# ---- bfloat16 inference ------------------------------------------------------------------------------------
def test_bfloat16_frustum_stages_track_float32(kitti_samples) -> None:
    from robustbench3d.errors import RobustBenchError
    from robustbench3d.kitti.dataset import KittiDataset
    from robustbench3d.victims import create_victim

    ds = KittiDataset(kitti_samples, split=None)
    frames = [ds.frame(f) for f in ds.frame_ids[:3]]
    f32 = create_victim("fpointnet-v1-lite", allow_untrained=True, seed=3)
    b16 = create_victim("fpointnet-v1-lite", allow_untrained=True, seed=3, precision="bfloat16")
    assert (f32.precision, b16.precision) == ("float32", "bfloat16")
    r32, r16 = f32.detect(frames, proposals="gt"), b16.detect(frames, proposals="gt")
    compared = 0
    for a, b in zip(r32, r16, strict=True):
        assert len(a) == len(b)
        for arr in (b.location, b.dimensions, b.rotation_y, b.score):
            assert np.isfinite(arr).all()
        if len(a):  # bfloat16 keeps 8 bits of mantissa: close, not equal
            np.testing.assert_allclose(b.location, a.location, atol=0.5)
            compared += len(a)
            assert not np.array_equal(a.location, b.location)
    assert compared > 0
    with pytest.raises(RobustBenchError, match="precision"):
        create_victim("fpointnet-v1-lite", allow_untrained=True, precision="float16")
