"""An attack that hides part of each target car from the LiDAR: every return inside a target car's 3D box is
removed with probability ``fraction`` (as a coat of LiDAR-absorbing paint would), the camera image is left as it is.

Frames: the scan is in the velodyne frame (x forward, y left, z up; m), the target boxes in the KITTI rect frame
(bottom-centre location, m; rotation_y about rect y, rad); the points are taken to rect with the frame's
calibration to be tested against the boxes.
"""

from __future__ import annotations

import dataclasses
from numbers import Real
from typing import Any

import numpy as np

from robustbench3d.attacks.base import Attack
from robustbench3d.attacks.spec import AttackSpecError
from robustbench3d.geometry import points_in_boxes
from robustbench3d.kitti.dataset import Frame
from robustbench3d.kitti.labels import Labels

#: Range of ``fraction``: a probability (0 removes nothing and leaves every frame as it is, 1 every return).
FRACTION_RANGE = (0.0, 1.0)


def check_fraction(fraction: object) -> float:
    """``fraction`` as a float if it is a number in :data:`FRACTION_RANGE`; :class:`AttackSpecError` naming the
    field and the range otherwise (``create_attack`` prefixes the attack's name)."""
    lo, hi = FRACTION_RANGE
    if isinstance(fraction, bool) or not isinstance(fraction, Real) or not lo <= float(fraction) <= hi:
        raise AttackSpecError(f"field 'fraction': expected a number in [{lo:g}, {hi:g}], got {fraction!r}")
    return float(fraction)


class LidarDropoutAttack(Attack):
    """Removes each LiDAR return inside a target car's box with probability ``fraction``."""

    def __init__(self, fraction: float = 0.5) -> None:
        self.fraction = check_fraction(fraction)

    def apply(self, frame: Frame, targets: Labels, rng: np.random.Generator) -> Frame:
        """The frame with the removed returns left out of its scan (a new array; the rest of the frame is
        shared, a lazily rendered image included). One uniform number is drawn from ``rng`` per scan row."""
        if len(targets) == 0 or self.fraction == 0.0:
            return frame
        rect = frame.calib.velo_to_rect_points(frame.scan[:, :3])
        inside = points_in_boxes(rect, targets.dimensions, targets.location, targets.rotation_y).any(axis=1)
        removed = inside & (rng.random(len(frame.scan)) < self.fraction)
        return dataclasses.replace(frame, scan=frame.scan[~removed])

    def describe(self) -> dict[str, Any]:
        return {"attack": "lidar-dropout", "fraction": self.fraction}


def build(fraction: float = 0.5) -> LidarDropoutAttack:
    """Factory of the registry entry: ``fraction`` in [0, 1] (default 0.5; NaN is refused like any value outside)."""
    return LidarDropoutAttack(fraction)


__all__ = ["FRACTION_RANGE", "LidarDropoutAttack", "build", "check_fraction"]
