"""Which ground-truth objects of a frame carry an attack object: :data:`TARGET_TYPES` and :func:`target_cars`.

Below both :mod:`robustbench3d.attacks.base` (the contract, which re-exports them) and
:mod:`robustbench3d.attacks.record` (which finds each target's row in a frame's labels).
"""

from __future__ import annotations

from robustbench3d.kitti.labels import Labels

#: Object types whose instances carry an attack object.
TARGET_TYPES: tuple[str, ...] = ("Car",)


def target_cars(labels: Labels | None) -> Labels:
    """The frame's attack targets: every ground-truth object of a :data:`TARGET_TYPES` type
    (rect frame; bottom-centre location in m, rotation_y in rad). Empty without labels."""
    if labels is None:
        return Labels.empty()
    return labels.of_types(TARGET_TYPES)


__all__ = ["TARGET_TYPES", "target_cars"]
