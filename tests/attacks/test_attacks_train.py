"""Universal optimisation (``attack train``) on two generated training frames against the shipped victim:
what each mode changes, determinism, resume, the loss going down, and the refusals and stops."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from robustbench3d.attacks.base import target_cars
from robustbench3d.attacks.object import NEUTRAL_GREY, TANH_EPS, template_vertices
from robustbench3d.attacks.objectfile import read_object_file
from robustbench3d.attacks.placement import cars_of, place_on_roof
from robustbench3d.attacks.train import UniversalTrainer
from robustbench3d.attacks.train_config import TrainConfig, TrainingError
from robustbench3d.attacks.train_run import checkpoint_path, data_identity, train_universal
from robustbench3d.cli import main
from robustbench3d.datasets import dataset_identity, load_ground_truth, resolve_dataset
from robustbench3d.victims.cascade import FPointNetCascade

FAST = {"batch_cars": 4, "occlusion": "none", "supersample": 1}


pytestmark = pytest.mark.usefixtures("cache")  # a fresh cache per test (conftest)


@pytest.fixture(scope="module")
def dataset(shared_split) -> Path:
    """Generated frames 0-3; train: 1 and 2 (25 cars)."""
    return shared_split(4, seed=0, val_fraction=0.5)


@pytest.fixture(scope="module")
def data(dataset):
    resolved = resolve_dataset(dataset, "train", progress=False)
    gt = load_ground_truth(resolved)
    return resolved, gt


@pytest.fixture(scope="module")
def victim(lite_victim) -> FPointNetCascade:
    return lite_victim  # the session's shared one (conftest): read only


def train(victim, data, out: Path, **kw):
    resolved, gt = data
    config = TrainConfig(**{**FAST, **{k: v for k, v in kw.items() if k not in ("resume", "on_step")}})
    return train_universal(victim, {"name": "fpointnet-v1-lite"}, resolved.kitti(), gt.frame_ids, gt.labels, config,
                           out, data_identity=data_identity(dataset_identity(resolved, gt), resolved.root),
                           resume=kw.get("resume", False), progress=False, on_step=kw.get("on_step"))


def test_adv_shape_moves_vertices_keeps_grey_and_records_provenance(victim, data, tmp_path):
    made_by = train(victim, data, tmp_path / "s.ply", mode="adv-shape", steps=3)
    loaded = read_object_file(tmp_path / "s.ply")
    obj = loaded.obj
    assert np.all(obj.colors == np.round(NEUTRAL_GREY * 255) / 255)
    # the start (delta = 0) is the template scaled by 1 - TANH_EPS; three steps of 5e-3 move it by millimetres
    assert np.abs(obj.vertices() - (1 - TANH_EPS) * template_vertices()).max() > 2e-3
    assert np.all(np.abs(obj.vertices()) <= obj.bounds)
    side = loaded.made_by
    assert side == json.loads(json.dumps(made_by))
    assert side["attack"] == "adv-shape" and side["steps"] == 3 and side["seed"] == 0 and side["cars"] == 25
    assert side["victim"]["name"] == "fpointnet-v1-lite"
    assert side["losses"]["weights"] == {"lidar": 1.0, "laplacian": 0.01}
    assert set(side["losses"]["last_step"]) >= {"lidar", "laplacian", "total"}
    assert side["training_data"]["split"] == "train" and len(side["training_data"]["sha256"]) == 64
    assert len(side["training_data"]["manifest_sha256"]) == 64  # a generated dataset has a manifest
    assert side["config"]["lr_shape"] == 5e-3 and side["wall_time_s"] > 0


def test_adv_texture_changes_only_colours_and_lowers_its_loss(victim, data):
    """Full batches of all 25 cars without EOT: every step sees the same cars, and the image loss is smooth
    in the colours, so a few small Adam steps lower it."""
    resolved, gt = data
    config = TrainConfig(mode="adv-texture", steps=4, **{**FAST, "batch_cars": 25})
    trainer = UniversalTrainer(victim, resolved.kitti(), gt.frame_ids, gt.labels, config)
    first = trainer.compute_step(0)
    trainer.apply_step(first)
    for s in range(1, 4):
        trainer.apply_step(trainer.compute_step(s))
    after = trainer.compute_step(4)
    assert after.losses["image"] < first.losses["image"] - 1e-4
    obj = trainer.current_object()
    np.testing.assert_array_equal(obj.vertices(), template_vertices())
    assert np.abs(obj.colors - NEUTRAL_GREY).max() > 1 / 255


def test_same_command_same_bytes(victim, data, tmp_path):
    kw = {"mode": "adv-object", "steps": 2, "eot": ("jitter", "range-noise", "dropout")}
    train(victim, data, tmp_path / "a.ply", **kw)
    train(victim, data, tmp_path / "b.ply", **kw)
    assert (tmp_path / "a.ply").read_bytes() == (tmp_path / "b.ply").read_bytes()
    sa, sb = (read_object_file(tmp_path / f"{n}.ply").made_by for n in "ab")
    sa.pop("wall_time_s")
    sb.pop("wall_time_s")
    assert sa == sb
    # another seed draws other cars and other EOT draws: another object
    train(victim, data, tmp_path / "c.ply", **kw, seed=1)
    assert (tmp_path / "c.ply").read_bytes() != (tmp_path / "a.ply").read_bytes()


class Stop(Exception):
    pass


def test_resume_equals_uninterrupted(victim, data, tmp_path):
    kw = {"mode": "adv-object", "steps": 4, "checkpoint_every": 2, "eot": ("jitter",)}
    train(victim, data, tmp_path / "full.ply", **kw)

    def interrupt(trainer):
        if trainer.step == 3:  # after the checkpoint of step 2, before that of step 4
            raise Stop

    with pytest.raises(Stop):
        train(victim, data, tmp_path / "part.ply", **kw, on_step=interrupt)
    assert not (tmp_path / "part.ply").exists()
    assert torch.load(checkpoint_path(tmp_path / "part.ply"), weights_only=True)["step"] == 2
    train(victim, data, tmp_path / "part.ply", **kw, resume=True)
    assert (tmp_path / "part.ply").read_bytes() == (tmp_path / "full.ply").read_bytes()
    hist = [read_object_file(tmp_path / f"{n}.ply").made_by["losses"] for n in ("part", "full")]
    assert hist[0] == hist[1]
    # a checkpoint of another configuration is refused
    with pytest.raises(TrainingError, match=r"another training.*config.lr_shape"):
        train(victim, data, tmp_path / "part.ply", **{**kw, "steps": 5}, lr_shape=1e-3, resume=True)


class NoProposals(FPointNetCascade):
    """The shipped victim without a way to enumerate its own 2D proposals."""

    proposals = None


def test_lidar_loss_on_the_detectors_boxes(victim, data, tmp_path):
    kw = {"mode": "adv-object", "steps": 2}
    made_by = train(victim, data, tmp_path / "d.ply", **kw, lidar_boxes="detector")
    assert made_by["lidar_proposals"] == "the victim's 2D detections on the attacked image"
    assert made_by["config"]["lidar_boxes"] == "detector" and made_by["losses"]["last_step"]["lidar"] > 0
    train(victim, data, tmp_path / "g.ply", **kw)
    assert (tmp_path / "d.ply").read_bytes() != (tmp_path / "g.ply").read_bytes()  # other frustums, other object
    with pytest.raises(TrainingError, match=r"does not implement proposals\(frames, source\)"):
        train(as_class(victim, NoProposals), data, tmp_path / "x.ply", **kw, lidar_boxes="detector")


class NoOracles:
    supported_proposals = ("detector", "gt")

    def detect(self, frames, proposals="detector"):
        return []


class ObjectnessOnly(NoOracles):
    def objectness(self, images, targets, *, iou_threshold=0.3):
        raise AssertionError("not called: refused up front")


@pytest.mark.parametrize("mode", ["adv-shape", "adv-texture", "adv-object"])
def test_victim_without_oracle_is_refused(data, tmp_path, mode):
    """No oracle at all: no gradients, and the query-based optimiser named; a LiDAR term without target_scores
    (nor frustum oracles): the missing interface named."""
    with pytest.raises(TrainingError, match=r"victim 'fpointnet-v1-lite' has no gradients \(it implements no "
                                            r"white-box oracle.*--optimizer cma attacks it by queries$"):
        train(NoOracles(), data, tmp_path / "x.ply", mode=mode, steps=1)
    if mode != "adv-texture":
        with pytest.raises(TrainingError, match=rf"cannot be attacked with {mode}: it does not implement "
                                                r"TargetScoreOracle \(target_scores, for the LiDAR loss\)$"):
            train(ObjectnessOnly(), data, tmp_path / "x.ply", mode=mode, steps=1)
    assert not (tmp_path / "x.ply").exists()


def test_data_without_cars_is_refused_by_the_cli(dataset, tmp_path, capsys):
    root = tmp_path / "nocars"
    for sub in ("calib", "image_2", "velodyne", "label_2"):
        (root / "training" / sub).mkdir(parents=True)
        for f in (dataset / "training" / sub).iterdir():
            target = root / "training" / sub / f.name
            if sub == "label_2":
                target.write_text("".join(r + "\n" for r in f.read_text().splitlines() if not r.startswith("Car ")))
            else:
                target.symlink_to(f)
    (root / "ImageSets").mkdir()
    (root / "ImageSets" / "train.txt").write_text((dataset / "ImageSets" / "train.txt").read_text())
    code = main(["attack", "train", "adv-shape", "--victim", "fpointnet-v1-lite", "--data", str(root),
                 "--out", str(tmp_path / "o.ply"), "--steps", "1", "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2 and "has no target cars (label type Car)" in err and "Traceback" not in err
    code = main(["attack", "train", "adv-shape", "--victim", "fpointnet-v1-lite", "--data", str(root),
                 "--out", str(tmp_path / "o.ply"), "--eot", "jitter,fog"])
    assert code == 2 and "--eot jitter,fog: unknown fog" in capsys.readouterr().err
    code = main(["attack", "train", "adv-object", "--victim", "fpointnet-v1-lite", "--data", str(root),
                 "--out", str(tmp_path / "o.ply"), "--steps", "0"])
    assert code == 2 and "field 'steps' (--steps): must be an integer >= 1, got 0" in capsys.readouterr().err
    assert not (tmp_path / "o.ply").exists() and not checkpoint_path(tmp_path / "o.ply").exists()


def test_cli_trains_and_reports(dataset, tmp_path, capsys):
    out = tmp_path / "cli.ply"
    code = main(["attack", "train", "adv-shape", "--victim", "fpointnet-v1-lite", "--victim-arg", "seed=0",
                 "--data", str(dataset), "--out", str(out), "--steps", "1", "--batch-cars", "2", "--no-progress",
                 "--eot", "all", "--seed", "3"])
    printed = capsys.readouterr().out
    assert code == 0 and f"{out}: adv-shape after 1 steps on 25 cars" in printed and "lidar" in printed
    side = read_object_file(out).made_by
    assert side["config"]["eot"] == ["jitter", "range-noise", "dropout"] and side["seed"] == 3
    assert side["victim"]["kwargs"] == {"seed": "0"} and checkpoint_path(out).is_file()


class NaNVictim(FPointNetCascade):
    """The shipped victim with NaN segmentation logits."""

    def frustum_logits(self, *args, **kwargs):
        out = super().frustum_logits(*args, **kwargs)
        return None if out is None else type(out)(out.logits * float("nan"), out.sample_index, out.rot_angle,
                                                  out.points)


class BlindVictim(FPointNetCascade):
    """The shipped victim whose segmentation ignores its input points (no gradient reaches the object)."""

    def frustum_logits(self, *args, **kwargs):
        out = super().frustum_logits(*args, **kwargs)
        return None if out is None else type(out)(out.logits.detach(), out.sample_index, out.rot_angle, out.points)


def as_class(victim, cls):
    other = object.__new__(cls)
    other.__dict__.update(victim.__dict__)
    return other


def test_nan_loss_stops_with_a_clear_message(victim, data, tmp_path):
    with pytest.raises(TrainingError, match=r"step 0: the loss of frame \d+ is not finite"):
        train(as_class(victim, NaNVictim), data, tmp_path / "n.ply", mode="adv-shape", steps=3)
    assert not (tmp_path / "n.ply").exists()


def test_zero_gradient_stops_after_patience(victim, data, tmp_path):
    with pytest.raises(TrainingError, match=r"no gradient for 2 consecutive steps.*last checkpoint"):
        train(as_class(victim, BlindVictim), data, tmp_path / "z.ply", mode="adv-shape", steps=5,
              zero_grad_patience=2, checkpoint_every=1)


class NoBoxOracle(FPointNetCascade):
    """The shipped victim without the box oracle."""

    frustum_box = None


def test_box_term_trains_the_regressed_boxes_iou(victim, data, tmp_path):
    """``lidar_loss="box"``: the LiDAR term is the mean BEV IoU of the regressed boxes (in [0, 1], the
    victim's own boxes: a car whose clean box matches its label well gives about its detection IoU); with
    ``"seed+box"`` the seed term is added (a larger loss); a bad name and a victim without the box oracle
    are refused up front."""
    kw = {"mode": "adv-shape", "steps": 2}
    box = train(victim, data, tmp_path / "b.ply", **kw, lidar_loss="box")
    both = train(victim, data, tmp_path / "s.ply", **kw, lidar_loss="seed+box", lambda_box=2.0)
    first_box, first_both = box["losses"]["first_step"]["lidar"], both["losses"]["first_step"]["lidar"]
    assert 0.0 < first_box <= 1.0 and first_both > 2 * first_box  # the same cars: 2 x IoU + a positive seed term
    assert box["config"]["lidar_loss"] == "box" and both["config"]["lambda_box"] == 2.0
    with pytest.raises(TrainingError, match=r"field 'lidar_loss' \(--lidar-loss\): expected one of seed, box"):
        TrainConfig(mode="adv-shape", lidar_loss="iou")
    with pytest.raises(TrainingError, match=r"does not implement FrustumBoxOracle \(frustum_box"):
        train(as_class(victim, NoBoxOracle), data, tmp_path / "x.ply", **kw, lidar_loss="box")


@pytest.mark.parametrize("boxes", ["gt", "detector"])
def test_box_terms_weight_the_seed_term_by_the_box_detect_reports_for_the_car(victim, data, boxes):
    """With the box term on, ``IoU_k`` of each car is the BEV IoU (the evaluator's) with its label of the box
    the victim regresses from the car's own frustum on the attacked frame (the row ``detect`` writes for that
    proposal, where ``detect`` keeps it), and the car's term is ``lambda_box IoU_k + max(IoU_k, floor)
    softplus(max margin)`` of that frustum's logits."""
    from dataclasses import replace

    import torch.nn.functional as F

    from robustbench3d.attacks.placement import rect_to_velo
    from robustbench3d.attacks.train import _matched_index, _proposal_index
    from robustbench3d.eval.iou import bev_iou
    from robustbench3d.sensors.lidar_render import render_lidar

    resolved, gt = data
    cfg = TrainConfig(**{**FAST, "mode": "adv-object", "lidar_loss": "seed+box", "lambda_box": 2.0,
                         "lidar_boxes": boxes})
    trainer = UniversalTrainer(victim, resolved.kitti(), gt.frame_ids, gt.labels, cfg)
    frame = trainer._frame(trainer.frame_ids[0], with_image=True)
    targets = target_cars(frame.labels)
    chosen = list(range(len(targets)))
    placed, poses = zip(*[place_on_roof(trainer.vertices(), car) for car in cars_of(targets)], strict=True)
    placed = list(placed)
    attacked_image = trainer._render_image(frame, targets, placed, trainer.colours())
    terms, iou = trainer._lidar(frame, targets, chosen, placed, list(poses), trainer.colours(), trainer.eot_rng(0),
                                attacked_image)
    # the reference: the attacked scan rendered again (no EOT noise in this config), the victim's own proposals
    albedo = trainer.colours().detach().numpy()
    scan = render_lidar(frame.scan, [(rect_to_velo(p, frame.calib), trainer._faces, albedo) for p in placed]).scan
    seen = replace(frame, scan=np.ascontiguousarray(scan, dtype=np.float32), labels=None, image=attacked_image)
    props = victim.proposals([seen], "detector")[0] if boxes == "detector" else trainer._proposals(frame)
    index = (_matched_index if boxes == "detector" else _proposal_index)(props.boxes, targets)
    rows = victim.detect([seen], [props])[0]
    points = torch.from_numpy(np.concatenate([frame.calib.velo_to_rect_points(scan[:, :3].astype(np.float64)),
                                              scan[:, 3:4].astype(np.float64)], axis=1))
    k = against_detect = 0
    for t in chosen:
        j = index[t]
        fb = None if j is None else victim.frustum_box(points, frame.calib, frame.image_size, props.boxes[j],
                                                       frame_id=frame.frame_id, proposal=j)
        if fb is None:
            assert iou[t] == 0.0
            continue
        c, (length, width, _), ry = fb.center.detach().numpy(), fb.size_lwh.detach().numpy(), fb.heading.item()
        label = np.array([[*targets.dimensions[t], *targets.location[t], targets.rotation_y[t]]])
        box = np.array([[0.0, width, length, c[0], 0.0, c[2], ry]])  # h, w, l, x, y, z, ry
        want = bev_iou(label, box)[0, 0]
        assert iou[t] == pytest.approx(want, abs=1e-3)
        row = np.flatnonzero(np.all(rows.bbox == props.boxes[j], axis=1))
        if len(row):  # detect kept the proposal: the same box
            r = int(row[0])
            det = np.column_stack([rows.dimensions, rows.location, rows.rotation_y])[r:r + 1]
            assert iou[t] == pytest.approx(bev_iou(label, det)[0, 0], abs=1e-3)
            against_detect += 1
        margin = (fb.logits[:, 1] - fb.logits[:, 0]).max().double()
        assert terms[k].item() == pytest.approx(2.0 * iou[t] + max(iou[t], 0.1) * F.softplus(margin).item(),
                                                rel=1e-4, abs=1e-4)
        k += 1
    assert k == len(terms) and against_detect >= 3 and (iou >= 0.7).sum() >= 3


def test_image_loss_summed_over_the_candidates_that_can_still_detect_a_car(victim, data, tmp_path):
    """``image_loss="sum"`` (``--image-loss sum``): per car the sum of -log(1 - o c) over its candidates of IoU
    >= 0.5, not the mean over all of them; the same cars and object at step 0, so the summed loss equals the
    hand sum from the victim's candidates; recorded in the config; a bad name is refused."""
    from robustbench3d.attacks.losses import neg_log_one_minus_product

    kw = {"mode": "adv-texture", "steps": 1}
    mean = train(victim, data, tmp_path / "m.ply", **kw)
    summed = train(victim, data, tmp_path / "s.ply", **kw, image_loss="sum")
    assert mean["config"]["image_loss"] == "mean" and summed["config"]["image_loss"] == "sum"
    first_mean, first_sum = mean["losses"]["first_step"]["image"], summed["losses"]["first_step"]["image"]
    assert first_sum > first_mean  # the confident candidates summed, not averaged with the weak ones
    # the step-0 image loss by hand: the trainer's first batch, the grey sphere, the victim's candidates
    resolved, gt = data
    trainer = UniversalTrainer(victim, resolved.kitti(), gt.frame_ids, gt.labels,
                               TrainConfig(**{**FAST, **kw, "image_loss": "sum"}))
    by_frame: dict[int, list[int]] = {}
    for fi, k in trainer.batch(0):
        by_frame.setdefault(fi, []).append(k)
    total = 0.0
    for fi, chosen in by_frame.items():
        frame = trainer._frame(trainer.frame_ids[fi], with_image=True)
        targets = target_cars(frame.labels)
        placed = [place_on_roof(trainer.vertices(), car)[0] for car in cars_of(targets)]
        cands = victim.objectness(_rendered(trainer, frame, targets, placed), [targets.bbox[chosen]])
        keep = cands.iou >= 0.5
        total += neg_log_one_minus_product(cands.objectness_logit[keep], cands.class_logit[keep]).sum().item()
    assert first_sum == pytest.approx(total / sum(len(c) for c in by_frame.values()), rel=1e-6)
    with pytest.raises(TrainingError, match=r"field 'image_loss' \(--image-loss\): expected one of mean, sum"):
        TrainConfig(mode="adv-texture", image_loss="max")


def _rendered(trainer, frame, targets, placed) -> torch.Tensor:
    """(1, 3, H, W) float32 camera image with the trainer's object on every car, as its image loss sees it."""
    from robustbench3d.sensors.camera_render import render_camera_torch

    image = torch.from_numpy(frame.image.astype(np.float64) / 255.0)
    out = render_camera_torch(image, frame.calib, [(p, trainer._faces, trainer.colours()) for p in placed],
                              scene_depth=trainer._depth.scene_depth(frame, targets),
                              supersample=trainer.config.supersample)
    return out.permute(2, 0, 1)[None].float()


@pytest.mark.parametrize("source", ["gt-object", "gt-append"])
def test_training_under_a_frustum_protocol_builds_the_cells_proposals(victim, data, source):
    """``--lidar-boxes gt-object|gt-append``: the proposals of the LiDAR term are those a benchmark cell of the
    same object hands the victim (the runner's ``apply_recorded`` record through ``victim_inputs``): the same
    union boxes, the same appended rows of the same attacked scan."""
    from dataclasses import replace

    from robustbench3d.attacks.base import attack_rng
    from robustbench3d.attacks.placement import rect_to_velo
    from robustbench3d.attacks.record import target_rows
    from robustbench3d.attacks.roof import RoofObjectAttack
    from robustbench3d.attacks.train import _object_proposals
    from robustbench3d.sensors.lidar_render import render_lidar
    from robustbench3d.victims.base import victim_inputs

    resolved, gt = data
    cfg = TrainConfig(**{**FAST, "mode": "adv-shape", "lidar_boxes": source, "eval_every": 0})
    trainer = UniversalTrainer(victim, resolved.kitti(), gt.frame_ids, gt.labels, cfg)
    frame = trainer._frame(trainer.frame_ids[0], with_image=True)
    targets = target_cars(frame.labels)
    assert len(targets) >= 2
    placed, poses = zip(*[place_on_roof(trainer.vertices(), car) for car in cars_of(targets)], strict=True)
    albedo = trainer.colours().detach().numpy()
    res = render_lidar(frame.scan, [(rect_to_velo(p, frame.calib), trainer._faces, albedo) for p in placed])
    attacked = replace(frame, scan=np.ascontiguousarray(res.scan, dtype=np.float32), labels=None)
    mine = _object_proposals(frame, attacked, targets, target_rows(frame.labels, targets), list(poses), res, source)

    cell_frame, record = RoofObjectAttack(trainer.current_object()).apply_recorded(
        frame, targets, attack_rng(0, frame.frame_id))
    assert cell_frame.scan.shape == attacked.scan.shape
    assert np.allclose(cell_frame.scan, attacked.scan, rtol=0, atol=1e-5)
    _, (theirs,) = victim_inputs([cell_frame], [frame.labels], source, objects=[record])
    assert mine.source == theirs.source == source
    assert np.allclose(mine.boxes, theirs.boxes, rtol=0, atol=1e-4)
    if source == "gt-object":
        assert mine.extra_points is None and not np.array_equal(mine.boxes, gt_proposals_of(frame).boxes)
    else:
        assert all(np.array_equal(a, b) for a, b in zip(mine.extra_points, theirs.extra_points, strict=True))
        assert sum(len(a) for a in mine.extra_points) == len(res.added) > 0


def gt_proposals_of(frame):
    from robustbench3d.victims.base import gt_proposals

    return gt_proposals(frame.labels)
