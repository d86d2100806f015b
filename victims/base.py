"""The victim contract: the seam between the harness (attacks, evaluation) and every model.

A victim is any object implementing :class:`Detector`. White-box victims additionally implement
the oracle protocols an attack needs gradients from; the harness discovers them with
``isinstance(victim, ImageObjectnessOracle)`` etc. (runtime-checkable protocols), so a LiDAR-only
detector, a camera-only detector or a fusion model plugs in without harness changes: it simply
implements the protocols that make sense for it and declares its :class:`Capabilities`.

* :class:`Detector` — ``detect(frames, proposals) -> list[Labels]``: KITTI result rows per frame
  (rect frame, bottom-centre location, 2D box in image-2 pixels, ``score`` filled).
* :class:`ImageObjectnessOracle` — the 2D detector's objectness logits for the candidate
  predictions around target boxes, differentiable w.r.t. an image tensor.
* :class:`FrustumSegmentationOracle` — frustum construction from rect-frame points (selection and
  resampling are non-differentiable and seeded) and the segmentation logits, differentiable
  w.r.t. the point coordinates.

Victims are registered in :data:`robustbench3d.victims.VICTIMS` as :class:`VictimSpec` objects
(a factory plus :class:`~robustbench3d.registry.EntryInfo` metadata).

This module imports torch only for type checking.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal, Protocol, runtime_checkable

import numpy as np

from robustbench3d.kitti.dataset import Frame
from robustbench3d.kitti.labels import Labels
from robustbench3d.registry import Capabilities, EntryInfo
from robustbench3d.victims.spec import VictimSpec

if TYPE_CHECKING:
    import torch

    from robustbench3d.kitti.calib import Calibration

#: Where 2D proposals come from: the victim's own 2D detector, or the frame's ground-truth boxes.
ProposalSource = Literal["detector", "gt"]


@dataclass(frozen=True)
class Proposals:
    """Externally supplied 2D proposals of one frame (e.g. a GT box enlarged over a roof object).

    Attributes:
        boxes: (K, 4) left, top, right, bottom in image-2 pixels.
        scores: (K,) scores written to the result rows.
    """

    boxes: np.ndarray
    scores: np.ndarray

    def __post_init__(self) -> None:
        boxes = np.asarray(self.boxes, dtype=np.float64).reshape(-1, 4)
        scores = np.asarray(self.scores, dtype=np.float64).reshape(-1)
        if len(boxes) != len(scores):
            raise ValueError(f"Proposals: {len(boxes)} boxes but {len(scores)} scores")
        object.__setattr__(self, "boxes", boxes)
        object.__setattr__(self, "scores", scores)


ProposalsArg = ProposalSource | Sequence[Proposals]


@runtime_checkable
class Detector(Protocol):
    """Every victim. ``supported_proposals`` lists the :data:`ProposalSource` values it accepts
    (a LiDAR-only detector accepts only ``"detector"``)."""

    supported_proposals: tuple[str, ...]

    def detect(self, frames: Sequence[Frame], proposals: ProposalsArg = "detector") -> list[Labels]:
        """One scored :class:`Labels` per frame: KITTI rows in the rect frame (bottom-centre
        location, m; rotation_y, rad), 2D boxes in image-2 pixels, ``score`` set.

        ``proposals`` is a source name or, for cascades, one :class:`Proposals` per frame.
        """
        ...


@dataclass(frozen=True)
class ObjectnessCandidates:
    """Predictions of a 2D detector selected around target boxes (one row per candidate).

    Logit tensors are differentiable w.r.t. the input image; everything else is detached.

    Attributes:
        objectness_logit: (K,) logit of "an object is assigned to this prior" (sigmoid -> prob).
        class_logit: (K,) logit of the target class (Car), independent sigmoid.
        boxes: (K, 4) decoded boxes in original image pixels (left, top, right, bottom).
        iou: (K,) IoU of each box with its target box.
        image_index: (K,) int64 index of the image in the batch.
        target_index: (K,) int64 index of the target box within that image's targets.
    """

    objectness_logit: torch.Tensor
    class_logit: torch.Tensor
    boxes: torch.Tensor
    iou: torch.Tensor
    image_index: torch.Tensor
    target_index: torch.Tensor

    @property
    def objectness(self) -> torch.Tensor:
        """(K,) objectness probabilities."""
        return self.objectness_logit.sigmoid()


@runtime_checkable
class ImageObjectnessOracle(Protocol):
    """White-box access to a YOLO-style 2D detector's objectness."""

    def objectness(self, images: torch.Tensor, targets: Sequence[np.ndarray], *,
                   iou_threshold: float = 0.3) -> ObjectnessCandidates:
        """Candidates around each target box.

        Args:
            images: (B, 3, H, W) float RGB in [0, 1] at the original image resolution (e.g. the
                attacked, composited camera image); gradients flow back to it.
            targets: per image, (T_b, 4) target boxes in original pixels.
            iou_threshold: a prediction is a candidate of a target if their IoU is at least this,
                or if the prediction's centre lies inside the target box.
        """
        ...


@dataclass(frozen=True)
class FrustumLogits:
    """Segmentation output of one frustum.

    Attributes:
        logits: (N, 2) logits, channel 0 background, channel 1 object; differentiable w.r.t. the
            input points.
        sample_index: (N,) int64 index of each resampled point in the input point tensor.
        rot_angle: rotation (rad) about rect y that maps the 2D-box centre ray onto +z.
        points: (N, 4) network input: frustum-frame xyz (m) and reflectance.
    """

    logits: torch.Tensor
    sample_index: np.ndarray
    rot_angle: float
    points: torch.Tensor

    @property
    def object_prob(self) -> torch.Tensor:
        """(N,) softmax probability of the object channel."""
        return self.logits.softmax(dim=-1)[:, 1]


@runtime_checkable
class FrustumSegmentationOracle(Protocol):
    """White-box access to a frustum-based point segmentation stage (Frustum-PointNet)."""

    num_points: int

    def frustum_logits(self, points_rect: torch.Tensor, calib: Calibration, image_size: tuple[int, int],
                       box2d: np.ndarray, *, seed: int = 0, class_id: int = 0) -> FrustumLogits | None:
        """Segment the frustum of ``box2d``.

        Args:
            points_rect: (P, 4) rect-frame xyz (m) and reflectance (e.g. scan points plus
                differentiable points of a rendered object).
            calib: the frame's calibration (P2 for the image projection).
            image_size: (width, height) of the camera image in pixels.
            box2d: (4,) left, top, right, bottom in image-2 pixels.
            seed: seed of the resampling to ``num_points`` (with replacement).
            class_id: one-hot class (0 Car, 1 Pedestrian, 2 Cyclist).
        Returns:
            The logits, or None if the frustum holds no point.
        """
        ...

    def segmentation_logits(self, points: torch.Tensor, one_hot: torch.Tensor) -> torch.Tensor:
        """(B, N, 2) logits of frustum-frame points (B, N, 4) with class one-hot (B, 3)."""
        ...


def check_victim(victim: Any, capabilities: Capabilities) -> None:
    """Raise TypeError unless ``victim`` honours the contract its capabilities declare.

    A victim declaring ``gradients`` must implement at least one oracle; one using the camera
    and declaring gradients must implement :class:`ImageObjectnessOracle`, one using the LiDAR
    and declaring gradients the point-level :class:`FrustumSegmentationOracle` or another oracle.
    """
    if not isinstance(victim, Detector):
        raise TypeError(f"{type(victim).__name__} does not implement Detector (detect, supported_proposals)")
    bad = set(victim.supported_proposals) - {"detector", "gt"}
    if bad or not victim.supported_proposals:
        raise TypeError(f"{type(victim).__name__}.supported_proposals must be a non-empty subset of "
                        f"('detector', 'gt'), got {victim.supported_proposals}")
    if capabilities.gradients:
        oracles = [isinstance(victim, ImageObjectnessOracle), isinstance(victim, FrustumSegmentationOracle)]
        if not any(oracles):
            raise TypeError(f"{type(victim).__name__} declares gradients but implements no oracle protocol")
        if "camera" in capabilities.modalities and not oracles[0]:
            raise TypeError(f"{type(victim).__name__} uses the camera and declares gradients but does not "
                            "implement ImageObjectnessOracle")


def empty_detections() -> Labels:
    """A scored, empty :class:`Labels` (a frame without detections)."""
    return Labels.empty(with_score=True)


__all__ = [
    "Capabilities", "Detector", "EntryInfo", "FrustumLogits", "FrustumSegmentationOracle",
    "ImageObjectnessOracle", "ObjectnessCandidates", "ProposalSource", "Proposals", "ProposalsArg",
    "VictimSpec", "check_victim", "empty_detections",
]
