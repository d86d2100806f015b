"""Example robustbench3d attack plugin: the LiDAR returns of the target cars removed at random.

The entry point ``lidar-dropout = "rb3d_lidar_dropout:SPEC"`` in the ``robustbench3d.attacks``
group makes it available as ``robustbench3d.attacks.create_attack("lidar-dropout", fraction=0.5)``
and ``robustbench3d run --attacks lidar-dropout --attack-arg lidar-dropout:fraction=0.8``.
"""

from __future__ import annotations

from rb3d_lidar_dropout.attack import FRACTION_RANGE, LidarDropoutAttack, build
from robustbench3d.attacks.spec import AttackRequirements, AttackSpec

#: What the registry holds: the factory, what a victim must offer (the LiDAR: a camera-only victim's cell is
#: skipped, it could not be affected) and the line ``attack list`` shows.
SPEC = AttackSpec(
    factory=build,
    requirements=AttackRequirements(needs_lidar=True),
    summary="removes each LiDAR return inside a target car's box with probability fraction (param fraction)",
)

__all__ = ["FRACTION_RANGE", "SPEC", "LidarDropoutAttack", "build"]
