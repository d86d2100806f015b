"""The F-PN cascade's inference pipeline in numpy: proposals -> frustums -> networks -> KITTI rows.

One implementation for every backend: :class:`~robustbench3d.victims.cascade.FPointNetCascade`
(torch) and the ONNX victim (:mod:`robustbench3d.victims.onnx`) both call :func:`detect_frames`
with their own 2D detector function and :class:`~robustbench3d.victims.fpointnet.glue.FrustumStages`.

Determinism: the resampling of each frustum to N points (with replacement, as the original) and
the random object-point gather draw from :func:`frustum_rng` (``numpy.random.default_rng([seed,
frame, proposal])``), so a frustum's result does not depend on the batch or on other frames; the
frustum oracle (``frustum_logits``) resamples with the same generator, so an attack's loss sees the
frustums that ``detect`` scores. Proposal filters follow
§1.3: 2D height >= 25 px, and at least ``min_points_detector`` (5) frustum points for detector
boxes or ``min_points_gt`` (1) for GT boxes (every source of
:data:`~robustbench3d.victims.spec.GT_PROPOSAL_SOURCES`).

Frustum protocols: ``gt-object`` proposals are GT boxes like any other (the harness made the target cars'
boxes the union with the object's image box); for proposals with ``extra_points`` (``gt-append``) a box's
frustum is its points united with those scan rows that lie in front of the camera
(:func:`~robustbench3d.victims.fpointnet.frustum.extract_frustum`), in scan order; resampling, the gather
and the box stages are unchanged, so with empty extra rows the result is the ``gt`` result bit for bit.

Imports numpy only (no torch).
"""

from __future__ import annotations

import zlib
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from robustbench3d.kitti.dataset import Frame
from robustbench3d.kitti.labels import Labels
from robustbench3d.victims.base import Proposals, ProposalsArg, empty_detections, victim_inputs
from robustbench3d.victims.fpointnet.box_coding import car_one_hot
from robustbench3d.victims.fpointnet.frustum import (
    Frustum,
    extract_frustum,
    project_scan,
    resample_indices,
    rotate_to_frustum,
)
from robustbench3d.victims.fpointnet.glue import FrustumStages, GatherMode, run_frustum_stages
from robustbench3d.victims.fpointnet.to_kitti import decode, to_labels
from robustbench3d.victims.spec import GT_PROPOSAL_SOURCES, OBJECT_PROPOSAL_SOURCES
from robustbench3d.victims.yolo.postprocess import Detections2D

#: A 2D detector: (H, W, 3) uint8 images -> one :class:`Detections2D` per image.
Detect2DFn = Callable[[Sequence[np.ndarray]], list[Detections2D]]


@dataclass(frozen=True)
class CascadeSettings:
    """Inference settings of the cascade.

    seed: base seed of the per-frustum resampling / gather generators.
    gather: "random" (original, seeded) or "topk" object-point choice.
    min_box_height: proposals lower than this (px) are skipped.
    min_points_detector / min_points_gt: minimum frustum points for detector / GT proposals.
    gt_types: label types used as GT proposals.
    batch_size: frustums per segmentation pass (4: larger batches of the full config run ~2x slower
        per frustum on CPU, the 1091-channel per-point features no longer fit in cache); the stages
        decide how they run a batch (the torch victim over each frustum's distinct points, one call per
        batch, see :mod:`~robustbench3d.victims.fpointnet.distinct_stages`; ONNX stages of fixed shapes
        one T-Net and box call per frustum).
    """

    seed: int = 0
    gather: GatherMode = "random"
    min_box_height: float = 25.0
    min_points_detector: int = 5
    min_points_gt: int = 1
    gt_types: tuple[str, ...] = ("Car",)
    batch_size: int = 4

    def to_dict(self) -> dict[str, Any]:
        return {**asdict(self), "gt_types": list(self.gt_types)}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> CascadeSettings:
        d = dict(data)
        if "gt_types" in d:
            d["gt_types"] = tuple(d["gt_types"])
        return cls(**d)


def frame_key(frame_id: str) -> int:
    """Integer seed component of a frame id (its value if numeric, else a CRC32)."""
    return int(frame_id) if frame_id.isdigit() else zlib.crc32(frame_id.encode("utf-8"))


def frustum_rng(seed: int, frame_id: str, proposal: int) -> np.random.Generator:
    """The generator of one frustum: proposal ``proposal`` (its index in the frame's proposal set,
    as :func:`make_proposals` returns it) of frame ``frame_id``. It draws the resampling to N points
    and then, with the random gather, the object points; ``detect`` and the oracle both use it."""
    return np.random.default_rng([int(seed), frame_key(frame_id), int(proposal)])


def make_proposals(frames: Sequence[Frame], source: ProposalsArg, detect_2d: Detect2DFn, car_class: int,
                   gt_types: Sequence[str]) -> list[Proposals]:
    """2D proposals per frame: the detector's ``car_class`` detections for ``"detector"``, else the
    given list (one :class:`Proposals` per frame) with ground-truth sets (the sources of
    :data:`~robustbench3d.victims.spec.GT_PROPOSAL_SOURCES`) reduced to ``gt_types``, their extra points
    with them.

    ``"gt"`` (outside the harness only) takes :func:`~robustbench3d.victims.base.gt_proposals` of
    each frame's labels. ``"gt-object"`` / ``"gt-append"`` come only as lists (the harness builds them
    from the attack's placement, :func:`~robustbench3d.victims.base.victim_inputs`). Extra points that are
    no rows of their frame's scan raise ValueError before anything runs.
    """
    if isinstance(source, str):
        if source == "detector":
            dets = detect_2d([f.image for f in frames])
            return [Proposals(d.boxes[d.classes == car_class], d.scores[d.classes == car_class], "detector")
                    for d in dets]
        if source in OBJECT_PROPOSAL_SOURCES:
            raise ValueError(f"proposals {source!r} come as a list of Proposals built by victim_inputs from the "
                             "attack's object records, not as a name")
        if source != "gt":
            raise ValueError(f"proposals must be 'detector', 'gt' or a list of Proposals, got {source!r}")
        source = victim_inputs(frames, [f.labels for f in frames], "gt")[1]
    if len(source) != len(frames):
        raise ValueError(f"{len(source)} proposal sets for {len(frames)} frames")
    for frame, p in zip(frames, source, strict=True):
        _check_extra_points(frame, p)
    return [p.of_types(gt_types) if p.source in GT_PROPOSAL_SOURCES else p for p in source]


def _check_extra_points(frame: Frame, proposals: Proposals) -> None:
    """ValueError unless every extra point of ``proposals`` is a row of ``frame.scan``."""
    if proposals.extra_points is None:
        return
    count = len(frame.scan)
    for k, rows in enumerate(proposals.extra_points):
        if len(rows) and rows[-1] >= count:
            raise ValueError(f"frame {frame.frame_id}: extra_points of proposal {k} name scan row {int(rows[-1])}, "
                             f"but the scan has {count} points")


@dataclass(frozen=True)
class FrustumInput:
    """One usable proposal: its frame, frustum, 2D score, generator, the (N, 4) float32 network
    input (frustum-frame xyz in m, reflectance) and whether it is a ground-truth box."""

    frame_index: int
    frustum: Frustum
    score: float
    rng: np.random.Generator
    points: np.ndarray
    ground_truth: bool = False


def frustum_inputs(frames: Sequence[Frame], proposals: Sequence[Proposals], settings: CascadeSettings,
                   num_points: int, min_points: int | None = None) -> list[FrustumInput]:
    """Frustums of every proposal that passes the filters, resampled to ``num_points`` points.

    A proposal's frustum holds its box's points and, with ``extra_points``, those rows of the scan in front
    of the camera. ``min_points`` defaults to ``settings.min_points_gt`` for ground-truth proposal sets (the
    sources of :data:`~robustbench3d.victims.spec.GT_PROPOSAL_SOURCES`) and ``settings.min_points_detector``
    for the others.
    """
    out: list[FrustumInput] = []
    for fi, (frame, prop) in enumerate(zip(frames, proposals, strict=True)):
        if len(prop.boxes) == 0:
            continue
        gt = prop.source in GT_PROPOSAL_SOURCES
        least = min_points if min_points is not None else (
            settings.min_points_gt if gt else settings.min_points_detector)
        projected = project_scan(frame.scan, frame.calib, frame.image_size)
        for k, (box, score) in enumerate(zip(prop.boxes, prop.scores, strict=True)):
            if box[3] - box[1] < settings.min_box_height:
                continue
            fr = extract_frustum(projected, box, frame.calib,
                                 None if prop.extra_points is None else prop.extra_points[k])
            if len(fr) < max(least, 1):
                continue
            rng = frustum_rng(settings.seed, frame.frame_id, k)
            idx = resample_indices(len(fr), num_points, rng)
            pts = rotate_to_frustum(fr.points[idx], fr.rot_angle).astype(np.float32)
            out.append(FrustumInput(fi, fr, float(score), rng, pts, gt))
    return out


def detect_frames(frames: Sequence[Frame], proposals: ProposalsArg, *, detect_2d: Detect2DFn, car_class: int,
                  stages: FrustumStages, settings: CascadeSettings, num_points: int,
                  num_object_points: int) -> list[Labels]:
    """KITTI Car rows per frame (rect frame; score = 2D score, or the 3D score for GT boxes: proposals of
    the sources of :data:`~robustbench3d.victims.spec.GT_PROPOSAL_SOURCES`).

    ``settings.batch_size`` frustums go through ``stages`` at a time.
    """
    props = make_proposals(frames, proposals, detect_2d, car_class, settings.gt_types)
    inputs = frustum_inputs(frames, props, settings, num_points)
    per_frame: list[list[Labels]] = [[] for _ in frames]
    bs = settings.batch_size
    for start in range(0, len(inputs), bs):
        chunk = inputs[start:start + bs]
        out = run_frustum_stages(stages, np.stack([j.points for j in chunk]), car_one_hot(len(chunk)),
                                 num_object_points, settings.gather, [j.rng for j in chunk])
        boxes = decode(out)
        scores = np.where([j.ground_truth for j in chunk], boxes.score_3d, [j.score for j in chunk])
        rows = to_labels(boxes, np.array([j.frustum.rot_angle for j in chunk]),
                         np.stack([j.frustum.box2d for j in chunk]), scores)
        for r, job in enumerate(chunk):
            per_frame[job.frame_index].append(rows.select(np.array([r])))
    return [Labels.concatenate(p) if p else empty_detections() for p in per_frame]
