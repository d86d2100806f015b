"""The F-PN v1 cascade victim: YOLO 2D detector -> frustums -> Frustum-PointNet v1 -> KITTI rows.

Implements :class:`~robustbench3d.victims.base.Detector`,
:class:`~robustbench3d.victims.base.ImageObjectnessOracle`,
:class:`~robustbench3d.victims.base.FrustumSegmentationOracle`,
:class:`~robustbench3d.victims.base.FrustumBoxOracle` and, through the last two,
:class:`~robustbench3d.victims.base.TargetScoreOracle` (:func:`~robustbench3d.victims.base.frustum_target_scores`).

``detect`` is the numpy pipeline of :mod:`robustbench3d.victims.fpointnet.pipeline` (letterbox,
2D decoding and NMS, frustum extraction, resampling, masking, gather, box decoding — shared with
the ONNX victim) around the torch networks. Determinism: the resampling of each frustum to N
points (with replacement, as the original) and the random object-point gather draw from
:func:`~robustbench3d.victims.fpointnet.pipeline.frustum_rng` (``numpy.random.default_rng([seed,
frame, proposal])``), so a frustum's result does not depend on the batch or on other frames, and
``frustum_logits`` resamples exactly the points ``detect`` feeds the network; the networks run
in eval mode (BatchNorm running statistics, no dropout). Proposal filters follow §1.3: 2D height
>= 25 px, and at least ``min_points_detector`` (5) frustum points for detector boxes or one for
GT boxes.

Fidelity knobs (victim arguments, for speed/accuracy sweeps; the defaults are the trained
settings): ``num_points`` — points each frustum is resampled to (the segmentation PointNet
max-pools over them, so any N works; the T-Net / box stage still gathers the trained M object
points, repeating points when fewer are masked); ``input_size`` — the 2D stage's "WxH" input
(letterbox, decoding and the objectness oracle follow it); ``precision`` — float32, bfloat16
autocast or a float64 copy of the frustum stages. ``frustum_logits`` / ``frustum_box`` resample to
the same ``num_points`` as ``detect``. :meth:`FPointNetCascade.fidelity` lists the values in effect.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from robustbench3d.errors import DataFormatError, RobustBenchError
from robustbench3d.fileio import atomic_open, sha256_file
from robustbench3d.kitti.calib import Calibration
from robustbench3d.kitti.dataset import Frame
from robustbench3d.kitti.labels import Labels
from robustbench3d.victims.base import (
    PROPOSAL_SOURCES,
    AttackedScene,
    AttackTargets,
    FrustumBox,
    FrustumLogits,
    ObjectnessCandidates,
    Proposals,
    ProposalsArg,
    TargetScores,
    frustum_target_scores,
)
from robustbench3d.victims.fpointnet.box_coding import HEADING_BIN_WIDTH, MEAN_SIZES, ONE_HOT_CLASSES
from robustbench3d.victims.fpointnet.distinct_stages import DistinctPointStages
from robustbench3d.victims.fpointnet.frustum import extract_frustum, project_rect_points, resample_indices
from robustbench3d.victims.fpointnet.model import (
    FPointNetConfig,
    FrustumPointNetV1,
    TorchFrustumStages,
    build_model,
    rotate_to_frustum_torch,
)
from robustbench3d.victims.fpointnet.pipeline import (
    CascadeSettings,
    detect_frames,
    frame_key,
    frustum_rng,
    make_proposals,
)
from robustbench3d.victims.torchfile import (
    CASCADE_FORMAT,
    build_network,
    cascade_part,
    load_network_part,
    load_torch_data,
    network_sha256,
    shared_reference,
    stored_part,
)
from robustbench3d.victims.yolo.config import YoloConfig
from robustbench3d.victims.yolo.detector import YoloDetector
from robustbench3d.victims.yolo.model import Darknet

#: Inference precisions of :meth:`FPointNetCascade.detect`'s frustum stages (victim kwarg ``precision``).
PRECISIONS = ("float32", "bfloat16", "float64")
#: Bounds of the victim argument ``num_points``. Any N >= 1 runs (the segmentation net max-pools
#: over N; resampling draws with replacement; the object-point gather repeats points). The upper
#: bound keeps a typo from exhausting memory: the full config's segmentation pass holds about
#: 4 x N x 1603 float32 per-point features per batch of 4 frustums (~1.7 GB at 65536).
NUM_POINTS_RANGE = (1, 65536)
#: Largest side, px, of the victim argument ``input_size``: over 3x KITTI's 1242 px image width (larger
#: only upsamples the letterboxed image); the 2D stage's activations grow with W x H, so a typo such as
#: 96000x288 would exhaust memory instead of failing.
INPUT_SIDE_MAX = 4096


class BFloat16FrustumStages(TorchFrustumStages):
    """The frustum stages under ``torch.autocast("cpu", dtype=torch.bfloat16)`` (convolutions and matrix
    products in bfloat16, as autocast chooses), outputs returned as float32."""

    def _run(self, module: torch.nn.Module, points: np.ndarray, one_hot: np.ndarray) -> np.ndarray:  # type: ignore[override]
        with torch.inference_mode(), torch.autocast("cpu", dtype=torch.bfloat16):
            out = module(torch.from_numpy(np.ascontiguousarray(points, dtype=np.float32)),
                         torch.from_numpy(np.ascontiguousarray(one_hot, dtype=np.float32)))
        return out.float().numpy()


class Float64FrustumStages(TorchFrustumStages):
    """The frustum stages run by a float64 copy of the network (given): inputs (float32 points from
    the numpy glue) widened to float64, outputs returned as float64 (the glue rounds them to float32)."""

    def _run(self, module: torch.nn.Module, points: np.ndarray, one_hot: np.ndarray) -> np.ndarray:  # type: ignore[override]
        with torch.inference_mode():
            return module(torch.from_numpy(np.asarray(points, dtype=np.float64)),
                          torch.from_numpy(np.asarray(one_hot, dtype=np.float64))).numpy()


def parse_num_points(value: object) -> int | None:
    """The victim argument ``num_points``: None (the network's trained N) or an int in
    :data:`NUM_POINTS_RANGE`; anything else raises :class:`RobustBenchError` naming it."""
    if value is None:
        return None
    lo, hi = NUM_POINTS_RANGE
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or not lo <= int(value) <= hi:
        raise RobustBenchError(f"victim argument 'num_points': {value!r} is not an integer in [{lo}, {hi}]")
    return int(value)


def parse_input_size(value: object, max_stride: int) -> tuple[int, int] | None:
    """The victim argument ``input_size``: None (the trained size), ``"WxH"`` or a (W, H) pair of
    multiples of ``max_stride`` (the network's largest downsampling) in [1, :data:`INPUT_SIDE_MAX`];
    anything else raises :class:`RobustBenchError` naming it."""
    if value is None:
        return None
    if isinstance(value, str):
        parts: list[object] = [int(p) if p.strip().isdigit() else p for p in value.lower().split("x")]
    else:
        parts = list(value) if isinstance(value, list | tuple) else [value]
    sides = [int(p) for p in parts if isinstance(p, int | np.integer) and not isinstance(p, bool) and p > 0]
    if len(parts) != 2 or len(sides) != 2:
        raise RobustBenchError(f"victim argument 'input_size': {value!r} is not WxH with positive integers "
                               "(e.g. '640x192')")
    w, h = sides
    if max(w, h) > INPUT_SIDE_MAX:
        raise RobustBenchError(f"victim argument 'input_size': {w}x{h} has a side over {INPUT_SIDE_MAX} px "
                               f"(sides are in [1, {INPUT_SIDE_MAX}])")
    if w % max_stride or h % max_stride:
        raise RobustBenchError(f"victim argument 'input_size': {w}x{h} is not a multiple of the 2D network's "
                               f"largest stride {max_stride} in both sides")
    return w, h


#: Temperature of the straight-through mask of :meth:`FPointNetCascade.frustum_box` (see
#: :meth:`~robustbench3d.victims.fpointnet.model.FrustumPointNetV1.forward`).
BOX_ORACLE_TEMPERATURE = 1.0


class FPointNetCascade:
    """YOLO -> Frustum-PointNet v1 for KITTI cars (see the module docstring)."""

    supported_proposals: tuple[str, ...] = PROPOSAL_SOURCES

    def __init__(self, yolo: YoloDetector, fpn: FrustumPointNetV1, settings: CascadeSettings | None = None):
        self.yolo = yolo
        self.fpn = fpn.eval()
        self.settings = settings or CascadeSettings()
        self.car_class = self.yolo.cfg.class_names.index("Car")
        self.precision = "float32"
        self._fpn64: FrustumPointNetV1 | None = None
        self._num_points: int | None = None
        #: :meth:`objectness` runs the 2D network on crops around the targets unless told otherwise.
        self.objectness_crop = True

    def with_precision(self, precision: str) -> FPointNetCascade:
        """Set the precision of :meth:`detect`'s frustum stages (one of :data:`PRECISIONS`): "bfloat16"
        autocast, or "float64" on a float64 copy of the network (the float32 glue in between). The 2D
        stage and the attack oracles stay float32. Returns ``self``."""
        if precision not in PRECISIONS:
            raise RobustBenchError(f"victim argument 'precision': {precision!r} is not one of {', '.join(PRECISIONS)}")
        self.precision = precision
        if precision == "float64" and self._fpn64 is None:
            self._fpn64 = copy.deepcopy(self.fpn).double().eval()
        return self

    def with_num_points(self, num_points: int | None) -> FPointNetCascade:
        """Resample every frustum to ``num_points`` points in :meth:`detect` and the frustum oracles
        (None: the network's trained N; see :func:`parse_num_points`). Returns ``self``."""
        self._num_points = parse_num_points(num_points)
        return self

    def with_input_size(self, input_size: str | Sequence[int] | None) -> FPointNetCascade:
        """Run the 2D stage at ``input_size`` ("WxH" or (W, H), multiples of the network's largest
        stride; None keeps the current size): letterbox, decoding (strides are input size / grid
        size) and the objectness oracle follow it; anchors stay in input pixels. Returns ``self``."""
        size = parse_input_size(input_size, max(self.yolo.net.head_strides))
        if size is not None and size != tuple(self.yolo.cfg.input_size):
            self.yolo.cfg = replace(self.yolo.cfg, input_size=size)
        return self

    def fidelity(self) -> dict[str, Any]:
        """The fidelity settings in effect: frustum points, 2D input (W, H) and frustum-stage precision."""
        return {"num_points": self.num_points, "input_size": list(self.yolo.cfg.input_size),
                "precision": self.precision}

    # ---- construction ------------------------------------------------------------------
    @property
    def num_points(self) -> int:
        """Points per frustum: the ``num_points`` victim argument, else the network's trained N."""
        return self._num_points if self._num_points is not None else self.fpn.cfg.num_points

    @classmethod
    def untrained(cls, fpn_config: FPointNetConfig | str = "full", yolo_config: YoloConfig | str = "mini",
                  seed: int = 0, settings: CascadeSettings | None = None) -> FPointNetCascade:
        """Randomly initialised networks (seeded) — for tests and plumbing, not for results."""
        return cls(YoloDetector.untrained(yolo_config, seed), build_model(fpn_config, seed + 1), settings)

    def state(self) -> dict[str, Any]:
        return {"format": CASCADE_FORMAT,
                "yolo": {"config": self.yolo.cfg.to_dict(), "state_dict": self.yolo.net.state_dict()},
                "fpointnet": {"config": self.fpn.cfg.to_dict(), "state_dict": self.fpn.state_dict()}}

    def save(self, path: str | Path, share_yolo: str | Path | None = None) -> None:
        """Write both networks to one weights file (atomically). With ``share_yolo`` (a weights file in
        the same directory that stores this cascade's 2D-stage weights) the file refers to it for them
        instead of holding a copy (:func:`~robustbench3d.victims.torchfile.cascade_part`)."""
        state = self.state()
        if share_yolo is not None:
            share, own = Path(share_yolo), state["yolo"]["state_dict"]
            if share.resolve().parent != Path(path).resolve().parent:
                raise RobustBenchError(f"{share}: a shared 2D stage must be in the directory of {path}")
            ref = shared_reference(share, own)
            if network_sha256(stored_part(share, "yolo")["state_dict"]) != ref["state_sha256"]:
                raise RobustBenchError(f"{share}: its yolo weights are not this cascade's; cannot share them")
            state["yolo"] = {"config": state["yolo"]["config"], "shared": ref}
        with atomic_open(path, "wb") as f:
            torch.save(state, f)

    @classmethod
    def load(cls, path: str | Path, settings: CascadeSettings | None = None,
             sha256: str | None = None) -> FPointNetCascade:
        """From :meth:`save`'s file (read as data only); with ``sha256`` the file's hash is checked first."""
        path = Path(path)
        if sha256 is not None and path.is_file() and sha256_file(path) != sha256:
            raise RobustBenchError(f"{path}: sha256 does not match the registered weights ({sha256})")
        what = "cascade weights file"
        data = load_torch_data(path, what)
        if not isinstance(data, dict) or data.get("format") != CASCADE_FORMAT:
            raise DataFormatError(path, f"not a {what}: expected format {CASCADE_FORMAT!r} (written by "
                                        "`robustbench3d victims pack`)", field="format")
        yolo, fpn = (cascade_part(data.get(name), path, name, what) for name in ("yolo", "fpointnet"))
        return cls.from_parts(yolo, fpn, settings, origins=(path, path))

    @classmethod
    def from_parts(cls, yolo: dict[str, Any] | str | Path, fpointnet: dict[str, Any] | str | Path,
                   settings: CascadeSettings | None = None,
                   origins: tuple[str | Path, str | Path] | None = None) -> FPointNetCascade:
        """From the two trainers' ``model.pt`` files (read as data only) or their loaded dicts; a
        cascade weights file (:meth:`save`) given for a part contributes that network. ``origins``
        name the files loaded dicts came from, for errors."""
        def part(source: dict[str, Any] | str | Path, name: str, i: int) -> tuple[dict[str, Any], str | Path]:
            if isinstance(source, dict):
                return source, origins[i] if origins else f"<{name} part>"
            return load_network_part(source, name), source

        (y, y_origin), (p, p_origin) = part(yolo, "yolo", 0), part(fpointnet, "fpointnet", 1)
        net = build_network(lambda c: Darknet(YoloConfig.from_dict(c)), y, y_origin, "yolo")
        fpn = build_network(lambda c: FrustumPointNetV1(FPointNetConfig.from_dict(c)), p, p_origin, "fpointnet")
        return cls(YoloDetector(net), fpn, settings)

    # ---- Detector ----------------------------------------------------------------------
    def proposals(self, frames: Sequence[Frame], source: ProposalsArg) -> list[Proposals]:
        """2D proposals per frame: YOLO Car detections for ``"detector"``, else the given list with
        ground-truth sets (``source`` "gt", "gt-object" or "gt-append") reduced to ``settings.gt_types``
        (:func:`~robustbench3d.victims.fpointnet.pipeline.make_proposals`)."""
        return make_proposals(frames, source, self.yolo.detect, self.car_class, self.settings.gt_types)

    def detect(self, frames: Sequence[Frame], proposals: ProposalsArg = "detector") -> list[Labels]:
        """KITTI Car rows per frame (rect frame; score = 2D score, or the 3D score for GT boxes,
        i.e. proposals with ``source`` "gt", "gt-object" or "gt-append"; the last adds each box's
        ``extra_points`` to its frustum, see :mod:`~robustbench3d.victims.fpointnet.pipeline`)."""
        stages: TorchFrustumStages
        if self.precision == "float64":
            assert self._fpn64 is not None
            stages = Float64FrustumStages(self._fpn64)
        else:
            stages = (BFloat16FrustumStages if self.precision == "bfloat16" else DistinctPointStages)(self.fpn)
        return detect_frames(frames, proposals, detect_2d=self.yolo.detect, car_class=self.car_class,
                             stages=stages, settings=self.settings,
                             num_points=self.num_points, num_object_points=self.fpn.cfg.num_object_points)

    # ---- ImageObjectnessOracle --------------------------------------------------------
    def objectness(self, images: torch.Tensor, targets: Sequence[np.ndarray], *,
                   iou_threshold: float = 0.3, crop: bool | None = None) -> ObjectnessCandidates:
        """Objectness / Car logits of the priors around each target box (see base protocol). With flip TTA
        the detector also sees the mirrored image: its priors count too, their boxes mirrored back as the
        numpy glue does. ``crop`` (default :attr:`objectness_crop`): run the 2D network only on the slices
        of the input that its candidates read (:meth:`YoloDetector.target_candidates`; the same candidates,
        values and gradients as the whole input, bit for bit)."""
        if len(targets) != images.shape[0]:
            raise ValueError(f"{len(targets)} target sets for {images.shape[0]} images")
        parts: dict[str, list[torch.Tensor]] = {k: [] for k in ("obj", "cls", "boxes", "iou", "image", "target")}
        found = self.yolo.target_candidates(images, targets, iou_threshold,
                                            self.objectness_crop if crop is None else crop)
        for c in found:
            parts["obj"].append(c.obj_logit)
            parts["cls"].append(c.cls_logit[:, self.car_class])
            parts["boxes"].append(c.boxes.float())
            parts["iou"].append(c.iou.float())
            parts["image"].append(torch.full_like(c.prior, c.image))
            parts["target"].append(c.target)
        return ObjectnessCandidates(
            objectness_logit=torch.cat(parts["obj"]), class_logit=torch.cat(parts["cls"]),
            boxes=torch.cat(parts["boxes"]).reshape(-1, 4), iou=torch.cat(parts["iou"]),
            image_index=torch.cat(parts["image"]), target_index=torch.cat(parts["target"]),
        )

    # ---- FrustumSegmentationOracle / FrustumBoxOracle ----------------------------------
    def _frustum(self, points_rect: torch.Tensor, calib: Calibration, image_size: tuple[int, int],
                 box2d: np.ndarray, frame_id: str, proposal: int, class_id: int,
                 extra_points: np.ndarray | None = None,
                 ) -> tuple[torch.Tensor, torch.Tensor, np.ndarray, float, np.random.Generator] | None:
        """Frustum-frame points (1, N, 4) of ``box2d`` (plus the rows ``extra_points`` of ``points_rect`` in
        front of the camera) resampled as ``detect`` does, their one-hot, sample indices, rotation angle and
        the generator (positioned for the object-point gather)."""
        projected = project_rect_points(points_rect.detach().cpu().double().numpy(), calib, image_size)
        fr = extract_frustum(projected, np.asarray(box2d, dtype=np.float64), calib, extra_points)
        if len(fr) == 0:
            return None
        rng = frustum_rng(self.settings.seed, frame_id, proposal)
        idx = fr.indices[resample_indices(len(fr), self.num_points, rng)]
        pts = rotate_to_frustum_torch(points_rect[torch.from_numpy(idx)], fr.rot_angle)
        one_hot = torch.zeros(1, len(ONE_HOT_CLASSES), dtype=pts.dtype)
        one_hot[0, class_id] = 1.0
        return pts[None], one_hot, idx, fr.rot_angle, rng

    def frustum_logits(self, points_rect: torch.Tensor, calib: Calibration, image_size: tuple[int, int],
                       box2d: np.ndarray, *, frame_id: str, proposal: int, class_id: int = 0,
                       extra_points: np.ndarray | None = None) -> FrustumLogits | None:
        """Seg logits of the frustum of ``box2d`` (with the rows ``extra_points`` of ``points_rect`` in front
        of the camera, as ``detect`` adds a ``gt-append`` box's extra points) over (P, 4) rect points
        (differentiable), resampled with :func:`frustum_rng` of ``settings.seed``, ``frame_id`` and
        ``proposal`` as ``detect`` does."""
        got = self._frustum(points_rect, calib, image_size, box2d, frame_id, proposal, class_id, extra_points)
        if got is None:
            return None
        pts, one_hot, idx, rot, _ = got
        logits = self.segmentation_logits(pts, one_hot)[0]
        return FrustumLogits(logits=logits, sample_index=idx, rot_angle=rot, points=pts[0])

    def frustum_box(self, points_rect: torch.Tensor, calib: Calibration, image_size: tuple[int, int],
                    box2d: np.ndarray, *, frame_id: str, proposal: int, class_id: int = 0,
                    extra_points: np.ndarray | None = None) -> FrustumBox | None:
        """The box ``detect`` regresses for the frustum of ``box2d`` (and ``extra_points``, as in
        :meth:`frustum_logits`; same resampling and object-point
        gather), differentiable w.r.t. ``points_rect``: the whole network in eval mode in its own dtype,
        the argmax heading bin and size template held fixed, the mask straight-through
        (:data:`BOX_ORACLE_TEMPERATURE`; its forward values are the hard mask), decoded as
        :func:`~robustbench3d.victims.fpointnet.to_kitti.decode` and rotated back to the rect frame."""
        got = self._frustum(points_rect, calib, image_size, box2d, frame_id, proposal, class_id, extra_points)
        if got is None:
            return None
        pts, one_hot, _, rot, rng = got
        dtype = next(self.fpn.parameters()).dtype
        out = self.fpn(pts.to(dtype), one_hot.to(dtype), gather=self.settings.gather, rng=[rng],
                       straight_through=BOX_ORACLE_TEMPERATURE)
        h = int(out.heading_scores[0].argmax())
        s = int(out.size_scores[0].argmax())
        heading = h * HEADING_BIN_WIDTH + out.heading_residuals[0, h] + rot
        size = torch.as_tensor(MEAN_SIZES[s], dtype=dtype) + out.size_residuals[0, s]
        center = rotate_to_frustum_torch(out.center[0], -rot)
        return FrustumBox(center=center, size_lwh=size, heading=heading, logits=out.seg_logits[0],
                          mask_count=int(out.mask_count[0]))

    # ---- TargetScoreOracle -------------------------------------------------------------
    def target_scores(self, scene: AttackedScene, targets: AttackTargets, *,
                      with_box: bool = False) -> TargetScores:
        """Per target: the largest object-minus-background margin (float64) of the frustum of its proposal
        (``targets.proposal`` into ``scene.proposals``) from :meth:`frustum_logits`, or with ``with_box`` the
        margin and the box of :meth:`frustum_box`; absent without a proposal or a frustum point
        (:func:`~robustbench3d.victims.base.frustum_target_scores`). The camera term of an attack stays the
        2D stage's :meth:`objectness`."""
        return frustum_target_scores(self, scene, targets, with_box=with_box)

    def segmentation_logits(self, points: torch.Tensor, one_hot: torch.Tensor) -> torch.Tensor:
        """(B, N, 2) logits of (B, N, 4) frustum-frame points (eval-mode network)."""
        seg = self.fpn.seg
        if points.dtype != next(seg.parameters()).dtype:
            points = points.to(next(seg.parameters()).dtype)
        return seg(points, one_hot)


__all__ = ["CascadeSettings", "FPointNetCascade", "frame_key", "frustum_rng"]
