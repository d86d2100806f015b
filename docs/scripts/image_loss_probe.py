"""``attack train`` with the image loss summed over each car's candidates of IoU >= 0.5 instead of averaged over
all its candidates (docs/attacks.md): the loss of ``docs/scripts/texture_bound.py``, swapped into the trainer
for an exploratory run; every argument is passed to ``robustbench3d`` unchanged.

Usage: python docs/scripts/image_loss_probe.py attack train adv-texture --victim fpointnet-v1-lite \\
           --out OBJ.ply --steps 40 --seed 0 --lr-color 0.05 --no-progress
"""

from __future__ import annotations

import sys

import torch

import robustbench3d.attacks.train as train
from robustbench3d.attacks.losses import neg_log_one_minus_product
from robustbench3d.cli import main


def summed_losses(candidates, n_targets: int, image_index: int = 0, use_class: bool = True) -> torch.Tensor:
    """(n_targets,) sum over each target's candidates of IoU >= 0.5 of ``-log(1 - o * c)`` (from logits)."""
    on = (candidates.image_index == image_index) & (candidates.iou >= 0.5)
    per = neg_log_one_minus_product(candidates.objectness_logit[on],
                                    candidates.class_logit[on] if use_class else None)
    return torch.zeros(n_targets, dtype=per.dtype).index_add(0, candidates.target_index[on], per)


if __name__ == "__main__":
    train.image_target_losses = summed_losses
    sys.exit(main(sys.argv[1:]))
