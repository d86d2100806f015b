"""Torch vs onnxruntime parity of an F-PN cascade and its ONNX export, at three levels.

1. Stage tensors: each stage graph against its torch module on the same inputs (letterboxed
   frame images; the frames' frustums; object points derived from the torch segmentation):
   max |Δ| <= ``tensor_atol``; also reported: the share of elements that differ at all and the
   share beyond ``mismatch_atol + mismatch_rtol·|ref|``. Input sensitivity: perturbing one input
   at a time must move the ONNX outputs wherever it moves the torch outputs (catches inputs baked
   in as constants), and the perturbed outputs must agree too.
2. Boxes per frame: both victims' decoded ``detect`` results must be identical — the same rows,
   every geometry value (2D box px, dimensions and location m, angles rad) within
   ``geometry_atol``, far below the written precision (comparing the rounded text instead
   would flag values that merely straddle a rounding boundary); scores within ``score_atol``.
   A frame that differs is re-run in lockstep (:mod:`.divergence`): it passes as a *near tie*
   only if some discrete decision flipped and every flipped decision's torch margin is within
   ``tie_atol`` (logits, scores, IoU) or ``tie_px`` (pixels) — e.g. a LiDAR point 1e-5 px from a
   2D box edge. Any other difference fails.
3. AP: every AP value of the built-in evaluator (metrics x R11/R40 x difficulties, in percent)
   on the written-and-parsed results, |ΔAP| <= ``ap_atol`` percentage points.

Stage inputs are capped (:data:`MAX_IMAGES`, :data:`MAX_FRUSTUMS`); levels 2 and 3 use every frame.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from robustbench3d.kitti.dataset import Frame
from robustbench3d.kitti.labels import RESULT_PRECISION, Labels, parse_labels
from robustbench3d.victims.base import victim_inputs
from robustbench3d.victims.cascade import FPointNetCascade
from robustbench3d.victims.fpointnet.glue import gather_points, mask_centroid, object_point_indices
from robustbench3d.victims.fpointnet.model import TorchFrustumStages
from robustbench3d.victims.fpointnet.pipeline import frustum_inputs, make_proposals
from robustbench3d.victims.onnx.divergence import FrameDivergence, trace_frame
from robustbench3d.victims.onnx.manifest import BOX, CENTER, DETECTOR_2D, SEGMENTATION, STAGES
from robustbench3d.victims.onnx.runtime import OnnxCascade
from robustbench3d.victims.yolo.preprocess import letterbox_image

#: At most this many frame images and frustums enter the stage-tensor comparison.
MAX_IMAGES = 8
MAX_FRUSTUMS = 32


@dataclass(frozen=True)
class Tolerances:
    """Pass thresholds (see the module docstring). ``ap_atol`` is in AP percentage points."""

    tensor_atol: float = 1e-4
    mismatch_atol: float = 1e-6
    mismatch_rtol: float = 1e-5
    score_atol: float = 1e-5
    geometry_atol: float = 1e-3
    tie_atol: float = 2e-4
    tie_px: float = 1e-3
    ap_atol: float = 0.01
    sensitivity_min: float = 1e-6


@dataclass(frozen=True)
class TensorParity:
    """One output tensor of one stage: ONNX vs torch."""

    stage: str
    tensor: str
    shape: tuple[int, ...]
    max_abs_diff: float
    max_abs_ref: float
    differing_fraction: float
    mismatch_fraction: float
    ok: bool


@dataclass(frozen=True)
class InputSensitivity:
    """How much perturbing one input moves a stage's outputs, in torch and in ONNX."""

    stage: str
    input: str
    torch_change: float
    onnx_change: float
    perturbed_max_abs_diff: float
    ok: bool


@dataclass(frozen=True)
class BoxParity:
    """Result rows of both victims over the frames, for one proposal source."""

    proposals: str
    frames: int
    rows_torch: int
    rows_onnx: int
    identical_frames: int
    near_tie_frames: int
    max_score_diff: float
    first_difference: str | None
    divergences: tuple[str, ...]
    ok: bool


@dataclass(frozen=True)
class APParity:
    """Every AP value (percent) of both victims' results, for one proposal source."""

    proposals: str
    values: int
    max_abs_delta: float
    worst: str
    bev_moderate_r40: tuple[float, float]
    ok: bool


@dataclass
class ParityReport:
    """All three levels (plus input sensitivity) and the tolerances they were judged by."""

    tolerances: Tolerances
    tensors: list[TensorParity] = field(default_factory=list)
    sensitivity: list[InputSensitivity] = field(default_factory=list)
    boxes: list[BoxParity] = field(default_factory=list)
    ap: list[APParity] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        checks = [*self.tensors, *self.sensitivity, *self.boxes, *self.ap]
        return bool(checks) and all(c.ok for c in checks)

    def to_dict(self) -> dict[str, Any]:
        return {"ok": self.ok, "tolerances": asdict(self.tolerances),
                "tensors": [asdict(t) for t in self.tensors], "sensitivity": [asdict(s) for s in self.sensitivity],
                "boxes": [asdict(b) for b in self.boxes], "ap": [asdict(a) for a in self.ap]}


def compare_tensors(stage: str, name: str, ref: np.ndarray, got: np.ndarray, tol: Tolerances) -> TensorParity:
    """ONNX output ``got`` against torch output ``ref``."""
    if ref.shape != got.shape:
        return TensorParity(stage, name, tuple(ref.shape), float("inf"), float(np.abs(ref).max(initial=0)), 1.0, 1.0,
                            False)
    ref64, got64 = ref.astype(np.float64), got.astype(np.float64)
    diff = np.abs(got64 - ref64)
    mismatch = diff > tol.mismatch_atol + tol.mismatch_rtol * np.abs(ref64)
    max_diff = float(diff.max(initial=0.0))
    return TensorParity(stage, name, tuple(ref.shape), max_diff, float(np.abs(ref64).max(initial=0.0)),
                        float((diff > 0).mean()) if diff.size else 0.0,
                        float(mismatch.mean()) if diff.size else 0.0,
                        bool(np.isfinite(max_diff) and max_diff <= tol.tensor_atol))


def stage_inputs(victim: FPointNetCascade, frames: Sequence[Frame],
                 rng: np.random.Generator) -> dict[str, list[np.ndarray]]:
    """Inputs of each stage: letterboxed images, frustum points (GT proposals when the frames
    have labels, else the detector's; seeded random points if no frustum is usable), and the
    object points the glue derives from the torch segmentation ("topk" gather)."""
    cfg = victim.yolo.cfg
    images = np.stack([letterbox_image(f.image, cfg.input_size, cfg.fill)[0] for f in frames[:MAX_IMAGES]])
    source = "gt" if all(f.labels is not None for f in frames) else "detector"
    bare, given = victim_inputs(frames, [f.labels for f in frames], source)
    props = make_proposals(bare, given, victim.yolo.detect, victim.car_class, victim.settings.gt_types)
    found = frustum_inputs(frames, props, victim.settings, victim.num_points, min_points=1)[:MAX_FRUSTUMS]
    n = victim.num_points
    if found:
        points = np.stack([j.points for j in found])
    else:
        xyz = rng.normal(0, 2, (4, n, 3)) + np.array([0.0, 1.0, 20.0])  # a blob 20 m ahead
        points = np.concatenate([xyz, rng.uniform(0, 1, (4, n, 1))], axis=2).astype(np.float32)
    k = victim.fpn.cfg.one_hot_dim
    one_hot = np.eye(k, dtype=np.float32)[np.arange(len(points)) % k]
    stages = TorchFrustumStages(victim.fpn)
    logits = stages.segmentation(points, one_hot)
    xyz = points[..., :3].astype(np.float64)
    mask, _, centroid = mask_centroid(logits, xyz)
    idx = object_point_indices(mask, logits[..., 1] - logits[..., 0], victim.fpn.cfg.num_object_points, "topk")
    object_points = gather_points(xyz - centroid[:, None, :], idx).astype(np.float32)
    delta = stages.center_delta(object_points, one_hot)
    box_points = (object_points - delta[:, None, :]).astype(np.float32)
    return {DETECTOR_2D: [images], SEGMENTATION: [points, one_hot], CENTER: [object_points, one_hot],
            BOX: [box_points, one_hot]}


def torch_stage_outputs(victim: FPointNetCascade, stage: str,
                        inputs: Sequence[np.ndarray]) -> list[np.ndarray]:
    """The torch module of ``stage`` on numpy inputs (eval mode; as the torch victim runs it)."""
    if stage == DETECTOR_2D:
        return victim.yolo.run_heads(inputs[0])
    stages = TorchFrustumStages(victim.fpn)
    fn = {SEGMENTATION: stages.segmentation, CENTER: stages.center_delta, BOX: stages.box_output}[stage]
    return [fn(*inputs)]


def _perturb(stage: str, index: int, x: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A different value of one input: image noise, point jitter, or the next one-hot class."""
    if stage == DETECTOR_2D:
        return np.clip(x + rng.uniform(-0.1, 0.1, x.shape), 0, 1).astype(np.float32)
    if index == 1:  # one-hot
        return np.roll(x, 1, axis=1)
    out = x.copy()
    out[..., :3] += rng.normal(0, 0.05, out[..., :3].shape).astype(np.float32)
    return out


def tensor_parity(victim: FPointNetCascade, onnx_victim: OnnxCascade, frames: Sequence[Frame], tol: Tolerances,
                  seed: int = 0) -> tuple[list[TensorParity], list[InputSensitivity]]:
    """Level 1 and the input-sensitivity check, for every stage."""
    rng = np.random.default_rng(seed)
    inputs = stage_inputs(victim, frames, rng)
    tensors: list[TensorParity] = []
    sensitivity: list[InputSensitivity] = []
    for stage in STAGES:
        session = onnx_victim.stages[stage]
        ref = torch_stage_outputs(victim, stage, inputs[stage])
        got = session.run(*inputs[stage])
        tensors += [compare_tensors(stage, name, r, g, tol) for name, r, g in zip(session.output_names, ref, got,
                                                                                 strict=True)]
        for i, name in enumerate(session.input_names):
            changed = list(inputs[stage])
            changed[i] = _perturb(stage, i, changed[i], rng)
            ref2, got2 = torch_stage_outputs(victim, stage, changed), session.run(*changed)
            t_change = max(float(np.abs(a - b).max()) for a, b in zip(ref2, ref, strict=True))
            o_change = max(float(np.abs(a - b).max()) for a, b in zip(got2, got, strict=True))
            diff = max(float(np.abs(a.astype(np.float64) - b).max()) for a, b in zip(got2, ref2, strict=True))
            baked = t_change > tol.sensitivity_min and o_change <= tol.sensitivity_min
            sensitivity.append(InputSensitivity(stage, name, t_change, o_change, diff,
                                                not baked and diff <= tol.tensor_atol))
    return tensors, sensitivity


def _geometry_lines(labels: Labels) -> list[str]:
    """Result-file lines without the score column (the geometry as written)."""
    return [line.rsplit(" ", 1)[0] for line in labels.to_text(RESULT_PRECISION).splitlines()]


def _geometry(labels: Labels) -> np.ndarray:
    """(N, 12) decoded geometry: alpha, 2D box, dimensions, location, rotation_y."""
    return np.column_stack([labels.alpha, labels.bbox, labels.dimensions, labels.location,
                            labels.rotation_y]).astype(np.float64).reshape(-1, 12)


def box_parity(frames: Sequence[Frame], proposals: str, dets_torch: Sequence[Labels], dets_onnx: Sequence[Labels],
               tol: Tolerances, trace: Callable[[Frame], FrameDivergence] | None = None) -> BoxParity:
    """Level 2 for one proposal source; ``trace`` re-runs a differing frame in lockstep (without
    it every differing frame fails)."""
    identical, ties, max_score, first = 0, 0, 0.0, None
    notes: list[str] = []
    for frame, a, b in zip(frames, dets_torch, dets_onnx, strict=True):
        ga, gb = _geometry(a), _geometry(b)
        if len(ga) == len(gb) and (len(ga) == 0 or float(np.abs(ga - gb).max()) <= tol.geometry_atol):
            identical += 1
            if len(a):
                max_score = max(max_score, float(np.abs(a.score - b.score).max()))
            continue
        if first is None:
            la, lb = _geometry_lines(a), _geometry_lines(b)
            diff = next((i for i, (x, y) in enumerate(zip(la, lb, strict=False)) if x != y), min(len(la), len(lb)))
            first = (f"frame {frame.frame_id} row {diff}: torch {la[diff] if diff < len(la) else '<none>'!r} vs "
                     f"onnx {lb[diff] if diff < len(lb) else '<none>'!r}")
        if trace is None:
            notes.append(f"frame {frame.frame_id}: differs (not traced)")
            continue
        div = trace(frame)
        ties += div.explained
        notes.append(("near tie: " if div.explained else "UNEXPLAINED: ") + div.summary())
    ok = identical + ties == len(frames) and max_score <= tol.score_atol
    return BoxParity(proposals, len(frames), sum(len(x) for x in dets_torch), sum(len(x) for x in dets_onnx),
                     identical, ties, max_score, first, tuple(notes), ok)


def lockstep_tracer(victim: FPointNetCascade, onnx_victim: OnnxCascade, source: str,
                    tol: Tolerances) -> Callable[[Frame], FrameDivergence]:
    """:func:`~.divergence.trace_frame` of the two victims for ``source``."""
    stages_t = TorchFrustumStages(victim.fpn)

    def trace(frame: Frame) -> FrameDivergence:
        return trace_frame(frame, source, yolo_cfg=victim.yolo.cfg, car_class=victim.car_class,
                           heads_t=victim.yolo.run_heads, heads_o=onnx_victim.run_heads, stages_t=stages_t,
                           stages_o=onnx_victim.frustum_stages, settings=victim.settings,
                           num_points=victim.num_points, num_object_points=victim.fpn.cfg.num_object_points,
                           tie_atol=tol.tie_atol, tie_px=tol.tie_px)

    return trace


def _as_written(dets: Sequence[Labels]) -> list[Labels]:
    """Detections parsed back from their result-file text (what the runner evaluates)."""
    return [parse_labels(d.to_text(RESULT_PRECISION), "<result>", scored=True) for d in dets]


def _ap_values(metrics: dict[str, Any]) -> dict[str, float]:
    """Every AP value of an evaluation, keyed ``class/metric/recall/difficulty``."""
    from robustbench3d.results import APResult

    return {f"{v.cls}/{v.metric}/{v.recall}/{v.difficulty}": float(v.ap) for v in APResult(metrics).values()}


def ap_parity(gt: Sequence[Labels], proposals: str, dets_torch: Sequence[Labels], dets_onnx: Sequence[Labels],
              tol: Tolerances) -> APParity:
    """Level 3 for one proposal source (Car, every metric, R11 and R40, every difficulty)."""
    from robustbench3d.eval.kitti_eval import evaluate

    a = _ap_values(evaluate(gt, _as_written(dets_torch)))
    b = _ap_values(evaluate(gt, _as_written(dets_onnx)))
    keys = sorted(set(a) | set(b))
    deltas = {k: abs(a.get(k, np.nan) - b.get(k, np.nan)) for k in keys}
    max_delta = float(np.nanmax(list(deltas.values()))) if keys else 0.0
    worst = max(keys, key=lambda k: np.inf if np.isnan(deltas[k]) else deltas[k]) if max_delta > 0 else "-"
    bev = "Car/bev/R40/moderate"
    ok = bool(keys) and not any(np.isnan(v) for v in deltas.values()) and max_delta <= tol.ap_atol
    return APParity(proposals, len(keys), max_delta, worst, (a.get(bev, np.nan), b.get(bev, np.nan)), ok)


def run_parity(victim: FPointNetCascade, onnx_victim: OnnxCascade, frames: Sequence[Frame],
               tol: Tolerances | None = None, proposals: Sequence[str] = ("gt", "detector")) -> ParityReport:
    """All levels on ``frames``; AP only for frames with labels (GT proposals need them too)."""
    tol = tol or Tolerances()
    report = ParityReport(tol)
    report.tensors, report.sensitivity = tensor_parity(victim, onnx_victim, frames, tol)
    labelled = all(f.labels is not None for f in frames)
    for source in proposals:
        if source == "gt" and not labelled:
            continue
        bare, given = victim_inputs(frames, [f.labels for f in frames], source)  # as the runner calls them
        dets_torch = victim.detect(bare, given)
        dets_onnx = onnx_victim.detect(bare, given)
        report.boxes.append(box_parity(frames, source, dets_torch, dets_onnx, tol,
                                       lockstep_tracer(victim, onnx_victim, source, tol)))
        if labelled:
            gt = [f.labels for f in frames if f.labels is not None]
            report.ap.append(ap_parity(gt, source, dets_torch, dets_onnx, tol))
    return report


def format_report(report: ParityReport) -> str:
    """Plain-text tables of every level."""
    from robustbench3d.bench import dict_table

    t = report.tolerances
    parts = [f"== stage tensors (pass: max |Δ| <= {t.tensor_atol:g}; mismatch: |Δ| > {t.mismatch_atol:g} + "
             f"{t.mismatch_rtol:g}·|ref|)",
             dict_table([{"stage": r.stage, "tensor": r.tensor, "shape": "x".join(map(str, r.shape)),
                          "max_abs_diff": r.max_abs_diff, "max_abs_ref": r.max_abs_ref,
                          "differing": r.differing_fraction, "mismatch": r.mismatch_fraction, "ok": r.ok}
                         for r in report.tensors]),
             "== input sensitivity (an input that moves the torch output must move the ONNX output)",
             dict_table([{"stage": s.stage, "input": s.input, "torch_change": s.torch_change,
                          "onnx_change": s.onnx_change, "perturbed_max_abs_diff": s.perturbed_max_abs_diff,
                          "ok": s.ok, "note": "" if s.torch_change > t.sensitivity_min else
                          "vacuous: constant in torch too (e.g. the zero-initialised T-Net head)"}
                         for s in report.sensitivity])]
    if report.boxes:
        parts += [f"== boxes per frame (same rows, decoded geometry within {t.geometry_atol:g} px/m/rad; "
                  f"|Δscore| <= {t.score_atol:g}; a differing frame passes as a near tie if only decisions within "
                  f"{t.tie_atol:g} (logit/score/IoU) or {t.tie_px:g} px of their boundary flipped)",
                  dict_table([{"proposals": b.proposals, "frames": b.frames, "rows_torch": b.rows_torch,
                               "rows_onnx": b.rows_onnx, "identical_frames": b.identical_frames,
                               "near_tie_frames": b.near_tie_frames, "max_score_diff": b.max_score_diff,
                               "ok": b.ok} for b in report.boxes])]
        for b in report.boxes:
            if b.first_difference:
                parts.append(f"  first difference ({b.proposals}): {b.first_difference}")
            parts += [f"  {b.proposals}: {note}" for note in b.divergences]
    if report.ap:
        parts += [f"== AP (Car; all metrics, R11/R40, difficulties; |ΔAP| <= {t.ap_atol:g} points)",
                  dict_table([{"proposals": a.proposals, "values": a.values, "max_abs_delta": a.max_abs_delta,
                               "worst": a.worst, "bev_R40_mod_torch": a.bev_moderate_r40[0],
                               "bev_R40_mod_onnx": a.bev_moderate_r40[1], "ok": a.ok} for a in report.ap])]
    parts.append(f"parity: {'PASS' if report.ok else 'FAIL'}")
    return "\n".join(parts)
