"""Control attacks: the reference cells attacked results are compared against.

``none`` places no object: frames reach the victim unchanged (the clean AP); its record
(:meth:`~robustbench3d.attacks.base.Attack.apply_recorded`) is the nominal one, so the clean cell of the
``gt-object`` protocol gets the default object's union boxes and that of ``gt-append`` the bare GT frustums.
``benign-sphere`` (the undeformed grey sphere) and ``random-shape`` (a seeded random smooth deformation with
random colours) put a physical but unoptimised object on every target car
(:class:`~robustbench3d.attacks.roof.RoofObjectAttack` with :func:`~robustbench3d.attacks.object.benign_sphere` /
:func:`~robustbench3d.attacks.object.random_shape`): how much AP a mere object costs.

This module holds the one control with its own :class:`~robustbench3d.attacks.base.Attack` class,
:class:`NoAttack`; every control is registered in :mod:`robustbench3d.attacks.zoo`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from robustbench3d.attacks.base import Attack
from robustbench3d.kitti.dataset import Frame
from robustbench3d.kitti.labels import Labels


class NoAttack(Attack):
    """No object: :meth:`apply` returns the frame itself, bit for bit."""

    def apply(self, frame: Frame, targets: Labels, rng: np.random.Generator) -> Frame:
        return frame

    def describe(self) -> dict[str, Any]:
        return {"object": None}


__all__ = ["NoAttack"]
