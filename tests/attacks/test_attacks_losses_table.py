"""The trainer looks its image loss up in ``attacks.losses.IMAGE_LOSSES`` by name: a registered loss is what it
computes, on the candidate set the loss declares, and ``mean`` and ``sum`` are the hand values on the victim's
candidates (the table itself: ``tests/attacks/test_attacks_losses.py``)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hand_losses import nl

from robustbench3d.attacks.losses import register_image_loss
from robustbench3d.victims.base import ObjectnessCandidates


def test_train_config_takes_a_registered_name(table):
    from robustbench3d.attacks.train_config import TrainConfig, TrainingError

    with pytest.raises(TrainingError, match=r"field 'image_loss' \(--image-loss\): expected one of mean, sum, got"):
        TrainConfig(mode="adv-texture", image_loss="probe")
    register_image_loss("probe", lambda c, n, i, u: torch.zeros(n))
    assert TrainConfig(mode="adv-texture", image_loss="probe").image_loss == "probe"


# ---- the trainer looks the loss up by name --------------------------------------------------------------------


@pytest.fixture(scope="module")
def data(shared_split):
    from robustbench3d.datasets import load_ground_truth, resolve_dataset

    root = shared_split(4, seed=0, val_fraction=0.5)
    resolved = resolve_dataset(root, "train", progress=False)
    return resolved, load_ground_truth(resolved)


@pytest.fixture(scope="module")
def victim(lite_victim):
    return lite_victim  # the session's shared one (conftest): read only


def _image_term(victim, data, image_loss: str) -> tuple[torch.Tensor, torch.Tensor, list[int]]:
    """The trainer's image terms of its first batch's first frame (grey sphere on the chosen cars), the image it
    renders for them (1, 3, H, W) and the chosen cars' indices among the frame's targets."""
    from robustbench3d.attacks.base import target_cars
    from robustbench3d.attacks.placement import cars_of, place_on_roof
    from robustbench3d.attacks.train import UniversalTrainer
    from robustbench3d.attacks.train_config import TrainConfig
    from robustbench3d.sensors.camera_render import render_camera_torch

    resolved, gt = data
    config = TrainConfig(mode="adv-texture", steps=1, batch_cars=4, occlusion="none", supersample=1,
                         image_loss=image_loss)
    trainer = UniversalTrainer(victim, resolved.kitti(), gt.frame_ids, gt.labels, config)
    fi = trainer.batch(0)[0][0]
    chosen = [k for f, k in trainer.batch(0) if f == fi]
    frame = trainer._frame(trainer.frame_ids[fi], with_image=True)
    targets = target_cars(frame.labels)
    placed = [place_on_roof(trainer.vertices(), car)[0] for car in cars_of(targets)]
    terms, _, _ = trainer._image(frame, targets, chosen, placed, trainer.colours())
    image = torch.from_numpy(frame.image.astype(np.float64) / 255.0)
    rendered = render_camera_torch(image, frame.calib, [(p, trainer._faces, trainer.colours()) for p in placed],
                                   scene_depth=trainer._depth.scene_depth(frame, targets),
                                   supersample=trainer.config.supersample)
    return terms, rendered.permute(2, 0, 1)[None].float(), [targets.bbox[chosen]]


def test_the_trainer_uses_a_registered_loss_and_its_candidate_set(table, victim, data, cache):
    """A loss registered as ``probe`` (per car the sum of its candidates' objectness logits, candidate set 0.1)
    is what the trainer's image term computes for ``image_loss="probe"``: the per-car sums over the victim's
    candidates at IoU threshold 0.1, a set neither ``mean`` (0.3) nor ``sum`` (0.5) reads."""
    def probe(c: ObjectnessCandidates, n: int, image_index: int, use_class: bool) -> torch.Tensor:
        on = c.image_index == image_index
        return torch.zeros(n, dtype=torch.float64).index_add(0, c.target_index[on], c.objectness_logit[on].double())

    register_image_loss("probe", probe, candidate_iou=0.1)
    terms, rendered, boxes = _image_term(victim, data, "probe")
    with torch.no_grad():
        wide = victim.objectness(rendered, boxes, iou_threshold=0.1)
        usual = victim.objectness(rendered, boxes, iou_threshold=0.3)
    assert len(wide.iou) > len(usual.iou)  # the threshold matters for this frame
    hand = np.zeros(len(boxes[0]))
    for t, a in zip(wide.target_index.tolist(), wide.objectness_logit.double().tolist(), strict=True):
        hand[t] += a
    np.testing.assert_allclose(terms.detach().numpy(), hand, rtol=1e-9)
    assert terms.requires_grad


def test_the_trainer_terms_of_mean_and_sum_by_hand(victim, data, cache):
    """The trainer's ``mean`` and ``sum`` image terms: per car the mean of -log(1 - o c) over the victim's
    candidates at threshold 0.3, and the sum over those of IoU >= 0.5, computed here in float64 from the
    candidates' logits."""
    for name, threshold in (("mean", 0.3), ("sum", 0.5)):
        terms, rendered, boxes = _image_term(victim, data, name)
        with torch.no_grad():
            c = victim.objectness(rendered, boxes, iou_threshold=threshold)
        per = [[] for _ in boxes[0]]
        for t, a, b, iou in zip(c.target_index.tolist(), c.objectness_logit.tolist(), c.class_logit.tolist(),
                                c.iou.tolist(), strict=True):
            if name == "mean" or iou >= 0.5:
                per[t].append(nl(a, b))
        hand = [(sum(v) / len(v) if name == "mean" else sum(v)) if v else 0.0 for v in per]
        np.testing.assert_allclose(terms.detach().numpy(), hand, rtol=1e-5)
