"""The roof attack's camera image is rendered only when read (:class:`LazyImageFrame`): a cell with
ground-truth proposals never renders it, a detector cell does, and the image is the eager render's, bit for bit
(the occlusion depth, which needs the target cars, is fetched when the frame is attacked)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch

import robustbench3d.sensors.camera_render as camera_render
from robustbench3d.attacks import create_attack
from robustbench3d.attacks.base import target_cars
from robustbench3d.attacks.depth_cache import CroppedDepth, TabulatedDepth, depth_for_render, render_positions
from robustbench3d.attacks.roof import RoofObjectAttack
from robustbench3d.datasets import GroundTruth
from robustbench3d.kitti.dataset import DeferredImageError, KittiDataset, LazyImageFrame
from robustbench3d.runner.cell import CellFailure, CellInputs, attack_rng, run_cell
from robustbench3d.sensors.lidar_render import render_lidar
from robustbench3d.testing import synth_dataset
from robustbench3d.victims.cascade import CascadeSettings, FPointNetCascade

torch.set_num_threads(1)
FRAMES = 3


pytestmark = pytest.mark.usefixtures("cache")  # a fresh cache per test (conftest)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return synth_dataset(tmp_path_factory.mktemp("synth"), FRAMES, seed=2, val_fraction=1.0)


@pytest.fixture(scope="module")
def victim() -> FPointNetCascade:
    cascade = FPointNetCascade.untrained("lite", "mini", seed=1, settings=CascadeSettings(seed=1))
    cascade.yolo.cfg = dataclasses.replace(cascade.yolo.cfg, max_detections=4)  # bounded random proposals
    return cascade


@pytest.fixture
def calls(monkeypatch) -> dict[str, int]:
    """Counts of camera renders and scene-depth fetches (the attack imports both at call time)."""
    counts = {"render_camera": 0, "scene_depth": 0}
    render, depth = camera_render.render_camera, RoofObjectAttack.scene_depth

    def counted_render(*args, **kwargs):
        counts["render_camera"] += 1
        return render(*args, **kwargs)

    def counted_depth(self, *args, **kwargs):
        counts["scene_depth"] += 1
        return depth(self, *args, **kwargs)

    monkeypatch.setattr(camera_render, "render_camera", counted_render)
    monkeypatch.setattr(RoofObjectAttack, "scene_depth", counted_depth)
    return counts


def _run(victim, dataset: Path, proposals: str, out: Path) -> dict:
    kitti = KittiDataset(dataset, split="val")
    ids = kitti.frame_ids
    gt = GroundTruth(ids, [kitti.labels(f) for f in ids], len(ids), "0" * 64)
    attack = create_attack("random-shape", seed=0)
    attack.bind_dataset(kitti)
    inputs = CellInputs(kitti, gt, seed=0, batch_size=2, classes=("Car",), progress=False)
    return run_cell(victim, "fpointnet-v1-lite", attack, "random-shape", proposals, inputs, out)


def test_gt_proposal_cell_never_renders_the_camera(victim, dataset, tmp_path, calls):
    kitti = KittiDataset(dataset, split="val")
    attacked = sum(len(target_cars(kitti.labels(f))) > 0 for f in kitti.frame_ids)
    assert attacked > 0  # something is attacked
    _run(victim, dataset, "gt", tmp_path / "cell")
    assert calls == {"render_camera": 0, "scene_depth": attacked}  # the depth is the attack's, fetched in apply
    assert len(list((tmp_path / "cell" / "data").iterdir())) == FRAMES


def test_detector_cell_renders_each_attacked_frame_once(victim, dataset, tmp_path, calls):
    kitti = KittiDataset(dataset, split="val")
    attacked = sum(len(target_cars(kitti.labels(f))) > 0 for f in kitti.frame_ids)
    _run(victim, dataset, "detector", tmp_path / "cell")
    assert calls == {"render_camera": attacked, "scene_depth": attacked}


@pytest.mark.parametrize("settings", [{}, {"supersample": 2}, {"cull": False}, {"bound": False}],
                         ids=["default", "even-supersample", "full-image", "lidar-depth"])
def test_lazy_image_is_the_eager_render_bit_for_bit(dataset, calls, settings):
    """Whatever the depth source (cached crops, crops missing the even supersample's pixel centres so that
    the exact scene answers them, the full-image reference, the scan's depth map without a bound dataset)."""
    kitti = KittiDataset(dataset, split="val")
    fid = next(f for f in kitti.frame_ids if len(target_cars(kitti.labels(f))))
    frame = kitti.frame(fid)
    targets = target_cars(frame.labels)
    settings = dict(settings)
    bound = settings.pop("bound", True)
    attack = create_attack("random-shape", seed=0, **settings)
    if bound:
        attack.bind_dataset(kitti)
    out = attack.apply(frame, targets, attack_rng(0, fid))
    assert isinstance(out, LazyImageFrame) and out.image_size == frame.image_size
    bare = dataclasses.replace(out, labels=None)  # what victim_inputs hands the victim
    assert isinstance(bare, LazyImageFrame) and bare.labels is None and bare.image_size == frame.image_size
    assert calls["render_camera"] == 0
    # The eager reference: both renders from the placements the frame's generator gives.
    rng = attack_rng(0, fid)
    placed = attack.place(targets, rng)
    velo = [(frame.calib.rect_to_velo_points(v), attack.obj.faces.copy(), attack.obj.colors.copy()) for v, _ in placed]
    lidar = render_lidar(frame.scan, velo, rng=rng)
    eager = camera_render.render_camera(frame.image, frame.calib,
                                        [(v, attack.obj.faces, attack.obj.colors) for v, _ in placed],
                                        scene_depth=attack.scene_depth(frame, targets),
                                        supersample=attack.supersample, full_image=not attack.cull).image
    assert calls["render_camera"] == 1
    assert out.scan.tobytes() == lidar.scan.tobytes()
    assert bare.image.dtype == np.uint8 and bare.image.tobytes() == eager.tobytes()
    assert not np.array_equal(bare.image, frame.image)  # the objects are in it
    assert out.image is bare.image and calls["render_camera"] == 2  # one render shared by the copies


def test_attack_changed_after_apply_does_not_change_the_image(dataset):
    kitti = KittiDataset(dataset, split="val")
    fid = next(f for f in kitti.frame_ids if len(target_cars(kitti.labels(f))))
    frame = kitti.frame(fid)
    targets = target_cars(frame.labels)
    attack = create_attack("random-shape", seed=0)
    ref = attack.apply(frame, targets, attack_rng(0, fid)).image
    later = attack.apply(frame, targets, attack_rng(0, fid))
    attack.supersample, attack.occlusion = 1, "none"
    assert later.image.tobytes() == ref.tobytes()


def test_a_failing_render_is_the_attacks_error(victim, dataset, tmp_path, monkeypatch):
    def broken(*args, **kwargs):
        raise AttributeError("no camera today")

    monkeypatch.setattr(camera_render, "render_camera", broken)
    kitti = KittiDataset(dataset, split="val")
    fid = next(f for f in kitti.frame_ids if len(target_cars(kitti.labels(f))))
    frame = kitti.frame(fid)
    out = create_attack("random-shape", seed=0).apply(frame, target_cars(frame.labels), attack_rng(0, fid))
    with pytest.raises(DeferredImageError, match=f"frame {fid}: making its image failed: AttributeError"):
        _ = out.image
    with pytest.raises(CellFailure, match=r"attack 'random-shape' failed: frame \d{6}: .*no camera today"):
        _run(victim, dataset, "detector", tmp_path / "cell")
    _run(victim, dataset, "gt", tmp_path / "gt")  # never read: the cell succeeds


def test_made_image_must_have_the_announced_size():
    frame = LazyImageFrame("000007", np.zeros((0, 4), np.float32), None, None, (4, 2),
                           lambda: np.zeros((2, 3, 3), np.uint8))
    assert frame.image_size == (4, 2)
    with pytest.raises(DeferredImageError, match=r"frame 000007: made an image of shape \(2, 3, 3\)"):
        _ = frame.image
    with pytest.raises(AttributeError, match="no attribute 'other'"):
        _ = frame.other


@pytest.mark.parametrize(("supersample", "grow"), [(3, 1.0), (3, 3.0), (2, 1.0)],
                         ids=["within-crops", "object-beyond-its-bounds", "even-supersample"])
def test_the_kept_depth_answers_every_render_query_as_its_source_without_holding_it(dataset, supersample, grow):
    """What an attacked frame keeps of the exact depth: the crops, and the exact depths of the render's queries
    outside them (an object larger than the crops' bounds; pixel centres between an even supersample's samples),
    asked at once -- the values of the source, which reaches the dataset's path and the rebuilt scene."""
    kitti = KittiDataset(dataset, split="val")
    fid = next(f for f in kitti.frame_ids if len(target_cars(kitti.labels(f))))
    frame = kitti.frame(fid)
    targets = target_cars(frame.labels)
    attack = create_attack("random-shape", seed=0, supersample=supersample)
    attack.bind_dataset(kitti)
    source = attack.scene_depth(frame, targets)
    assert isinstance(source, CroppedDepth) and isinstance(source.exact, Callable)
    placed = []
    for v, _ in attack.place(targets, attack_rng(0, fid)):
        centre = v.mean(axis=0)
        placed.append(centre + grow * (v - centre))
    kept = depth_for_render(source, frame.calib, placed, frame.image_size, supersample)
    assert isinstance(kept, CroppedDepth) and kept.exact is None and isinstance(kept._fallback, TabulatedDepth)
    assert (len(kept._fallback.keys) > 0) == (grow > 1 or supersample % 2 == 0)
    u, v = render_positions(frame.calib, placed, frame.image_size, supersample)
    assert kept.depth(u, v).tobytes() == source.depth(u, v).tobytes()
    assert np.isfinite(kept.depth(u, v)).any()  # the queries see the scene
    with pytest.raises(ValueError, match="not tabulated"):  # only the render's queries were asked
        kept.depth(u[:1] + 0.1234, v[:1])  # off every sample grid
