"""The attack contract: an object placed on the roof of each target car of a frame.

An :class:`Attack` turns a clean :class:`~robustbench3d.kitti.dataset.Frame` into an attacked one
(LiDAR hits added and occluded points removed, object pixels composited into camera image 2);
calibration, frame id and ground-truth labels stay as they were. The benchmark runner calls, per
victim x attack cell::

    attack.bind_dataset(kitti)                   # once per run: the dataset the frames come from
    attack.prepare(victim)                       # once; only white-box attacks use the victim
    attacked = attack.apply(frame, targets, rng) # per frame, in frame order

or, for the proposal sources whose boxes or frustums the harness builds from the object's placement
(``gt-object``, ``gt-append``), ``attacked, record = attack.apply_recorded(frame, targets, rng)``: the same
frame and an :class:`~robustbench3d.attacks.record.ObjectRecord` of where the object went (harness-side only).

``targets`` are the frame's target cars (:func:`target_cars`, rect frame) and ``rng`` a
``numpy.random.Generator`` seeded from (run seed, frame id) only, so every attack and every victim
sees the same placement randomness for a frame (common random numbers across cells). Attacks must
draw all randomness from ``rng`` and must not modify the input frame's arrays.

:data:`TARGET_TYPES` and :func:`target_cars` are defined in :mod:`robustbench3d.attacks.targets` (below
:mod:`robustbench3d.attacks.record`, which uses them too) and re-exported here.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any

import numpy as np

from robustbench3d.attacks.record import ObjectRecord, nominal_record
from robustbench3d.attacks.targets import TARGET_TYPES, target_cars
from robustbench3d.kitti.dataset import Frame, KittiDataset
from robustbench3d.kitti.labels import Labels

#: Third entropy word of the attack generators (separates them from other uses of the seed).
ATTACK_STREAM = 0x41545443  # "ATTC"


def attack_rng(seed: int, frame_id: str) -> np.random.Generator:
    """The generator of frame ``frame_id``'s attack in a benchmark cell (seeded from the run seed and the frame
    id only): the same for every attack and victim."""
    return np.random.default_rng([int(seed), int(frame_id), ATTACK_STREAM])


class Attack(ABC):
    """Base class of every attack object (see the module doc for the calling protocol)."""

    def prepare(self, victim: Any) -> None:  # noqa: B027 - optional hook, deliberately empty
        """Called once per benchmark cell before :meth:`apply` (one instance serves every cell of a
        run, so this replaces any earlier victim); white-box attacks (declaring ``needs_gradients``)
        keep the victim to query its oracles. Default: nothing."""

    def bind_dataset(self, kitti: KittiDataset) -> None:  # noqa: B027 - optional hook, deliberately empty
        """Called once per run (and by ``attack apply``) with the dataset whose frames :meth:`apply` will
        get, before any of them: attacks that need more than a frame says (e.g. the generated scene a
        frame came from, for exact occlusion) note it here. Default: nothing."""

    @abstractmethod
    def apply(self, frame: Frame, targets: Labels, rng: np.random.Generator) -> Frame:
        """The attacked frame (a new :class:`Frame`; the input's arrays are left untouched).

        Args:
            frame: the clean frame (scan in the velodyne frame, image 2, calibration, labels).
            targets: the target cars, rect frame (:func:`target_cars`).
            rng: the only source of randomness (placement, sensor noise, lighting).
        """

    def apply_recorded(self, frame: Frame, targets: Labels, rng: np.random.Generator) -> tuple[Frame, ObjectRecord]:
        """The attacked frame (as :meth:`apply`, the same bytes from the same ``rng``) and the record of what was
        placed on each target (:class:`~robustbench3d.attacks.record.ObjectRecord`). Default: :meth:`apply` and
        the nominal record (the default 0.40 m object's bounds at the roof-centre placement, no returns:
        :func:`~robustbench3d.attacks.record.nominal_record`); an attack that places its own object overrides it.
        The record is the harness's: it must not be reachable from the returned frame."""
        return self.apply(frame, targets, rng), nominal_record(frame, targets)

    @abstractmethod
    def describe(self) -> dict[str, Any]:
        """JSON-serialisable parameters identifying the object (e.g. a mesh file's sha256, its
        placement offsets in m). Part of each cell's configuration fingerprint and provenance."""


__all__ = ["ATTACK_STREAM", "TARGET_TYPES", "Attack", "attack_rng", "target_cars"]
