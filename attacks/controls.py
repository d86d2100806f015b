"""Control attacks: the reference cells attacked results are compared against.

``none`` places no object: frames reach the victim unchanged (the clean AP). The benign sphere
and random-shape controls will join here.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from robustbench3d.attacks import register_attack
from robustbench3d.attacks.base import Attack
from robustbench3d.attacks.spec import AttackRequirements
from robustbench3d.kitti.dataset import Frame
from robustbench3d.kitti.labels import Labels


@register_attack("none", requirements=AttackRequirements(),
                 summary="control: no object placed, frames unchanged (clean AP)")
class NoAttack(Attack):
    """No object: :meth:`apply` returns the frame itself, bit for bit."""

    def apply(self, frame: Frame, targets: Labels, rng: np.random.Generator) -> Frame:
        return frame

    def describe(self) -> dict[str, Any]:
        return {"object": None}
