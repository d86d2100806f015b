"""The one differentiable victim interface (issue #35): ``attack train`` scores every white-box victim through
``target_scores(AttackedScene, AttackTargets) -> TargetScores``.

* the F-PN cascades: the interface gives exactly the numbers of their frustum oracles (the largest
  object-minus-background margin of a frustum's logits, the regressed box), and a training step through it has the
  losses and gradients, bit for bit, of the trainer before the interface (its LiDAR code kept here as the
  reference);
* any other victim: a tiny whole-scene torch detector written here (no frustums, ``detector`` proposals only) is
  trained by the real trainer through the LiDAR, one through the camera, one through both; the refusals (no
  gradients, a mode whose sensor the victim does not use, frustum ``--lidar-boxes``) are one line each, before the
  data is read; ``check_victim`` accepts a victim that implements ``target_scores`` alone.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from robustbench3d.attacks.base import target_cars
from robustbench3d.attacks.train import UniversalTrainer
from robustbench3d.attacks.train_config import TrainConfig, TrainingError, check_oracles
from robustbench3d.attacks.train_run import train_universal
from robustbench3d.cli import main
from robustbench3d.datasets import load_ground_truth, resolve_dataset
from robustbench3d.kitti.labels import Labels
from robustbench3d.victims import VICTIMS
from robustbench3d.victims.base import (
    AttackedScene,
    AttackTargets,
    Proposals,
    TargetScoreOracle,
    TargetScores,
    check_victim,
    gt_proposals,
)
from robustbench3d.victims.spec import Capabilities, EntryInfo, VictimSpec

FAST = {"batch_cars": 4, "occlusion": "none", "supersample": 1, "eval_every": 0}

pytestmark = pytest.mark.usefixtures("cache")  # a fresh cache per test (conftest)


@pytest.fixture(scope="module")
def dataset(shared_split) -> Path:
    """Generated frames 0-3; train: 1 and 2 (25 cars)."""
    return shared_split(4, seed=0, val_fraction=0.5)


@pytest.fixture(scope="module")
def data(dataset):
    resolved = resolve_dataset(dataset, "train", progress=False)
    return resolved, load_ground_truth(resolved)


def rect_points(frame) -> torch.Tensor:
    """(N, 4) float64 rect-frame xyz and reflectance of the frame's scan."""
    xyz = frame.calib.velo_to_rect_points(frame.scan[:, :3].astype(np.float64))
    return torch.from_numpy(np.concatenate([xyz, frame.scan[:, 3:4].astype(np.float64)], axis=1))


def margin(logits: torch.Tensor) -> torch.Tensor:
    """The reference logit of a frustum: the largest object-minus-background margin, in float64."""
    l64 = logits.to(torch.float64)
    return (l64[:, 1] - l64[:, 0]).max()


# ---- (a) the F-PN cascades: the interface is their oracles ---------------------------------------------------------
def test_fpn_target_scores_are_the_frustum_oracles_margin_and_box(lite_victim, data):
    """Per target with a proposal: the logit is the margin of ``frustum_logits`` (``with_box``: of
    ``frustum_box``'s logits, and the box its centre, l/w/h and heading), a ``gt-append`` box's rows joining its
    frustum; a target without a proposal (-1) is absent; gradients reach the points through the logits."""
    resolved, gt = data
    frame = resolved.kitti().frame(gt.frame_ids[0])
    targets = target_cars(frame.labels)
    props = lite_victim.proposals([replace(frame, labels=None)], [gt_proposals(frame.labels)])[0]
    # a gt-append set: the first box gets 40 rows of the scan added to its frustum
    extra = tuple(np.arange(40, dtype=np.int64) if k == 0 else np.zeros(0, np.int64) for k in range(len(props.boxes)))
    appended = Proposals(props.boxes, props.scores, "gt-append", props.types, extra)
    index = [int(np.flatnonzero(np.all(props.boxes == b, axis=1))[0]) for b in targets.bbox]
    index[-1] = -1  # the last car: no proposal
    boxes3d = np.column_stack([targets.location, targets.dimensions, targets.rotation_y])
    aimed = AttackTargets(targets.bbox, boxes3d, index)
    points = rect_points(frame).requires_grad_(True)
    assert isinstance(lite_victim, TargetScoreOracle)
    for given in (props, appended):
        scene = AttackedScene(replace(frame, labels=None), points, None, given)
        plain = lite_victim.target_scores(scene, aimed)
        boxed = lite_victim.target_scores(scene, aimed, with_box=True)
        assert plain.box is None and boxed.box.shape == (len(targets), 7)
        for n, j in enumerate(index):
            if j < 0:
                assert not plain.present[n] and not boxed.present[n]
                continue
            where: dict[str, Any] = {"frame_id": frame.frame_id, "proposal": j}
            if given.extra_points is not None:
                where["extra_points"] = given.extra_points[j]
            fl = lite_victim.frustum_logits(points, frame.calib, frame.image_size, given.boxes[j], **where)
            fb = lite_victim.frustum_box(points, frame.calib, frame.image_size, given.boxes[j], **where)
            assert plain.present[n] == (fl is not None) and boxed.present[n] == (fb is not None)
            if fl is None:
                continue
            assert torch.equal(plain.logit[n], margin(fl.logits))
            assert torch.equal(boxed.logit[n], margin(fb.logits))
            want = np.concatenate([fb.center.detach().numpy(), fb.size_lwh.detach().numpy(), [fb.heading.item()]])
            np.testing.assert_array_equal(boxed.box[n].detach().numpy(), want)
        assert plain.present.sum() >= 3
        (grad,) = torch.autograd.grad(plain.logit[torch.from_numpy(plain.present)].sum(), points)
        assert torch.isfinite(grad).all() and grad.abs().sum() > 0
    # the appended rows changed the first car's frustum (and only its)
    first = [lite_victim.target_scores(AttackedScene(frame, points, None, given), aimed).logit[0]
             for given in (props, appended)]
    assert not torch.equal(*first)


class LegacyTrainer(UniversalTrainer):
    """The trainer's LiDAR term as it was before the interface (commit 8049a4e, verbatim but for the names it
    imports): the frustum oracles called directly, the seed paper's and the box losses of their outputs."""

    def _lidar(self, frame, targets, chosen, placed, poses, colours, rng, attacked_image):
        from robustbench3d.attacks.losses import box_car_loss, gt_bev_boxes, lidar_car_loss
        from robustbench3d.attacks.placement import rect_to_velo
        from robustbench3d.attacks.record import target_rows
        from robustbench3d.attacks.train import (
            _bev_iou_per_target,
            _matched_index,
            _object_proposals,
            _proposal_index,
            _velo_to_rect_torch,
        )
        from robustbench3d.attacks.train_config import EOT_DROPOUT, EOT_RANGE_NOISE_M, OBJECT_LIDAR_BOXES
        from robustbench3d.sensors.lidar_render import render_lidar

        cfg, calib = self.config, frame.calib
        albedo = colours.detach().numpy()
        res = render_lidar(frame.scan, [(rect_to_velo(p, calib), self._faces, albedo) for p in placed], rng=rng,
                           range_noise_m=EOT_RANGE_NOISE_M if "range-noise" in cfg.eot else 0.0,
                           dropout=EOT_DROPOUT if "dropout" in cfg.eot else 0.0)
        k = len(res.added)
        kept = res.scan[:len(res.scan) - k, :3].astype(np.float64)
        xyz = torch.cat([torch.from_numpy(calib.velo_to_rect_points(kept)),
                         _velo_to_rect_torch(res.added_torch, calib.velo_to_rect)])
        points = torch.cat([xyz, torch.from_numpy(res.scan[:, 3:4].astype(np.float64))], dim=1)
        attacked = replace(frame, scan=np.ascontiguousarray(res.scan, dtype=np.float32), labels=None,
                           image=frame.image if attacked_image is None else attacked_image)
        with torch.no_grad():
            if cfg.lidar_boxes == "detector":
                props = self.victim.proposals([attacked], "detector")[0]
                index = _matched_index(props.boxes, targets)
                scored = props
            elif cfg.lidar_boxes in OBJECT_LIDAR_BOXES:
                rows = target_rows(frame.labels, targets)
                scored = _object_proposals(frame, attacked, targets, rows, poses, res, cfg.lidar_boxes,
                                           self.family.bounds)
                props = self.victim.proposals([attacked], [scored])[0]
                index = _proposal_index(props.boxes, targets, scored.boxes[rows])
            else:
                props = self._proposals(frame)
                index = _proposal_index(props.boxes, targets)
                scored = gt_proposals(frame.labels)
            if cfg.lidar_loss == "seed":
                iou = _bev_iou_per_target(self.victim.detect([attacked], [scored])[0], targets)[chosen]
            else:
                iou = np.zeros(len(chosen))
        gt_boxes = gt_bev_boxes(targets)
        terms = []
        for n, t in enumerate(chosen):
            j = index[t]
            if j is None:
                continue
            where: dict[str, Any] = dict(frame_id=frame.frame_id, proposal=j)
            if props.extra_points is not None:
                where["extra_points"] = props.extra_points[j]
            if cfg.lidar_loss == "seed":
                fl = self.victim.frustum_logits(points, calib, frame.image_size, props.boxes[j], **where)
                if fl is not None:
                    terms.append(lidar_car_loss(fl.logits.to(torch.float64), float(iou[n]), cfg.iou_floor))
                continue
            fb = self.victim.frustum_box(points, calib, frame.image_size, props.boxes[j], **where)
            if fb is None:
                continue
            box_iou = box_car_loss(fb.center, fb.size_lwh, fb.heading, gt_boxes[t])
            iou[n] = box_iou.item()
            term = cfg.lambda_box * box_iou
            if cfg.lidar_loss == "seed+box":
                term = term + lidar_car_loss(fb.logits.to(torch.float64), float(iou[n]), cfg.iou_floor)
            terms.append(term)
        return terms, iou


@pytest.mark.parametrize(("mode", "boxes", "loss", "eot"), [
    ("adv-shape", "gt", "seed", ()),
    ("adv-shape", "gt", "box", ()),
    ("adv-shape", "gt-append", "seed+box", ("jitter", "range-noise", "dropout")),
    ("adv-shape", "gt-object", "seed", ()),
    ("adv-object", "detector", "seed", ("dropout",)),
])
def test_fpn_step_through_the_interface_equals_the_direct_oracle_trainer(lite_victim, data, mode, boxes, loss, eot):
    """Two steps (the second after an Adam update) and the held-out losses of the trainer, whose LiDAR term goes
    through ``target_scores``, equal those of the trainer that called the frustum oracles itself, bit for bit:
    every loss, count and gradient."""
    resolved, gt = data
    cfg = TrainConfig(**{**FAST, "mode": mode, "lidar_boxes": boxes, "lidar_loss": loss, "eot": eot,
                         "lambda_box": 2.0, "batch_cars": 6})
    new, old = (cls(lite_victim, resolved.kitti(), gt.frame_ids, gt.labels, cfg)
                for cls in (UniversalTrainer, LegacyTrainer))
    for step in range(2):
        a, b = new.compute_step(step), old.compute_step(step)
        assert a.losses == b.losses and a.losses["lidar"] > 0
        assert (a.cars, a.detected, a.clean_cars, a.detected_clean) == (b.cars, b.detected, b.clean_cars,
                                                                         b.detected_clean)
        assert all(torch.equal(x, y) for x, y in zip(a.grads, b.grads, strict=True))
        assert any(bool(g.any()) for g in a.grads)
        new.apply_step(a)
        old.apply_step(b)
    assert new.heldout_losses(gt.frame_ids[:1], "h") == old.heldout_losses(gt.frame_ids[:1], "h")


# ---- (b) any victim: a whole-scene detector written here ------------------------------------------------------------
#: The toy LiDAR detector: a car stands out by its tallest points: logit = (smooth maximum, ``TAU`` m soft, of the
#: heights over the box bottom of the points in its BEV footprint - ``TALL`` m) x ``GAIN``.
TAU, TALL, GAIN = 0.1, 1.0, 4.0


def toy_lidar_logits(points_rect: torch.Tensor, boxes3d: np.ndarray) -> torch.Tensor:
    """(T,) logits of the toy LiDAR detector; boxes (T, 7): bottom-centre x, y, z, h, w, l, rotation_y (rect
    frame, y down)."""
    p = points_rect[:, :3].to(torch.float64)
    out = []
    for x, y, z, _, w, length, ry in np.asarray(boxes3d, dtype=np.float64):
        dx, dz = p[:, 0] - x, p[:, 2] - z
        u, v = np.cos(ry) * dx - np.sin(ry) * dz, np.sin(ry) * dx + np.cos(ry) * dz
        log_inside = (torch.nn.functional.logsigmoid((length / 2 - u.abs()) / TAU)
                      + torch.nn.functional.logsigmoid((w / 2 - v.abs()) / TAU))
        height = y - p[:, 1]
        top = TAU * torch.logsumexp(height / TAU + log_inside, dim=0)
        out.append((top - TALL) * GAIN)
    return torch.stack(out) if out else torch.zeros(0, dtype=torch.float64)


def mean_brightness(image: torch.Tensor, boxes2d: np.ndarray) -> torch.Tensor:
    """(T,) mean of the (H, W, 3) image in [0, 1] over each 2D box grown upwards by half its height (where a roof
    object shows; whole pixels inside it)."""
    out = []
    for left, top, right, bottom in np.asarray(boxes2d, dtype=np.float64):
        top = max(0.0, top - (bottom - top) / 2)
        region = image[int(np.ceil(top)):int(bottom) + 1, int(np.ceil(left)):int(right) + 1]
        out.append(region.mean())
    return torch.stack(out)


class ToyVictim:
    """A whole-scene detector that knows where each frame's cars may be (``anchors``: frame id -> Car labels, its
    "prior") and reports an anchor when its logit is positive: LiDAR how tall the points in the anchor's footprint
    stand (:func:`toy_lidar_logits`), camera the brightness of its 2D box, fusion their sum. ``target_scores``
    gives the same logit on the targets' boxes, so the attack lowers exactly what ``detect`` thresholds. It records
    what it is handed."""

    supported_proposals = ("detector",)

    def __init__(self, anchors: dict[str, Labels] | None = None, sensors: tuple[str, ...] = ("lidar",)) -> None:
        self.anchors, self.sensors = anchors or {}, sensors
        self.detect_calls: list[Any] = []
        self.scenes: list[tuple[AttackedScene, AttackTargets]] = []

    def _logits(self, points: torch.Tensor, image: torch.Tensor | None, frame, boxes3d, boxes2d) -> torch.Tensor:
        out = torch.zeros(len(boxes3d), dtype=torch.float64)
        if "lidar" in self.sensors:
            out = out + toy_lidar_logits(points, boxes3d)
        if "camera" in self.sensors:
            if image is None:
                image = torch.from_numpy(frame.image.astype(np.float64) / 255.0)
            out = out + (mean_brightness(image, boxes2d) - 0.25) * 20.0
        return out

    def detect(self, frames, proposals="detector") -> list[Labels]:
        self.detect_calls.append(proposals)
        assert proposals == "detector", "handed a proposal mode it does not list"
        out = []
        for frame in frames:
            cars = self.anchors.get(frame.frame_id, Labels.empty()).of_types(("Car",))
            with torch.no_grad():
                boxes3d = np.column_stack([cars.location, cars.dimensions, cars.rotation_y])
                logit = self._logits(rect_points(frame), None, frame, boxes3d, cars.bbox).numpy()
            keep = logit > 0
            out.append(replace(cars.select(keep), score=1.0 / (1.0 + np.exp(-logit[keep]))))
        return out

    def target_scores(self, scene: AttackedScene, targets: AttackTargets, *, with_box: bool = False) -> TargetScores:
        self.scenes.append((scene, targets))
        logit = self._logits(scene.points_rect, scene.image, scene.frame, targets.boxes3d, targets.boxes2d)
        box = None
        if with_box:  # it regresses the targets' boxes exactly: centre, l/w/h, rotation_y
            b = targets.boxes3d
            centre = b[:, :3] - np.column_stack([np.zeros(len(b)), b[:, 3] / 2, np.zeros(len(b))])
            box = torch.from_numpy(np.column_stack([centre, b[:, 5], b[:, 4], b[:, 3], b[:, 6]]))
        return TargetScores(logit=logit, present=np.ones(len(targets), dtype=bool), box=box)


def _caps(*modalities: str, gradients: bool = True) -> Capabilities:
    return Capabilities(modalities, "torch", gradients=gradients, deterministic=True)


#: Registered for the command-line refusals (factories of empty-prior toys: they are refused before any call).
TOYS = {"test-iface-lidar": (("lidar",), True), "test-iface-camera": (("camera",), True),
        "test-iface-fusion": (("camera", "lidar"), True), "test-iface-nograd": (("lidar",), False)}
for _name, (_sensors, _grad) in TOYS.items():
    if _name not in VICTIMS:
        VICTIMS.register(_name, VictimSpec(factory=lambda s=_sensors: ToyVictim(sensors=s),
                                           info=EntryInfo(_caps(*_sensors, gradients=_grad), summary="TEST ONLY")))


def toy(data, sensors: tuple[str, ...]) -> ToyVictim:
    _, gt = data
    return ToyVictim(dict(zip(gt.frame_ids, gt.labels, strict=True)), sensors)


def trainer_of(victim, data, **kw) -> UniversalTrainer:
    resolved, gt = data
    return UniversalTrainer(victim, resolved.kitti(), gt.frame_ids, gt.labels, TrainConfig(**{**FAST, **kw}))


def run_steps(trainer: UniversalTrainer, steps: int) -> list[Any]:
    out = []
    for s in range(steps):
        result = trainer.compute_step(s)
        assert all(torch.isfinite(g).all() for g in result.grads)
        out.append(result)
        trainer.apply_step(result)
    return out


def test_a_lidar_only_whole_scene_victim_is_trained_through_its_target_scores(data):
    """adv-shape against the LiDAR toy: every scene has no proposals and every target index -1, the points carry
    gradients and no image is rendered; its detect is only ever asked for its own detections; the same 25 cars
    each step, so a few Adam steps (the object sinks onto the roofs) lower the loss, and the LiDAR loss is the
    independent formula ``mean over cars of max(IoU_k, 0.1) softplus(logit)`` with ``IoU_k`` 1 for a car its
    detect reports (its boxes are the labels') and 0 otherwise."""
    victim = toy(data, ("lidar",))
    trainer = trainer_of(victim, data, mode="adv-shape", batch_cars=25, lr_shape=0.05)
    first, *_, last = run_steps(trainer, 4)
    assert last.losses["lidar"] < first.losses["lidar"] - 1e-3
    assert any(bool(g.any()) for g in first.grads)
    assert set(victim.detect_calls) == {"detector"}
    scenes = victim.scenes
    assert scenes and all(s.proposals is None and s.image is None and s.points_rect.requires_grad
                          and np.all(t.proposal == -1) for s, t in scenes)
    # the first step's LiDAR loss by hand, from the first step's scenes (the step's frames, in order)
    total, cars = 0.0, 0
    for scene, aimed in scenes[:2]:
        with torch.no_grad():
            logit = toy_lidar_logits(scene.points_rect, aimed.boxes3d)
        seen = logit.numpy() > 0  # what its detect reports on this attacked frame: IoU 1, else none
        weight = np.where(seen, 1.0, 0.1)
        total += float((weight * torch.nn.functional.softplus(logit).numpy()).sum())
        cars += len(aimed)
    assert cars == 25 and first.losses["lidar"] == pytest.approx(total / cars, rel=1e-9)


def test_a_camera_victim_without_objectness_is_trained_through_the_image(data):
    """adv-texture against the camera toy: the scene's image is the differentiable attacked image (its points
    carry no gradient), the loss is ``softplus(logit)`` per car, and a few colour steps lower it."""
    victim = toy(data, ("camera",))
    trainer = trainer_of(victim, data, mode="adv-texture", batch_cars=25, lr_color=0.2)
    first, *_, last = run_steps(trainer, 3)
    assert last.losses["image"] < first.losses["image"] - 1e-3
    scene, aimed = victim.scenes[0]
    assert scene.image.requires_grad and scene.image.dtype == torch.float64
    assert scene.image.shape == (*scene.frame.image.shape[:2], 3) and not scene.points_rect.requires_grad
    with torch.no_grad():
        logit = (mean_brightness(scene.image, aimed.boxes2d) - 0.25) * 20.0
    assert len(aimed) > 0 and torch.nn.functional.softplus(logit).sum().item() > 0
    assert set(victim.detect_calls) == {"detector"}


def test_a_fusion_victim_gets_one_scene_per_sensor_term(data):
    """adv-object against the fusion toy: the LiDAR term's scene carries gradients in its points (no image), the
    image term's in its image (points detached), both terms are present and both parameters get gradient; the
    held-out losses go through the same terms."""
    victim = toy(data, ("camera", "lidar"))
    trainer = trainer_of(victim, data, mode="adv-object")
    (result,) = run_steps(trainer, 1)
    assert {"lidar", "image"} <= set(result.losses)
    assert all(bool(g.any()) for g in result.grads)  # shape and colour
    kinds = {(s.points_rect.requires_grad, s.image is not None and s.image.requires_grad) for s, _ in victim.scenes}
    assert kinds == {(True, False), (False, True)}
    _, gt = data
    held = trainer.heldout_losses(gt.frame_ids[:1], "held-out")
    assert {"lidar", "image", "laplacian", "total"} <= set(held) and np.isfinite(held["total"])


def test_a_generic_victim_trains_end_to_end_with_a_detector_curve(shared_split, tmp_path):
    """``train_universal`` on the LiDAR toy (registered, lidar, gradients) with the held-out curve: the curve
    scores its own detections (``detector``), the object file is written."""
    root = shared_split(6, seed=0, val_fraction=0.0)
    resolved = resolve_dataset(root, "train", progress=False)
    gt = load_ground_truth(resolved)
    victim = ToyVictim(dict(zip(gt.frame_ids, gt.labels, strict=True)), ("lidar",))
    cfg = TrainConfig(**{**FAST, "mode": "adv-shape", "steps": 2, "eval_every": 2, "eval_frames": 1})
    made_by = train_universal(victim, {"name": "test-iface-lidar"}, resolved.kitti(), gt.frame_ids, gt.labels, cfg,
                              tmp_path / "o.ply", progress=False)
    assert made_by["curve"]["held_out"]["proposals"] == "detector"
    assert made_by["lidar_proposals"].startswith("none: the victim finds the cars itself")
    assert (tmp_path / "o.ply").is_file() and set(victim.detect_calls) == {"detector"}


# ---- (c) refusals: one line, before the data is read ---------------------------------------------------------------
@pytest.mark.parametrize(("victim", "args", "message"), [
    ("test-iface-lidar", ["adv-texture"], "victim 'test-iface-lidar' cannot be attacked with adv-texture: the mode "
                                          "attacks through the camera, which the victim does not use (modalities: "
                                          "lidar)"),
    ("test-iface-camera", ["adv-object"], "victim 'test-iface-camera' cannot be attacked with adv-object: the mode "
                                          "attacks through the lidar, which the victim does not use (modalities: "
                                          "camera)"),
    ("test-iface-lidar", ["adv-shape", "--lidar-boxes", "gt-append"],
     "field 'lidar_boxes' (--lidar-boxes): 'gt-append' builds frustums, but victim 'test-iface-lidar' has no "
     "frustum oracles"),
    ("test-iface-fusion", ["adv-object", "--lidar-boxes", "detector"], "'detector' builds frustums"),
    ("test-iface-nograd", ["adv-shape"], "victim 'test-iface-nograd' has no gradients (registered with "
                                         "gradients=False): gradient training cannot attack it; --optimizer cma "
                                         "attacks it by queries"),
])
def test_refusals_are_one_line_before_the_data(tmp_path, capsys, victim, args, message):
    out = tmp_path / "x.ply"
    code = main(["attack", "train", *args, "--victim", victim, "--data", str(tmp_path / "no-such-data"),
                 "--out", str(out), "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.startswith("robustbench3d: error: ") and message in err and "\n" not in err
    assert not any(tmp_path.iterdir())  # nothing written, the missing data never looked at


def test_a_frustum_victim_is_refused_a_proposal_mode_it_does_not_list(lite_victim):
    class GtOnly:
        supported_proposals = ("gt",)
        frustum_logits = lite_victim.frustum_logits
        segmentation_logits = lite_victim.segmentation_logits
        num_points = lite_victim.num_points

        def detect(self, frames, proposals="detector"):
            return []

    check_oracles(GtOnly(), "adv-shape", "gt-only", "gt")
    with pytest.raises(TrainingError, match=r"^field 'lidar_boxes' \(--lidar-boxes\): victim 'gt-only' does not "
                                            r"accept the proposal mode 'gt-append' \(its supported_proposals: gt\)$"):
        check_oracles(GtOnly(), "adv-shape", "gt-only", "gt-append")


# ---- (d) the contract check -------------------------------------------------------------------------------------
def test_check_victim_accepts_a_victim_with_target_scores_alone():
    for sensors in (("lidar",), ("camera",), ("camera", "lidar")):
        check_victim(ToyVictim(sensors=sensors), _caps(*sensors))

    class DetectOnly:
        supported_proposals = ("detector",)

        def detect(self, frames, proposals="detector"):
            return []

    with pytest.raises(TypeError, match="declares gradients but implements no oracle protocol"):
        check_victim(DetectOnly(), _caps("lidar"))
    check_victim(DetectOnly(), _caps("lidar", gradients=False))


# ---- the example plugin's surrogate ----------------------------------------------------------------------------------
def test_the_cluster_plugins_target_scores_follow_its_points(data):
    """examples/lidar_cluster_victim: the logit of a car is a soft count of its non-ground points minus the
    clustering's ``min_points``: removing the car's points lowers it below 0, the points carry finite gradients,
    and a car the detector reports has a positive logit."""
    plugin = pytest.importorskip("rb3d_lidar_cluster")
    from robustbench3d.eval.iou import bev_iou

    resolved, gt = data
    victim = plugin.build()
    frame = replace(resolved.kitti().frame(gt.frame_ids[0]), labels=None)
    cars = target_cars(gt.labels[0])
    boxes3d = np.column_stack([cars.location, cars.dimensions, cars.rotation_y])
    aimed = AttackTargets(cars.bbox, boxes3d, -np.ones(len(cars), dtype=np.int64))
    points = rect_points(frame).requires_grad_(True)
    scores = victim.target_scores(AttackedScene(frame, points, None, None), aimed)
    assert scores.present.all() and scores.logit.shape == (len(cars),)
    (grad,) = torch.autograd.grad(scores.logit.sum(), points)
    assert torch.isfinite(grad).all() and grad.abs().sum() > 0
    det = victim.detect([frame])[0]
    if len(det):
        boxes = np.column_stack([det.dimensions, det.location, det.rotation_y])
        truth = np.column_stack([cars.dimensions, cars.location, cars.rotation_y])
        found = bev_iou(truth, boxes).max(axis=1) >= 0.5
        assert found.any() and (scores.logit.detach().numpy()[found] > 0).all()
    # the points inside the first car's footprint removed: its logit drops below 0
    with torch.no_grad():
        x, _, z, _, w, length, ry = boxes3d[0]
        p = points.detach().numpy()
        u = np.cos(ry) * (p[:, 0] - x) - np.sin(ry) * (p[:, 2] - z)
        v = np.sin(ry) * (p[:, 0] - x) + np.cos(ry) * (p[:, 2] - z)
        keep = ~((np.abs(u) < length / 2 + 0.5) & (np.abs(v) < w / 2 + 0.5))
        emptied = replace(frame, scan=frame.scan[keep])
        after = victim.target_scores(AttackedScene(emptied, points.detach()[torch.from_numpy(keep)], None, None),
                                     aimed)
    assert after.logit[0] < 0 < scores.logit[0]
