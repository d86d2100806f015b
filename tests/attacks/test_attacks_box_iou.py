"""The differentiable BEV IoU of the box term against the evaluator's exact polygon IoU, its gradient against
float64 finite differences, and finite values and gradients at degenerate boxes."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from robustbench3d.attacks.box_iou import bev_iou_torch
from robustbench3d.attacks.losses import box_car_loss, gt_bev_boxes
from robustbench3d.eval.iou import bev_iou
from robustbench3d.kitti.labels import parse_labels


def _kitti(box: np.ndarray) -> np.ndarray:
    """(1, 7) evaluator box h, w, l, x, y, z, ry of an (x, z, l, w, ry) box."""
    x, z, length, width, ry = box
    return np.array([[1.5, width, length, x, 1.0, z, ry]])


def test_equals_the_evaluator_on_random_and_near_identical_boxes():
    rng = np.random.default_rng(0)
    for i in range(600):
        a = np.array([*(rng.uniform(-2, 2, 2) + 40.0), *rng.uniform(0.3, 5.0, 2), rng.uniform(-4, 4)])
        b = a + rng.normal(0, 0.05, 5) if i % 3 == 0 else \
            np.array([*(rng.uniform(-2, 2, 2) + 40.0), *rng.uniform(0.3, 5.0, 2), rng.uniform(-4, 4)])
        want = bev_iou(_kitti(a), _kitti(b))[0, 0]
        got = bev_iou_torch(torch.tensor(a), torch.tensor(b)).item()
        assert got == pytest.approx(want, abs=1e-12)


def test_hand_cases():
    unit = torch.tensor([0.0, 0.0, 2.0, 1.0, 0.0], dtype=torch.float64)
    assert bev_iou_torch(unit, unit).item() == pytest.approx(1.0, abs=1e-15)
    shifted = unit + torch.tensor([1.0, 0, 0, 0, 0], dtype=torch.float64)  # overlap 1 x 1 of 2 + 2 - 1
    assert bev_iou_torch(unit, shifted).item() == pytest.approx(1 / 3, abs=1e-15)
    turned = unit + torch.tensor([0, 0, 0, 0, np.pi], dtype=torch.float64)  # a half turn is the same footprint
    assert bev_iou_torch(unit, turned).item() == pytest.approx(1.0, abs=1e-12)
    apart = unit + torch.tensor([5.0, 0, 0, 0, 0], dtype=torch.float64)
    assert bev_iou_torch(unit, apart).item() == 0.0


def test_gradient_matches_finite_differences():
    b = torch.tensor([30.2, 20.1, 3.9, 1.7, 0.25], dtype=torch.float64)
    for a0 in ([30.0, 20.0, 4.0, 1.6, 0.3], [30.5, 19.7, 4.2, 1.5, 0.9], [29.9, 20.3, 3.0, 2.0, -0.4]):
        a = torch.tensor(a0, dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(lambda x: bev_iou_torch(x, b), (a,))


@pytest.mark.parametrize("a0", [[0.0, 0.0, 0.0, 0.0, 0.0],  # zero-size box
                                [0.0, 0.0, 2.0, 1.0, 0.0],  # coincident
                                [2.0, 0.0, 2.0, 1.0, 0.0],  # touching along an edge
                                [0.0, 0.0, 2.0, 1.0, np.pi / 2]])  # corners on edges
def test_degenerate_boxes_give_finite_values_and_gradients(a0):
    a = torch.tensor(a0, dtype=torch.float64, requires_grad=True)
    b = torch.tensor([0.0, 0.0, 2.0, 1.0, 0.0], dtype=torch.float64)
    iou = bev_iou_torch(a, b)
    iou.backward()
    assert torch.isfinite(iou) and 0.0 <= iou.item() <= 1.0 and torch.isfinite(a.grad).all()
    with pytest.raises(ValueError, match="x, z, l, w, ry"):
        bev_iou_torch(a[:4], b)


def test_box_car_loss_reads_kitti_rows_and_the_regressed_box():
    labels = parse_labels("Car 0 0 0 100 100 200 200 1.5 1.6 4.0 3.0 1.7 25.0 0.2\n")
    gt = gt_bev_boxes(labels)
    np.testing.assert_array_equal(gt, [[3.0, 25.0, 4.0, 1.6, 0.2]])
    center = torch.tensor([3.0, 0.95, 25.0], dtype=torch.float32, requires_grad=True)
    size = torch.tensor([4.0, 1.6, 1.5], dtype=torch.float32)
    loss = box_car_loss(center, size, torch.tensor(0.2), gt[0])
    assert loss.item() == pytest.approx(1.0, abs=1e-6)
    loss2 = box_car_loss(center + torch.tensor([0.4, 0.0, 0.0]), size, torch.tensor(0.2), gt[0])
    assert loss2.item() == pytest.approx(bev_iou(_kitti(gt[0]), _kitti(gt[0] + [0.4, 0, 0, 0, 0]))[0, 0], abs=1e-6)
    loss2.backward()
    assert center.grad[0] < 0 and center.grad[1] == 0  # moving further right lowers the IoU; height is not BEV


def test_box_car_loss_measures_a_float32_regressed_box_in_float64():
    """The victim regresses float32 boxes; the loss compares them with the ground truth in float64 (the
    project's rule where geometry decides): the same value, bit for bit, as the box given in float64, with a
    float32 or a float64 ground-truth row, and float64 rows from ``gt_bev_boxes``."""
    labels = parse_labels("Car 0 0 0 100 100 200 200 1.5 1.6 3.9 1.1 1.7 20.3 0.21\n")
    assert gt_bev_boxes(labels).dtype == np.float64
    center = torch.tensor([1.3, 1.6, 20.1], dtype=torch.float32)
    size = torch.tensor([3.7, 1.7, 1.5], dtype=torch.float32)
    heading = torch.tensor(0.3, dtype=torch.float32)
    want = box_car_loss(center.double(), size.double(), heading.double(), gt_bev_boxes(labels)[0])
    assert want.dtype == torch.float64 and 0.3 < want.item() < 0.95
    for gt in (gt_bev_boxes(labels)[0], gt_bev_boxes(labels)[0].astype(np.float32)):
        got = box_car_loss(center, size, heading, gt)
        assert got.dtype == torch.float64
        if gt.dtype == np.float64:
            assert got.item() == want.item()
