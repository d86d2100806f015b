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
  resampling are non-differentiable and seeded per frame and proposal, as in ``detect``; a
  ``gt-append`` box's extra rows join the frustum through ``extra_points``) and the segmentation
  logits, differentiable w.r.t. the point coordinates.
* :class:`FrustumBoxOracle` — the 3D box a frustum's stages regress (centre, size, heading in the
  rect frame), differentiable w.r.t. the point coordinates (the mask and the discrete choices of
  heading bin and size template held fixed), the same box ``detect`` reports.
* :class:`TargetScoreOracle` — the one interface ``attack train`` trains every white-box victim through:
  ``target_scores(AttackedScene, AttackTargets) -> TargetScores``, per target car a detection logit (and
  the regressed box), differentiable w.r.t. the attacked points and image. A whole-scene detector
  implements only this (and ``detect``); the F-PN cascades implement it through their frustum oracles
  (:func:`frustum_target_scores`, which also serves a victim that has the frustum oracles alone).

Victims are registered in :data:`robustbench3d.victims.VICTIMS` as
:class:`~robustbench3d.victims.spec.VictimSpec` objects (a factory plus :class:`EntryInfo` metadata; both in
:mod:`robustbench3d.victims.spec`, whose ``create`` checks this contract: :func:`check_victim`).

What the harness hands ``detect`` (:func:`victim_inputs`), per proposal mode of a cell:

* every mode: frames with ``labels=None`` (image, scan, calibration and frame id only; the scene
  may have been modified by the cell's attack). A victim never sees a 3D label, a label file or
  the dataset's location.
* ``detector``: ``proposals="detector"``; the victim finds its own objects.
* ``gt``: a list with one :class:`Proposals` per frame, built by :func:`gt_proposals` from that
  frame's labels: every ground-truth 2D box except DontCare, in label order, with
  ``source="gt"``, its KITTI ``types`` and scores of 1 -- nothing 3D. The victim chooses which
  types it uses (the F-PN cascade keeps ``settings.gt_types``, default Car).
* ``gt-object``: as ``gt`` (same boxes in the same order, types, scores of 1), ``source="gt-object"``,
  except that the box of each attack target is its GT box united with the image box of the object the
  attack placed on that car (:func:`object_proposals`, from the harness's record of the placement; the
  clean control gets the union with the default object's box at the nominal placement).
* ``gt-append``: the ``gt`` boxes with ``source="gt-append"`` and ``extra_points``: per box, the rows of
  the frame's scan that are the object returns of that car (empty arrays for the other boxes and in
  the clean control). The victim adds them to that box's frustum (the F-PN cascades: the points in front
  of the camera among them, whether or not they project into the box).

The harness builds every one of these from the labels and, for the last two, from what the attack
placed; the victim never receives the labels or the attack's record. A victim gets a mode only if it
lists it in ``supported_proposals``; otherwise the harness skips those cells.

A list of ``source="external"`` (or ``"detector"``) proposals is for direct calls, e.g. an attack
study feeding chosen boxes (with ``extra_points`` if it wants rows added to frustums). Calling
``detect(frames, "gt")`` on labelled frames is a convenience of the shipped cascades outside the harness
(same result as ``gt_proposals`` of each frame's labels); the harness never does it and plugins need not
accept it. ``"gt-object"`` and ``"gt-append"`` come only as lists (they need the attack's record).

This module imports torch only for type checking.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any, Literal, Protocol, get_args, runtime_checkable

import numpy as np

from robustbench3d.kitti.dataset import Frame
from robustbench3d.kitti.labels import Labels, type_mask
from robustbench3d.kitti.velodyne import row_indices
from robustbench3d.victims.capabilities import (
    GT_PROPOSAL_SOURCES,
    OBJECT_PROPOSAL_SOURCES,
    PROPOSAL_SOURCES,
    PROTOCOL_LABELS,
    Capabilities,
    EntryInfo,
    ProposalSource,
)

if TYPE_CHECKING:
    import torch

    from robustbench3d.kitti.calib import Calibration

#: Where the boxes of one :class:`Proposals` come from: a proposal mode, or anything else.
ProposalOrigin = Literal[ProposalSource, "external"]
PROPOSAL_ORIGINS: tuple[str, ...] = get_args(ProposalOrigin)


@dataclass(frozen=True)
class Proposals:
    """2D proposals of one frame.

    Attributes:
        boxes: (K, 4) left, top, right, bottom in image-2 pixels.
        scores: (K,) 2D scores (1 for ground-truth boxes).
        source: "gt" for ground-truth boxes (:func:`gt_proposals`), "gt-object" / "gt-append" for the
            harness's frustum protocols (:func:`object_proposals`), "detector" for a 2D detector's,
            "external" for anything else (e.g. a GT box enlarged over a roof object).
        types: (K,) KITTI type of each box (str); required for the sources of
            :data:`~robustbench3d.victims.spec.GT_PROPOSAL_SOURCES`, else optional (None).
        extra_points: None, or per box a sorted, unique (E_k,) int64 array of rows of the frame's scan
            (``frame.scan``) to add to that box's frustum (E_k may be 0); required for "gt-append".
    """

    boxes: np.ndarray
    scores: np.ndarray
    source: ProposalOrigin = "external"
    types: np.ndarray | None = None
    extra_points: tuple[np.ndarray, ...] | None = None

    def __post_init__(self) -> None:
        boxes = np.asarray(self.boxes, dtype=np.float64).reshape(-1, 4)
        scores = np.asarray(self.scores, dtype=np.float64).reshape(-1)
        if len(boxes) != len(scores):
            raise ValueError(f"Proposals: {len(boxes)} boxes but {len(scores)} scores")
        if self.source not in PROPOSAL_ORIGINS:
            raise ValueError(f"Proposals: source must be one of {PROPOSAL_ORIGINS}, got {self.source!r}")
        if self.types is None and self.source in GT_PROPOSAL_SOURCES:
            raise ValueError(f"Proposals: source {self.source!r} needs the type of each box")
        if self.types is not None:
            types = np.asarray(self.types, dtype=str).reshape(-1)
            if len(types) != len(boxes):
                raise ValueError(f"Proposals: {len(boxes)} boxes but {len(types)} types")
            object.__setattr__(self, "types", types)
        if self.extra_points is None and self.source == "gt-append":
            raise ValueError("Proposals: source 'gt-append' needs extra_points (one row array per box)")
        if self.extra_points is not None:
            object.__setattr__(self, "extra_points", _row_arrays(self.extra_points, len(boxes)))
        object.__setattr__(self, "boxes", boxes)
        object.__setattr__(self, "scores", scores)

    def select(self, keep: np.ndarray) -> Proposals:
        """The proposals where the (K,) boolean ``keep`` is set, in order (extra points follow their boxes)."""
        keep = np.asarray(keep, dtype=bool).reshape(-1)
        extra = None if self.extra_points is None else tuple(
            e for e, k in zip(self.extra_points, keep, strict=True) if k)
        return Proposals(self.boxes[keep], self.scores[keep], self.source,
                         None if self.types is None else self.types[keep], extra)

    def of_types(self, types: Sequence[str]) -> Proposals:
        """The boxes whose type is in ``types`` (in order); raises ValueError without types."""
        if self.types is None:
            raise ValueError(f"Proposals from {self.source!r} carry no box types")
        return self.select(type_mask(self.types, types))


def _row_arrays(extra: Sequence[np.ndarray], count: int) -> tuple[np.ndarray, ...]:
    """``extra`` as ``count`` read-only int64 arrays of non-negative, strictly increasing scan rows
    (ValueError naming the box otherwise)."""
    if isinstance(extra, np.ndarray) or not isinstance(extra, Sequence):
        raise ValueError(f"Proposals: extra_points must be a sequence of {count} row arrays, "
                         f"got {type(extra).__name__}")
    if len(extra) != count:
        raise ValueError(f"Proposals: {count} boxes but {len(extra)} extra_points arrays")
    return tuple(row_indices(e, f"Proposals: extra_points of box {k}") for k, e in enumerate(extra))


#: A ``detect`` call's proposals: a mode name or one :class:`Proposals` per frame.
ProposalsArg = ProposalSource | Sequence[Proposals]


def gt_proposals(labels: Labels) -> Proposals:
    """The ground-truth proposals of a frame: every 2D box but DontCare, in label order, with its
    type and score 1. The only thing a victim ever receives that is derived from labels."""
    types = labels.type.astype(str)
    keep = types != "DontCare"
    return Proposals(labels.bbox[keep], np.ones(int(keep.sum())), source="gt", types=types[keep])


@runtime_checkable
class PlacementRecord(Protocol):
    """What :func:`victim_inputs` reads of the harness's record of one attacked frame: any object with these
    attributes (the runner passes :class:`robustbench3d.attacks.record.ObjectRecord`; the victim side never
    imports the attack side). One entry per attack target car T of the frame:

    Attributes:
        boxes: (T, 4) image-2 box (left, top, right, bottom; px) of the object placed on each target; a box
            with right < left or bottom < top (e.g. ``(+inf, +inf, -inf, -inf)``) shows nowhere in the image.
        returns: T sorted, unique int64 arrays of rows of the attacked scan: each target's object returns.
        target_index: (T,) int64 row of each target in the frame's labels (-1: no row of them).
    """

    @property
    def boxes(self) -> np.ndarray: ...

    @property
    def returns(self) -> Sequence[np.ndarray]: ...

    @property
    def target_index(self) -> np.ndarray: ...


def object_proposals(frame: Frame, labels: Labels, record: PlacementRecord | None, source: str) -> Proposals:
    """The ``gt-object`` or ``gt-append`` proposals of one (attacked) frame: :func:`gt_proposals` of ``labels``
    with ``source`` set and, for each target of ``record`` (its labels row ``target_index[k]``):

    * ``gt-object``: the box is the union of its GT box and ``record.boxes[k]`` clipped to the image
      ([0, W-1] x [0, H-1] px, as KITTI clips its 2D labels; an empty box leaves the GT box);
    * ``gt-append``: ``extra_points`` of the box is ``record.returns[k]`` (rows of ``frame.scan``).

    The other boxes are the GT boxes unchanged (no extra points). ``record`` None: no object on any car.
    Raises ValueError for a record that does not fit the labels or the scan.
    """
    base = gt_proposals(labels)
    if source not in OBJECT_PROPOSAL_SOURCES:
        raise ValueError(f"object proposals are {' or '.join(OBJECT_PROPOSAL_SOURCES)}, got {source!r}")
    boxes = base.boxes.copy()
    extra = [np.zeros(0, dtype=np.int64) for _ in range(len(boxes))]
    for k, pos in _record_targets(frame, labels, record):
        assert record is not None
        if source == "gt-object":
            boxes[pos] = _united(boxes[pos], np.asarray(record.boxes[k], dtype=np.float64), frame.image_size)
        else:
            extra[pos] = _scan_rows(record.returns[k], len(frame.scan), frame.frame_id, k)
    return Proposals(boxes, base.scores, source, base.types, tuple(extra) if source == "gt-append" else None)


def _record_targets(frame: Frame, labels: Labels, record: PlacementRecord | None) -> list[tuple[int, int]]:
    """(k, position in :func:`gt_proposals`) of each target of ``record`` that is a row of ``labels``."""
    if record is None:
        return []
    where = f"frame {frame.frame_id}: object record"
    index = np.asarray(record.target_index).reshape(-1)
    t = len(index)
    if np.asarray(record.boxes).shape != (t, 4) or len(record.returns) != t:
        raise ValueError(f"{where}: {t} targets but boxes of shape {np.asarray(record.boxes).shape} and "
                         f"{len(record.returns)} return arrays")
    keep = labels.type.astype(str) != "DontCare"
    position = np.cumsum(keep) - 1
    out, seen = [], set()
    for k, row in enumerate(index.tolist()):
        if row == -1:
            continue
        if not 0 <= row < len(labels) or not keep[row] or row in seen:
            raise ValueError(f"{where}: target {k} names labels row {row}, which is not a distinct non-DontCare "
                             f"row of the frame's {len(labels)}")
        seen.add(row)
        out.append((k, int(position[row])))
    return out


def _united(gt_box: np.ndarray, object_box: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    """The union of ``gt_box`` and ``object_box`` clipped to [0, W-1] x [0, H-1]; an empty object box
    (right < left or bottom < top) leaves ``gt_box``."""
    if np.isnan(object_box).any():
        raise ValueError(f"object box {object_box.tolist()} holds NaN")
    if object_box[2] < object_box[0] or object_box[3] < object_box[1]:
        return gt_box
    w, h = image_size
    clipped = np.clip(object_box, 0.0, [w - 1, h - 1, w - 1, h - 1])
    return np.concatenate([np.minimum(gt_box[:2], clipped[:2]), np.maximum(gt_box[2:], clipped[2:])])


def _scan_rows(rows: np.ndarray, scan_rows: int, frame_id: str, k: int) -> np.ndarray:
    """``rows`` as int64 after checking they are rows of a scan of ``scan_rows`` points."""
    arr = np.asarray(rows)
    if arr.size and (arr.dtype.kind not in "iu" or arr.min() < 0 or arr.max() >= scan_rows):
        raise ValueError(f"frame {frame_id}: object record: returns of target {k} are not rows of the "
                         f"attacked scan ({scan_rows} points)")
    return arr.astype(np.int64).reshape(-1)


def victim_inputs(frames: Sequence[Frame], labels: Sequence[Labels | None], source: str,
                  objects: Sequence[PlacementRecord | None] | None = None) -> tuple[list[Frame], ProposalsArg]:
    """What the harness passes to ``detect`` for proposal mode ``source``: the frames with ``labels=None``,
    and ``"detector"`` or one :class:`Proposals` per frame: :func:`gt_proposals` of ``labels`` for
    ``"gt"``, :func:`object_proposals` of ``labels`` and ``objects`` (one record per frame, from the attack
    that made the frame; None for a frame without one) for ``"gt-object"`` / ``"gt-append"``.
    ``objects`` is given for those two modes only. Raises ValueError for inputs that do not fit."""
    bare = [replace(f, labels=None) for f in frames]
    if source not in PROPOSAL_SOURCES:
        raise ValueError(f"proposal mode must be one of {', '.join(PROPOSAL_SOURCES)}, got {source!r}")
    needs_objects = source in OBJECT_PROPOSAL_SOURCES
    if needs_objects and (objects is None or len(objects) != len(frames)):
        got = "none" if objects is None else str(len(objects))
        raise ValueError(f"proposals {source!r} ({PROTOCOL_LABELS[source]}) need one object record per frame: "
                         f"{len(frames)} frames, {got} records")
    if not needs_objects and objects is not None:
        raise ValueError(f"proposals {source!r} take no object records")
    if source == "detector":
        return bare, "detector"
    if len(labels) != len(frames):
        raise ValueError(f"{len(labels)} label sets for {len(frames)} frames")
    props = []
    for i, (frame, lab) in enumerate(zip(frames, labels, strict=True)):
        if lab is None:
            raise ValueError(f"frame {frame.frame_id} has no labels; proposals {source!r} need them")
        props.append(object_proposals(frame, lab, objects[i], source) if objects is not None else gt_proposals(lab))
    return bare, props


@runtime_checkable
class Detector(Protocol):
    """Every victim. ``supported_proposals`` lists the :data:`ProposalSource` modes it accepts
    (a LiDAR-only detector accepts only ``"detector"``; ``"gt"`` means it takes a list of
    :class:`Proposals`, see the module docstring)."""

    supported_proposals: tuple[str, ...]

    def detect(self, frames: Sequence[Frame], proposals: ProposalsArg = "detector") -> list[Labels]:
        """One scored :class:`Labels` per frame: KITTI rows in the rect frame (bottom-centre
        location, m; rotation_y, rad), 2D boxes in image-2 pixels, ``score`` set.

        ``proposals`` is ``"detector"`` or one :class:`Proposals` per frame; frames given by the
        harness have ``labels=None`` (see the module docstring).
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
                       box2d: np.ndarray, *, frame_id: str, proposal: int, class_id: int = 0,
                       extra_points: np.ndarray | None = None) -> FrustumLogits | None:
        """Segment the frustum of ``box2d``, resampled to ``num_points`` (with replacement) by the
        same generator ``detect`` uses for proposal ``proposal`` of frame ``frame_id`` (the victim's
        own seed), so the frustum an attack's loss sees is the one that gets scored.

        Args:
            points_rect: (P, 4) rect-frame xyz (m) and reflectance (e.g. scan points plus
                differentiable points of a rendered object).
            calib: the frame's calibration (P2 for the image projection).
            image_size: (width, height) of the camera image in pixels.
            box2d: (4,) left, top, right, bottom in image-2 pixels.
            frame_id: the frame's id.
            proposal: index of ``box2d`` in the frame's proposal set as ``detect`` enumerates it
                (for the F-PN cascades: ``victim.proposals([frame], source)[0]``).
            class_id: one-hot class (0 Car, 1 Pedestrian, 2 Cyclist).
            extra_points: None, or sorted unique int64 rows of ``points_rect`` added to the frustum of
                ``box2d`` as ``detect`` adds a ``gt-append`` box's
                :attr:`Proposals.extra_points` (for the F-PN cascades: the rows in front of the camera,
                wherever they project, in row order without duplicates, before the resampling); the
                points stay differentiable. ``gt-object`` needs no parameter: pass its union box as
                ``box2d``.
        Returns:
            The logits, or None if the frustum holds no point.
        """
        ...

    def segmentation_logits(self, points: torch.Tensor, one_hot: torch.Tensor) -> torch.Tensor:
        """(B, N, 2) logits of frustum-frame points (B, N, 4) with class one-hot (B, 3)."""
        ...


@dataclass(frozen=True)
class FrustumBox:
    """The 3D box one frustum regresses, differentiable w.r.t. the input points.

    Attributes:
        center: (3,) geometric box centre, rect frame, m (KITTI's location is its bottom centre).
        size_lwh: (3,) length, width, height, m.
        heading: () rotation about rect y, rad (KITTI ``rotation_y`` before wrapping to (-pi, pi]).
        logits: (N, 2) segmentation logits of the frustum's resampled points.
        mask_count: number of points segmented as object (the box net's input).
    """

    center: torch.Tensor
    size_lwh: torch.Tensor
    heading: torch.Tensor
    logits: torch.Tensor
    mask_count: int


@runtime_checkable
class FrustumBoxOracle(Protocol):
    """White-box access to the box a frustum-based detector regresses from its points."""

    def frustum_box(self, points_rect: torch.Tensor, calib: Calibration, image_size: tuple[int, int],
                    box2d: np.ndarray, *, frame_id: str, proposal: int, class_id: int = 0,
                    extra_points: np.ndarray | None = None) -> FrustumBox | None:
        """The box ``detect`` gives the frustum of ``box2d`` (arguments, ``extra_points`` included, as
        :meth:`FrustumSegmentationOracle.frustum_logits`), differentiable w.r.t. ``points_rect``;
        None if the frustum holds no point."""
        ...


@dataclass(frozen=True)
class AttackedScene:
    """One attacked frame as a white-box attack holds it (the input of :meth:`TargetScoreOracle.target_scores`).

    Attributes:
        frame: the attacked frame with ``labels=None``: ``scan`` (N, 4) float32 velodyne rows with the objects'
            returns in it, ``image`` the attacked uint8 image (or the clean one when the attack does not render
            the camera), calibration and frame id.
        points_rect: (N, 4) float64 tensor, row-aligned with ``frame.scan``: rect-frame xyz (m) and reflectance;
            the rows of the objects' returns carry gradients w.r.t. the objects' parameters.
        image: (H, W, 3) float64 tensor in [0, 1], the attacked image, differentiable w.r.t. the objects'
            parameters; None when the attack does not render the camera (LiDAR-only modes).
        proposals: the frame's :class:`Proposals` of the attack's frustum protocol as ``detect`` enumerates them
            (e.g. ``gt``: the GT boxes, for the F-PN cascades those of ``settings.gt_types``; ``gt-append``: with
            each car's object rows; ``detector``: the victim's own 2D detections on the attacked image), which
            :attr:`AttackTargets.proposal` indexes; None for victims that find their own objects (victims without
            frustum oracles, :func:`has_frustum_oracles`). Whole-scene detectors ignore it.
    """

    frame: Frame
    points_rect: torch.Tensor
    image: torch.Tensor | None = None
    proposals: Proposals | None = None


@dataclass(frozen=True)
class AttackTargets:
    """The target cars of an attacked frame: the white-box attacker's knowledge, given to
    :meth:`TargetScoreOracle.target_scores` only (never to ``detect``).

    Attributes:
        boxes2d: (T, 4) ground-truth image-2 boxes (left, top, right, bottom; px).
        boxes3d: (T, 7) ground-truth boxes in the rect frame: bottom-centre x, y, z (m), height, width, length
            (m), rotation_y (rad) -- the KITTI label columns.
        proposal: (T,) int64 index of each target's box in ``AttackedScene.proposals`` (-1: none there, e.g. the
            victim's own 2D detector missed it).
    """

    boxes2d: np.ndarray
    boxes3d: np.ndarray
    proposal: np.ndarray

    def __post_init__(self) -> None:
        b2 = np.asarray(self.boxes2d, dtype=np.float64).reshape(-1, 4)
        b3 = np.asarray(self.boxes3d, dtype=np.float64).reshape(-1, 7)
        prop = np.asarray(self.proposal, dtype=np.int64).reshape(-1)
        if not len(b2) == len(b3) == len(prop):
            raise ValueError(f"AttackTargets: {len(b2)} 2D boxes, {len(b3)} 3D boxes, {len(prop)} proposal indices")
        object.__setattr__(self, "boxes2d", b2)
        object.__setattr__(self, "boxes3d", b3)
        object.__setattr__(self, "proposal", prop)

    def __len__(self) -> int:
        return len(self.proposal)


@dataclass(frozen=True)
class TargetScores:
    """What a victim says about each target of an :class:`AttackTargets` (output of
    :meth:`TargetScoreOracle.target_scores`).

    Attributes:
        logit: (T,) detection logit per target, differentiable w.r.t. the scene's differentiable inputs:
            ``sigmoid(logit)`` is how confidently the victim detects the target (the attack minimises it).
        present: (T,) bool; False where the victim has nothing for the target (no frustum point, no prediction
            near it): the attack takes no term there and ``logit`` is ignored.
        box: None, or (T, 7) the box regressed for each target, differentiable: geometric centre x, y, z (rect
            frame, m), length, width, height (m), rotation_y (rad).
    """

    logit: torch.Tensor
    present: np.ndarray
    box: torch.Tensor | None = None


@runtime_checkable
class TargetScoreOracle(Protocol):
    """The one differentiable victim interface every white-box attack trains through.

    How ``attack train`` calls it, per attacked frame: ``scene.points_rect`` carries gradients to the object's
    shape in the modes with a LiDAR term, ``scene.image`` to its shape and colours in those with an image term
    (None otherwise: ``scene.frame.image`` is then the attacked or clean uint8 image, without gradient). A
    victim with frustum oracles gets ``scene.proposals`` (the frame's proposals of the training's
    ``lidar_boxes`` protocol, as ``detect`` enumerates them) and each target's index in them; any other victim
    gets ``proposals=None`` and indices -1, and finds the targets itself. The losses: LiDAR
    ``max(IoU_k, floor) * softplus(logit)`` (+ ``lambda_box`` x the BEV IoU of ``box`` with the target's ground
    truth, ``with_box``), image ``softplus(logit)``; ``IoU_k`` is the BEV IoU of the victim's own ``detect``
    row for the car (:mod:`robustbench3d.attacks.train`), so ``logit`` should fall where ``detect`` loses the
    car.
    """

    def target_scores(self, scene: AttackedScene, targets: AttackTargets, *,
                      with_box: bool = False) -> TargetScores:
        """Per target of ``targets``: the detection logit (and with ``with_box`` the regressed box) the victim
        gives it on ``scene``, differentiable w.r.t. ``scene.points_rect`` (and ``scene.image`` if the victim
        uses the camera). ``logit`` and ``present`` have one entry per target, ``box`` (``with_box``) one row."""
        ...


def frustum_target_scores(oracle: Any, scene: AttackedScene, targets: AttackTargets, *,
                          with_box: bool = False) -> TargetScores:
    """:meth:`TargetScoreOracle.target_scores` of a frustum victim (``oracle``: a
    :class:`FrustumSegmentationOracle`, and with ``with_box`` a :class:`FrustumBoxOracle`).

    Per target with a proposal index ``j >= 0``: the frustum of ``scene.proposals.boxes[j]`` (``frame_id``,
    ``proposal=j`` and, for a ``gt-append`` set, ``extra_points[j]``, as ``detect`` builds it) over
    ``scene.points_rect``; the logit is the largest object-minus-background margin of its segmentation logits
    in float64, ``(l[:, 1] - l[:, 0]).max()`` (``sigmoid`` of it: the largest object probability of the
    frustum); with ``with_box`` the logits and the box (centre, l/w/h, heading; float64) of
    :meth:`FrustumBoxOracle.frustum_box`. ``present`` is False for ``j = -1``, without proposals, or where
    the frustum holds no point (logit 0 and a zero box there). Raises ValueError for an index outside the
    proposals."""
    import torch

    frame, props = scene.frame, scene.proposals
    zero = torch.zeros((), dtype=torch.float64)
    logits: list[torch.Tensor] = []
    boxes: list[torch.Tensor] = []
    present = np.zeros(len(targets), dtype=bool)
    for n, j in enumerate(targets.proposal.tolist()):
        got = None
        if j >= 0 and props is not None:
            if j >= len(props.boxes):
                raise ValueError(f"AttackTargets: target {n} names proposal {j} of {len(props.boxes)}")
            where: dict[str, Any] = {"frame_id": frame.frame_id, "proposal": j}
            if props.extra_points is not None:  # gt-append: the car's object returns join its frustum
                where["extra_points"] = props.extra_points[j]
            call = oracle.frustum_box if with_box else oracle.frustum_logits
            got = call(scene.points_rect, frame.calib, frame.image_size, props.boxes[j], **where)
        if got is None:
            logits.append(zero)
            boxes.append(torch.zeros(7, dtype=torch.float64))
            continue
        present[n] = True
        margin = got.logits.to(torch.float64)
        logits.append((margin[:, 1] - margin[:, 0]).max())
        if with_box:
            boxes.append(torch.cat([got.center, got.size_lwh, got.heading.reshape(1)]).to(torch.float64))
    logit = torch.stack(logits) if logits else torch.zeros(0, dtype=torch.float64)
    box = (torch.stack(boxes) if boxes else torch.zeros(0, 7, dtype=torch.float64)) if with_box else None
    return TargetScores(logit=logit, present=present, box=box)


def has_frustum_oracles(victim: Any) -> bool:
    """Whether ``victim`` segments per-proposal frustums (:class:`FrustumSegmentationOracle` or
    :class:`FrustumBoxOracle`): an attack then hands it proposals and each target's index in them."""
    return isinstance(victim, (FrustumSegmentationOracle, FrustumBoxOracle))


def check_victim(victim: Any, capabilities: Capabilities) -> None:
    """Raise TypeError unless ``victim`` honours the contract its capabilities declare.

    A victim declaring ``gradients`` must implement :class:`TargetScoreOracle` (the one interface white-box
    training uses) or one of the older oracles (:class:`ImageObjectnessOracle`,
    :class:`FrustumSegmentationOracle`, :class:`FrustumBoxOracle`); one using the camera and declaring
    gradients must give image gradients: :class:`TargetScoreOracle` or :class:`ImageObjectnessOracle`.
    """
    if not isinstance(victim, Detector):
        raise TypeError(f"{type(victim).__name__} does not implement Detector (detect, supported_proposals)")
    bad = set(victim.supported_proposals) - set(PROPOSAL_SOURCES)
    if bad or not victim.supported_proposals:
        raise TypeError(f"{type(victim).__name__}.supported_proposals must be a non-empty subset of "
                        f"{PROPOSAL_SOURCES}, got {victim.supported_proposals}")
    if capabilities.gradients:
        scores, image = isinstance(victim, TargetScoreOracle), isinstance(victim, ImageObjectnessOracle)
        if not (scores or image or has_frustum_oracles(victim)):
            raise TypeError(f"{type(victim).__name__} declares gradients but implements no oracle protocol "
                            "(TargetScoreOracle.target_scores, or ImageObjectnessOracle / FrustumSegmentationOracle)")
        if "camera" in capabilities.modalities and not (scores or image):
            raise TypeError(f"{type(victim).__name__} uses the camera and declares gradients but implements "
                            "neither TargetScoreOracle nor ImageObjectnessOracle")


def empty_detections() -> Labels:
    """A scored, empty :class:`Labels` (a frame without detections)."""
    return Labels.empty(with_score=True)


__all__ = [
    "GT_PROPOSAL_SOURCES",
    "OBJECT_PROPOSAL_SOURCES",
    "PROPOSAL_ORIGINS",
    "PROPOSAL_SOURCES",
    "PROTOCOL_LABELS",
    "AttackTargets",
    "AttackedScene",
    "Capabilities",
    "Detector",
    "EntryInfo",
    "FrustumBox",
    "FrustumBoxOracle",
    "FrustumLogits",
    "FrustumSegmentationOracle",
    "ImageObjectnessOracle",
    "ObjectnessCandidates",
    "PlacementRecord",
    "ProposalOrigin",
    "ProposalSource",
    "Proposals",
    "ProposalsArg",
    "TargetScoreOracle",
    "TargetScores",
    "check_victim",
    "empty_detections",
    "frustum_target_scores",
    "gt_proposals",
    "has_frustum_oracles",
    "object_proposals",
    "victim_inputs",
]
