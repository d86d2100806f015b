"""The fast F-PN trainer (issue 17): row layout = conv layout, tensor batches = make_item's
distribution, the portable frustum cache round trip, bf16 autocast."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from robustbench3d.errors import DataFormatError, RobustBenchError
from robustbench3d.geometry import points_in_boxes
from robustbench3d.kitti.dataset import KittiDataset
from robustbench3d.testing import box_car_dataset
from robustbench3d.victims.fpointnet.batches import TensorFrustums, angle_to_class_torch
from robustbench3d.victims.fpointnet.box_coding import angle_to_class
from robustbench3d.victims.fpointnet.cache import read_frustum_cache, write_frustum_cache
from robustbench3d.victims.fpointnet.data import FrustumSet, build_frustum_set, make_item
from robustbench3d.victims.fpointnet.frustum import rotate_to_frustum
from robustbench3d.victims.fpointnet.model import FULL, build_model
from robustbench3d.victims.fpointnet.training import FPointNetTask, FPointNetTrainConfig
from robustbench3d.victims.fpointnet.training import train as train_fpn
from robustbench3d.victims.training import LoopOptions


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory) -> Path:
    return box_car_dataset(tmp_path_factory.mktemp("tiny_kitti"))


def _inputs(b: int, n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    pts = torch.randn(b, n, 4, generator=g) * torch.tensor([3.0, 1.0, 3.0, 0.3]) + torch.tensor([0.0, 1.0, 20.0, 0.5])
    return pts, torch.eye(3)[torch.zeros(b, dtype=torch.long)]


@pytest.mark.parametrize("train_mode", [False, True])
def test_row_layout_gives_the_conv_layout_outputs_gradients_and_bn_statistics(train_mode):
    """Same arithmetic: in float64 the two layouts agree to rounding (1e-9), in float32 to 1e-4."""
    cfg = replace(FULL, num_points=256, dropout=0.0)  # dropout masks are drawn per layout; all else must agree
    pts, oh = _inputs(4, 256)
    for dtype, tol in ((torch.float64, 1e-9), (torch.float32, 1e-4)):
        conv = build_model(cfg, seed=3).to(dtype)
        rows = build_model(cfg, seed=3).to(dtype).set_layout("rows")
        outs = []
        for model in (conv, rows):
            model.train(train_mode)
            out = model(pts.to(dtype), oh.to(dtype), gather="topk")
            (out.center.sum() + out.seg_logits.square().mean() + out.heading_scores.sum()).backward()
            outs.append(out)
        a, b = outs
        assert torch.equal(a.mask, b.mask)
        torch.testing.assert_close(b.seg_logits, a.seg_logits, rtol=tol, atol=tol)
        if dtype == torch.float64:
            assert torch.equal(a.object_indices, b.object_indices)
            for name in ("center", "heading_scores", "size_residuals"):
                torch.testing.assert_close(getattr(b, name), getattr(a, name), rtol=tol, atol=tol)
            for (name, pa), (_, pb) in zip(conv.named_parameters(), rows.named_parameters(), strict=True):
                torch.testing.assert_close(pb.grad, pa.grad, rtol=1e-7, atol=1e-9, msg=name)
        for (name, ba), (_, bb) in zip(conv.named_buffers(), rows.named_buffers(), strict=True):
            torch.testing.assert_close(bb, ba, rtol=tol, atol=tol, msg=name)
    assert list(conv.state_dict()) == list(rows.state_dict())
    with pytest.raises(ValueError, match="layout"):
        conv.set_layout("nhwc")  # type: ignore[arg-type]


def test_angle_to_class_torch_matches_numpy_at_bin_edges():
    w = 2 * np.pi / 12
    angles = np.concatenate([np.arange(-30, 31) * w / 2, np.linspace(-7, 7, 301), [np.pi, -np.pi, 2 * np.pi]])
    cls, res = angle_to_class(angles)
    tc, tr = angle_to_class_torch(torch.tensor(angles))
    np.testing.assert_array_equal(tc.numpy(), cls)
    np.testing.assert_allclose(tr.numpy(), res, atol=1e-12)


def _hand_set() -> FrustumSet:
    """Two frustums by hand: 3 and 2 points, rotations 0.3 and -0.2 rad."""
    pts = np.array([[1, 0, 10, .1], [2, 1, 11, .2], [0, -1, 9, .3], [-3, 0, 20, .4], [-2, 1, 21, .5]], np.float32)
    return FrustumSet(points=pts, seg=np.array([1, 0, 1, 0, 1], np.uint8), offsets=np.array([0, 3, 5]),
                      box2d=np.zeros((2, 4)), rot_angle=np.array([0.3, -0.2]),
                      center=np.array([[1.0, 0.5, 10.0], [-2.5, 0.8, 20.5]]), ry=np.array([0.5, 3.0]),
                      size_lwh=np.array([[3.9, 1.6, 1.5], [4.2, 1.7, 1.4]]), types=np.array(["Car", "Car"]),
                      frame_ids=np.array(["000000", "000001"]))


def test_tensor_batches_draw_the_rotated_frustum_points_and_targets():
    fs = _hand_set()
    tf = TensorFrustums.from_set(fs)
    idx = np.array([1, 0, 1])
    pts, oh, t = tf.batch(idx, 64, torch.Generator().manual_seed(0))
    assert pts.shape == (3, 64, 4) and oh.tolist() == [[1, 0, 0]] * 3
    for row, i in enumerate(idx):
        ref_pts, ref_seg = fs.frustum(i)
        ref = rotate_to_frustum(ref_pts, fs.rot_angle[i]).astype(np.float32)
        got = pts[row].numpy()
        # every drawn point is one of the frustum's rotated points, with its label; all are drawn
        match = np.abs(got[:, None, :] - ref[None]).max(-1).argmin(1)
        np.testing.assert_allclose(got, ref[match], atol=1e-5)
        np.testing.assert_array_equal(t.seg[row].numpy(), ref_seg[match])
        assert set(match) == set(range(len(ref)))
        item = make_item(fs, int(i), 8, np.random.default_rng(0))
        np.testing.assert_allclose(t.center[row].numpy(), item.center, atol=1e-5)
        assert int(t.heading_class[row]) == item.heading_class
        assert float(t.heading_residual[row]) == pytest.approx(item.heading_residual, abs=1e-6)
        assert int(t.size_class[row]) == item.size_class
        np.testing.assert_allclose(t.size_residual[row].numpy(), item.size_residual, atol=1e-6)


def test_tensor_batches_flip_and_shift_follow_make_item():
    fs = _hand_set()
    tf = TensorFrustums.from_set(fs)
    base, _, t0 = tf.batch(np.zeros(400, np.int64), 4, torch.Generator().manual_seed(1))
    flipped, _, tf_ = tf.batch(np.zeros(400, np.int64), 4, torch.Generator().manual_seed(1), flip=True)
    sign = torch.sign(tf_.center[:, 0] / t0.center[:, 0])
    assert 0.4 < (sign < 0).float().mean() < 0.6  # p = 0.5
    torch.testing.assert_close(flipped[..., 0], base[..., 0] * sign[:, None])
    heading = torch.where(sign < 0, np.pi - (fs.ry[0] - fs.rot_angle[0]), torch.tensor(fs.ry[0] - fs.rot_angle[0]))
    cls, _ = angle_to_class(heading.numpy())
    np.testing.assert_array_equal(tf_.heading_class.numpy(), cls)
    shifted, _, ts = tf.batch(np.zeros(400, np.int64), 4, torch.Generator().manual_seed(1), shift="faithful")
    d = float(torch.hypot(t0.center[0, 0], t0.center[0, 1]))
    delta = ts.center[:, 2] - t0.center[:, 2]
    assert delta.min() >= 0.8 * d - 1e-5 and delta.max() <= 1.2 * d + 1e-5
    torch.testing.assert_close(shifted[..., 2] - base[..., 2], delta[:, None].expand(-1, 4), atol=1e-4, rtol=0)


def _synthetic_frames() -> tuple[FrustumSet, dict]:
    """Two frames of points on a 1 mm / 0.01 grid; P2 a pinhole (f 500, c 600/180); frustums by
    hand (none of the points projects within 0.5 px of a box edge)."""
    p2 = np.array([[500.0, 0, 600, 0], [0, 500, 180, 0], [0, 0, 1, 0]])
    rng = np.random.default_rng(0)
    frames, cols = {}, []
    for f, name in enumerate(["000003", "000007"]):
        pts = np.round(np.concatenate([rng.uniform(-8, 8, (400, 1)), rng.uniform(-1, 2, (400, 1)),
                                       rng.uniform(5, 30, (400, 1))], axis=1), 3)
        uv = pts[:, :2] / pts[:, 2:3] * 500 + [600, 180]
        pts = pts[np.all(np.abs(uv - np.round(uv)) > 0.01, axis=1)]  # none on an integer box edge
        frames[name] = (np.concatenate([pts, np.round(rng.uniform(0, 1, (len(pts), 1)), 2)], axis=1), p2)
        for k, box in enumerate([[500.0, 100, 700, 300], [350.0, 50, 650, 250]]):
            cols.append((name, np.array(box), f + 0.1 * k))
    pts_all, seg_all, counts = [], [], []
    box3d = (np.array([0.0, 0.5, 15.0]), np.array([4.0, 1.8, 1.5]), 0.3)  # centre, l w h, ry
    for name, box, _ in cols:
        p = frames[name][0]
        uv = p[:, :2] / p[:, 2:3] * 500 + [600, 180]
        sel = p[(uv[:, 0] >= box[0]) & (uv[:, 0] < box[2]) & (uv[:, 1] >= box[1]) & (uv[:, 1] < box[3])]
        c, (l, w, h), ry = box3d
        seg = points_in_boxes(sel, np.array([[h, w, l]]), (c + np.array([0, h / 2, 0]))[None], np.array([ry]))[:, 0]
        pts_all.append(sel.astype(np.float32))
        seg_all.append(seg.astype(np.uint8))
        counts.append(len(sel))
    n = len(cols)
    fs = FrustumSet(points=np.concatenate(pts_all), seg=np.concatenate(seg_all),
                    offsets=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
                    box2d=np.array([c[1] for c in cols]), rot_angle=np.array([c[2] for c in cols]),
                    center=np.tile(box3d[0], (n, 1)), ry=np.full(n, box3d[2]), size_lwh=np.tile(box3d[1], (n, 1)),
                    types=np.array(["Car"] * n), frame_ids=np.array([c[0] for c in cols]))
    return fs, frames


def test_frustum_cache_round_trip_is_exact_on_grid_points(tmp_path):
    fs, frames = _synthetic_frames()
    assert fs.seg.any() and not fs.seg.all()
    path = tmp_path / "c.npz"
    write_frustum_cache(path, fs, frames, {"seed": 4})
    got, key = read_frustum_cache(path)
    assert key == {"seed": 4}
    np.testing.assert_array_equal(got.offsets, fs.offsets)
    np.testing.assert_allclose(got.points, fs.points, atol=1e-6)
    np.testing.assert_array_equal(got.seg, fs.seg)
    for name in ("box2d", "rot_angle", "center", "ry", "size_lwh", "types", "frame_ids"):
        np.testing.assert_array_equal(getattr(got, name), getattr(fs, name))


def test_frustum_cache_refuses_a_foreign_or_inconsistent_file(tmp_path):
    bad = tmp_path / "bad.npz"
    np.savez(bad, format=np.array("something else"))
    with pytest.raises(DataFormatError, match="frustum cache"):
        read_frustum_cache(bad)
    fs, frames = _synthetic_frames()
    path = tmp_path / "c.npz"
    write_frustum_cache(path, fs, frames, {})
    with np.load(path) as z:
        d = dict(z)
    d["ry"] = d["ry"][:-1]
    np.savez(bad, **d)
    with pytest.raises(DataFormatError, match="inconsistent") as err:
        read_frustum_cache(bad)
    assert err.value.field == "ry"


def test_training_from_a_cache_matches_the_dataset_set_and_checks_its_key(tiny_data, tmp_path):
    opts = LoopOptions(epochs=1, batch_size=4, seed=0, max_steps=2, progress=False)
    cfg = FPointNetTrainConfig(model="lite", augment_x=2)
    cache = tmp_path / "train.cache.npz"
    train_fpn(tiny_data, tmp_path / "a", cfg, opts, cache=cache, val_limit=0)
    fs, _ = read_frustum_cache(cache)
    ref = FrustumSet.load(tmp_path / "a" / "frustums_train.npz")
    assert len(fs) == len(ref)
    assert np.abs(np.diff(fs.offsets) - np.diff(ref.offsets)).sum() <= 0.002 * len(ref.points)
    same = np.flatnonzero(np.diff(fs.offsets) == np.diff(ref.offsets))
    err = np.array([np.abs(fs.frustum(i)[0] - ref.frustum(i)[0]).max(axis=0) for i in same])
    assert np.mean(err[:, :3].max(axis=1) < 1e-3) > 0.9  # xyz to the 1 mm quantum (a moved edge point shifts a row)
    assert np.median(err[:, 3]) <= 0.005 + 1e-6  # reflectance to the 0.01 quantum
    # a cache built for other augmentation copies is refused; a run without the dataset reads it
    with pytest.raises(RobustBenchError, match="frustum cache was built with"):
        train_fpn(tiny_data, tmp_path / "b", replace(cfg, augment_x=3), opts, cache=cache, val_limit=0)
    state = train_fpn(tmp_path / "no-such-dataset", tmp_path / "c", cfg, opts, cache=cache, val_limit=0)
    assert state["step"] == 2


def test_bf16_step_trains_in_float32_master_weights(tiny_data):
    ds_set = build_frustum_set(KittiDataset(tiny_data, split="train"), np.random.default_rng(0), augment_x=1)
    losses = {}
    for prec in ("fp32", "bf16"):
        task = FPointNetTask(ds_set, None, FPointNetTrainConfig(model="lite", precision=prec, flip=False, shift="off"),
                             seed=0)
        idx = np.arange(min(4, len(ds_set)))
        task.model.train()
        loss, terms = task.loss(idx, np.random.default_rng(0), torch.Generator().manual_seed(0))
        assert loss.dtype == torch.float32 and np.isfinite(list(terms.values())).all()
        loss.backward()
        task.optimizer.step()
        assert all(p.dtype == torch.float32 for p in task.model.parameters())
        losses[prec] = loss.item()
    assert losses["bf16"] == pytest.approx(losses["fp32"], rel=0.05)



def test_bench_times_the_trainers_own_step_and_leaves_the_thread_count():
    from robustbench3d.victims.fpointnet.bench_train import step_times, synthetic_set

    fs = synthetic_set(3, 50)
    assert len(fs) == 3 and fs.seg.any() and not fs.seg.all()
    threads = torch.get_num_threads()
    t = step_times("lite", "fp32", "rows", batch=2, steps=1)
    assert t["wall"] > 0 and t["cpu"] > 0 and torch.get_num_threads() == threads
