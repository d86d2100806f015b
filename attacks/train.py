"""Universal optimisation of one roof object against a white-box victim (reference §3.7).

One object for every target car of a training split: vertex displacements through the tanh box
parametrisation (:func:`~robustbench3d.attacks.object.tanh_vertices`) and per-vertex colours as
``sigmoid(logits)``, both float64, optimised with Adam (one parameter group each; :class:`Adam`, torch.optim.Adam
written out, the same bits without importing ``torch._dynamo``). Settings and modes:
:mod:`~robustbench3d.attacks.train_config`; the loop, checkpoints and output:
:mod:`~robustbench3d.attacks.train_run`; the held-out curve (frames cut off before the trainer is built,
evaluated with :meth:`UniversalTrainer.heldout_losses` and the victim's ``detect``):
:mod:`~robustbench3d.attacks.train_curve`. Modes:

* ``adv-shape``: LiDAR loss + Laplacian; shape optimised, colour fixed at the neutral grey;
* ``adv-texture``: image loss; colours optimised on the undeformed sphere;
* ``adv-object``: LiDAR loss + ``lambda_img`` x image loss + Laplacian; both optimised.

The object is of the config's family (:attr:`~robustbench3d.attacks.train_config.TrainConfig.family`: icosphere
level and radius, default the level-2 sphere of radius 0.40 m): V = 162, 642 or 2562 vertices, each displaced
and coloured, inside the family's box +-radius.

A step takes ``batch_cars`` cars: the split's cars (every target car of every frame, frame order, then
label order) are visited in a random permutation per epoch, ``numpy.random.default_rng([seed, epoch,
0xBA7C])``. Each car's frame is attacked as a benchmark cell does (:mod:`~robustbench3d.attacks.roof`):
the object on every target car of the frame (EOT jitter, one draw per car in label order, then the
LiDAR dropout and range noise, all from ``default_rng([seed, step, 0xE07])``), rendered into the scan
(:func:`~robustbench3d.sensors.lidar_render.render_lidar`, whose added points carry gradients) and the
image (:func:`~robustbench3d.sensors.camera_render.render_camera_torch`, occlusion as
:meth:`RoofObjectAttack.scene_depth`); the losses (:mod:`~robustbench3d.attacks.losses`) are taken on
the batch's cars only:

* LiDAR: the car's frustum from its **ground-truth 2D box** (``lidar_boxes="gt"``, the default; the
  proposal index the victim's ``detect`` gives it, so the frustum resampling is the scored one), or from
  the victim's own 2D detection on the attacked image that overlaps the car's box most (image IoU >= 0.5;
  ``lidar_boxes="detector"``, reference §1.12; a car the 2D detector misses gets no LiDAR term).
  With ``lidar_loss="box"`` the term is ``lambda_box`` x the BEV IoU of the box the victim regresses from
  that frustum with the car's ground truth (``"seed+box"``: both terms). ``IoU_k`` (detached) is that
  IoU when a box term is on (the box ``detect`` reports for the car's proposal, from the same forward
  pass; ``detect``'s proposal filters, e.g. its minimum 2D height, do not apply); with ``"seed"`` alone
  the BEV IoU of the victim's best detection of the car on the attacked frame from the same proposals
  (one ``detect`` of the whole frame). A car without a frustum has 0;
* image: the objectness candidates around the car's ground-truth 2D box.

Every LiDAR term, and the image term of a victim without a 2D objectness oracle, goes through the one
differentiable victim interface, :meth:`~robustbench3d.victims.base.TargetScoreOracle.target_scores`: per frame
one :class:`~robustbench3d.victims.base.AttackedScene` (the attacked frame with ``labels=None``, its rect-frame
points with the object's returns differentiable, the proposals above) and the
:class:`~robustbench3d.victims.base.AttackTargets` of the chosen cars (GT 2D and 3D boxes, each car's proposal
index, -1 for none); per present car the seed term ``max(IoU_k, floor) softplus(logit)`` and the box term
(:func:`~robustbench3d.attacks.losses.lidar_target_terms`). For the F-PN cascades the logit is the frustum's
largest object margin, so the terms are those above, bit for bit (a victim with the frustum oracles alone is
scored through :func:`~robustbench3d.victims.base.frustum_target_scores`). The image term of a victim with
:class:`~robustbench3d.victims.base.ImageObjectnessOracle` stays the objectness loss.

Any victim (one without frustum oracles, e.g. a whole-scene LiDAR detector supporting only the ``detector``
mode): ``scene.proposals`` is None and every proposal index -1 (the victim finds the cars itself); ``IoU_k`` and
the detection checks are the BEV IoU of the car with the victim's own ``detect(frames, "detector")`` on the
attacked frame (clean: on the clean frame); the image term (no objectness oracle) is ``softplus(logit)`` per car
from a scene whose ``image`` is the differentiable attacked image (points without gradient), the LiDAR term comes
from one whose points carry gradients (``image`` None). The frame's image and scan are the clean ones where the
mode renders no image or no LiDAR. Refusals before any work: :func:`~robustbench3d.attacks.train_config.
check_oracles` (no gradients, a mode whose sensor the victim does not use, ``lidar_boxes`` other than ``gt``).

The loss of a step is the mean over its cars of each term (plus the Laplacian). Randomness comes only
from (seed, epoch) and (seed, step), and the state saved every ``checkpoint_every`` steps (parameters,
Adam state, history; written atomically) is all a resumed run needs, so a resumed run ends with the
same object bytes as an uninterrupted one. A non-finite loss or gradient stops the run at once; an
attack loss that gives the object no gradient for ``zero_grad_patience`` consecutive steps stops it too.

The progress line shows the step's losses and a running estimate of the drop: 1 - (share of the last
:data:`DROP_WINDOW` steps' cars detected on the attacked frames) / (share of a reference sample detected
clean); the sample is the first :data:`CLEAN_SAMPLE` cars of the epoch-0 permutation, i.e. the first
steps' cars, so the clean detections cost one extra victim call per frame of those steps only. A car
counts as detected by the LiDAR branch if its ``IoU_k`` is >= 0.7 (clean: the best BEV IoU of ``detect``'s
rows), by the image branch if a candidate with IoU >= 0.5 scores objectness x class >= 0.5 (adv-object: both).
"""
from __future__ import annotations

import io
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from robustbench3d.attacks.base import target_cars
from robustbench3d.attacks.losses import (
    best_candidate_scores,
    gt_bev_boxes,
    image_logit_losses,
    image_target_losses,
    laplacian_loss,
    lidar_target_terms,
)
from robustbench3d.attacks.object import (
    NEUTRAL_GREY,
    RoofObject,
    benign_sphere,
    tanh_vertices,
    template_faces,
    template_vertices,
)
from robustbench3d.attacks.placement import (
    POSITION_JITTER_M,
    YAW_JITTER_RAD,
    cars_of,
    place_on_roof,
    rect_to_velo,
    sample_jitter,
)
from robustbench3d.attacks.record import target_rows
from robustbench3d.attacks.train_config import (
    BATCH_STREAM,
    BEV_IOU_DETECTED,
    CANDIDATE_IOU,
    CHECKPOINT_FORMAT,
    CLEAN_SAMPLE,
    DROP_WINDOW,
    EOT_DROPOUT,
    EOT_RANGE_NOISE_M,
    EOT_STREAM,
    HELDOUT_STREAM,
    LEGACY_IDENTITY,
    OBJECT_LIDAR_BOXES,
    SCORE_DETECTED,
    TrainConfig,
    TrainingError,
    training_cars,
)
from robustbench3d.kitti.dataset import Frame, KittiDataset
from robustbench3d.kitti.labels import Labels


def _velo_to_rect_torch(points: torch.Tensor, m: np.ndarray) -> torch.Tensor:
    t = torch.from_numpy(np.array(m, dtype=np.float64))
    return points @ t[:3, :3].T + t[:3, 3]


def _proposal_index(boxes: np.ndarray, targets: Labels, target_boxes: np.ndarray | None = None) -> list[int | None]:
    """Index into ``boxes`` of each target's 2D box (``target_boxes``, default the labels' boxes; equal rows, in
    order of occurrence), None if absent."""
    used: set[int] = set()
    out: list[int | None] = []
    for box in targets.bbox if target_boxes is None else target_boxes:
        hits = [j for j in np.flatnonzero(np.all(boxes == box, axis=1)).tolist() if j not in used]
        out.append(hits[0] if hits else None)
        if hits:
            used.add(hits[0])
    return out


def _object_proposals(frame: Frame, attacked: Frame, targets: Labels, rows: np.ndarray, poses: list[Any], res: Any,
                      source: str, bounds: Any = None) -> Any:
    """The ``gt-object`` / ``gt-append`` proposals of an attacked training frame, as the runner builds them for
    a cell: the :class:`~robustbench3d.attacks.record.ObjectRecord` of the placed bounds boxes (``bounds``: the
    object's half extents, m, default the default family's; each car's union partner) and of the render's returns
    (``res``, a ``LidarRenderResult``: each car's appended rows)."""
    from robustbench3d.attacks.object import BOUNDS
    from robustbench3d.attacks.record import ObjectRecord, added_rows, placed_object_boxes
    from robustbench3d.victims.base import object_proposals

    box = BOUNDS if bounds is None else bounds
    record = ObjectRecord(placed_object_boxes(box, poses, attacked.calib, attacked.image_size),
                          added_rows(len(frame.scan), len(res.removed_index), res.object_index, len(targets)), rows)
    return object_proposals(attacked, frame.labels, record, source)


def _matched_index(boxes: np.ndarray, targets: Labels, min_iou: float = 0.5) -> list[int | None]:
    """Per target the index of the box of ``boxes`` with the largest image IoU with its 2D box, None if
    that IoU is below ``min_iou`` (the 2D detector missed the car)."""
    from robustbench3d.eval.iou import image_iou

    if len(boxes) == 0:
        return [None] * len(targets)
    iou = image_iou(targets.bbox, boxes)
    best = iou.argmax(axis=1)
    return [int(j) if iou[t, j] >= min_iou else None for t, j in enumerate(best)]


def _bev_iou_per_target(det: Labels, targets: Labels) -> np.ndarray:
    """(T,) best BEV IoU of each target with any detection (0 without detections)."""
    from robustbench3d.eval.iou import bev_iou

    if len(det) == 0 or len(targets) == 0:
        return np.zeros(len(targets))

    def boxes(lab: Labels) -> np.ndarray:
        return np.column_stack([lab.dimensions, lab.location, lab.rotation_y])

    return bev_iou(boxes(targets), boxes(det)).max(axis=1)


def _attack_targets(targets: Labels, chosen: list[int], index: list[int | None]) -> Any:
    """The :class:`~robustbench3d.victims.base.AttackTargets` of the ``chosen`` rows of ``targets``: their GT 2D
    boxes, their 3D boxes (location, dimensions h/w/l, rotation_y) and each one's proposal index (None: -1)."""
    from robustbench3d.victims.base import AttackTargets

    boxes3d = np.column_stack([targets.location, targets.dimensions, targets.rotation_y])
    return AttackTargets(targets.bbox[chosen], boxes3d[chosen], [-1 if j is None else j for j in index])


#: torch.optim.Adam's defaults, in the order its param groups hold them (after ``params`` and ``lr``).
_ADAM_DEFAULTS: dict[str, Any] = {"betas": (0.9, 0.999), "eps": 1e-8, "weight_decay": 0, "amsgrad": False,
                                  "maximize": False, "foreach": None, "capturable": False, "differentiable": False,
                                  "fused": None, "decoupled_weight_decay": False}


def _adam_step_count(value: float) -> torch.Tensor:
    """Adam's step counter as torch keeps it: a CPU scalar tensor, float64 only under a float64 default dtype
    (torch.optim.optimizer._get_scalar_dtype)."""
    return torch.tensor(value, dtype=torch.float64 if torch.get_default_dtype() == torch.float64 else torch.float32)


class Adam:
    """``torch.optim.Adam(groups)`` with its defaults, written out: the same update bits, state and
    ``state_dict()`` (so checkpoints of either load into the other).

    torch's optimisers import ``torch._dynamo`` on their first call (``torch._disable_dynamo``), about a
    second of CPU at start-up (several on a loaded machine); this class does not. It performs, per parameter
    of each group in order, the operations of torch's single-tensor CPU path (``torch.optim.adam.
    _single_tensor_adam`` without weight decay, amsgrad, maximize): ``step += 1`` (a float32 tensor),
    ``m.lerp_(g, 1 - b1)``, ``v.mul_(b2).addcmul_(g, g, value=1 - b2)``, then ``p.addcdiv_(m, (v.sqrt() /
    sqrt(1 - b2**t)).add_(eps), value=-lr / (1 - b1**t))`` with the scalars in Python floats.
    tests/attacks/test_attack_train_warm.py compares it with torch.optim.Adam bit for bit over several steps.
    """

    def __init__(self, groups: list[dict[str, Any]]) -> None:
        self.param_groups = [{"params": list(g["params"]), "lr": g["lr"], **_ADAM_DEFAULTS} for g in groups]
        self.state: dict[int, dict[str, torch.Tensor]] = {}  # by parameter index, in order of first update

    def _params(self) -> list[torch.Tensor]:
        return [p for g in self.param_groups for p in g["params"]]

    @torch.no_grad()
    def step(self, grads: list[torch.Tensor]) -> None:
        """One update with gradient ``grads[i]`` for the i-th parameter (groups in order)."""
        i = 0
        for group in self.param_groups:
            beta1, beta2 = group["betas"]
            lr, eps = group["lr"], group["eps"]
            for param in group["params"]:
                grad = grads[i]
                if i not in self.state:
                    self.state[i] = {"step": _adam_step_count(0.0),
                                     "exp_avg": torch.zeros_like(param, memory_format=torch.preserve_format),
                                     "exp_avg_sq": torch.zeros_like(param, memory_format=torch.preserve_format)}
                state = self.state[i]
                exp_avg, exp_avg_sq = state["exp_avg"], state["exp_avg_sq"]
                state["step"] += 1
                exp_avg.lerp_(grad, 1 - beta1)
                exp_avg_sq.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
                step = state["step"].item()
                bias_correction1 = 1 - beta1**step
                bias_correction2_sqrt = (1 - beta2**step) ** 0.5
                denom = (exp_avg_sq.sqrt() / bias_correction2_sqrt).add_(eps)
                param.addcdiv_(exp_avg, denom, value=-(lr / bias_correction1))
                i += 1

    def state_dict(self) -> dict[str, Any]:
        """torch.optim.Adam's ``state_dict()`` layout: ``state`` by parameter index, ``param_groups`` with
        their hyperparameters and parameter indices."""
        groups, start = [], 0
        for g in self.param_groups:
            n = len(g["params"])
            groups.append({**{k: v for k, v in g.items() if k != "params"}, "params": list(range(start, start + n))})
            start += n
        return {"state": dict(self.state), "param_groups": groups}

    def load_state_dict(self, saved: dict[str, Any]) -> None:
        """Take the state and hyperparameters of a :meth:`state_dict` (this class's or torch.optim.Adam's);
        ValueError if its groups do not match or it uses a setting this class does not implement."""
        groups = saved["param_groups"]
        if len(groups) != len(self.param_groups) or any(
                len(a["params"]) != len(b["params"]) for a, b in zip(groups, self.param_groups, strict=True)):
            raise ValueError("the optimiser state has other parameter groups")
        for g in groups:
            other = {k: g.get(k, v) for k, v in _ADAM_DEFAULTS.items() if k not in ("betas", "eps")}
            if other != {k: v for k, v in _ADAM_DEFAULTS.items() if k not in ("betas", "eps")}:
                raise ValueError(f"the optimiser state uses Adam settings this trainer does not implement: {other}")
        params = self._params()
        index = {k: i for i, k in enumerate(k for g in groups for k in g["params"])}
        state: dict[int, dict[str, torch.Tensor]] = {}
        for key, value in saved["state"].items():
            p = params[index[key]]
            step = value["step"]  # torch before 1.12 saved a number
            if not torch.is_tensor(step):
                step = _adam_step_count(float(step))
            state[index[key]] = {"step": step,
                                 "exp_avg": value["exp_avg"].to(dtype=p.dtype, device=p.device),
                                 "exp_avg_sq": value["exp_avg_sq"].to(dtype=p.dtype, device=p.device)}
        self.param_groups = [{**{k: v for k, v in g.items() if k != "params"}, "params": mine["params"]}
                             for g, mine in zip(groups, self.param_groups, strict=True)]
        self.state = state


@dataclass
class _FrameTerms:
    """One frame's part of a step: its weighted loss (a tensor, differentiable in the parameters), the
    unweighted sums of its terms (``lidar``, ``image``; absent when the frame has none), which chosen cars are
    still detected and which reference cars are detected clean."""

    loss: torch.Tensor
    sums: dict[str, float]
    ok: np.ndarray
    clean_ok: np.ndarray


@dataclass
class StepResult:
    """Losses (weighted terms and total), detections of a step's cars and the gradient it produced."""

    losses: dict[str, float]
    cars: int
    detected: int
    clean_cars: int
    detected_clean: int
    grads: list[torch.Tensor] = field(repr=False)
    attack_grad_zero: bool = False


class UniversalTrainer:
    """The optimisation state and one step of it (module doc)."""

    def __init__(self, victim: Any, kitti: KittiDataset, frame_ids: list[str], labels: list[Labels],
                 config: TrainConfig) -> None:
        from robustbench3d.attacks.roof import RoofObjectAttack
        from robustbench3d.victims.base import ImageObjectnessOracle, has_frustum_oracles

        self.victim, self.kitti, self.frame_ids, self.labels, self.config = victim, kitti, frame_ids, labels, config
        #: Whether the LiDAR term goes through per-proposal frustums (the F-PN cascades), and the image term
        #: through a 2D detector's objectness (else both through ``target_scores`` alone; module doc).
        self.frustums = has_frustum_oracles(victim)
        self._objectness = isinstance(victim, ImageObjectnessOracle)
        self.cars = training_cars(labels)
        if not self.cars:
            raise TrainingError(f"the training data ({len(frame_ids)} frame(s) of split {kitti.split!r} under "
                                f"{kitti.root}) has no target cars (label type Car): nothing to attack")
        m = config.kind
        self.family = config.family
        n = self.family.n_vertices
        self.delta = torch.zeros(n, 3, dtype=torch.float64, requires_grad=m.shape)
        grey = math.log(NEUTRAL_GREY / (1.0 - NEUTRAL_GREY))
        self.colour_logit = torch.full((n, 3), grey, dtype=torch.float64, requires_grad=m.colour)
        groups = ([{"params": [self.delta], "lr": config.lr_shape}] if m.shape else []) + \
                 ([{"params": [self.colour_logit], "lr": config.lr_color}] if m.colour else [])
        self.params = [g["params"][0] for g in groups]
        self.optimizer = Adam(groups)
        self.step = 0
        self.history: list[dict[str, float]] = []
        self.zero_run = 0
        self.elapsed_s = 0.0
        self._faces = template_faces(self.family).copy()
        self._depth = RoofObjectAttack(benign_sphere(self.family), occlusion=config.occlusion,
                                       supersample=config.supersample)
        self._depth.bind_dataset(kitti)
        self._clean: dict[str, np.ndarray] = {}
        first = np.random.default_rng([config.seed, 0, BATCH_STREAM]).permutation(len(self.cars))[:CLEAN_SAMPLE]
        self._reference = {self.cars[int(i)] for i in first}
        self.ckpt: Path | None = None  # where checkpoints go (set by train_universal)
        self._saved_step = 0
        #: The run loop's own state, saved with the checkpoint (train_run: the held-out curve, the best state).
        self.run_state: dict[str, Any] = {}

    # ---- the object ---------------------------------------------------------------------------
    def vertices(self) -> torch.Tensor:
        """(V, 3) float64 object-frame vertices: the template when the shape is fixed, else the tanh
        parametrisation (differentiable in ``delta``; at ``delta = 0`` the template scaled by 0.999, the
        parametrisation's eps, as template vertices lie on the box faces)."""
        return self._vertices_at(self.delta)

    def _vertices_at(self, delta: torch.Tensor) -> torch.Tensor:
        """:meth:`vertices` at displacement parameters ``delta``."""
        if not self.config.kind.shape:
            return torch.from_numpy(template_vertices(self.family).copy())
        return tanh_vertices(delta, family=self.family)

    def colours(self) -> torch.Tensor:
        """(V, 3) float64 colours in (0, 1)."""
        return torch.sigmoid(self.colour_logit)

    def current_object(self) -> RoofObject:
        """The object at the current parameters, at file precision."""
        return self.object_at(self.delta, self.colour_logit)

    def object_at(self, delta: torch.Tensor, colour_logit: torch.Tensor) -> RoofObject:
        """The object at parameters ``delta`` and ``colour_logit`` (e.g. a kept best state), at file precision."""
        with torch.no_grad():
            return RoofObject.from_vertices(self._vertices_at(delta).numpy(), torch.sigmoid(colour_logit).numpy(),
                                            family=self.family)

    # ---- randomness ---------------------------------------------------------------------------
    def batch(self, step: int) -> list[tuple[int, int]]:
        """The cars of ``step``: positions ``step * B ...`` of the concatenated epoch permutations."""
        n, b = len(self.cars), self.config.batch_cars
        out, perms = [], {}
        for q in range(step * b, (step + 1) * b):
            epoch = q // n
            if epoch not in perms:
                perms[epoch] = np.random.default_rng([self.config.seed, epoch, BATCH_STREAM]).permutation(n)
            out.append(self.cars[int(perms[epoch][q % n])])
        return out

    def step_frames(self, start: int, stop: int) -> list[str]:
        """The frames whose cars steps ``start`` .. ``stop - 1`` draw (:meth:`batch`), in order of first use."""
        n, b = len(self.cars), self.config.batch_cars
        frame_of = np.array([fi for fi, _ in self.cars])
        wanted = len(set(frame_of.tolist()))
        seen: dict[int, None] = {}
        q = start * b
        while q < stop * b and len(seen) < wanted:  # every frame is drawn once an epoch
            epoch, at = divmod(q, n)
            upto = min(n, at + stop * b - q)
            perm = np.random.default_rng([self.config.seed, epoch, BATCH_STREAM]).permutation(n)
            seen.update(dict.fromkeys(frame_of[perm[at:upto]].tolist()))
            q += upto - at
        return [self.frame_ids[fi] for fi in seen]

    def depth_jobs(self, frame_ids: list[str]) -> list[Any]:
        """The exact-occlusion cache files (:class:`~robustbench3d.attacks.depth_cache.DepthJob`) the steps
        and the held-out losses read for ``frame_ids``: none unless the mode renders the camera image
        (an image term, or the LiDAR term on the detector's boxes) under exact occlusion."""
        from robustbench3d.attacks.depth_cache import attack_depth_jobs

        if not (self.config.kind.image or self.config.lidar_boxes == "detector"):
            return []
        return attack_depth_jobs(self._depth, self.kitti, frame_ids)

    def eot_rng(self, step: int) -> np.random.Generator:
        return np.random.default_rng([self.config.seed, step, EOT_STREAM])

    # ---- one step -----------------------------------------------------------------------------
    def compute_step(self, step: int) -> StepResult:
        """Losses and gradients of ``step`` at the current parameters (nothing is updated). Each frame's
        terms are differentiated as soon as they are computed (the loss is a sum over frames), so memory
        holds one frame's graph at a time."""
        cfg, m = self.config, self.config.kind
        rng = self.eot_rng(step)
        by_frame: dict[int, list[int]] = {}
        for fi, k in self.batch(step):
            by_frame.setdefault(fi, []).append(k)
        n = sum(len(c) for c in by_frame.values())
        weights = cfg.weights()
        sums = {"lidar": 0.0, "image": 0.0}
        g_attack = [torch.zeros_like(p) for p in self.params]
        detected = clean_cars = detected_clean = 0
        for fi, chosen in by_frame.items():
            ref = [t for t in chosen if (fi, t) in self._reference]  # cars of the clean reference sample
            terms = self._frame_terms(f"step {step}", self.frame_ids[fi], chosen, rng, n, ref)
            for key, value in terms.sums.items():
                sums[key] += value
            for acc, g in zip(g_attack, _grads(terms.loss, self.params), strict=True):
                acc += g
            detected += int(terms.ok.sum())
            clean_cars += len(ref)
            detected_clean += int(terms.clean_ok.sum())
        losses = {k: sums[k] / n for k, used in (("lidar", m.lidar), ("image", m.image)) if used}
        total = sum(weights[k] * v for k, v in losses.items())
        g_lap = [torch.zeros_like(p) for p in self.params]
        if m.shape:
            verts = self.vertices()
            lap = laplacian_loss(verts, 1.0)
            losses["laplacian"] = lap.item()
            total += weights["laplacian"] * lap.item()
            g_lap = _grads(weights["laplacian"] * lap, self.params)
        losses["total"] = total
        for p, ga, gl in zip(self.params, g_attack, g_lap, strict=True):
            if not (torch.isfinite(ga).all() and torch.isfinite(gl).all()):
                name = "shape" if p is self.delta else "colour"
                raise TrainingError(f"step {step}: the {name} gradient has NaN or inf values "
                                    f"({format_losses(losses)}); stopping ({self._resume_hint()})")
        zero_grad = all(not bool(g.any()) for g in g_attack)
        grads = [ga + gl for ga, gl in zip(g_attack, g_lap, strict=True)]
        return StepResult(losses, n, detected, clean_cars, detected_clean, grads, zero_grad)

    def _frame_terms(self, when: str, frame_id: str, chosen: list[int], rng: np.random.Generator, n: int,
                     ref: list[int]) -> _FrameTerms:
        """The attack terms of the ``chosen`` targets of frame ``frame_id`` (the object on every target car,
        EOT draws from ``rng``), weighted and divided by ``n`` (the cars of the whole batch) into one loss
        tensor; which chosen cars are still detected, and which ``ref`` cars (a subset) are detected clean.
        ``when`` names the step in error messages."""
        cfg, m = self.config, self.config.kind
        weights = cfg.weights()
        if self.frustums:
            frame = self._frame(frame_id, with_image=m.image or cfg.lidar_boxes == "detector", with_scan=m.lidar)
        else:  # a victim that finds its own objects sees the clean image and scan where the mode renders neither
            frame = self._frame(frame_id, with_image=True)
        targets = target_cars(frame.labels)
        verts, colours = self.vertices(), self.colours()  # a fresh graph per frame
        placed, poses = [], []
        for car in cars_of(targets):
            jitter = sample_jitter(rng, POSITION_JITTER_M, YAW_JITTER_RAD) if "jitter" in cfg.eot else None
            vertices, pose = place_on_roof(verts, car, jitter)
            placed.append(vertices)
            poses.append(pose)
        ok = np.ones(len(chosen), dtype=bool)
        clean_ok = np.ones(len(ref), dtype=bool)
        sums: dict[str, float] = {}
        frame_loss = torch.zeros((), dtype=torch.float64)
        attacked_image: np.ndarray | None = None
        if m.image and self._objectness:
            terms_t, score, attacked_image = self._image(frame, targets, chosen, placed, colours, as_uint8=m.lidar)
            image = terms_t.sum()
            sums["image"] = image.item()
            frame_loss = frame_loss + weights["image"] / n * image
            ok &= score >= SCORE_DETECTED
            if ref:
                clean_ok &= self._clean_value(frame, targets, "image")[ref] >= SCORE_DETECTED
        if not self.frustums:
            try:
                generic, iou = self._generic(frame, targets, chosen, placed, colours, rng, attacked_image,
                                             m.image and not self._objectness)
            except ValueError as exc:  # the loss refuses non-finite logits (a diverged victim)
                raise TrainingError(f"{when}: the loss of frame {frame.frame_id} is not finite ({exc}); "
                                    f"stopping ({self._resume_hint()})") from exc
            for key, term in generic.items():
                sums[key] = term.item()
                frame_loss = frame_loss + weights[key] / n * term
            ok &= iou >= BEV_IOU_DETECTED
            if ref:
                clean_ok &= self._clean_value(frame, targets, "lidar")[ref] >= BEV_IOU_DETECTED
        elif m.lidar:
            if cfg.lidar_boxes == "detector" and attacked_image is None:
                attacked_image = self._render_image(frame, targets, placed, colours)
            try:
                terms, iou = self._lidar(frame, targets, chosen, placed, poses, colours, rng, attacked_image)
            except ValueError as exc:  # the loss refuses non-finite logits (a diverged victim)
                raise TrainingError(f"{when}: the loss of frame {frame.frame_id} is not finite ({exc}); "
                                    f"stopping ({self._resume_hint()})") from exc
            if terms:
                lidar = torch.stack(terms).sum()
                sums["lidar"] = lidar.item()
                frame_loss = frame_loss + weights["lidar"] / n * lidar
            ok &= iou >= BEV_IOU_DETECTED
            if ref:
                clean_ok &= self._clean_value(frame, targets, "lidar")[ref] >= BEV_IOU_DETECTED
        if not math.isfinite(frame_loss.item()):
            raise TrainingError(f"{when}: the loss of frame {frame.frame_id} is not finite (NaN or inf); "
                                f"stopping ({self._resume_hint()})")
        return _FrameTerms(frame_loss, sums, ok, clean_ok)

    def heldout_losses(self, frame_ids: list[str], when: str) -> dict[str, float]:
        """The training loss of the current object on every target car of ``frame_ids`` (frames the sampler
        never draws, :mod:`~robustbench3d.attacks.train_curve`), without gradients: per term the mean over
        the cars, the Laplacian and the weighted total as in a step. EOT draws come from one generator per
        frame, ``default_rng([seed, i, HELDOUT_STREAM])`` for the i-th frame, so the value is a function of
        the object alone. ``when`` names the evaluation in error messages."""
        m, weights = self.config.kind, self.config.weights()
        sums = {"lidar": 0.0, "image": 0.0}
        cars = 0
        with torch.no_grad():
            for i, fid in enumerate(frame_ids):
                chosen = list(range(len(target_cars(self.kitti.labels(fid)))))
                if not chosen:
                    continue
                rng = np.random.default_rng([self.config.seed, i, HELDOUT_STREAM])
                terms = self._frame_terms(when, fid, chosen, rng, 1, [])
                for key, value in terms.sums.items():
                    sums[key] += value
                cars += len(chosen)
            losses = {k: sums[k] / max(cars, 1) for k, used in (("lidar", m.lidar), ("image", m.image)) if used}
            total = sum(weights[k] * v for k, v in losses.items())
            if m.shape:
                losses["laplacian"] = laplacian_loss(self.vertices(), 1.0).item()
                total += weights["laplacian"] * losses["laplacian"]
        losses["total"] = total
        return losses

    def _frame(self, frame_id: str, with_image: bool, with_scan: bool = True) -> Frame:
        """The frame; without ``with_image`` its image is a black placeholder of the right size (the LiDAR
        branch uses only its size), which saves decoding the PNG; without ``with_scan`` (no LiDAR term) its
        scan is empty, which saves reading it."""
        if with_image and not with_scan:
            return Frame(frame_id, self.kitti.image(frame_id), np.zeros((0, 4), np.float32),
                         self.kitti.calib(frame_id), self.kitti.labels(frame_id))
        if with_image:
            return self.kitti.frame(frame_id)
        from PIL import Image

        with Image.open(self.kitti.path("image", frame_id)) as im:  # reads the header only
            width, height = im.size
        return Frame(frame_id, np.zeros((height, width, 3), dtype=np.uint8), self.kitti.scan(frame_id),
                     self.kitti.calib(frame_id), self.kitti.labels(frame_id))

    def _lidar(self, frame: Frame, targets: Labels, chosen: list[int], placed: list[torch.Tensor],
               poses: list[Any], colours: torch.Tensor, rng: np.random.Generator,
               attacked_image: np.ndarray | None) -> tuple[list[torch.Tensor], np.ndarray]:
        """LiDAR loss terms of the chosen targets and their attacked BEV IoUs (``attacked_image``: the
        attacked camera image, needed for ``lidar_boxes="detector"``; ``poses``: each target's placement, for the
        frustum protocols ``gt-object`` / ``gt-append``, whose proposals are built as the runner builds them)."""
        from robustbench3d.victims.base import AttackedScene, gt_proposals

        cfg = self.config
        res, points = self._render_scan(frame, placed, colours, rng)
        attacked = replace(frame, scan=np.ascontiguousarray(res.scan, dtype=np.float32), labels=None,
                           image=frame.image if attacked_image is None else attacked_image)
        with torch.no_grad():
            if cfg.lidar_boxes == "detector":
                props = self.victim.proposals([attacked], "detector")[0]
                index = _matched_index(props.boxes, targets)
                scored = props
            elif cfg.lidar_boxes in OBJECT_LIDAR_BOXES:
                rows = target_rows(frame.labels, targets)
                scored = _object_proposals(frame, attacked, targets, rows, poses, res, cfg.lidar_boxes,
                                           self.family.bounds)
                enumerate_ = getattr(self.victim, "proposals", None)
                props = enumerate_([attacked], [scored])[0] if callable(enumerate_) else scored.of_types(("Car",))
                index = _proposal_index(props.boxes, targets, scored.boxes[rows])
            else:
                props = self._proposals(frame)
                index = _proposal_index(props.boxes, targets)
                scored = gt_proposals(frame.labels)
            if cfg.lidar_loss == "seed":  # the box terms regress each car's box themselves (module doc)
                iou = _bev_iou_per_target(self.victim.detect([attacked], [scored])[0], targets)[chosen]
            else:
                iou = np.zeros(len(chosen))
        scene = AttackedScene(attacked, points, None, props)
        scores = self._scores(scene, _attack_targets(targets, chosen, [index[t] for t in chosen]),
                              with_box=cfg.lidar_loss != "seed")
        terms = lidar_target_terms(scores, iou, gt_bev_boxes(targets)[chosen], lidar_loss=cfg.lidar_loss,
                                   lambda_box=cfg.lambda_box, floor=cfg.iou_floor)
        return terms, iou

    def _render_scan(self, frame: Frame, placed: list[torch.Tensor], colours: torch.Tensor,
                     rng: np.random.Generator) -> tuple[Any, torch.Tensor]:
        """The attacked scan (a ``LidarRenderResult``: the object on every placed car, EOT noise from ``rng``) and
        its (N, 4) float64 rect-frame points, row-aligned with ``res.scan``, the object's returns differentiable
        in the placed vertices."""
        from robustbench3d.sensors.lidar_render import render_lidar

        cfg, calib = self.config, frame.calib
        albedo = colours.detach().numpy()
        res = render_lidar(frame.scan, [(rect_to_velo(p, calib), self._faces, albedo) for p in placed], rng=rng,
                           range_noise_m=EOT_RANGE_NOISE_M if "range-noise" in cfg.eot else 0.0,
                           dropout=EOT_DROPOUT if "dropout" in cfg.eot else 0.0)
        k = len(res.added)
        kept = res.scan[:len(res.scan) - k, :3].astype(np.float64)
        xyz = torch.cat([torch.from_numpy(calib.velo_to_rect_points(kept)),
                         _velo_to_rect_torch(res.added_torch, calib.velo_to_rect)])
        return res, torch.cat([xyz, torch.from_numpy(res.scan[:, 3:4].astype(np.float64))], dim=1)

    def _scores(self, scene: Any, targets: Any, *, with_box: bool = False) -> Any:
        """The victim's :class:`~robustbench3d.victims.base.TargetScores` of ``targets`` on ``scene``: its
        ``target_scores``, or for a victim with the frustum oracles alone
        :func:`~robustbench3d.victims.base.frustum_target_scores`; TrainingError for an answer of the wrong
        shape."""
        from robustbench3d.victims.base import TargetScoreOracle, frustum_target_scores

        if isinstance(self.victim, TargetScoreOracle):
            out = self.victim.target_scores(scene, targets, with_box=with_box)
        else:
            out = frustum_target_scores(self.victim, scene, targets, with_box=with_box)
        t = len(targets)
        if with_box and out.box is None:
            raise TrainingError(f"frame {scene.frame.frame_id}: the victim's target_scores gives no boxes (with_box), "
                                f"which --lidar-loss {self.config.lidar_loss} needs; train with --lidar-loss seed")
        shapes = (tuple(out.logit.shape), np.shape(out.present), None if out.box is None else tuple(out.box.shape))
        if shapes[:2] != ((t,), (t,)) or (with_box and shapes[2] != (t, 7)):
            raise TrainingError(f"frame {scene.frame.frame_id}: the victim's target_scores gave logit, present and box "
                                f"of shapes {shapes[0]}, {shapes[1]}, {shapes[2]} for {t} targets (expected ({t},), "
                                f"({t},){f' and ({t}, 7)' if with_box else ''})")
        return out

    def _generic(self, frame: Frame, targets: Labels, chosen: list[int], placed: list[torch.Tensor],
                 colours: torch.Tensor, rng: np.random.Generator, attacked_image: np.ndarray | None,
                 image_term: bool) -> tuple[dict[str, torch.Tensor], np.ndarray]:
        """The terms of the chosen targets for a victim without frustum oracles (module doc, "Any victim"): the
        LiDAR term when the mode has one, the image term (``softplus`` of the logits) with ``image_term``; and each
        chosen car's BEV IoU with the victim's own ``detect`` on the attacked frame. ``attacked_image``: the
        attacked uint8 image if one was rendered (else the clean image is the frame's)."""
        from robustbench3d.victims.base import AttackedScene

        cfg, m = self.config, self.config.kind
        image_t = None
        if image_term:
            image_t = self._rendered(frame, targets, placed, colours)
            attacked_image = np.clip(np.round(image_t.detach().numpy() * 255.0), 0, 255).astype(np.uint8)
        if m.lidar:
            res, points = self._render_scan(frame, placed, colours, rng)
            scan = np.ascontiguousarray(res.scan, dtype=np.float32)
        else:  # no LiDAR term: the clean scan, without gradient
            scan = frame.scan
            xyz = frame.calib.velo_to_rect_points(scan[:, :3].astype(np.float64))
            points = torch.from_numpy(np.concatenate([xyz, scan[:, 3:4].astype(np.float64)], axis=1))
        image = frame.image if attacked_image is None else attacked_image
        attacked = replace(frame, scan=scan, labels=None, image=image)
        aimed = _attack_targets(targets, chosen, [None] * len(chosen))
        with torch.no_grad():
            iou = _bev_iou_per_target(self.victim.detect([attacked], "detector")[0], targets)[chosen]
        out: dict[str, torch.Tensor] = {}
        if image_term:
            scores = self._scores(AttackedScene(attacked, points.detach(), image_t, None), aimed)
            out["image"] = image_logit_losses(scores).sum()
        if m.lidar:
            box = cfg.lidar_loss != "seed"
            scores = self._scores(AttackedScene(attacked, points, None, None), aimed, with_box=box)
            terms = lidar_target_terms(scores, iou.copy(), gt_bev_boxes(targets)[chosen], lidar_loss=cfg.lidar_loss,
                                       lambda_box=cfg.lambda_box, floor=cfg.iou_floor)
            if terms:
                out["lidar"] = torch.stack(terms).sum()
        return out, iou

    def _image(self, frame: Frame, targets: Labels, chosen: list[int], placed: list[torch.Tensor],
               colours: torch.Tensor, as_uint8: bool = True) -> tuple[torch.Tensor, np.ndarray, np.ndarray | None]:
        """(len(chosen),) image loss terms of the chosen targets, their best candidate scores and (``as_uint8``:
        the LiDAR term's victim is given the attacked frame; else None) the attacked image as uint8 (rounded as
        :func:`~robustbench3d.sensors.camera_render.render_camera` does)."""
        from robustbench3d.attacks.losses import IMAGE_LOSSES

        rendered = self._rendered(frame, targets, placed, colours)
        boxes = targets.bbox[chosen]
        # the loss's candidate set (IMAGE_LOSSES: "mean" averages the 0.3 set; "sum", like the scores, reads only IoU
        # >= 0.5, all of which 0.5 returns: the same terms, bit for bit, while a cropping victim reads less image)
        threshold = min(IMAGE_LOSSES[self.config.image_loss].candidate_iou, CANDIDATE_IOU)
        cands = self.victim.objectness(rendered.permute(2, 0, 1)[None].float(), [boxes], iou_threshold=threshold)
        terms = image_target_losses(cands, len(chosen), 0, self.config.use_class,
                                    self.config.image_loss).to(torch.float64)
        attacked = np.clip(np.round(rendered.detach().numpy() * 255.0), 0, 255).astype(np.uint8) if as_uint8 else None
        return terms, best_candidate_scores(cands, len(chosen), 0, CANDIDATE_IOU), attacked

    def _rendered(self, frame: Frame, targets: Labels, placed: list[torch.Tensor],
                  colours: torch.Tensor) -> torch.Tensor:
        """The attacked camera image, (H, W, 3) float64 in [0, 1], differentiable in the placed vertices and the
        colours (occlusion by the scene as :meth:`RoofObjectAttack.scene_depth`)."""
        from robustbench3d.sensors.camera_render import render_camera_torch

        image = torch.from_numpy(frame.image.astype(np.float64) / 255.0)
        return render_camera_torch(image, frame.calib, [(p, self._faces, colours) for p in placed],
                                   scene_depth=self._depth.scene_depth(frame, targets),
                                   supersample=self.config.supersample)

    def _render_image(self, frame: Frame, targets: Labels, placed: list[torch.Tensor],
                      colours: torch.Tensor) -> np.ndarray:
        """The attacked camera image (uint8, no gradient)."""
        from robustbench3d.sensors.camera_render import render_camera

        meshes = [(p.detach().numpy(), self._faces, colours.detach().numpy()) for p in placed]
        return render_camera(frame.image, frame.calib, meshes, scene_depth=self._depth.scene_depth(frame, targets),
                             supersample=self.config.supersample).image

    def _proposals(self, frame: Frame) -> Any:
        """The frame's ground-truth proposals as the victim's ``detect`` enumerates them."""
        from robustbench3d.victims.base import gt_proposals

        props = gt_proposals(frame.labels)
        enumerate_ = getattr(self.victim, "proposals", None)
        bare = replace(frame, labels=None)
        return enumerate_([bare], [props])[0] if callable(enumerate_) else props.of_types(("Car",))

    def _clean_proposals(self, frame: Frame, targets: Labels) -> Any:
        """The clean frame's GT-box proposals under ``lidar_boxes``: ``gt`` and ``gt-append`` (no object, no
        returns) the GT boxes, ``gt-object`` the union with the nominal object's box of the trained family (for
        the default family what the clean cell gets)."""
        from robustbench3d.victims.base import gt_proposals, object_proposals

        if self.config.lidar_boxes != "gt-object":
            return gt_proposals(frame.labels)
        from robustbench3d.attacks.record import nominal_record

        return object_proposals(frame, frame.labels, nominal_record(frame, targets, self.family), "gt-object")

    def _clean_value(self, frame: Frame, targets: Labels, branch: str) -> np.ndarray:
        """Per target of ``frame``: clean BEV IoU (``lidar``) or best candidate score (``image``), cached."""
        key = f"{branch}:{frame.frame_id}"
        if key not in self._clean:
            with torch.no_grad():
                if branch == "lidar":

                    source = ("detector" if self.config.lidar_boxes == "detector" or not self.frustums
                              else [self._clean_proposals(frame, targets)])
                    det = self.victim.detect([replace(frame, labels=None)], source)[0]
                    self._clean[key] = _bev_iou_per_target(det, targets)
                else:
                    image = torch.from_numpy(np.array(frame.image)).permute(2, 0, 1)[None].float() / 255.0
                    cands = self.victim.objectness(image, [targets.bbox])
                    self._clean[key] = best_candidate_scores(cands, len(targets), 0, CANDIDATE_IOU)
        return self._clean[key]

    def apply_step(self, result: StepResult) -> None:
        """Adam update with ``result``'s gradients; records the step."""
        self.optimizer.step(result.grads)
        self.zero_run = self.zero_run + 1 if result.attack_grad_zero else 0
        self.history.append({**result.losses, "cars": result.cars, "detected": result.detected,
                             "clean_cars": result.clean_cars, "detected_clean": result.detected_clean})
        self.step += 1
        if self.zero_run >= self.config.zero_grad_patience:
            raise TrainingError(
                f"step {self.step - 1}: the attack loss gave the object no gradient for {self.zero_run} consecutive "
                "steps (no object point inside the cars' frustums, or no detector candidate around them, or a victim "
                f"whose oracle ignores its input); stopping ({self._resume_hint()})")

    def drop_estimate(self) -> float | None:
        """The running drop estimate of the module doc (None before a reference car was detected clean)."""
        clean = sum(h["detected_clean"] for h in self.history)
        if clean == 0:
            return None
        window = self.history[-DROP_WINDOW:]
        attacked_rate = sum(h["detected"] for h in window) / sum(h["cars"] for h in window)
        return 1.0 - attacked_rate / (clean / sum(h["clean_cars"] for h in self.history))

    # ---- checkpoints --------------------------------------------------------------------------
    def _resume_hint(self) -> str:
        if self.ckpt is not None and self.ckpt.is_file():
            return f"the last checkpoint is {self.ckpt} (step {self._saved_step}); --resume continues from it"
        return "no checkpoint written yet"

    def state(self, identity: dict[str, Any]) -> dict[str, Any]:
        return {"format": CHECKPOINT_FORMAT, "identity": identity, "step": self.step,
                "delta": self.delta.detach().clone(), "colour_logit": self.colour_logit.detach().clone(),
                "optimizer": self.optimizer.state_dict(), "history": self.history, "zero_run": self.zero_run,
                "elapsed_s": self.elapsed_s, "run": self.run_state}

    def save_checkpoint(self, path: Path, identity: dict[str, Any]) -> None:
        from robustbench3d.fileio import atomic_write_bytes

        buf = io.BytesIO()
        torch.save(self.state(identity), buf)
        atomic_write_bytes(path, buf.getvalue())
        self._saved_step = self.step

    def load_checkpoint(self, path: Path, identity: dict[str, Any]) -> None:
        from robustbench3d.errors import DataFormatError

        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:  # torch raises many types on a damaged file
            raise DataFormatError(path, f"not a readable training checkpoint ({type(exc).__name__})") from None
        if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
            raise DataFormatError(path, f"expected {CHECKPOINT_FORMAT!r}", field="format")
        have = state.get("identity")
        if isinstance(have, dict) and isinstance(have.get("config"), dict):  # fields it predates: LEGACY_IDENTITY
            have = {**have, "config": {**LEGACY_IDENTITY, **have["config"]}}
        if have != identity:
            have = have or {}
            diff = sorted(k for k in set(have) | set(identity) if k != "config" and have.get(k) != identity.get(k))
            hc, wc = have.get("config") or {}, identity["config"]
            diff += sorted(f"config.{k}" for k in set(hc) | set(wc) if hc.get(k) != wc.get(k))
            raise TrainingError(f"{path}: field 'identity': the checkpoint belongs to another training "
                                f"({', '.join(diff)} differ); use another --out or drop --resume")
        with torch.no_grad():
            self.delta.copy_(state["delta"])
            self.colour_logit.copy_(state["colour_logit"])
        try:
            self.optimizer.load_state_dict(state["optimizer"])
        except (KeyError, TypeError, ValueError, IndexError, AttributeError) as exc:
            raise DataFormatError(path, f"not this training's optimiser state ({type(exc).__name__}: {exc})",
                                  field="optimizer") from None
        self.step, self.history = int(state["step"]), list(state["history"])
        self.zero_run, self.elapsed_s = int(state["zero_run"]), float(state["elapsed_s"])
        self.run_state = dict(state.get("run") or {})
        self._saved_step = self.step


def _grads(loss: torch.Tensor, params: list[torch.Tensor]) -> list[torch.Tensor]:
    if not loss.requires_grad:
        return [torch.zeros_like(p) for p in params]
    grads = torch.autograd.grad(loss, params, allow_unused=True)
    return [torch.zeros_like(p) if g is None else g for p, g in zip(params, grads, strict=True)]


def format_losses(losses: dict[str, float]) -> str:
    return " ".join(f"{k} {v:.4g}" for k, v in losses.items())
