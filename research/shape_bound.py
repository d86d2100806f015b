"""How far a shape fitted to each frame alone can move the cascade under a frustum protocol: a per-frame bound.

For each of the first N val frames of the embedded dataset with target cars, an adv-shape object (the tanh box
parametrisation of ``attack train``, grey) is optimised against that frame's cars alone, with the trainer of
``attack train`` (``UniversalTrainer`` over one frame: LiDAR loss ``seed+box``, lr_shape 0.02, batch = every car
of the frame, no held-out curve), for STEPS steps under ``--lidar-boxes PROTOCOL``. Each frame's own object is
then applied as a benchmark cell applies it (``RoofObjectAttack.apply_recorded``, ``victim_inputs`` with the
record, the victim's ``detect``), and Car BEV AP @0.7 (R40, easy / moderate / hard) is computed over the N
frames, beside the clean cell's (the nominal record) and those of the grey sphere and of the universal shapes
given as OBJECTS (object files) on the same frames.

A shape refitted to every frame is stronger than any universal shape (one shape for every car of every frame),
so its drop bounds from above what universal training can reach with this parametrisation, protocol and loss
(within the optimiser's reach at STEPS steps).

Usage: python research/shape_bound.py [N] [STEPS] [PROTOCOL] [OBJECTS...]
       (default 10 40 gt-object)
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from robustbench3d.attacks.base import attack_rng, target_cars
from robustbench3d.attacks.object import benign_sphere
from robustbench3d.attacks.objectfile import load_object
from robustbench3d.attacks.record import nominal_record
from robustbench3d.attacks.roof import RoofObjectAttack
from robustbench3d.attacks.train import UniversalTrainer
from robustbench3d.attacks.train_config import TrainConfig
from robustbench3d.datasets import load_ground_truth, resolve_dataset
from robustbench3d.eval.kitti_eval import evaluate
from robustbench3d.runner.shards import worker_setup
from robustbench3d.victims import VICTIMS
from robustbench3d.victims.base import victim_inputs

VICTIM = "fpointnet-v1-lite"
SEED = 0


def bev_moderate(gt: list, det: list) -> tuple[float, float, float]:
    """Car BEV AP @0.7, R40, easy / moderate / hard (percent)."""
    ap = evaluate(gt, det)["Car"]["bev"]["R40"]
    return ap["easy"], ap["moderate"], ap["hard"]


def detect_under(victim, frame, labels, attack, protocol: str):
    """The victim's detections of ``frame`` attacked by ``attack`` (None: clean, the nominal record) under
    ``protocol``, as a benchmark cell computes them."""
    targets = target_cars(labels)
    if attack is None:
        out, record = frame, nominal_record(frame, targets)
    else:
        out, record = attack.apply_recorded(frame, targets, attack_rng(SEED, frame.frame_id))
    bare, props = victim_inputs([out], [labels], protocol, objects=[record])
    return victim.detect(bare, props)[0]


def main(argv: list[str]) -> int:
    n = int(argv[0]) if argv else 10
    steps = int(argv[1]) if len(argv) > 1 else 40
    protocol = argv[2] if len(argv) > 2 else "gt-object"
    objects = [Path(p) for p in argv[3:]]
    worker_setup()
    victim = VICTIMS.get(VICTIM).create()
    dataset = resolve_dataset(None, "val", lazy=True, max_frames=n)
    gt = load_ground_truth(dataset, n)
    kitti = dataset.kitti()
    frames = [(fid, lab) for fid, lab in zip(gt.frame_ids, gt.labels, strict=True) if len(target_cars(lab))]
    fixed = {"clean": None, "benign-sphere": RoofObjectAttack(benign_sphere())}
    fixed.update({p.stem: RoofObjectAttack(load_object(p)) for p in objects})
    dets: dict[str, list] = {name: [] for name in [*fixed, "per-frame shape"]}
    labels_used = []
    t0 = time.time()
    for i, (fid, lab) in enumerate(frames):
        frame = kitti.lazy_frame(fid, lab)
        for name, attack in fixed.items():
            dets[name].append(detect_under(victim, frame, lab, attack, protocol))
        cars = len(target_cars(lab))
        cfg = TrainConfig(mode="adv-shape", steps=steps, batch_cars=cars, seed=SEED, lr_shape=0.02,
                          lidar_loss="seed+box", lidar_boxes=protocol, eval_every=0)
        trainer = UniversalTrainer(victim, kitti, [fid], [lab], cfg)
        for step in range(steps):
            trainer.apply_step(trainer.compute_step(step))
        fitted = RoofObjectAttack(trainer.current_object())
        dets["per-frame shape"].append(detect_under(victim, frame, lab, fitted, protocol))
        labels_used.append(lab)
        print(f"frame {fid} ({i + 1}/{len(frames)}, {cars} cars): fitted in {steps} steps, "
              f"{time.time() - t0:.0f} s so far", file=sys.stderr, flush=True)
    clean = bev_moderate(labels_used, dets["clean"])
    print(f"{len(frames)} frames, protocol {protocol}, {steps} steps per frame; Car BEV R40 E / M / H, "
          f"relative moderate drop")
    for name, det in dets.items():
        ap = bev_moderate(labels_used, det)
        rel = 100.0 * (clean[1] - ap[1]) / clean[1] if clean[1] > 0 else float("nan")
        print(f"  {name:>24}: {ap[0]:6.2f} / {ap[1]:6.2f} / {ap[2]:6.2f}   {rel:5.1f} %")
    print(f"  ({time.time() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
