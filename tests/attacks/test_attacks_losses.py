"""The universal object's losses: hand-computed values, extreme logits, float64 finite differences."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hand_losses import nl, sigmoid

from robustbench3d.attacks.losses import (
    IMAGE_LOSSES,
    ImageLoss,
    best_candidate_scores,
    image_target_losses,
    laplacian_loss,
    lidar_car_loss,
    max_object_margin,
    neg_log_one_minus_product,
    register_image_loss,
)
from robustbench3d.attacks.object import laplacian_smoothness, template_vertices
from robustbench3d.victims.base import ObjectnessCandidates


def test_lidar_loss_hand_values():
    logits = torch.tensor([[0.0, 1.0], [2.0, 0.0], [0.0, 3.0], [1.0, 1.5]], dtype=torch.float64)
    assert max_object_margin(logits).item() == 3.0
    # p = max softmax object probability = e^3 / (e^0 + e^3); loss = -IoU log(1 - p)
    p = math.exp(3.0) / (1.0 + math.exp(3.0))
    assert lidar_car_loss(logits, 0.5).item() == pytest.approx(-0.5 * math.log(1 - p), rel=1e-12)
    # the IoU is floored (0.1 by default, or the given floor)
    assert lidar_car_loss(logits, 0.02).item() == pytest.approx(-0.1 * math.log(1 - p), rel=1e-12)
    assert lidar_car_loss(logits, 0.0, floor=0.3).item() == pytest.approx(-0.3 * math.log(1 - p), rel=1e-12)
    with pytest.raises(ValueError, match="logits"):
        max_object_margin(torch.zeros(0, 2))


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_lidar_loss_extreme_logits_finite(sign):
    logits = torch.tensor([[-1e4 * sign, 1e4 * sign], [0.0, 0.0]], dtype=torch.float64, requires_grad=True)
    loss = lidar_car_loss(logits, 0.7)
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(logits.grad).all()
    if sign > 0:  # object certain: -log(1 - p) = margin 2e4 (log of p would give inf)
        assert loss.item() == pytest.approx(0.7 * 2e4)
        np.testing.assert_allclose(logits.grad.numpy(), [[-0.7, 0.7], [0.0, 0.0]])
    else:  # the max is the (0, 0) row: p = 1/2
        assert loss.item() == pytest.approx(0.7 * math.log(2.0))
        np.testing.assert_allclose(logits.grad.numpy(), [[0.0, 0.0], [-0.35, 0.35]])


def test_image_term_hand_values_and_extremes():
    for a, b in [(0.0, 0.0), (2.0, -1.0), (-3.0, 4.0), (10.0, 10.0)]:
        ref = -math.log(1.0 - sigmoid(a) * sigmoid(b))
        got = neg_log_one_minus_product(torch.tensor(a, dtype=torch.float64), torch.tensor(b, dtype=torch.float64))
        assert got.item() == pytest.approx(ref, rel=1e-12)
        assert neg_log_one_minus_product(torch.tensor(a, dtype=torch.float64)).item() == pytest.approx(
            -math.log(1.0 - sigmoid(a)), rel=1e-12)
    # o = c = 1 - e^-1e4: 1 - o c ~ 2 e^-1e4, so the loss is 1e4 - log 2 (the probability form gives inf)
    a = torch.tensor([1e4, -1e4, 1e4], dtype=torch.float64, requires_grad=True)
    b = torch.tensor([1e4, 1e4, -1e4], dtype=torch.float64, requires_grad=True)
    out = neg_log_one_minus_product(a, b)
    out.sum().backward()
    np.testing.assert_allclose(out.detach().numpy(), [1e4 - math.log(2.0), 0.0, 0.0], atol=1e-9)
    assert torch.isfinite(a.grad).all() and torch.isfinite(b.grad).all()
    np.testing.assert_allclose(a.grad.numpy(), [0.5, 0.0, 0.0], atol=1e-12)


def candidates(obj, cls, iou, target) -> ObjectnessCandidates:
    n = len(obj)
    return ObjectnessCandidates(
        objectness_logit=torch.tensor(obj, dtype=torch.float64), class_logit=torch.tensor(cls, dtype=torch.float64),
        boxes=torch.zeros(n, 4), iou=torch.tensor(iou, dtype=torch.float32),
        image_index=torch.tensor([0] * (n - 1) + [1], dtype=torch.int64),
        target_index=torch.tensor(target, dtype=torch.int64))


def test_image_target_losses_mean_per_target():
    c = candidates([0.0, 2.0, -1.0, 5.0], [1.0, 0.0, 3.0, 5.0], [0.6, 0.2, 0.9, 0.9], [0, 0, 1, 0])
    got = image_target_losses(c, 3).numpy()  # image 0: target 0 has rows 0, 1; target 1 row 2; target 2 none
    t0 = (-math.log(1 - sigmoid(0) * sigmoid(1)) - math.log(1 - sigmoid(2) * sigmoid(0))) / 2
    t1 = -math.log(1 - sigmoid(-1) * sigmoid(3))
    np.testing.assert_allclose(got, [t0, t1, 0.0], rtol=1e-12)
    no_class = image_target_losses(c, 3, use_class=False).numpy()
    np.testing.assert_allclose(no_class, [(math.log1p(math.exp(0)) + math.log1p(math.exp(2))) / 2,
                                          math.log1p(math.exp(-1)), 0.0], rtol=1e-12)
    # reduce="sum": the sum over each target's candidates of IoU >= 0.5 (target 0: row 0 only, row 1 has IoU 0.2)
    summed = image_target_losses(c, 3, reduce="sum").numpy()
    np.testing.assert_allclose(summed, [-math.log(1 - sigmoid(0) * sigmoid(1)), t1, 0.0], rtol=1e-12)
    c2 = candidates([0.0, 2.0, -1.0, 5.0], [1.0, 0.0, 3.0, 5.0], [0.6, 0.5, 0.9, 0.9], [0, 0, 1, 0])
    both = -math.log(1 - sigmoid(0) * sigmoid(1)) - math.log(1 - sigmoid(2) * sigmoid(0))  # IoU 0.5 counts
    np.testing.assert_allclose(image_target_losses(c2, 3, reduce="sum").numpy(), [both, t1, 0.0], rtol=1e-12)
    np.testing.assert_allclose(image_target_losses(c2, 3, use_class=False, reduce="sum").numpy(),
                               [math.log1p(math.exp(0)) + math.log1p(math.exp(2)), math.log1p(math.exp(-1)), 0.0],
                               rtol=1e-12)
    with pytest.raises(ValueError, match="field 'reduce'"):
        image_target_losses(c, 3, reduce="max")
    # best score among candidates with IoU >= 0.5 (row 1 has IoU 0.2; row 3 is image 1)
    np.testing.assert_allclose(best_candidate_scores(c, 3), [sigmoid(0) * sigmoid(1), sigmoid(-1) * sigmoid(3), 0.0])


def test_gradients_match_float64_finite_differences():
    rng = np.random.default_rng(0)
    logits = torch.tensor(rng.normal(0, 3, (7, 2)), dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: lidar_car_loss(x, 0.4), (logits,))
    a = torch.tensor(rng.normal(0, 4, 6), dtype=torch.float64, requires_grad=True)
    b = torch.tensor(rng.normal(0, 4, 6), dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(neg_log_one_minus_product, (a, b))

    def per_target(a_: torch.Tensor, b_: torch.Tensor) -> torch.Tensor:
        c = ObjectnessCandidates(a_, b_, torch.zeros(6, 4), torch.ones(6), torch.zeros(6, dtype=torch.int64),
                                 torch.tensor([0, 1, 0, 2, 1, 0]))
        return image_target_losses(c, 3)

    assert torch.autograd.gradcheck(per_target, (a, b))
    v = torch.tensor(template_vertices() + rng.normal(0, 0.02, (162, 3)), requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: laplacian_loss(x, 0.5), (v,))


def test_laplacian_loss_is_weighted_smoothness():
    v = template_vertices()
    assert laplacian_loss(torch.tensor(v), 0.25).item() == pytest.approx(0.25 * laplacian_smoothness(v), rel=1e-12)


def test_losses_edge_cases_from_mutation_testing():
    """Logits that are not (N, 2) are refused whatever else is wrong; the image term runs in the objectness
    logit's dtype even with float64 class logits; a candidate exactly at the IoU threshold counts."""
    for bad in (torch.zeros(4, 3), torch.zeros(2, 2, 2), torch.zeros(0, 2)):
        with pytest.raises(ValueError, match="logits"):
            max_object_margin(bad)
    for bad in (torch.tensor([[0.0, float("nan")]]), torch.tensor([[float("-inf"), 1.0]])):
        with pytest.raises(ValueError) as err:
            max_object_margin(bad)
        assert str(err.value) == "field 'logits': contains NaN or inf (the victim's segmentation head diverged)"
    a = torch.tensor([0.3, -2.0], dtype=torch.float32)
    b = torch.tensor([1.0, 4.0], dtype=torch.float64)
    got = neg_log_one_minus_product(a, b)
    assert got.dtype == torch.float32
    expect = [-math.log(1 - sigmoid(0.3) * sigmoid(1.0)), -math.log(1 - sigmoid(-2.0) * sigmoid(4.0))]
    np.testing.assert_allclose(got.numpy(), expect, rtol=2e-5)
    c = candidates([0.0, 1.0], [0.0, 0.0], [0.5, 0.4999], [0, 0])
    np.testing.assert_allclose(best_candidate_scores(c, 2, min_iou=0.5), [0.25, 0.0])


# ---- the image losses as a table (name -> function and candidate set) -------------------------------------


def tiny() -> ObjectnessCandidates:
    """Five candidates: image 0 holds rows 0-2 and 4 (targets 0, 0, 1, 0), image 1 row 3."""
    return ObjectnessCandidates(
        objectness_logit=torch.tensor([0.0, 2.0, -1.0, 5.0, 1.5], dtype=torch.float64),
        class_logit=torch.tensor([1.0, 0.0, 3.0, 5.0, -2.0], dtype=torch.float64),
        boxes=torch.zeros(5, 4), iou=torch.tensor([0.6, 0.2, 0.9, 0.9, 0.5], dtype=torch.float32),
        image_index=torch.tensor([0, 0, 0, 1, 0]), target_index=torch.tensor([0, 0, 1, 0, 0]))


def test_mean_and_sum_are_table_entries_with_their_hand_values():
    """``mean``: per target the mean over its candidates of -log(1 - o c); ``sum``: the sum over those of IoU >=
    0.5; as table entries, called directly and through ``image_target_losses`` by name; ``mean`` reads the
    oracle's 0.3 candidate set, ``sum`` the 0.5 one."""
    c = tiny()
    assert set(IMAGE_LOSSES) == {"mean", "sum"}
    assert all(isinstance(e, ImageLoss) for e in IMAGE_LOSSES.values())
    assert IMAGE_LOSSES["mean"].candidate_iou == 0.3 and IMAGE_LOSSES["sum"].candidate_iou == 0.5
    mean = [(nl(0, 1) + nl(2, 0) + nl(1.5, -2)) / 3, nl(-1, 3), 0.0]
    total = [nl(0, 1) + nl(1.5, -2), nl(-1, 3), 0.0]  # row 1 (IoU 0.2) out; row 4 (IoU exactly 0.5) in
    mean_obj = [(nl(0) + nl(2) + nl(1.5)) / 3, nl(-1), 0.0]
    total_obj = [nl(0) + nl(1.5), nl(-1), 0.0]
    for name, with_class, without in (("mean", mean, mean_obj), ("sum", total, total_obj)):
        np.testing.assert_allclose(IMAGE_LOSSES[name](c, 3).numpy(), with_class, rtol=1e-12)
        np.testing.assert_allclose(IMAGE_LOSSES[name](c, 3, 0, False).numpy(), without, rtol=1e-12)
        assert torch.equal(image_target_losses(c, 3, 0, True, name), IMAGE_LOSSES[name](c, 3, 0, True))
    # image 1: its one candidate (target 0)
    np.testing.assert_allclose(IMAGE_LOSSES["mean"](c, 3, 1).numpy(), [nl(5, 5), 0.0, 0.0], rtol=1e-12)
    np.testing.assert_allclose(IMAGE_LOSSES["sum"](c, 3, 1).numpy(), [nl(5, 5), 0.0, 0.0], rtol=1e-12)


def test_a_registered_loss_is_used_by_name(table):
    """``register_image_loss`` adds a name; ``image_target_losses`` then computes that function's terms by name,
    with the arguments it was given."""
    calls = []

    def max_objectness(c: ObjectnessCandidates, n: int, image_index: int, use_class: bool) -> torch.Tensor:
        calls.append((n, image_index, use_class))
        per = [c.objectness_logit[(c.image_index == image_index) & (c.target_index == k)] for k in range(n)]
        return torch.stack([v.max() if len(v) else v.new_zeros(()) for v in per])

    entry = register_image_loss("max-obj", max_objectness, candidate_iou=0.1)
    assert table["max-obj"] is entry and entry.candidate_iou == 0.1
    got = image_target_losses(tiny(), 3, 0, False, "max-obj")
    np.testing.assert_array_equal(got.numpy(), [2.0, -1.0, 0.0])  # rows 0, 1, 4 -> max(0, 2, 1.5); row 2
    assert calls == [(3, 0, False)]
    assert list(table) == ["mean", "sum", "max-obj"]


def test_register_refuses_bad_entries(table):
    def f(c, n, i, u):
        return torch.zeros(n)

    for name in ("mean", "sum"):  # the shipped objects' losses are never replaced
        with pytest.raises(ValueError, match=f"field 'name': '{name}' is already an image loss"):
            register_image_loss(name, f)
    for bad in ("", "Mean", "a b", "x,y", 3):
        with pytest.raises(ValueError, match="field 'name'"):
            register_image_loss(bad, f)
    with pytest.raises(ValueError, match="field 'terms': expected a function"):
        register_image_loss("fine", "not a function")
    for iou in (-0.01, 1.01, float("nan"), "0.5"):
        with pytest.raises(ValueError, match="field 'candidate_iou': expected 0 to 1"):
            register_image_loss("fine", f, candidate_iou=iou)
    assert set(table) == {"mean", "sum"}  # nothing half-registered
    register_image_loss("edge0", f, candidate_iou=0)
    register_image_loss("edge1", f, candidate_iou=1)
    register_image_loss("wrong-shape", lambda c, n, i, u: torch.zeros(n + 1))
    with pytest.raises(ValueError, match=r"image loss 'wrong-shape' returned shape \(4,\), expected \(3,\)"):
        image_target_losses(tiny(), 3, reduce="wrong-shape")
    with pytest.raises(ValueError, match="field 'reduce': expected one of mean, sum, edge0, edge1, wrong-shape"):
        image_target_losses(tiny(), 3, reduce="max")
