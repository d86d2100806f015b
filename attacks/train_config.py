"""Settings of the universal optimisation (:mod:`robustbench3d.attacks.train`): modes, EOT choices,
:class:`TrainConfig`, and the up-front refusals (a victim without the needed oracle, data without cars)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

from robustbench3d.attacks.base import target_cars
from robustbench3d.attacks.losses import IMAGE_LOSSES, IOU_FLOOR
from robustbench3d.attacks.object import LEVEL, RADIUS, Family
from robustbench3d.attacks.roof import SETTING_MAX
from robustbench3d.attacks.spec import MAX_SEED
from robustbench3d.errors import RobustBenchError
from robustbench3d.kitti.labels import Labels

CHECKPOINT_FORMAT = "robustbench3d.attack_train_checkpoint/1"
#: Generator streams: the epoch permutations of the cars, the per-step EOT draws, the held-out loss's EOT draws.
BATCH_STREAM, EOT_STREAM, HELDOUT_STREAM = 0xBA7C, 0xE07, 0x4E1D
#: EOT choices and their magnitudes (the issue's EOT evaluation: +-5 cm / +-5 deg, 2 cm, 5 %).
EOT_CHOICES = ("jitter", "range-noise", "dropout")
EOT_RANGE_NOISE_M = 0.02
EOT_DROPOUT = 0.05
#: Detection thresholds of the running drop estimate (module doc) and its window in steps.
BEV_IOU_DETECTED, SCORE_DETECTED, CANDIDATE_IOU = 0.7, 0.5, 0.5
#: Where the LiDAR loss's frustums come from: the cars' ground-truth 2D boxes, or the victim's own 2D
#: detections on the attacked image (each car gets the detection of largest image IoU >= 0.5 with its box).
LIDAR_BOXES = ("gt", "detector", "gt-object", "gt-append")
#: The frustum protocols whose training proposals come from the placed object (robustbench3d.attacks.record).
OBJECT_LIDAR_BOXES = ("gt-object", "gt-append")
#: The LiDAR loss's terms (:mod:`~robustbench3d.attacks.losses`): the seed paper's segmentation term, the
#: box term (BEV IoU of the box the victim regresses with the car's ground truth), or their sum.
LIDAR_LOSSES = ("seed", "box", "seed+box")
#: Defaults of the held-out curve (:mod:`~robustbench3d.attacks.train_curve`): an evaluation every
#: :data:`EVAL_EVERY` steps on the last :data:`EVAL_FRAMES` frames of the split (at most a fifth of them,
#: :data:`EVAL_SHARE`), and the plateau stop: the best held-out loss improved by less than :data:`PLATEAU_TOL`
#: (relative) over the last :data:`PLATEAU_WINDOW` steps. The shipped texture's held-out loss moved < 0.4 % over
#: 60 further steps at any step size or batch (issue #33), hence the plateau defaults; the others keep the
#: evaluation's cost modest (docs/attacks.md, "The held-out curve").
EVAL_EVERY, EVAL_FRAMES, PLATEAU_WINDOW, PLATEAU_TOL = 25, 5, 60, 0.004
#: At most this share of the split's frames is held out (rounded down), so training keeps four fifths of them.
EVAL_SHARE = 0.2
#: Config fields added after objects were shipped, with the value those objects were trained with: a record
#: (a sidecar's ``made_by.config``) without one of them means that value. Objects trained before the held-out
#: curve were trained on every frame of their split with no evaluation (``eval_every`` 0); the other settings
#: of the curve have no effect then and read as their defaults.
#: A record without the object family (``level``, ``radius``; recorded only when not the default family,
#: :meth:`TrainConfig.record`) means the default family.
RECORD_DEFAULTS = {"image_loss": "mean", "eval_every": 0, "eval_frames": EVAL_FRAMES,
                   "plateau_window": PLATEAU_WINDOW, "plateau_tol": PLATEAU_TOL, "level": LEVEL, "radius": RADIUS}
#: The config fields of the object family (:class:`~robustbench3d.attacks.object.Family`): recorded only when not
#: the default family, so a default run's sidecar and checkpoint are those of a run before families existed.
FAMILY_FIELDS = ("level", "radius")
#: The per-step counts kept in the history beside the losses.
COUNTS = ("cars", "detected", "clean_cars", "detected_clean")
DROP_WINDOW = 50
CLEAN_SAMPLE = 64


#: The range of each numeric field (inclusive; a learning rate must also be > 0). steps and checkpoint_every
#: up to a million (the shipped objects took 75 to 600 steps; a million is weeks of CPU time); batch_cars up to
#: 1024 (the shipped objects used 4 and 8; a step holds one frame's graph at a time, but a batch of 1024 cars
#: takes minutes per step, and the embedded train split has ~11000 cars, so larger batches are epochs);
#: zero_grad_patience up to 10000 steps. lr_shape and lr_color in (0, 10]: Adam steps in the tanh and logit
#: parametrisations, where 10 already carries a vertex across its box or a colour from black to white in one
#: step (the shipped objects used 0.02 and 0.2). The loss weights in [0, 1000]: relative weights, 1000 times
#: the default of 1 makes the other terms noise (set a weight to 0 to drop its term instead). iou_floor is an
#: IoU, in [0, 1]. supersample as the attack's (attacks.roof.SETTING_MAX, 1 to 16). seed in [0, 2**32 - 1]
#: (attacks.spec.MAX_SEED, as run --seed). The held-out curve: eval_every in [0, 1000000] steps (0: no
#: evaluation, no held-out frames: every frame trains, as before the curve existed), eval_frames in [1, 10000]
#: (an evaluation costs about a second per frame on one core; 10000 frames are hours per evaluation, and a
#: KITTI-sized train split has 3712 frames), plateau_window in [1, 1000000] steps (as steps), plateau_tol a
#: relative improvement in [0, 1] (0: never stop on a plateau, as the best loss never rises; 1: stop at the
#: first check that the loss did not fall to 0). The object family's level and radius: those of
#: robustbench3d.attacks.object.Family (LEVELS: 2, 3, 4; RADIUS_RANGE: [0.2, 0.6] m in whole centimetres).
INT_RANGES = {"steps": (1, 1_000_000), "batch_cars": (1, 1024), "checkpoint_every": (1, 1_000_000),
              "zero_grad_patience": (1, 10_000), "supersample": (1, SETTING_MAX["supersample"]),
              "seed": (0, MAX_SEED), "eval_every": (0, 1_000_000), "eval_frames": (1, 10_000),
              "plateau_window": (1, 1_000_000)}
FLOAT_RANGES = {"lr_shape": (0.0, 10.0), "lr_color": (0.0, 10.0), "lambda_lap": (0.0, 1000.0),
                "lambda_img": (0.0, 1000.0), "lambda_box": (0.0, 1000.0), "iou_floor": (0.0, 1.0),
                "plateau_tol": (0.0, 1.0)}
#: Float fields whose lower end is excluded.
_POSITIVE = ("lr_shape", "lr_color")


class TrainingError(RobustBenchError):
    """The optimisation cannot start or had to stop (the message says why)."""


#: Config fields set by an ``attack train`` option of another name than ``--field-name``.
_NO_FLAG = ("zero_grad_patience", "supersample", "iou_floor", "use_class")


def _field(name: str) -> str:
    """``field 'name'`` plus the command-line option that sets it."""
    flag = "" if name in _NO_FLAG or name == "mode" else f" (--{name.replace('_', '-')})"
    return f"field '{name}'{flag}"


def _check_int(name: str, value: object) -> None:
    """Refuse an integer field outside :data:`INT_RANGES` (one line naming the field and the range)."""
    low, high = INT_RANGES[name]
    span = f"(range [{low}, {high}])"
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise TrainingError(f"{_field(name)}: must be an integer >= {low}, got {value!r} {span}")
    if value > high:
        raise TrainingError(f"{_field(name)}: must be at most {high}, got {value!r} {span}")


def _check_float(name: str, value: object) -> None:
    """Refuse a number field outside :data:`FLOAT_RANGES` (one line naming the field and the range)."""
    low, high = FLOAT_RANGES[name]
    positive = name in _POSITIVE
    span = f"(range {'(' if positive else '['}{low:g}, {high:g}])"
    number = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if not number or value < low or (positive and value == low):
        raise TrainingError(f"{_field(name)}: must be a finite number {'>' if positive else '>='} {low:g}, "
                            f"got {value!r} {span}")
    if value > high:
        raise TrainingError(f"{_field(name)}: must be at most {high:g}, got {value!r} {span}")


@dataclass(frozen=True)
class Mode:
    """What a mode optimises and which losses it uses."""

    lidar: bool
    image: bool
    shape: bool
    colour: bool


MODES: dict[str, Mode] = {
    "adv-shape": Mode(lidar=True, image=False, shape=True, colour=False),
    "adv-texture": Mode(lidar=False, image=True, shape=False, colour=True),
    "adv-object": Mode(lidar=True, image=True, shape=True, colour=True),
}


@dataclass(frozen=True)
class TrainConfig:
    """Settings of one optimisation (defaults: reference §3.7)."""

    mode: str
    steps: int = 300
    batch_cars: int = 8
    seed: int = 0
    lr_shape: float = 5e-3
    lr_color: float = 1e-2
    lambda_lap: float = 0.01
    lambda_img: float = 1.0
    iou_floor: float = IOU_FLOOR
    use_class: bool = True
    eot: tuple[str, ...] = ()
    occlusion: str = "scan"
    lidar_boxes: str = "gt"
    lidar_loss: str = "seed"
    lambda_box: float = 1.0
    image_loss: str = "mean"
    supersample: int = 3
    checkpoint_every: int = 25
    zero_grad_patience: int = 10
    eval_every: int = EVAL_EVERY
    eval_frames: int = EVAL_FRAMES
    plateau_window: int = PLATEAU_WINDOW
    plateau_tol: float = PLATEAU_TOL
    level: int = LEVEL
    radius: float = RADIUS

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise TrainingError(f"{_field('mode')}: expected one of {', '.join(MODES)}, got {self.mode!r}")
        for name in INT_RANGES:
            _check_int(name, getattr(self, name))
        for name in FLOAT_RANGES:
            _check_float(name, getattr(self, name))
        try:
            family = Family(self.level, self.radius)
        except ValueError as exc:
            name, _, problem = str(exc).removeprefix("field '").partition("': ")
            raise TrainingError(f"{_field(name)}: {problem}") from None
        object.__setattr__(self, "radius", family.radius)
        bad = sorted(set(self.eot) - set(EOT_CHOICES))
        if bad:
            raise TrainingError(f"{_field('eot')}: unknown {', '.join(bad)} (choose from {', '.join(EOT_CHOICES)})")
        object.__setattr__(self, "eot", tuple(c for c in EOT_CHOICES if c in self.eot))
        if self.occlusion not in ("scan", "none"):
            raise TrainingError(f"{_field('occlusion')}: expected scan or none, got {self.occlusion!r}")
        if self.lidar_boxes not in LIDAR_BOXES:
            raise TrainingError(f"{_field('lidar_boxes')}: expected one of {', '.join(LIDAR_BOXES)}, "
                                f"got {self.lidar_boxes!r}")
        if self.image_loss not in IMAGE_LOSSES:
            raise TrainingError(f"{_field('image_loss')}: expected one of {', '.join(IMAGE_LOSSES)}, "
                                f"got {self.image_loss!r}")
        if self.lidar_loss not in LIDAR_LOSSES:
            raise TrainingError(f"{_field('lidar_loss')}: expected one of {', '.join(LIDAR_LOSSES)}, "
                                f"got {self.lidar_loss!r}")

    @property
    def kind(self) -> Mode:
        return MODES[self.mode]

    @property
    def family(self) -> Family:
        """The trained object's family (its template's level and radius)."""
        return Family(self.level, self.radius)

    @property
    def name(self) -> str:
        """The mode, followed by the family's name when not the default one: ``adv-texture``,
        ``adv-texture-l4-r0.40``."""
        family = self.family
        return self.mode if family.is_default else f"{self.mode}-{family.name}"

    def record(self) -> dict[str, Any]:
        """The configuration as a sidecar records it (``made_by.config``): every field, ``eot`` a list, the
        family's fields (:data:`FAMILY_FIELDS`) only when not the default family."""
        d = {**asdict(self), "eot": list(self.eot)}
        if self.family.is_default:
            for name in FAMILY_FIELDS:
                d.pop(name)
        return d

    def weights(self) -> dict[str, float]:
        """Weight of each loss term in this mode (absent terms are not used)."""
        m, w = self.kind, {}
        if m.lidar:
            w["lidar"] = 1.0
        if m.image:
            w["image"] = self.lambda_img if m.lidar else 1.0
        if m.shape:
            w["laplacian"] = self.lambda_lap
        return w

    def held_out(self, frames: int) -> int:
        """How many frames of a split of ``frames`` frames are held out for the curve (its last ones): none
        without evaluation (``eval_every`` 0), else ``eval_frames`` but at most :data:`EVAL_SHARE` of them."""
        return 0 if self.eval_every == 0 else min(self.eval_frames, int(frames * EVAL_SHARE))

    def identity(self) -> dict[str, Any]:
        """What a resumed run must share with the checkpoint: everything but the step budget, the checkpoint
        interval and the plateau stop's settings (:data:`RESUMABLE`); without evaluation ``eval_frames``
        reads 0 (no frame is held out)."""
        d = self.record()
        for name in RESUMABLE:
            d.pop(name)
        if self.eval_every == 0:
            d["eval_frames"] = 0
        return d


#: The identity of a checkpoint written before a config field existed means the value of the training it
#: continues: the averaged image loss; no held-out frames, no evaluation.
LEGACY_IDENTITY = {"image_loss": "mean", "eval_every": 0, "eval_frames": 0}
#: Config fields a resumed run may change: they decide when training stops, not what a step does (a run that
#: stopped on a plateau continues with a smaller ``plateau_tol``, as one that reached its steps with more).
RESUMABLE = ("steps", "checkpoint_every", "plateau_window", "plateau_tol")


def comparable_config(config: dict[str, Any]) -> dict[str, Any]:
    """A recorded config (a sidecar's ``made_by.config``) as a resumed run compares it: fields it predates at
    :data:`RECORD_DEFAULTS`, without the :data:`RESUMABLE` fields, ``eval_frames`` 0 without evaluation."""
    d = {**RECORD_DEFAULTS, **config}
    for name in RESUMABLE:
        d.pop(name, None)
    if d.get("eval_every") == 0:
        d["eval_frames"] = 0
    return d


#: The sensor each mode attacks the victim through (its loss terms' inputs).
MODE_SENSORS = {"adv-shape": ("lidar",), "adv-texture": ("camera",), "adv-object": ("camera", "lidar")}
#: What a victim without gradients is told (one line; ``attack train --optimizer cma`` attacks it by queries).
NO_GRADIENTS = ("{who} has no gradients ({why}): gradient training cannot attack it; --optimizer cma attacks it "
                "by queries")


def registered_capabilities(victim_name: str) -> Any:
    """The :class:`~robustbench3d.victims.spec.Capabilities` the registry declares for ``victim_name``, None for a
    name it does not hold (a victim object built outside the registry, e.g. in a test)."""
    from robustbench3d.victims import VICTIMS

    if victim_name not in VICTIMS:
        return None
    return VICTIMS.get(victim_name).info.capabilities


def check_oracles(victim: Any, mode: str, victim_name: str, lidar_boxes: str = "gt",
                  lidar_loss: str = "seed", capabilities: Any = None) -> None:
    """Refuse, before any work and in one line (:class:`TrainingError`), a victim ``mode`` cannot train against:

    * one without gradients (``capabilities.gradients`` False, or no white-box oracle at all), with the pointer to
      the query-based optimiser;
    * a mode whose sensor (:data:`MODE_SENSORS`) the victim does not use (``capabilities.modalities``);
    * a victim with frustum oracles (the F-PN cascades, :func:`~robustbench3d.victims.base.has_frustum_oracles`)
      without the one the LiDAR loss uses (``frustum_logits`` for ``seed``, ``frustum_box`` for the box terms),
      without ``proposals(frames, source)`` for ``lidar_boxes="detector"``, or not accepting ``lidar_boxes`` as a
      proposal mode;
    * any other victim without ``target_scores`` (:class:`~robustbench3d.victims.base.TargetScoreOracle`) for a
      LiDAR term, or for an image term without it or ``objectness``; with a ``lidar_boxes`` that needs frustums
      (anything but the default ``gt``, which such a victim ignores); or without the ``detector`` proposal mode
      (its own detections weight and check the attack).

    ``capabilities``: the victim's declared :class:`~robustbench3d.victims.spec.Capabilities`, default those the
    registry holds for ``victim_name`` (:func:`registered_capabilities`; none: only the oracles are checked)."""
    from robustbench3d.victims.base import (
        FrustumBoxOracle,
        FrustumSegmentationOracle,
        ImageObjectnessOracle,
        TargetScoreOracle,
        has_frustum_oracles,
    )

    caps = registered_capabilities(victim_name) if capabilities is None else capabilities
    who, m = f"victim {victim_name!r}", MODES[mode]
    scores, image, frustums = (isinstance(victim, TargetScoreOracle), isinstance(victim, ImageObjectnessOracle),
                               has_frustum_oracles(victim))
    if caps is not None and not caps.gradients:
        raise TrainingError(NO_GRADIENTS.format(who=who, why="registered with gradients=False"))
    if not (scores or image or frustums):
        raise TrainingError(NO_GRADIENTS.format(who=who, why="it implements no white-box oracle: target_scores, "
                                                          "objectness or frustum_logits"))
    unused = [s for s in MODE_SENSORS[mode] if caps is not None and s not in caps.modalities]
    if unused:
        raise TrainingError(f"{who} cannot be attacked with {mode}: the mode attacks through the "
                            f"{' and '.join(unused)}, which the victim does not use (modalities: "
                            f"{', '.join(caps.modalities)})")
    need = []
    if frustums:
        if m.lidar and lidar_loss == "seed" and not isinstance(victim, FrustumSegmentationOracle):
            need.append("FrustumSegmentationOracle (frustum_logits, for the LiDAR loss)")
        if m.lidar and lidar_loss != "seed" and not isinstance(victim, FrustumBoxOracle):
            need.append(f"FrustumBoxOracle (frustum_box, for the LiDAR loss {lidar_loss!r})")
        if m.image and not image:
            need.append("ImageObjectnessOracle (objectness, for the image loss)")
        if m.lidar and lidar_boxes == "detector" and not callable(getattr(victim, "proposals", None)):
            need.append("proposals(frames, source) (its own 2D proposals, for --lidar-boxes detector)")
    else:
        if m.lidar and not scores:
            need.append("TargetScoreOracle (target_scores, for the LiDAR loss)")
        if m.image and not (scores or image):
            need.append("TargetScoreOracle (target_scores) or ImageObjectnessOracle (objectness), for the image loss")
    if need:
        raise TrainingError(f"{who} cannot be attacked with {mode}: it does not implement " + " nor ".join(need))
    _check_proposal_modes(victim, who, m, lidar_boxes, frustums)


def _check_proposal_modes(victim: Any, who: str, m: Mode, lidar_boxes: str, frustums: bool) -> None:
    """Refuse a training that would hand ``victim`` a proposal mode it does not list (one line)."""
    listed = tuple(getattr(victim, "supported_proposals", ()))
    if frustums:
        if m.lidar and lidar_boxes not in listed:
            raise TrainingError(f"{_field('lidar_boxes')}: {who} does not accept the proposal mode {lidar_boxes!r} "
                                f"(its supported_proposals: {', '.join(listed) or 'none'})")
        return
    if m.lidar and lidar_boxes != "gt":
        raise TrainingError(f"{_field('lidar_boxes')}: {lidar_boxes!r} builds frustums, but {who} has no frustum "
                            "oracles (it finds its own objects and is scored through target_scores): keep the default "
                            "gt")
    if "detector" not in listed:
        raise TrainingError(f"{who} cannot be trained against: it finds its own objects (no frustum oracles), but "
                            f"does not accept proposals 'detector' (its supported_proposals: {', '.join(listed)}), "
                            "which weight and check the attack")


def training_cars(labels: list[Labels]) -> list[tuple[int, int]]:
    """(frame index, target index) of every target car, frame order then label order."""
    return [(i, k) for i, lab in enumerate(labels) for k in range(len(target_cars(lab)))]
