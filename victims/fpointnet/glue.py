"""Frustum-PointNet v1 inference glue in numpy (reference §1.6 b, e): the steps between the three
networks, shared by the torch victim and the ONNX victim.

segmentation net -> mask (logit₁ > logit₀), mask centroid, deterministic object-point gather ->
T-Net -> stage-1 centre -> box net -> parsed outputs (:class:`FrustumOutputs`). The networks are
any backend implementing :class:`FrustumStages` (numpy float32 in and out).

Frames: all coordinates are in the frustum frame (rect rotated about y so the 2D-box centre ray is
+z; m). Centroids and centres are float64; network inputs are cast to float32.

Gather: ``"random"`` (the original, drawn from a seeded ``numpy.random.Generator``) or ``"topk"``
(masked points by decreasing foreground margin, repeated cyclically); both are deterministic given
the generator. An empty mask gives a zero centroid and gathers point 0, as the TF code does.

Imports numpy only (no torch). The differentiable twin used for training is
:meth:`robustbench3d.victims.fpointnet.model.FrustumPointNetV1.forward`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal, Protocol

import numpy as np

from robustbench3d.victims.fpointnet.box_coding import MEAN_SIZES, NUM_HEADING_BIN, NUM_SIZE_CLUSTER

GatherMode = Literal["random", "topk"]
#: Box-net output size: centre (3) + heading scores and residuals (2·12) + size scores (8) and
#: residuals (3·8).
NUM_BOX_OUTPUTS = 3 + 2 * NUM_HEADING_BIN + 4 * NUM_SIZE_CLUSTER
#: Columns of the heading-bin scores and of the size-cluster scores in the box-net output.
HEADING_SCORES = slice(3, 3 + NUM_HEADING_BIN)
SIZE_SCORES = slice(3 + 2 * NUM_HEADING_BIN, 3 + 2 * NUM_HEADING_BIN + NUM_SIZE_CLUSTER)


class FrustumStages(Protocol):
    """The three F-PN v1 networks as numpy functions (float32, eval mode, B frustums)."""

    def segmentation(self, points: np.ndarray, one_hot: np.ndarray) -> np.ndarray:
        """(B, N, 4) frustum points (xyz m, reflectance), (B, 3) one-hot -> (B, N, 2) logits."""
        ...

    def center_delta(self, object_points: np.ndarray, one_hot: np.ndarray) -> np.ndarray:
        """T-Net: (B, M, 3) object points (mask-centroid frame), one-hot -> (B, 3) centre delta (m)."""
        ...

    def box_output(self, object_points: np.ndarray, one_hot: np.ndarray) -> np.ndarray:
        """Box net: (B, M, 3) object points (stage-1 centre frame), one-hot -> (B, 59) raw outputs."""
        ...


@dataclass(frozen=True)
class FrustumOutputs:
    """Inference results of B frustums (frustum frame, m; numpy).

    seg_logits (B, N, 2); mask (B, N) bool; mask_count (B,); mask_centroid (B, 3); object_indices
    (B, M); center_delta (B, 3); stage1_center (B, 3); center (B, 3) final box centre;
    heading_scores (B, 12); heading_residuals (B, 12) rad; size_scores (B, 8); size_residuals
    (B, 8, 3) m.
    """

    seg_logits: np.ndarray
    mask: np.ndarray
    mask_count: np.ndarray
    mask_centroid: np.ndarray
    object_indices: np.ndarray
    center_delta: np.ndarray
    stage1_center: np.ndarray
    center: np.ndarray
    heading_scores: np.ndarray
    heading_residuals: np.ndarray
    size_scores: np.ndarray
    size_residuals: np.ndarray


def object_point_indices(mask: np.ndarray, margin: np.ndarray, num: int, mode: GatherMode,
                         rng: np.random.Generator | Sequence[np.random.Generator] | None = None) -> np.ndarray:
    """(B, num) int64 indices of the object points to gather from each row of ``mask`` (B, N).

    ``"random"``: more than ``num`` masked points -> ``num`` of them without replacement; else all
    of them plus random repeats; shuffled (the original ``tf_gather_object_pc``). ``rng`` is one
    generator or one per row. ``"topk"``: masked points by decreasing ``margin`` (logit₁ − logit₀),
    repeated cyclically. Rows without a masked point gather index 0 everywhere.
    """
    mask = np.asarray(mask, dtype=bool)
    b = mask.shape[0]
    out = np.zeros((b, num), dtype=np.int64)
    if mode not in ("random", "topk"):
        raise ValueError(f"gather mode must be 'random' or 'topk', got {mode!r}")
    if mode == "random" and rng is None:
        raise ValueError("gather mode 'random' needs a numpy Generator")
    for i in range(b):
        pos = np.flatnonzero(mask[i])
        if len(pos) == 0:
            continue
        if mode == "topk":
            order = pos[np.argsort(-np.asarray(margin[i])[pos], kind="stable")]
            out[i] = order[np.arange(num) % len(order)]
            continue
        g = rng[i] if isinstance(rng, Sequence) else rng
        assert g is not None
        if len(pos) > num:
            choice = g.choice(len(pos), num, replace=False)
        else:
            choice = np.concatenate([np.arange(len(pos)), g.choice(len(pos), num - len(pos), replace=True)])
        g.shuffle(choice)
        out[i] = pos[choice]
    return out


def mask_centroid(seg_logits: np.ndarray, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mask (B, N) bool (logit₁ > logit₀), its count (B,) and the float64 centroid (B, 3) of the
    masked ``xyz`` (B, N, 3) points (zero for an empty mask)."""
    mask = seg_logits[..., 1] > seg_logits[..., 0]
    count = mask.sum(axis=1)
    total = (mask[..., None] * np.asarray(xyz, dtype=np.float64)).sum(axis=1)
    return mask, count, total / np.maximum(count, 1)[:, None]


def gather_points(points: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """(B, M, C) rows of ``points`` (B, N, C) at ``indices`` (B, M)."""
    return np.take_along_axis(points, indices[..., None], axis=1)


def run_frustum_stages(stages: FrustumStages, points: np.ndarray, one_hot: np.ndarray, num_object_points: int,
                       gather: GatherMode,
                       rng: np.random.Generator | Sequence[np.random.Generator] | None = None) -> FrustumOutputs:
    """Run segmentation -> mask/centroid/gather -> T-Net -> box net on (B, N, 4) float32 frustum
    points with (B, 3) one-hot vectors; ``rng`` as in :func:`object_point_indices`."""
    points = np.ascontiguousarray(points, dtype=np.float32)
    one_hot = np.ascontiguousarray(one_hot, dtype=np.float32)
    logits = np.asarray(stages.segmentation(points, one_hot), dtype=np.float32)
    xyz = points[..., :3].astype(np.float64)
    mask, count, centroid = mask_centroid(logits, xyz)
    idx = object_point_indices(mask, logits[..., 1] - logits[..., 0], num_object_points, gather, rng)
    delta, out = run_box_stages(stages, gather_points(xyz - centroid[:, None, :], idx), one_hot)
    return parse_box_output(out, logits, mask, count, centroid, idx, delta, centroid + delta)


def run_box_stages(stages: FrustumStages, object_points: np.ndarray,
                   one_hot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """T-Net, then the box net on the object points shifted by its delta: (B, M, 3) float64 object
    points (mask-centroid frame, m), (B, 3) one-hot -> (centre delta (B, 3), box output (B, 59)),
    both float32."""
    delta = np.asarray(stages.center_delta(object_points.astype(np.float32), one_hot), dtype=np.float32)
    box_in = (object_points - delta.astype(np.float64)[:, None, :]).astype(np.float32)
    return delta, np.asarray(stages.box_output(box_in, one_hot), dtype=np.float32)


def parse_box_output(out: np.ndarray, seg_logits: np.ndarray, mask: np.ndarray, count: np.ndarray,
                     centroid: np.ndarray, indices: np.ndarray, delta: np.ndarray,
                     stage1_center: np.ndarray) -> FrustumOutputs:
    """Split the (B, 59) box-net output (§1.6 e): centre offset + stage-1 centre, heading scores and
    residuals (normalised x π/12 -> rad), size scores and residuals (normalised x template -> m)."""
    if out.ndim != 2 or out.shape[1] != NUM_BOX_OUTPUTS:
        raise ValueError(f"box output must be (B, {NUM_BOX_OUTPUTS}), got {out.shape}")
    nh, ns = NUM_HEADING_BIN, NUM_SIZE_CLUSTER
    out64 = out.astype(np.float64)
    return FrustumOutputs(
        seg_logits=seg_logits, mask=mask, mask_count=count, mask_centroid=centroid, object_indices=indices,
        center_delta=delta, stage1_center=stage1_center, center=out64[:, :3] + stage1_center,
        heading_scores=out[:, HEADING_SCORES], heading_residuals=out64[:, 3 + nh:3 + 2 * nh] * (np.pi / nh),
        size_scores=out[:, SIZE_SCORES],
        size_residuals=out64[:, 3 + 2 * nh + ns:].reshape(-1, ns, 3) * MEAN_SIZES[None],
    )
