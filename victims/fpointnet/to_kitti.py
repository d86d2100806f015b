"""Frustum-PointNet outputs -> KITTI result rows (reference §1.9).

Per frustum: argmax heading bin with its residual, argmax size template with its residual;
(l, w, h) = template + residual; ry = heading + rot_angle (wrapped to [−π, π)); the centre is
rotated back from the frustum frame to rect by −rot_angle and moved from the geometric centre to
the KITTI bottom centre (``y += h/2``, y points down). The 2D box is the proposal that produced
the frustum; alpha is computed from ry and the location; truncation and occlusion are −1.

numpy only (no torch import): one decoding for the torch and the ONNX victim. :func:`decode`
also accepts the torch :class:`~robustbench3d.victims.fpointnet.model.FPointNetOutput` of a
training forward pass (converted to numpy first).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import TYPE_CHECKING, Any

import numpy as np

from robustbench3d.geometry import alpha_from_rotation_y, wrap_angle
from robustbench3d.kitti.labels import Labels
from robustbench3d.victims.fpointnet.box_coding import class_to_angle, class_to_size
from robustbench3d.victims.fpointnet.frustum import rotate_from_frustum
from robustbench3d.victims.fpointnet.glue import FrustumOutputs

if TYPE_CHECKING:
    from robustbench3d.victims.fpointnet.model import FPointNetOutput


@dataclass(frozen=True)
class DecodedBoxes:
    """Boxes in the frustum frame (K frustums).

    center (K, 3) geometric centre, m; heading (K,) rad in (−π, π]; size_lwh (K, 3) m;
    score_3d (K,) the GT-path confidence (see :func:`decode`).
    """

    center: np.ndarray
    heading: np.ndarray
    size_lwh: np.ndarray
    score_3d: np.ndarray


def as_numpy_outputs(out: FrustumOutputs | FPointNetOutput) -> FrustumOutputs:
    """:class:`FrustumOutputs` of either output type (tensors detached, moved to the CPU)."""
    if isinstance(out, FrustumOutputs):
        return out

    def arr(value: Any) -> np.ndarray:
        return value.detach().cpu().numpy() if hasattr(value, "detach") else np.asarray(value)

    return FrustumOutputs(**{f.name: arr(getattr(out, f.name)) for f in fields(FrustumOutputs)})


def _softmax(x: np.ndarray, axis: int) -> np.ndarray:
    x = np.asarray(x)
    with np.errstate(over="ignore"):  # x - max below the dtype's range is -inf: exp gives the exact 0
        e = np.exp(x - x.max(axis=axis, keepdims=True))
    return e / e.sum(axis=axis, keepdims=True)


def decode(out: FrustumOutputs | FPointNetOutput) -> DecodedBoxes:
    """Argmax decoding of the networks' outputs.

    ``score_3d`` = (mean object probability over the masked points) x (max heading-bin
    probability) x (max size probability): the exponential of the original code's log score. A
    frustum with an empty mask uses its maximum object probability instead of the mean. The score
    is computed in the logits' dtype (float32 at inference), so ulp-level differences of the
    logits (batch composition, backend) mostly vanish in it.
    """
    o = as_numpy_outputs(out)
    k = np.arange(len(o.center))
    hcls = np.asarray(o.heading_scores).argmax(axis=1)
    scls = np.asarray(o.size_scores).argmax(axis=1)
    prob = _softmax(o.seg_logits, axis=-1)[..., 1]
    count = np.asarray(o.mask_count)
    mean_obj = (prob * np.asarray(o.mask, dtype=prob.dtype)).sum(axis=1) / np.maximum(count, 1).astype(prob.dtype)
    obj = np.where(count > 0, mean_obj, prob.max(axis=1, initial=0.0))
    score = obj * _softmax(o.heading_scores, 1).max(axis=1) * _softmax(o.size_scores, 1).max(axis=1)
    return DecodedBoxes(
        center=np.asarray(o.center, dtype=np.float64),
        heading=class_to_angle(hcls, np.asarray(o.heading_residuals, dtype=np.float64)[k, hcls]),
        size_lwh=class_to_size(scls, np.asarray(o.size_residuals, dtype=np.float64)[k, scls]),
        score_3d=score.astype(np.float64),
    )


def to_labels(boxes: DecodedBoxes, rot_angles: np.ndarray, boxes2d: np.ndarray, scores: np.ndarray,
              type_name: str = "Car") -> Labels:
    """KITTI rows in the rect frame for K frustums (rotation angles (K,), 2D boxes (K, 4) pixels,
    scores (K,))."""
    k = len(boxes.heading)
    rot = np.asarray(rot_angles, dtype=np.float64).reshape(k)
    centers = np.stack([rotate_from_frustum(boxes.center[i], rot[i]) for i in range(k)]) if k else np.zeros((0, 3))
    lwh = boxes.size_lwh.reshape(k, 3)
    location = centers.copy()
    location[:, 1] += lwh[:, 2] / 2
    ry = wrap_angle(boxes.heading + rot) if k else np.zeros(0)
    return Labels(
        type=np.array([type_name] * k, dtype=object), truncated=np.full(k, -1.0),
        occluded=np.full(k, -1, dtype=np.int64), alpha=alpha_from_rotation_y(ry, location) if k else np.zeros(0),
        bbox=np.asarray(boxes2d, dtype=np.float64).reshape(k, 4), dimensions=lwh[:, [2, 1, 0]].copy(),
        location=location, rotation_y=np.asarray(ry, dtype=np.float64).reshape(k),
        score=np.asarray(scores, dtype=np.float64).reshape(k),
    )
