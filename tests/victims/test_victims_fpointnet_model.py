"""F-PN v1 network: layer widths, parameter counts (reference §1.6), masking / gather semantics,
finite gradients at degenerate inputs, determinism."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from robustbench3d.victims.fpointnet.model import (
    FULL,
    LITE,
    NUM_BOX_OUTPUTS,
    bn_momentum_at,
    build_model,
    count_parameters,
    object_point_indices,
)

torch.set_num_threads(1)


def test_parameter_counts_match_the_reference():
    m = build_model("full")
    # reference §1.6: ≈1.64 M total = seg 0.894 M + T-Net 0.152 M + box 0.596 M
    for module, expected in ((m.seg, 0.894e6), (m.tnet, 0.152e6), (m.box, 0.596e6), (m, 1.64e6)):
        assert count_parameters(module) == pytest.approx(expected, rel=0.01)


def test_layer_widths():
    m = build_model("full")
    convs = [c for c in m.seg.modules() if isinstance(c, torch.nn.Conv1d)]
    assert [c.out_channels for c in convs] == [64, 64, 64, 128, 1024, 512, 256, 128, 128, 2]
    assert convs[5].in_channels == 64 + 1024 + 3  # per-point 64 + global 1024 + one-hot
    tnet = [c.out_features for c in m.tnet.modules() if isinstance(c, torch.nn.Linear)]
    box = [c.out_features for c in m.box.modules() if isinstance(c, torch.nn.Linear)]
    assert tnet == [256, 128, 3] and box == [512, 256, 59] and NUM_BOX_OUTPUTS == 59
    assert [c.out_channels for c in m.box.modules() if isinstance(c, torch.nn.Conv1d)] == [128, 128, 256, 512]
    assert sum(isinstance(x, torch.nn.BatchNorm1d) for x in m.seg.modules()) == 9
    assert FULL.dropout == 0.5 and FULL.num_points == 1024 and FULL.num_object_points == 512
    assert (LITE.num_points, LITE.seg_global_mlp[-1], LITE.seg_head) == (512, 256, (128, 64))


@pytest.mark.parametrize("cfg", ["full", "lite"])
def test_output_shapes(cfg):
    m = build_model(cfg).eval()
    n = m.cfg.num_points
    pts = torch.randn(2, n, 4)
    one_hot = torch.tensor([[1.0, 0, 0], [0, 0, 1.0]])
    with torch.no_grad():
        out = m(pts, one_hot)
    assert out.seg_logits.shape == (2, n, 2) and out.mask.shape == (2, n)
    assert out.object_indices.shape == (2, 512)
    assert out.center.shape == out.stage1_center.shape == out.mask_centroid.shape == (2, 3)
    assert out.heading_scores.shape == out.heading_residuals.shape == (2, 12)
    assert out.size_scores.shape == (2, 8) and out.size_residuals.shape == (2, 8, 3)
    assert torch.allclose(out.heading_residuals, out.heading_residuals_normalized * np.pi / 12)


class FixedSeg(torch.nn.Module):
    """Stand-in segmentation: object iff x > threshold (logits (−x, x) shifted)."""

    def __init__(self, threshold: float):
        super().__init__()
        self.threshold = threshold

    def forward(self, points, one_hot, generator=None):
        s = points[..., 0] - self.threshold
        return torch.stack([-s, s], dim=-1)


def test_masking_centroid_gather_and_stage_composition():
    m = build_model("lite").eval()
    m.seg = FixedSeg(0.5)
    rng = np.random.default_rng(0)
    pts = torch.from_numpy(rng.normal(size=(3, 512, 4)).astype(np.float32))
    pts[2, :, 0] = -1.0  # frustum 2: nothing is object
    with torch.no_grad():
        out = m(pts, torch.eye(3), gather="random", rng=np.random.default_rng(1))
    for b in range(3):
        xyz = pts[b, :, :3].numpy()
        mask = xyz[:, 0] > 0.5
        assert np.array_equal(out.mask[b].numpy(), mask) and int(out.mask_count[b]) == mask.sum()
        expect = xyz[mask].mean(axis=0) if mask.any() else np.zeros(3)
        assert np.allclose(out.mask_centroid[b].numpy(), expect, atol=1e-5)
        idx = out.object_indices[b].numpy()
        if mask.any():
            assert mask[idx].all()  # only object points are gathered
        else:
            assert (idx == 0).all()  # empty mask: point 0, as the TF code
    # stage composition: stage1 = centroid + T-Net(object points - centroid); centre = stage1 + box[:3]
    with torch.no_grad():
        idx = out.object_indices[..., None].expand(-1, -1, 3)
        obj = torch.gather(pts[..., :3] - out.mask_centroid[:, None], 1, idx)
        delta = m.tnet(obj, torch.eye(3))
        box = m.box(obj - delta[:, None], torch.eye(3))
    assert torch.allclose(out.stage1_center, out.mask_centroid + delta)
    assert torch.allclose(out.center, out.stage1_center + box[:, :3])
    assert torch.allclose(out.size_residuals, box[:, 35:].reshape(3, 8, 3) * m.mean_sizes)


def test_object_point_indices_modes():
    mask = np.zeros((3, 20), dtype=bool)
    mask[0, :15] = True   # more than num
    mask[1, [2, 5, 7]] = True  # fewer than num
    margin = np.tile(np.arange(20.0), (3, 1))
    a = object_point_indices(mask, margin, 8, "random", np.random.default_rng(3))
    b = object_point_indices(mask, margin, 8, "random", np.random.default_rng(3))
    assert np.array_equal(a, b)
    assert len(np.unique(a[0])) == 8 and mask[0, a[0]].all()        # without replacement
    assert set(a[1]) == {2, 5, 7} and mask[1, a[1]].all()            # all of them, plus repeats
    assert (a[2] == 0).all()
    t = object_point_indices(mask, margin, 8, "topk")
    assert t[0].tolist() == [14, 13, 12, 11, 10, 9, 8, 7]              # by decreasing margin
    assert t[1].tolist() == [7, 5, 2, 7, 5, 2, 7, 5]                   # cyclic repeats
    per_row = object_point_indices(mask, margin, 8, "random", [np.random.default_rng(k) for k in range(3)])
    assert mask[1, per_row[1]].all()
    with pytest.raises(ValueError):
        object_point_indices(mask, margin, 8, "random")


def _finite_grads(module: torch.nn.Module, *tensors: torch.Tensor) -> bool:
    grads = [p.grad for p in module.parameters() if p.grad is not None] + [t.grad for t in tensors]
    return all(g is not None and torch.isfinite(g).all() for g in grads)


@pytest.mark.parametrize("train", [True, False])
def test_finite_gradients_with_identical_points(train):
    from robustbench3d.victims.fpointnet.losses import FPointNetTargets, fpointnet_loss

    m = build_model("lite").train(train)
    pts = torch.full((2, 512, 4), 0.7, requires_grad=True)
    gen = torch.Generator().manual_seed(0)
    out = m(pts, torch.eye(3)[:2], gather="random", rng=np.random.default_rng(0), generator=gen)
    t = FPointNetTargets(seg=torch.zeros(2, 512, dtype=torch.int64), center=torch.zeros(2, 3),
                         heading_class=torch.tensor([0, 5]), heading_residual=torch.zeros(2),
                         size_class=torch.tensor([0, 0]), size_residual=torch.zeros(2, 3))
    loss, _ = fpointnet_loss(out, t)
    loss.backward()
    assert torch.isfinite(loss) and _finite_grads(m, pts)


def test_finite_gradients_with_empty_mask():
    from robustbench3d.victims.fpointnet.losses import FPointNetTargets, fpointnet_loss

    m = build_model("lite").eval()
    with torch.no_grad():
        m.seg.classifier.bias.copy_(torch.tensor([1e4, -1e4]))  # every point background
    pts = torch.randn(2, 512, 4, requires_grad=True)
    out = m(pts, torch.eye(3)[:2], gather="topk")
    assert int(out.mask_count.sum()) == 0 and torch.equal(out.mask_centroid, torch.zeros(2, 3))
    t = FPointNetTargets(seg=torch.ones(2, 512, dtype=torch.int64), center=torch.tensor([[0, 1.0, 20], [1, 1, 30]]),
                         heading_class=torch.tensor([1, 2]), heading_residual=torch.tensor([0.1, -0.1]),
                         size_class=torch.tensor([0, 0]), size_residual=torch.zeros(2, 3))
    loss, _ = fpointnet_loss(out, t)
    loss.backward()
    assert torch.isfinite(loss) and _finite_grads(m, pts)
    # the seg logits themselves still give a finite gradient to the points (attack path)
    pts2 = torch.randn(1, 512, 4, requires_grad=True)
    m.seg(pts2, torch.eye(3)[:1]).softmax(-1)[..., 1].max().backward()
    assert torch.isfinite(pts2.grad).all()


def test_forward_is_deterministic_given_generators():
    m = build_model("lite")
    pts = torch.randn(2, 512, 4)
    outs = []
    for _ in range(2):
        torch.manual_seed(123)  # global state must not matter
        outs.append(m.train()(pts, torch.eye(3)[:2], gather="random", rng=np.random.default_rng(7),
                              generator=torch.Generator().manual_seed(9)).center)
        torch.manual_seed(456)
    assert torch.equal(outs[0], outs[1])
    w1, w2 = (build_model("lite", seed=3).seg.classifier.weight for _ in range(2))
    assert torch.equal(w1, w2)


def test_bn_momentum_schedule():
    assert bn_momentum_at(0) == 0.5 and bn_momentum_at(799_999) == 0.5
    assert bn_momentum_at(800_000) == 0.25 and bn_momentum_at(10**9) == 0.01  # decay capped at 0.99


def test_straight_through_mask_keeps_the_forward_and_reaches_the_logits():
    """``straight_through`` changes no forward value (every output bit equal, with masked, unmasked and
    empty-mask frustums) and adds gradient through the segmentation logits: the box centre then depends on
    the classifier's bias, which the hard mask hides from it (finite differences of the soft surrogate)."""
    m = build_model("lite", seed=4).eval()
    gen = torch.Generator().manual_seed(0)
    pts = torch.randn(3, 512, 4, generator=gen) * torch.tensor([2.0, 0.5, 2.0, 0.2]) + torch.tensor([0, 0, 20, 0.3])
    one_hot = torch.eye(3)[[0, 0, 1]]
    with torch.no_grad():  # shift the object logit so about half of frustum 0 is masked
        margin = m.seg(pts, one_hot)[0].diff(dim=-1)
        m.seg.classifier.bias[1] -= margin.median()
    hard = m(pts, one_hot, gather="topk")
    st = m(pts, one_hot, gather="topk", straight_through=1.0)
    assert 0 < int(hard.mask_count[0]) < 512
    for name in ("seg_logits", "mask", "mask_centroid", "object_indices", "center_delta", "center",
                 "heading_scores", "heading_residuals", "size_scores", "size_residuals"):
        assert torch.equal(getattr(hard, name), getattr(st, name)), name
    bias = m.seg.classifier.bias
    (g_hard,) = torch.autograd.grad(hard.center[0, 2], bias, allow_unused=True)
    (g_st,) = torch.autograd.grad(st.center[0, 2], bias)
    assert (g_hard is None or not bool(g_hard[1] != 0)) and torch.isfinite(g_st).all() and g_st[1] != 0
    with torch.no_grad():  # empty mask: point 0 gathered unscaled, the same outputs
        m.seg.classifier.bias.copy_(torch.tensor([1e4, -1e4]))
    empty_hard = m(pts[:1], one_hot[:1], gather="topk")
    empty_st = m(pts[:1], one_hot[:1], gather="topk", straight_through=1.0)
    assert int(empty_st.mask_count[0]) == 0 and torch.equal(empty_hard.center, empty_st.center)
