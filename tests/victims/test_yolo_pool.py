"""The 2D detector's strided max-pool: under inference mode the max of four strided slices, the same maxima
as PyTorch's pooling op; with autograd the pooling op itself (its tie rule decides gradients)."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from torch import nn

from robustbench3d.victims.cascade import FPointNetCascade
from robustbench3d.victims.shipped import shipped
from robustbench3d.victims.yolo.model import _MaxPoolStrided


@pytest.mark.parametrize("shape", [(2, 3, 8, 10), (1, 4, 7, 9), (3, 2, 3, 5), (1, 16, 288, 960)])
def test_inference_pool_equals_the_pooling_op(shape: tuple[int, ...]) -> None:
    rng = np.random.default_rng(sum(shape))
    x = torch.from_numpy(rng.normal(size=shape).astype(np.float32))
    x[..., ::3, ::2] = 0.25  # ties
    pool = _MaxPoolStrided(2, 2)
    with torch.inference_mode():
        got = pool(x)
    assert torch.equal(got, F.max_pool2d(x, 2, 2))


def test_with_autograd_the_pool_is_the_pooling_op_ties_and_gradients_included() -> None:
    x = torch.zeros(1, 2, 6, 6)
    x[0, 0, :2, :2] = torch.tensor([[1.0, 1.0], [1.0, 0.5]])
    x.requires_grad_(True)
    y = _MaxPoolStrided(2, 2)(x)
    (y * torch.arange(y.numel(), dtype=torch.float32).reshape(y.shape)).sum().backward()
    ref = x.detach().clone().requires_grad_(True)
    (F.max_pool2d(ref, 2, 2) * torch.arange(y.numel(), dtype=torch.float32).reshape(y.shape)).sum().backward()
    assert torch.equal(x.grad, ref.grad)
    assert x.grad[0, 0, :2, :2].sum() == 0.0 and torch.count_nonzero(x.grad[0, 0, :2, :2]) <= 1  # one winner


def test_the_shipped_detector_heads_equal_those_of_the_plain_pooling_op() -> None:
    weights = shipped("fpointnet-v1-lite")
    assert weights is not None
    yolo = FPointNetCascade.load(weights.path).yolo
    plain = copy.deepcopy(yolo.net)
    for i, block in enumerate(plain.blocks):
        if isinstance(block, _MaxPoolStrided):
            plain.blocks[i] = nn.MaxPool2d(block.kernel_size, block.stride)
    assert any(isinstance(b, _MaxPoolStrided) for b in yolo.net.blocks)
    rng = np.random.default_rng(0)
    h, w = yolo.cfg.input_size[1], yolo.cfg.input_size[0]
    images = rng.uniform(0, 1, size=(2, 3, h, w)).astype(np.float32)
    images[1, :, : h // 3] = 0.5  # a flat band, as the letterbox fill
    got = yolo.run_heads(images)
    with torch.inference_mode():
        want = [t.numpy() for t in plain(torch.from_numpy(images))]
    for g, wnt in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, wnt)
