"""Training entry points on a tiny KITTI-layout dataset (robustbench3d.testing.box_car_dataset):
frustum data (perturbation, targets, augmentations), resume == uninterrupted run, few-step
overfit sanity, the CLI."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from robustbench3d.cli import main
from robustbench3d.errors import RobustBenchError
from robustbench3d.fileio import sha256_file
from robustbench3d.geometry import points_in_boxes
from robustbench3d.kitti import KittiDataset
from robustbench3d.testing import IMAGE_SIZE, box_car_dataset
from robustbench3d.victims.cascade import FPointNetCascade
from robustbench3d.victims.fpointnet.box_coding import angle_to_class
from robustbench3d.victims.fpointnet.data import build_frustum_set, make_item
from robustbench3d.victims.fpointnet.frustum import rotate_to_frustum
from robustbench3d.victims.fpointnet.training import FPointNetTask, FPointNetTrainConfig
from robustbench3d.victims.fpointnet.training import train as train_fpn
from robustbench3d.victims.training import LoopOptions
from robustbench3d.victims.yolo.anchors import wh_iou_np
from robustbench3d.victims.yolo.config import MINI, MINI3, YoloConfig
from robustbench3d.victims.yolo.data import build_image_set
from robustbench3d.victims.yolo.letterbox import letterbox_geometry
from robustbench3d.victims.yolo.model import build_model as build_yolo
from robustbench3d.victims.yolo.training import YoloTask, YoloTrainConfig, average_precision, init_anchors
from robustbench3d.victims.yolo.training import train as train_yolo

torch.set_num_threads(1)

W, H = IMAGE_SIZE


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory) -> Path:
    return box_car_dataset(tmp_path_factory.mktemp("tiny_kitti"))


def test_frustum_set_and_items(tiny_data):
    ds = KittiDataset(tiny_data, split="train")
    val = build_frustum_set(ds, np.random.default_rng(0), augment_x=1, perturb=False)
    n_cars = sum(len(ds.labels(f)) for f in ds.frame_ids)
    assert len(val) == n_cars  # every synthetic car is tall enough and has points
    for i in range(len(val)):
        labels = ds.labels(str(val.frame_ids[i]))
        j = int(np.argmin(np.abs(labels.bbox - val.box2d[i]).sum(axis=1)))
        pts, seg = val.frustum(i)
        inside = points_in_boxes(pts, labels.dimensions[j:j + 1], labels.location[j:j + 1], labels.rotation_y[j:j + 1])
        assert np.array_equal(seg.astype(bool), inside[:, 0]) and seg.sum() > 50
        assert np.allclose(val.center[i], labels.location[j] - [0, labels.dimensions[j, 0] / 2, 0])
    train = build_frustum_set(ds, np.random.default_rng(0), augment_x=5, perturb=True)
    assert len(train) == 5 * n_cars
    assert not np.allclose(train.box2d[0], train.box2d[1])  # perturbed copies differ
    # a plain item: rotated points, centre and heading targets in the frustum frame
    item = make_item(val, 0, 256, np.random.default_rng(1))
    rot = val.rot_angle[0]
    assert item.points.shape == (256, 4) and item.rot_angle == rot
    assert np.allclose(item.center, rotate_to_frustum(val.center[0], rot))
    c, r = angle_to_class(val.ry[0] - rot)
    assert (item.heading_class, item.heading_residual) == (int(c), pytest.approx(float(r)))
    # flip negates x and maps heading h -> pi - h; the faithful shift pushes z by ~0.8·d
    for seed in range(20):
        flipped = make_item(val, 0, 256, np.random.default_rng(seed), flip=True)
        if flipped.center[0] != item.center[0]:
            assert flipped.center[0] == pytest.approx(-item.center[0])
            c2, r2 = angle_to_class(np.pi - (val.ry[0] - rot))
            assert (flipped.heading_class, flipped.heading_residual) == (int(c2), pytest.approx(float(r2)))
            break
    else:
        pytest.fail("flip never happened in 20 draws")
    shifted = make_item(val, 0, 256, np.random.default_rng(3), shift="faithful")
    d = np.hypot(item.center[0], item.center[1])
    assert shifted.center[2] - item.center[2] == pytest.approx(0.8 * d)
    intended = make_item(val, 0, 256, np.random.default_rng(3), shift="intended")
    assert abs(intended.center[2] - item.center[2]) <= 0.2 * d


def _state_dicts_equal(a: Path, b: Path) -> bool:
    sa = torch.load(a, weights_only=True)["state_dict"]
    sb = torch.load(b, weights_only=True)["state_dict"]
    return sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)


def test_fpointnet_resume_reproduces_the_uninterrupted_run(tiny_data, tmp_path):
    cfg = FPointNetTrainConfig(model="lite", augment_x=2)
    opts = LoopOptions(epochs=2, batch_size=4, seed=5, progress=False)
    full = train_fpn(tiny_data, tmp_path / "a", cfg, opts)
    assert full["finished"] and full["step"] >= 4
    interrupted = LoopOptions(**{**opts.__dict__, "max_steps": full["step"] // 2 + 1})
    stopped = train_fpn(tiny_data, tmp_path / "b", cfg, interrupted)
    assert not stopped["finished"] and not (tmp_path / "b" / "model.pt").exists()
    resumed = train_fpn(tiny_data, tmp_path / "b", cfg, opts, resume=True)
    assert resumed["finished"] and resumed["step"] == full["step"]
    assert _state_dicts_equal(tmp_path / "a" / "model.pt", tmp_path / "b" / "model.pt")
    assert (tmp_path / "a" / "log.jsonl").read_text() == (tmp_path / "b" / "log.jsonl").read_text()
    log = [json.loads(x) for x in (tmp_path / "a" / "log.jsonl").read_text().splitlines()]
    assert [r["epoch"] for r in log] == [1, 2] and all(np.isfinite(r["val_loss"]) for r in log)
    with pytest.raises(Exception, match="different configuration"):
        train_fpn(tiny_data, tmp_path / "b", FPointNetTrainConfig(model="lite", augment_x=3), opts, resume=True)


def test_yolo_resume_reproduces_the_uninterrupted_run(tiny_data, tmp_path):
    cfg = YoloTrainConfig(warmup_steps=1)
    opts = LoopOptions(epochs=2, batch_size=2, seed=1, progress=False)
    full = train_yolo(tiny_data, tmp_path / "a", cfg, opts)
    assert full["finished"] and full["step"] == 4
    train_yolo(tiny_data, tmp_path / "b", cfg, LoopOptions(**{**opts.__dict__, "max_steps": 3}))
    resumed = train_yolo(tiny_data, tmp_path / "b", cfg, opts, resume=True)
    assert resumed["finished"]
    assert _state_dicts_equal(tmp_path / "a" / "model.pt", tmp_path / "b" / "model.pt")
    # k-means anchors were fitted to the training boxes and saved with the model
    saved = np.array(torch.load(tmp_path / "a" / "model.pt", weights_only=True)["config"]["anchors"])
    ds = KittiDataset(tiny_data, split="train")
    wh = []
    for fid in ds.frame_ids:
        geo = letterbox_geometry((W, H), MINI.input_size)
        b = geo.to_input(ds.labels(fid).bbox)
        wh.append(b[:, 2:] - b[:, :2])
    wh = np.concatenate(wh)
    assert saved.shape == (6, 2) and np.all(np.diff(saved.prod(axis=1)) >= 0)
    assert wh_iou_np(wh, saved).max(axis=1).mean() > wh_iou_np(wh, np.array(MINI.anchors)).max(axis=1).mean()
    # the two trainers' outputs assemble into a working cascade
    fpn_out = tmp_path / "fpn"
    train_fpn(tiny_data, fpn_out, FPointNetTrainConfig(model="lite", augment_x=1),
              LoopOptions(epochs=1, batch_size=4, progress=False))
    victim = FPointNetCascade.from_parts(tmp_path / "a" / "model.pt", fpn_out / "model.pt")
    frame = KittiDataset(tiny_data, split="val")[0]
    rows = victim.detect([frame], proposals="gt")[0]
    assert len(rows) == len(frame.labels)


def test_yolo_fine_tune_starts_from_the_init_weights_at_a_new_input_size(tiny_data, tmp_path):
    opts = LoopOptions(epochs=1, batch_size=2, seed=0, progress=False)
    train_yolo(tiny_data, tmp_path / "base", YoloTrainConfig(warmup_steps=1), opts)
    base = torch.load(tmp_path / "base" / "model.pt", weights_only=True)
    # lr 0: Adam leaves every weight where the init put it (BN running statistics still move)
    cfg = YoloTrainConfig(warmup_steps=1, lr=0.0, init=str(tmp_path / "base" / "model.pt"), input_size=(320, 96))
    train_yolo(tiny_data, tmp_path / "ft", cfg, opts)
    ft = torch.load(tmp_path / "ft" / "model.pt", weights_only=True)
    assert tuple(ft["config"]["input_size"]) == (320, 96)
    # anchors are in input pixels: halving the input halves them
    assert [list(a) for a in ft["config"]["anchors"]] == [[round(w / 2, 2), round(h / 2, 2)]
                                                         for w, h in base["config"]["anchors"]]
    weights = [k for k in base["state_dict"] if not k.endswith(("running_mean", "running_var", "num_batches_tracked"))]
    assert weights and all(torch.equal(base["state_dict"][k], ft["state_dict"][k]) for k in weights)
    assert ft["train_config"]["init_sha256"] == sha256_file(tmp_path / "base" / "model.pt")
    with pytest.raises(RobustBenchError, match="largest stride 16"):
        train_yolo(tiny_data, tmp_path / "bad", YoloTrainConfig(input_size=(330, 96)), opts)
    with pytest.raises(RobustBenchError, match="is not the start of --layout 'tiny'"):
        train_yolo(tiny_data, tmp_path / "bad", YoloTrainConfig(layout="tiny", init=cfg.init), opts)
    with pytest.raises(RobustBenchError, match="no such YOLO weights file"):
        train_yolo(tiny_data, tmp_path / "bad", YoloTrainConfig(init=str(tmp_path / "missing.pt")), opts)


def test_yolo_mini3_starts_from_trained_mini_weights_with_a_fresh_stride_32_head(tiny_data, tmp_path):
    opts = LoopOptions(epochs=1, batch_size=2, seed=0, progress=False)
    train_yolo(tiny_data, tmp_path / "base", YoloTrainConfig(warmup_steps=1), opts)
    base = torch.load(tmp_path / "base" / "model.pt", weights_only=True)
    cfg = YoloTrainConfig(layout="mini3", warmup_steps=1, lr=0.0, init=str(tmp_path / "base" / "model.pt"),
                          input_size=(640, 192), anchors="config")
    train_yolo(tiny_data, tmp_path / "ft", cfg, opts)
    ft = torch.load(tmp_path / "ft" / "model.pt", weights_only=True)
    fresh = build_yolo(YoloConfig.from_dict(ft["config"]), seed=0).state_dict()
    frozen = ("running_mean", "running_var", "num_batches_tracked")
    inherited = [k for k in ft["state_dict"] if k in base["state_dict"]]
    new = [k for k in ft["state_dict"] if k not in base["state_dict"] and not k.endswith(frozen)]
    assert len(inherited) == len(base["state_dict"]) and new  # every mini tensor, plus the new head's
    assert all(int(k.split(".")[1]) > 19 for k in new)
    assert all(torch.equal(base["state_dict"][k], ft["state_dict"][k]) for k in inherited if not k.endswith(frozen))
    assert all(torch.equal(fresh[k], ft["state_dict"][k]) for k in new)  # the seeded initialisation
    anchors = ft["config"]["anchors"]
    assert [list(a) for a in anchors[:6]] == [list(a) for a in base["config"]["anchors"]]  # same input size
    assert [tuple(a) for a in anchors[6:]] == list(MINI3.anchors[6:])  # --anchors config: the layout's
    with pytest.raises(RobustBenchError, match="is not the start of --layout 'mini'"):
        train_yolo(tiny_data, tmp_path / "bad", YoloTrainConfig(init=str(tmp_path / "ft" / "model.pt")), opts)


def test_kmeans_anchors_need_as_many_training_boxes_as_anchors():
    from robustbench3d.victims.yolo.training import fit_anchors

    boxes = np.array([[0.0, 0, 10, 8], [0, 0, 20, 15], [0, 0, 40, 25]])
    assert len(fit_anchors(boxes, 3, seed=0)) == 3
    with pytest.raises(RobustBenchError, match=r"need at least 6 boxes .* got 3 in the training split; use --anchors"):
        fit_anchors(boxes, 6, seed=0)


def test_init_anchors_scale_with_the_input_and_add_the_largest_clusters():
    rng = np.random.default_rng(0)
    sizes = [(10, 8), (20, 15), (40, 25), (60, 80), (90, 50), (150, 90), (260, 150), (380, 200), (520, 260)]
    wh = np.concatenate([np.asarray(s) * rng.uniform(0.97, 1.03, (30, 2)) for s in sizes])
    boxes = np.concatenate([np.zeros_like(wh), wh], axis=1)
    anchors = init_anchors(MINI, MINI3, boxes, seed=0)
    assert anchors[:6] == tuple((round(w * 1.5, 2), round(h * 1.5, 2)) for w, h in MINI.anchors)  # 640 → 960
    for got, want in zip(anchors[6:], sizes[6:], strict=True):  # the three largest of the nine clusters
        assert got == pytest.approx(want, rel=0.02)
    assert init_anchors(MINI, MINI3, None, seed=0)[6:] == MINI3.anchors[6:]


def test_fpointnet_overfits_a_few_frustums(tiny_data):
    ds = KittiDataset(tiny_data, split="train")
    fs = build_frustum_set(ds, np.random.default_rng(0), augment_x=1)
    task = FPointNetTask(fs, fs, FPointNetTrainConfig(model="lite", flip=False, shift="off"), seed=0)
    idx = np.arange(min(4, len(fs)))
    losses = []
    for _ in range(40):
        task.model.train()
        loss, _ = task.loss(idx, np.random.default_rng(0), torch.Generator().manual_seed(0))
        task.optimizer.zero_grad()
        loss.backward()
        task.optimizer.step()
        losses.append(loss.item())
    assert np.mean(losses[-5:]) < 0.5 * np.mean(losses[:5])


def test_yolo_loss_decreases_on_one_image(tiny_data, tmp_path):
    ds = KittiDataset(tiny_data, split="train")
    images = build_image_set(ds, MINI.input_size, MINI.fill, tmp_path / "images")
    assert images.images.shape == (4, 192, 640, 3) and len(images.targets(0)[0]) == len(ds.labels(ds.frame_ids[0]))
    task = YoloTask(images, images, MINI, YoloTrainConfig(warmup_steps=1), seed=0, epochs=1, steps_per_epoch=1)
    losses = []
    for _ in range(8):
        task.model.train()
        loss, _ = task.loss(np.array([0, 1]), np.random.default_rng(0), torch.Generator())
        task.optimizer.zero_grad()
        loss.backward()
        task.optimizer.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0]


def test_average_precision_by_hand():
    gts = [np.array([[0.0, 0, 10, 10], [20, 20, 30, 30]])]
    # ranked: hit, miss, hit -> precision 1, 1/2, 2/3 at recall 1/2, 1/2, 1 -> AP = 0.5·1 + 0.5·2/3
    boxes = [np.array([[0.0, 0, 10, 10], [50, 50, 60, 60], [20, 20, 30, 31]])]
    scores = [np.array([0.9, 0.8, 0.7])]
    assert average_precision(scores, boxes, gts, 0.5) == pytest.approx(0.5 + 0.5 * 2 / 3)
    assert average_precision(scores, boxes, gts, 0.95) == pytest.approx(0.5)


def test_train_cli(tiny_data, tmp_path, capsys):
    out = tmp_path / "cli"
    argv = ["train", "fpointnet", "--data", str(tiny_data), "--out", str(out), "--epochs", "1", "--model", "lite",
            "--batch-size", "4", "--augment-x", "1", "--no-progress", "--threads", "1"]
    assert main(argv) == 0
    assert (out / "model.pt").exists() and (out / "last.pt").exists() and (out / "frustums_train.npz").exists()
    assert "finished" in capsys.readouterr().err


def test_zoom_augmentation_moves_content_and_boxes_together():
    from robustbench3d.victims.yolo.data import zoom

    rng = np.random.default_rng(0)
    img = rng.integers(0, 255, (48, 96, 3)).astype(np.uint8)
    out, (b,) = zoom(img, [np.array([[10.0, 20, 50, 40]])], 1.0, (0.0, 0.0), 128)
    assert np.array_equal(out, img) and np.array_equal(b, [[10.0, 20, 50, 40]])
    img = np.full((48, 96, 3), 128, np.uint8)
    img[10:20, 30:50] = 255
    for scale, off in ((1.2, (-8.0, -4.0)), (0.8, (12.0, 6.0))):
        out, (b,) = zoom(img, [np.array([[30.0, 10, 50, 20]])], scale, off, 128)
        ys, xs = np.nonzero(out[..., 0] > 191)  # pixels more than half covered by the white patch
        assert np.allclose(b, [[xs.min(), ys.min(), xs.max() + 1, ys.max() + 1]], atol=1.0)
        assert np.allclose(b, [[30 * scale + off[0], 10 * scale + off[1], 50 * scale + off[0], 20 * scale + off[1]]])
    # a box pushed mostly out of view is dropped, one partly out is clipped
    _, (b,) = zoom(img, [np.array([[0.0, 0, 20, 10], [60, 10, 96, 30]])], 1.0, (-15.0, 0.0), 128)
    assert np.allclose(b, [[45.0, 10, 81, 30]])


def test_cosine_lr_endpoints():
    from robustbench3d.victims.training import cosine_lr

    assert cosine_lr(1e-3, 0, 100, 1e-5) == pytest.approx(1e-3)
    assert cosine_lr(1e-3, 50, 100, 1e-5) == pytest.approx((1e-3 + 1e-5) / 2)
    assert cosine_lr(1e-3, 100, 100, 1e-5) == pytest.approx(1e-5)
    assert cosine_lr(1e-3, 250, 100, 1e-5) == pytest.approx(1e-5)
