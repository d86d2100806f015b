"""F-PN loss (reference §1.7) checked by hand and against a brute-force corner loss; output
decoding (§1.9) checked by an encode -> decode round trip of real labels."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from robustbench3d.geometry import alpha_from_rotation_y, box_corners, wrap_angle
from robustbench3d.kitti.dataset import KittiDataset
from robustbench3d.victims.fpointnet.box_coding import MEAN_SIZES, angle_to_class, size_to_class
from robustbench3d.victims.fpointnet.frustum import rotate_to_frustum
from robustbench3d.victims.fpointnet.losses import (
    FPointNetTargets,
    corner_loss,
    fpointnet_loss,
    huber,
    safe_norm,
)
from robustbench3d.victims.fpointnet.model import FPointNetOutput
from robustbench3d.victims.fpointnet.to_kitti import decode, to_labels


def fake_output(rng: np.random.Generator, b: int, n: int = 16) -> FPointNetOutput:
    def t(*shape: int) -> torch.Tensor:
        return torch.tensor(rng.normal(size=shape), dtype=torch.float64, requires_grad=True)

    seg = t(b, n, 2)
    center, stage1 = t(b, 3), t(b, 3)
    h_norm, s_norm = t(b, 12), t(b, 8, 3)
    mean = torch.tensor(MEAN_SIZES)
    mask = (seg[..., 1] > seg[..., 0]).detach()
    return FPointNetOutput(
        seg_logits=seg, mask=mask, mask_count=mask.sum(1), mask_centroid=torch.zeros(b, 3),
        object_indices=torch.zeros(b, 4, dtype=torch.int64), center_delta=torch.zeros(b, 3),
        stage1_center=stage1, center=center, heading_scores=t(b, 12), heading_residuals_normalized=h_norm,
        heading_residuals=h_norm * (np.pi / 12), size_scores=t(b, 8), size_residuals_normalized=s_norm,
        size_residuals=s_norm * mean[None])


def fake_targets(rng: np.random.Generator, b: int, n: int = 16) -> FPointNetTargets:
    return FPointNetTargets(
        seg=torch.tensor(rng.integers(0, 2, (b, n))), center=torch.tensor(rng.normal(size=(b, 3))),
        heading_class=torch.tensor(rng.integers(0, 12, b)),
        heading_residual=torch.tensor(rng.uniform(-np.pi / 12, np.pi / 12, b)),
        size_class=torch.tensor(rng.integers(0, 8, b)), size_residual=torch.tensor(rng.normal(0, 0.2, (b, 3))))


def test_huber_by_hand():
    x = torch.tensor([0.5, -3.0, 0.0])
    # δ=1: 0.125, 0.5 + 1·2 = 2.5, 0  -> mean 2.625/3
    assert float(huber(x, 1.0)) == pytest.approx((0.125 + 2.5 + 0.0) / 3)
    # δ=2: 0.125, 0.5·4 + 2·1 = 4, 0
    assert float(huber(x, 2.0)) == pytest.approx((0.125 + 4.0) / 3)


def test_safe_norm_has_finite_gradient_at_zero():
    z = torch.zeros(2, 3, requires_grad=True)
    safe_norm(z).sum().backward()
    assert torch.isfinite(z.grad).all()
    x = torch.tensor([[3.0, 4.0, 0.0]])
    assert float(safe_norm(x)) == pytest.approx(5.0)


def brute_force_corner_loss(out: FPointNetOutput, t: FPointNetTargets, double: bool) -> float:
    """Loop implementation from the §1.7 prose, using the devkit-style corners of geometry.py."""
    total, count = 0.0, 0
    for i in range(len(t.heading_class)):
        hc, sc = int(t.heading_class[i]), int(t.size_class[i])
        res = out.size_residuals[i, sc].detach().numpy()
        l, w, h = MEAN_SIZES[sc] + (2 if double else 1) * res
        heading = hc * np.pi / 6 + out.heading_residuals[i, hc].item()
        c = out.center[i].detach().numpy()
        pred = box_corners(np.array([[h, w, l]]), (c + np.array([0, h / 2, 0]))[None], np.array([heading]))[0]
        gl, gw, gh = MEAN_SIZES[sc] + t.size_residual[i].numpy()
        gheading = hc * np.pi / 6 + float(t.heading_residual[i])
        gc = t.center[i].numpy() + np.array([0, gh / 2, 0])
        gt = box_corners(np.array([[gh, gw, gl]]), gc[None], np.array([gheading]))[0]
        flip = box_corners(np.array([[gh, gw, gl]]), gc[None], np.array([gheading + np.pi]))[0]
        for k in range(8):
            d = min(np.linalg.norm(pred[k] - gt[k]), np.linalg.norm(pred[k] - flip[k]))
            total += 0.5 * d * d if d <= 1 else 0.5 + (d - 1)
            count += 1
    return total / count


@pytest.mark.parametrize("double", [True, False])
def test_corner_loss_matches_brute_force(double):
    rng = np.random.default_rng(0)
    out, t = fake_output(rng, 6), fake_targets(rng, 6)
    assert corner_loss(out, t, double).item() == pytest.approx(brute_force_corner_loss(out, t, double), rel=1e-9)
    assert corner_loss(out, t, True).item() != pytest.approx(corner_loss(out, t, False).item())


def test_total_loss_terms_and_weights():
    rng = np.random.default_rng(1)
    out, t = fake_output(rng, 4), fake_targets(rng, 4)
    total, terms = fpointnet_loss(out, t)
    seg = out.seg_logits.detach().reshape(-1, 2)
    lab = t.seg.reshape(-1)
    mask_ce = float((torch.logsumexp(seg, 1) - seg[torch.arange(len(lab)), lab]).mean())
    assert terms["mask"].item() == pytest.approx(mask_ce)
    i = torch.arange(4)
    d = (out.center - t.center).detach().norm(dim=1)
    assert terms["center"].item() == pytest.approx(float(torch.where(d <= 2, 0.5 * d**2, 2 + 2 * (d - 2)).mean()))
    hres = out.heading_residuals_normalized[i, t.heading_class].detach() - t.heading_residual / (np.pi / 12)
    assert terms["heading_residual"].item() == pytest.approx(float(huber(hres, 1.0)))
    mean = torch.tensor(MEAN_SIZES)
    sres = (out.size_residuals_normalized[i, t.size_class].detach() - t.size_residual / mean[t.size_class]).norm(dim=1)
    assert terms["size_residual"].item() == pytest.approx(float(huber(sres, 1.0)))
    expected = terms["mask"] + (terms["center"] + terms["heading_class"] + terms["size_class"]
                                + 20 * terms["heading_residual"] + 20 * terms["size_residual"]
                                + terms["stage1_center"] + 10 * terms["corner"])
    assert total.item() == pytest.approx(expected.item())
    total.backward()
    assert torch.isfinite(out.center.grad).all()


def test_exact_prediction_gives_zero_box_losses_and_finite_gradients():
    rng = np.random.default_rng(2)
    t = fake_targets(rng, 3)
    out = fake_output(rng, 3)
    with torch.no_grad():
        out.center.copy_(t.center)
        out.stage1_center.copy_(t.center)
        i = torch.arange(3)
        out.heading_residuals_normalized[i, t.heading_class] = t.heading_residual / (np.pi / 12)
        out.size_residuals_normalized[i, t.size_class] = t.size_residual / torch.tensor(MEAN_SIZES)[t.size_class]
    out.heading_residuals = out.heading_residuals_normalized * (np.pi / 12)
    out.size_residuals = out.size_residuals_normalized * torch.tensor(MEAN_SIZES)[None]
    _, terms = fpointnet_loss(out, t, double_size_residual=False)
    for k in ("center", "stage1_center", "heading_residual", "size_residual", "corner"):
        assert terms[k].item() < 1e-10, k
    total, _ = fpointnet_loss(out, t)
    total.backward()
    assert torch.isfinite(out.center.grad).all() and torch.isfinite(out.size_residuals_normalized.grad).all()


def test_decode_and_kitti_rows_invert_the_encoding(kitti_samples):
    """Encode real labels as training targets would, feed them as a perfect prediction, decode."""
    ds = KittiDataset(kitti_samples, split=None)
    labels = [ds.labels(f) for f in ds.frame_ids]
    objs = [lab.select(lab.type != "DontCare") for lab in labels]
    from robustbench3d.kitti.labels import Labels

    gt = Labels.concatenate(objs)
    k = len(gt)
    rng = np.random.default_rng(0)
    rot = rng.uniform(-0.3, 0.3, k) + np.pi / 2
    h, w, l = gt.dimensions.T
    centre = np.stack([rotate_to_frustum(gt.location[j] - [0, h[j] / 2, 0], rot[j]) for j in range(k)])
    hcls, hres = angle_to_class(gt.rotation_y - rot)
    scls, sres = size_to_class(np.stack([l, w, h], 1), gt.type)
    out = FPointNetOutput(
        seg_logits=torch.zeros(k, 4, 2), mask=torch.zeros(k, 4, dtype=torch.bool), mask_count=torch.zeros(k),
        mask_centroid=torch.zeros(k, 3), object_indices=torch.zeros(k, 4, dtype=torch.int64),
        center_delta=torch.zeros(k, 3), stage1_center=torch.zeros(k, 3), center=torch.tensor(centre),
        heading_scores=torch.nn.functional.one_hot(torch.tensor(hcls), 12).double(),
        heading_residuals_normalized=torch.zeros(k, 12),
        heading_residuals=torch.zeros(k, 12, dtype=torch.float64).index_put_(
            (torch.arange(k), torch.tensor(hcls)), torch.tensor(hres)),
        size_scores=torch.nn.functional.one_hot(torch.tensor(scls), 8).double(),
        size_residuals_normalized=torch.zeros(k, 8, 3),
        size_residuals=torch.zeros(k, 8, 3, dtype=torch.float64).index_put_(
            (torch.arange(k), torch.tensor(scls)), torch.tensor(sres)))
    rows = to_labels(decode(out), rot, gt.bbox, np.linspace(0, 1, k), type_name="Car")
    assert np.allclose(rows.location, gt.location, atol=1e-9)
    assert np.allclose(rows.dimensions, gt.dimensions, atol=1e-9)
    assert np.allclose(wrap_angle(rows.rotation_y - gt.rotation_y), 0, atol=1e-9)
    assert np.array_equal(rows.bbox, gt.bbox) and np.array_equal(rows.score, np.linspace(0, 1, k))
    assert np.allclose(rows.alpha, alpha_from_rotation_y(rows.rotation_y, rows.location))
    assert (rows.truncated == -1).all() and (rows.occluded == -1).all() and set(rows.type) == {"Car"}
    # score: empty mask -> max object prob 0.5; one-hot logits -> softmax max e/(e+11) and e/(e+7)
    expect = 0.5 * math.e / (math.e + 11) * math.e / (math.e + 7)
    assert np.allclose(decode(out).score_3d, expect)
