"""Why two backends' boxes differ on a frame: the discrete decisions that flipped, with margins.

Tensor parity bounds the continuous differences (|Δ| ~ 1e-5), but the cascade also takes discrete
decisions on those tensors: a 2D prior passes the score threshold, one box outranks or suppresses
another, a LiDAR point falls inside a 2D box, a point is foreground (logit₁ > logit₀), one heading
bin or size template wins the argmax. A decision whose torch quantity lies within a tensor
tolerance of its boundary can go either way on another backend, and everything downstream of it
then differs (a flipped mask point moves the centroid; a flipped frustum point changes the
resampling), so "identical boxes on every frame" is not a property any two float backends have.

:func:`trace_frame` re-runs one frame with both backends: the 2D stage gets the same image on
both; the frustum stages then follow each backend's own path from its own 2D boxes (so the tiny
shift of a frustum's rotation angle and the centroid and T-Net differences accumulate before the
heading and size argmax as in a real run), unless a LiDAR point changed frustum, in which case
both continue from the torch boxes so that their points stay comparable. A proposal whose mask
(or top-k gather order) flipped has its heading and size compared on the torch object points
(both T-Nets and box nets on the same input): the resampling after a flipped mask point is the
flip's consequence, not a decision of its own. Each decision is taken
on both outputs, and every comparison whose outcome differs is a :class:`Flip` with the torch
quantity's distance to the boundary. A
frame is *explained* when at least one decision flipped and every flip lies within the tie
tolerance (``tie_atol`` for logit, score and IoU margins; ``tie_px`` for pixel margins); a frame
that differs without an explaining flip is a real disagreement.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from robustbench3d.kitti.dataset import Frame
from robustbench3d.victims.base import Proposals, gt_proposals
from robustbench3d.victims.fpointnet.box_coding import car_one_hot
from robustbench3d.victims.fpointnet.frustum import box_mask, project_scan
from robustbench3d.victims.fpointnet.glue import (
    HEADING_SCORES,
    SIZE_SCORES,
    FrustumStages,
    gather_points,
    run_box_stages,
    run_frustum_stages,
)
from robustbench3d.victims.fpointnet.pipeline import CascadeSettings, FrustumInput, frustum_inputs
from robustbench3d.victims.yolo.config import YoloConfig
from robustbench3d.victims.yolo.postprocess import (
    PRE_NMS_TOP_K,
    Detections2D,
    HeadsFn,
    box_iou,
    image_priors,
    prior_scores,
    select_detections,
)

#: Decisions whose margin is in pixels (judged by ``tie_px``); the others are logit / score / IoU.
PIXEL_DECISIONS = ("frustum-membership", "min-box-height")


@dataclass(frozen=True)
class Flip:
    """One comparison whose outcome differs between the backends on the same inputs.

    decision: "2d-threshold", "2d-order", "2d-nms", "min-box-height", "frustum-membership",
    "segmentation-mask", "gather-order", "heading-bin" or "size-cluster"; where: which proposal /
    prior / point; margin: |torch quantity − boundary| (px for :data:`PIXEL_DECISIONS`, else in the
    quantity's own units: logits, scores or IoU).
    """

    decision: str
    where: str
    margin: float


@dataclass
class FrameDivergence:
    """The flips of one frame and whether they explain its differing boxes."""

    frame_id: str
    proposals: str
    flips: list[Flip] = field(default_factory=list)
    explained: bool = False
    note: str = ""

    def summary(self) -> str:
        if not self.flips:
            return f"frame {self.frame_id}: no decision flipped ({self.note or 'unexplained'})"
        worst = max(self.flips, key=lambda f: f.margin)
        kinds = sorted({f.decision for f in self.flips})
        return (f"frame {self.frame_id}: {len(self.flips)} flip(s) [{', '.join(kinds)}], largest torch margin "
                f"{worst.margin:.3g} ({worst.decision} at {worst.where})")


def _pair_flips(decision: str, values_t: np.ndarray, values_o: np.ndarray, boundary: float, labels: np.ndarray,
                strict: bool = True) -> list[Flip]:
    """Flips of ``value > boundary`` (``>=`` if not ``strict``) between the two backends."""
    side_t = values_t > boundary if strict else values_t >= boundary
    side_o = values_o > boundary if strict else values_o >= boundary
    return [Flip(decision, str(labels[i]), float(abs(values_t[i] - boundary)))
            for i in np.flatnonzero(side_t != side_o)]


def _order_flips(decision: str, values_t: np.ndarray, values_o: np.ndarray, names: np.ndarray) -> list[Flip]:
    """Pairs ranked differently (strict order of the values) by the two backends."""
    dt = np.sign(values_t[:, None] - values_t[None, :])
    do = np.sign(values_o[:, None] - values_o[None, :])
    i, j = np.nonzero(np.triu(dt != do, 1))
    return [Flip(decision, f"{names[a]} vs {names[b]}", float(abs(values_t[a] - values_t[b])))
            for a, b in zip(i, j, strict=True)]


def _flips_2d(image: np.ndarray, cfg: YoloConfig, heads_t: HeadsFn, heads_o: HeadsFn,
              car_class: int) -> tuple[list[Flip], Detections2D, Detections2D]:
    """Threshold, ranking and NMS flips of the 2D stage on one letterboxed image."""
    decoded = [image_priors([image], fn, cfg)[0] for fn in (heads_t, heads_o)]
    (bt, ot, ct, geo), (bo, oo, co, _) = decoded
    st, cls_t = prior_scores(ot, ct)
    so, _ = prior_scores(oo, co)
    thr = float(np.float32(cfg.conf_threshold))
    priors = np.arange(len(st))
    flips = _pair_flips("2d-threshold", st.astype(np.float64), so.astype(np.float64), thr, priors, strict=False)
    cand = np.flatnonzero((st >= thr) & (so >= thr))
    cand = cand[np.argsort(-st[cand], kind="stable")[:PRE_NMS_TOP_K]]
    flips += _order_flips("2d-order", st[cand].astype(np.float64), so[cand].astype(np.float64), cand)

    def xyxy(b: np.ndarray) -> np.ndarray:
        half = b[cand, 2:4] / np.float32(2.0)
        return np.concatenate([b[cand, 0:2] - half, b[cand, 0:2] + half], axis=1).astype(np.float64)

    same = cls_t[cand][:, None] == cls_t[cand][None, :]
    iou_t, iou_o = box_iou(xyxy(bt), xyxy(bt)), box_iou(xyxy(bo), xyxy(bo))
    iu, ju = np.nonzero(np.triu(same, 1))
    flips += _pair_flips("2d-nms", iou_t[iu, ju], iou_o[iu, ju], cfg.nms_threshold,
                         np.array([f"{cand[a]} vs {cand[b]}" for a, b in zip(iu, ju, strict=True)], dtype=object))
    dets = [select_detections(b, o, c, geo, cfg) for b, o, c, _ in decoded]
    cars = [Detections2D(d.boxes[d.classes == car_class], d.scores[d.classes == car_class],
                         d.classes[d.classes == car_class]) for d in dets]
    return flips, cars[0], cars[1]


def _membership_flips(frame: Frame, boxes_t: np.ndarray, boxes_o: np.ndarray, settings: CascadeSettings) -> list[Flip]:
    """LiDAR points inside one backend's 2D box but not the other's, and height-filter flips (px)."""
    projected = project_scan(frame.scan, frame.calib, frame.image_size)
    uv = projected.uv
    flips = _pair_flips("min-box-height", boxes_t[:, 3] - boxes_t[:, 1], boxes_o[:, 3] - boxes_o[:, 1],
                        settings.min_box_height, np.array([f"proposal {k}" for k in range(len(boxes_t))]),
                        strict=False)
    for k, (bt, bo) in enumerate(zip(boxes_t, boxes_o, strict=True)):
        inside_t = projected.in_fov & box_mask(uv, bt)
        inside_o = projected.in_fov & box_mask(uv, bo)
        for p in np.flatnonzero(inside_t != inside_o):
            edge = min(abs(uv[p, 0] - bt[0]), abs(uv[p, 0] - bt[2]), abs(uv[p, 1] - bt[1]), abs(uv[p, 1] - bt[3]))
            flips.append(Flip("frustum-membership", f"proposal {k} point {p}", float(edge)))
    return flips


def _argmax_flips(decision: str, scores_t: np.ndarray, scores_o: np.ndarray, names: list[str]) -> list[Flip]:
    at, ao = scores_t.argmax(axis=1), scores_o.argmax(axis=1)
    return [Flip(decision, f"{names[r]} bins {at[r]}/{ao[r]}", float(scores_t[r, at[r]] - scores_t[r, ao[r]]))
            for r in np.flatnonzero(at != ao)]


def _frustum_flips(jobs_t: list[FrustumInput], jobs_o: list[FrustumInput], stages_t: FrustumStages,
                   stages_o: FrustumStages, settings: CascadeSettings, num_object_points: int) -> list[Flip]:
    """Mask, gather-order, heading and size flips of each backend's own frustum path
    (:func:`~robustbench3d.victims.fpointnet.glue.run_frustum_stages` on its own inputs, batched as
    the victims batch them); ``jobs_t[k]`` and ``jobs_o[k]`` are the same proposal."""
    flips: list[Flip] = []
    bs = settings.batch_size
    for start in range(0, len(jobs_t), bs):
        chunk_t, chunk_o = jobs_t[start:start + bs], jobs_o[start:start + bs]
        names = [f"proposal {start + r}" for r in range(len(chunk_t))]
        one_hot = car_one_hot(len(chunk_t))
        out_t, out_o = (run_frustum_stages(stages, np.stack([j.points for j in chunk]), one_hot, num_object_points,
                                           settings.gather, [j.rng for j in chunk])
                        for stages, chunk in ((stages_t, chunk_t), (stages_o, chunk_o)))
        mt = out_t.seg_logits[..., 1] - out_t.seg_logits[..., 0]
        mo = out_o.seg_logits[..., 1] - out_o.seg_logits[..., 0]
        upstream: list[int] = []  # rows whose object points differ by a flipped mask / gather decision
        for r in range(len(names)):
            row = _pair_flips("segmentation-mask", mt[r].astype(np.float64), mo[r].astype(np.float64), 0.0,
                              np.array([f"{names[r]} point {p}" for p in range(mt.shape[1])], dtype=object))
            if settings.gather == "topk":
                fg = np.flatnonzero((mt[r] > 0) & (mo[r] > 0))
                row += _order_flips("gather-order", mt[r, fg].astype(np.float64), mo[r, fg].astype(np.float64),
                                    np.array([f"{names[r]} point {p}" for p in fg], dtype=object))
            flips += row
            if row:
                upstream.append(r)
        heading_o, size_o = out_o.heading_scores.copy(), out_o.size_scores.copy()
        if upstream:  # their T-Net and box net are compared on the torch object points (lockstep)
            xyz = np.stack([j.points for j in chunk_t])[upstream, :, :3].astype(np.float64)
            _, box = run_box_stages(stages_o, gather_points(xyz - out_t.mask_centroid[upstream, None, :],
                                                            out_t.object_indices[upstream]), one_hot[upstream])
            heading_o[upstream], size_o[upstream] = box[:, HEADING_SCORES], box[:, SIZE_SCORES]
        flips += _argmax_flips("heading-bin", out_t.heading_scores.astype(np.float64), heading_o.astype(np.float64),
                               names)
        flips += _argmax_flips("size-cluster", out_t.size_scores.astype(np.float64), size_o.astype(np.float64),
                               names)
    return flips


def trace_frame(frame: Frame, source: str, *, yolo_cfg: YoloConfig, car_class: int, heads_t: HeadsFn,
                heads_o: HeadsFn, stages_t: FrustumStages, stages_o: FrustumStages, settings: CascadeSettings,
                num_points: int, num_object_points: int, tie_atol: float, tie_px: float) -> FrameDivergence:
    """Lockstep re-run of one frame (``source`` "detector" or "gt"); see the module docstring."""
    result = FrameDivergence(frame.frame_id, source)
    if source == "detector":
        flips, cars_t, cars_o = _flips_2d(frame.image, yolo_cfg, heads_t, heads_o, car_class)
        result.flips += flips
        props = props_o = Proposals(cars_t.boxes, cars_t.scores, "detector")
        if len(cars_t.boxes) != len(cars_o.boxes):
            result.note = "2D detections differ in number; later stages not compared"
        else:
            membership = _membership_flips(frame, cars_t.boxes, cars_o.boxes, settings)
            result.flips += membership
            if not membership:  # same frustum points: the ONNX path continues from its own boxes
                props_o = Proposals(cars_o.boxes, cars_o.scores, "detector")
        min_points = settings.min_points_detector
    else:
        if frame.labels is None:  # diagnostics read the labels; the victims get only these boxes
            raise ValueError(f"frame {frame.frame_id} has no labels; tracing proposals 'gt' needs them")
        props = props_o = gt_proposals(frame.labels).of_types(settings.gt_types)
        min_points = settings.min_points_gt
    jobs_t = frustum_inputs([frame], [props], settings, num_points, min_points)
    jobs_o = frustum_inputs([frame], [props_o], settings, num_points, min_points)  # fresh generators
    result.flips += _frustum_flips(jobs_t, jobs_o, stages_t, stages_o, settings, num_object_points)
    result.explained = bool(result.flips) and all(
        f.margin <= (tie_px if f.decision in PIXEL_DECISIONS else tie_atol) for f in result.flips)
    return result
