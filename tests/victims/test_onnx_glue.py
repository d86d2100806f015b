"""The numpy inference glue shared by the torch and the ONNX victim, against its torch twins:
letterbox (torch's antialiased resize), YOLO head decoding, the F-PN stage composition, and the
batch invariance that makes a frustum's box independent of its batch."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from robustbench3d.kitti.dataset import KittiDataset
from robustbench3d.victims.fpointnet.glue import run_frustum_stages
from robustbench3d.victims.fpointnet.model import TorchFrustumStages, build_model
from robustbench3d.victims.fpointnet.to_kitti import decode
from robustbench3d.victims.yolo.letterbox import image_to_tensor, letterbox
from robustbench3d.victims.yolo.model import build_model as build_yolo
from robustbench3d.victims.yolo.model import flatten
from robustbench3d.victims.yolo.postprocess import decode_heads, head_masks, sigmoid
from robustbench3d.victims.yolo.preprocess import letterbox_image, resize_taps

torch.set_num_threads(1)


@pytest.mark.parametrize(("n_in", "n_out"), [(1242, 636), (375, 192), (100, 384), (7, 3), (5, 5)])
def test_resize_taps_are_torchs_weights(n_in, n_out):
    """Resizing the identity (one image per input pixel) reveals torch's weight matrix."""
    eye = torch.eye(n_in).reshape(n_in, 1, 1, n_in)
    ref = F.interpolate(eye, size=(1, n_out), mode="bilinear", align_corners=False, antialias=True)[:, 0, 0, :].T
    index, weight = resize_taps(n_in, n_out)
    dense = np.zeros((n_out, n_in))
    np.add.at(dense, (np.repeat(np.arange(n_out), index.shape[1]), index.ravel()), weight.ravel())
    assert np.abs(dense - ref.numpy()).max() <= 1e-7
    assert np.allclose(dense.sum(axis=1), 1.0, atol=1e-6)


def test_numpy_letterbox_matches_the_differentiable_one(kitti_samples):
    ds = KittiDataset(kitti_samples, split=None)
    rng = np.random.default_rng(0)
    images = [ds.image(ds.frame_ids[3]), rng.integers(0, 256, (370, 1224, 3), dtype=np.uint8),
              rng.integers(0, 256, (90, 200, 3), dtype=np.uint8)]  # KITTI, another KITTI size, upscaling
    for image in images:
        got, geo = letterbox_image(image, (640, 192), fill=0.5)
        ref, ref_geo = letterbox(image_to_tensor(image), (640, 192), fill=0.5)
        assert geo == ref_geo and got.shape == (3, 192, 640) and got.dtype == np.float32
        assert np.abs(got - ref[0].numpy()).max() <= 1e-6  # bit-identical where torch uses FMA
    with pytest.raises(ValueError, match="uint8"):
        letterbox_image(images[0].astype(np.float32), (640, 192))


@pytest.mark.parametrize("layout", ["mini", "mini3"])
def test_head_decoding_matches_flatten(layout):
    net = build_yolo(layout, seed=2).eval()
    w, h = net.cfg.input_size
    with torch.no_grad():
        heads = [h * 4 for h in net(torch.rand(2, 3, h, w, generator=torch.Generator().manual_seed(0)))]
    pred = flatten(heads, net)
    boxes, obj, cls = decode_heads([h.numpy() for h in heads], net.cfg)
    assert head_masks(net.cfg) == net.head_masks
    assert np.allclose(boxes, pred.boxes.numpy(), rtol=1e-6, atol=1e-4)
    assert np.array_equal(obj, pred.obj_logit.numpy()) and np.array_equal(cls, pred.cls_logit.numpy())
    with pytest.raises(ValueError, match="head"):
        decode_heads([heads[0].numpy()], net.cfg)


def test_sigmoid_is_stable():
    x = np.array([-1e4, -50, 0, 50, 1e4], dtype=np.float32)
    y = sigmoid(x)
    assert y.dtype == np.float32 and np.isfinite(y).all()
    assert np.allclose(y, torch.sigmoid(torch.from_numpy(x)).numpy(), rtol=1e-6, atol=0)


def _perturbed_fpn(seed: int, calibration: np.ndarray):
    """Seeded lite F-PN with a non-zero T-Net head and the seg bias set so that about half of the
    ``calibration`` points are foreground (an untrained net masks all or nothing)."""
    m = build_model("lite", seed=seed).eval()
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        m.tnet.out.weight.normal_(0, 0.05, generator=gen)  # the T-Net head starts at zero
        m.tnet.out.bias.normal_(0, 0.1, generator=gen)
        logits = m.seg(torch.from_numpy(calibration), torch.eye(3)[:1].expand(len(calibration), 3))
        m.seg.classifier.bias[1] -= (logits[..., 1] - logits[..., 0]).median()
    return m


def test_glue_composition_matches_the_training_forward():
    """The numpy pipeline (inference) and FrustumPointNetV1.forward (training) are twins."""
    rng = np.random.default_rng(1)
    pts = rng.normal(0, 1, (3, 512, 4)).astype(np.float32)
    pts[..., 2] += 15
    m = _perturbed_fpn(5, pts)
    one_hot = np.eye(3, dtype=np.float32)
    glue = run_frustum_stages(TorchFrustumStages(m), pts, one_hot, 512, "topk")
    with torch.no_grad():
        ref = m(torch.from_numpy(pts), torch.from_numpy(one_hot), gather="topk")
    assert np.array_equal(glue.mask, ref.mask.numpy()) and np.array_equal(glue.object_indices, ref.object_indices)
    assert glue.mask.any(axis=1).all() and not glue.mask.all()  # a non-trivial mask
    for name in ("mask_centroid", "stage1_center", "center", "heading_residuals", "size_residuals"):
        assert np.allclose(getattr(glue, name), getattr(ref, name).numpy(), atol=2e-5), name
    a, b = decode(glue), decode(ref)
    assert np.allclose(a.center, b.center, atol=2e-5) and np.allclose(a.size_lwh, b.size_lwh, atol=2e-5)
    assert np.allclose(a.score_3d, b.score_3d, rtol=1e-5)


def test_a_frustum_result_does_not_depend_on_its_batch():
    rng = np.random.default_rng(2)
    pts = rng.normal(0, 1, (5, 512, 4)).astype(np.float32)
    stages = TorchFrustumStages(_perturbed_fpn(6, pts))
    one_hot = np.tile(np.eye(3, dtype=np.float32)[:1], (5, 1))
    full = run_frustum_stages(stages, pts, one_hot, 512, "topk")
    for order in ([4, 3, 2, 1, 0], [2], [1, 3]):
        part = run_frustum_stages(stages, pts[order], one_hot[order], 512, "topk")
        for name in ("seg_logits", "center", "heading_scores", "size_residuals"):
            assert np.array_equal(getattr(part, name), getattr(full, name)[order]), (order, name)


def test_inference_glue_imports_no_torch():
    code = ("import sys\n"
            "import robustbench3d.victims.fpointnet.pipeline, robustbench3d.victims.yolo.postprocess\n"
            "import robustbench3d.victims.onnx.runtime, robustbench3d.victims.onnx.manifest\n"
            "print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
