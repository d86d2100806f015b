"""Frustum-PointNet v1 (reference §1.6): instance segmentation, masking, T-Net, box estimation.

Inputs live in the frustum frame (rect rotated about y so the 2D-box centre ray is +z; x right,
y down, z forward; m). "mlp(a, b)" = shared 1x1 Conv1d + BatchNorm + ReLU per layer, "FC" =
Linear + BatchNorm + ReLU; the last layer of each head is linear. Convolutions keep their bias
next to BatchNorm, as in the original TF code, which makes the parameter counts match (§1.6).

Randomness is explicit: dropout draws from a ``torch.Generator`` passed to :meth:`forward`; the
choice of the 512 object points is computed in numpy (:func:`object_point_indices`) from the
detached mask, either ``"random"`` with a ``numpy.random.Generator`` (the original behaviour,
reproducible when seeded) or ``"topk"`` (deterministic: masked points ordered by foreground
margin, repeated cyclically). An empty mask gives a zero centroid and gathers point 0, as the TF
code does.

:meth:`FrustumPointNetV1.forward` is the differentiable composition used for training. Inference
(the victim's ``detect``, torch and ONNX alike) runs the three networks through
:class:`TorchFrustumStages` and the numpy glue of :mod:`robustbench3d.victims.fpointnet.glue`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from typing import Any, Literal

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from robustbench3d.victims.fpointnet.box_coding import (
    MEAN_SIZES,
    NUM_HEADING_BIN,
    NUM_OBJECT_POINT,
    NUM_SIZE_CLUSTER,
)
from robustbench3d.victims.fpointnet.glue import NUM_BOX_OUTPUTS, GatherMode, object_point_indices

Layout = Literal["conv", "rows"]


@dataclass(frozen=True)
class FPointNetConfig:
    """Layer widths and sizes. :data:`FULL` is v1 exactly; :data:`LITE` is the CPU test config."""

    name: str = "full"
    num_points: int = 1024
    in_channels: int = 4
    one_hot_dim: int = 3
    seg_point_mlp: tuple[int, ...] = (64, 64, 64)
    seg_global_mlp: tuple[int, ...] = (128, 1024)
    seg_head: tuple[int, ...] = (512, 256, 128, 128)
    dropout: float = 0.5
    tnet_mlp: tuple[int, ...] = (128, 128, 256)
    tnet_fc: tuple[int, ...] = (256, 128)
    box_mlp: tuple[int, ...] = (128, 128, 256, 512)
    box_fc: tuple[int, ...] = (512, 256)
    num_object_points: int = NUM_OBJECT_POINT
    bn_eps: float = 1e-5

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> FPointNetConfig:
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in data.items()})


FULL = FPointNetConfig()
LITE = replace(FULL, name="lite", num_points=512, seg_global_mlp=(128, 256), seg_head=(128, 64))
CONFIGS: dict[str, FPointNetConfig] = {"full": FULL, "lite": LITE}


def shared_mlp(in_ch: int, widths: Sequence[int], eps: float) -> nn.Sequential:
    layers: list[nn.Module] = []
    for w in widths:
        layers += [nn.Conv1d(in_ch, w, 1), nn.BatchNorm1d(w, eps=eps), nn.ReLU()]
        in_ch = w
    return nn.Sequential(*layers)


def fc_stack(in_ch: int, widths: Sequence[int], eps: float) -> nn.Sequential:
    layers: list[nn.Module] = []
    for w in widths:
        layers += [nn.Linear(in_ch, w), nn.BatchNorm1d(w, eps=eps), nn.ReLU()]
        in_ch = w
    return nn.Sequential(*layers)


def run_mlp(seq: nn.Sequential, x: torch.Tensor, rows: bool) -> torch.Tensor:
    """Apply a :func:`shared_mlp` stack (or one 1x1 ``Conv1d``) to ``x``.

    ``rows=False``: ``x`` is (B, C, N) and the modules run as defined. ``rows=True``: ``x`` is
    (B, N, C); each 1x1 convolution runs as the per-point ``Linear`` with the same weight and bias
    and each BatchNorm on the (B·N, C) rows: the same arithmetic (statistics over B·N per channel),
    laid out for a single matrix product per layer.
    """
    if not rows:
        return seq(x)
    for m in seq if isinstance(seq, nn.Sequential) else (seq,):
        if isinstance(m, nn.Conv1d):
            x = F.linear(x, m.weight[:, :, 0], m.bias)
        elif isinstance(m, nn.BatchNorm1d):
            x = m(x.reshape(-1, x.shape[-1])).reshape(x.shape)
        else:
            x = m(x)
    return x


def dropout(x: torch.Tensor, p: float, training: bool, generator: torch.Generator | None) -> torch.Tensor:
    """Inverted dropout drawing its mask from ``generator`` (identity when not training)."""
    if not training or p <= 0.0:
        return x
    keep = 1.0 - p
    mask = torch.rand(x.shape, generator=generator, dtype=x.dtype, device=x.device) < keep
    return x * mask / keep


class InstanceSegNet(nn.Module):
    """3D instance segmentation PointNet: (B, N, 4) points + (B, 3) one-hot -> (B, N, 2) logits."""

    def __init__(self, cfg: FPointNetConfig):
        super().__init__()
        self.cfg = cfg
        self.point_mlp = shared_mlp(cfg.in_channels, cfg.seg_point_mlp, cfg.bn_eps)
        self.global_mlp = shared_mlp(cfg.seg_point_mlp[-1], cfg.seg_global_mlp, cfg.bn_eps)
        head_in = cfg.seg_point_mlp[-1] + cfg.seg_global_mlp[-1] + cfg.one_hot_dim
        self.head = shared_mlp(head_in, cfg.seg_head, cfg.bn_eps)
        self.classifier = nn.Conv1d(cfg.seg_head[-1], 2, 1)
        self.rows = False  # layout of the per-point layers, see run_mlp (not part of the state dict)

    def forward(self, points: torch.Tensor, one_hot: torch.Tensor,
                generator: torch.Generator | None = None) -> torch.Tensor:
        if self.rows:
            point_feat = run_mlp(self.point_mlp, points, True)  # (B, N, C)
            global_feat = run_mlp(self.global_mlp, point_feat, True).amax(dim=1)
            global_feat = torch.cat([global_feat, one_hot.to(global_feat.dtype)], dim=1)
            n = points.shape[1]
            feat = torch.cat([point_feat, global_feat[:, None, :].expand(-1, n, -1)], dim=2)
            feat = dropout(run_mlp(self.head, feat, True), self.cfg.dropout, self.training, generator)
            return run_mlp(self.classifier, feat, True)
        x = points.transpose(1, 2)  # (B, C, N)
        point_feat = self.point_mlp(x)
        global_feat = self.global_mlp(point_feat).amax(dim=2)
        global_feat = torch.cat([global_feat, one_hot.to(global_feat.dtype)], dim=1)
        n = points.shape[1]
        feat = torch.cat([point_feat, global_feat[:, :, None].expand(-1, -1, n)], dim=1)
        feat = dropout(self.head(feat), self.cfg.dropout, self.training, generator)
        return self.classifier(feat).transpose(1, 2)


class CenterRegressionNet(nn.Module):
    """T-Net: (B, M, 3) object points (mask-centroid frame) + one-hot -> (B, 3) centre delta (m)."""

    def __init__(self, cfg: FPointNetConfig):
        super().__init__()
        self.mlp = shared_mlp(3, cfg.tnet_mlp, cfg.bn_eps)
        self.fc = fc_stack(cfg.tnet_mlp[-1] + cfg.one_hot_dim, cfg.tnet_fc, cfg.bn_eps)
        self.out = nn.Linear(cfg.tnet_fc[-1], 3)
        nn.init.zeros_(self.out.weight)  # as the PyTorch port: start at the mask centroid
        nn.init.zeros_(self.out.bias)
        self.rows = False

    def forward(self, object_points: torch.Tensor, one_hot: torch.Tensor) -> torch.Tensor:
        if self.rows:
            feat = run_mlp(self.mlp, object_points, True).amax(dim=1)
        else:
            feat = self.mlp(object_points.transpose(1, 2)).amax(dim=2)
        return self.out(self.fc(torch.cat([feat, one_hot.to(feat.dtype)], dim=1)))


class BoxEstimationNet(nn.Module):
    """Amodal box PointNet v1: (B, M, 3) points (stage-1 centre frame) + one-hot -> (B, 59)."""

    def __init__(self, cfg: FPointNetConfig):
        super().__init__()
        self.mlp = shared_mlp(3, cfg.box_mlp, cfg.bn_eps)
        self.fc = fc_stack(cfg.box_mlp[-1] + cfg.one_hot_dim, cfg.box_fc, cfg.bn_eps)
        self.out = nn.Linear(cfg.box_fc[-1], NUM_BOX_OUTPUTS)
        self.rows = False

    def forward(self, object_points: torch.Tensor, one_hot: torch.Tensor) -> torch.Tensor:
        if self.rows:
            feat = run_mlp(self.mlp, object_points, True).amax(dim=1)
        else:
            feat = self.mlp(object_points.transpose(1, 2)).amax(dim=2)
        return self.out(self.fc(torch.cat([feat, one_hot.to(feat.dtype)], dim=1)))


@dataclass
class FPointNetOutput:
    """Forward results (B frustums; frustum frame, m).

    seg_logits (B, N, 2); mask (B, N) bool (logit₁ > logit₀); mask_count (B,); mask_centroid
    (B, 3); object_indices (B, M) gathered point indices; center_delta (B, 3) T-Net output;
    stage1_center (B, 3); center (B, 3) final box centre; heading_scores (B, 12);
    heading_residuals_normalized (B, 12) and heading_residuals (B, 12, rad); size_scores (B, 8);
    size_residuals_normalized (B, 8, 3) and size_residuals (B, 8, 3, m).
    """

    seg_logits: torch.Tensor
    mask: torch.Tensor
    mask_count: torch.Tensor
    mask_centroid: torch.Tensor
    object_indices: torch.Tensor
    center_delta: torch.Tensor
    stage1_center: torch.Tensor
    center: torch.Tensor
    heading_scores: torch.Tensor
    heading_residuals_normalized: torch.Tensor
    heading_residuals: torch.Tensor
    size_scores: torch.Tensor
    size_residuals_normalized: torch.Tensor
    size_residuals: torch.Tensor


class FrustumPointNetV1(nn.Module):
    """The v1 network. ``forward(points (B, N, 4), one_hot (B, 3))`` -> :class:`FPointNetOutput`."""

    def __init__(self, cfg: FPointNetConfig = FULL):
        super().__init__()
        self.cfg = cfg
        self.seg = InstanceSegNet(cfg)
        self.tnet = CenterRegressionNet(cfg)
        self.box = BoxEstimationNet(cfg)
        self.register_buffer("mean_sizes", torch.tensor(MEAN_SIZES, dtype=torch.float32), persistent=False)

    def set_layout(self, layout: Layout) -> FrustumPointNetV1:
        """Run the per-point layers as 1x1 convolutions on (B, C, N) (``"conv"``, the default and the
        ONNX export's) or as ``Linear`` on (B·N, C) rows (``"rows"``, faster to train). Same
        parameters, same state dict, same outputs to float tolerance (tests/victims/test_fpointnet_fast.py)."""
        if layout not in ("conv", "rows"):
            raise ValueError(f"unknown layout {layout!r} (expected 'conv' or 'rows')")
        for net in (self.seg, self.tnet, self.box):
            net.rows = layout == "rows"
        return self

    def forward(self, points: torch.Tensor, one_hot: torch.Tensor, *, gather: GatherMode = "topk",
                rng: np.random.Generator | Sequence[np.random.Generator] | None = None,
                generator: torch.Generator | None = None,
                straight_through: float | None = None) -> FPointNetOutput:
        """Run the cascade on (B, N, 4) frustum-frame points and (B, 3) one-hot vectors.

        Args:
            gather: object-point choice, see :func:`object_point_indices`.
            rng: numpy generator(s) for ``gather="random"``.
            generator: torch generator for dropout (training only).
            straight_through: temperature ``tau`` of a straight-through mask for attacks: the forward
                values are unchanged (hard mask), but the mask's gradient is that of
                ``sigmoid((logit1 - logit0) / tau)``, so the centroid and the gathered object points
                (scaled by the mask, 1 in the forward pass) pass gradient to the segmentation logits.
                None (default): the mask is a constant.
        """
        logits = self.seg(points, one_hot, generator)
        xyz = points[..., :3]
        mask = (logits[..., 1] > logits[..., 0]).detach()
        count = mask.sum(dim=1)
        maskf = mask.to(xyz.dtype)
        if straight_through is not None:
            soft = torch.sigmoid((logits[..., 1] - logits[..., 0]) / straight_through).to(xyz.dtype)
            maskf = maskf + (soft - soft.detach())  # exactly the hard mask in the forward pass
        centroid = (maskf[..., None] * xyz).sum(dim=1) / count.clamp_min(1).to(xyz.dtype)[:, None]
        margin = (logits[..., 1] - logits[..., 0]).detach().float().cpu().numpy()
        idx_np = object_point_indices(mask.cpu().numpy(), margin, self.cfg.num_object_points, gather, rng)
        idx = torch.from_numpy(idx_np).to(points.device)
        centred = xyz - centroid[:, None, :]
        if straight_through is not None:  # masked points x 1 (exact); an empty mask's point 0 stays unscaled
            scale = torch.where(mask, maskf, torch.ones_like(maskf))
            centred = centred * scale[..., None]
        object_points = torch.gather(centred, 1, idx[..., None].expand(-1, -1, 3))
        delta = self.tnet(object_points, one_hot)
        stage1 = centroid + delta
        out = self.box(object_points - delta[:, None, :], one_hot)
        nh, ns = NUM_HEADING_BIN, NUM_SIZE_CLUSTER
        h_norm = out[:, 3 + nh:3 + 2 * nh]
        s_norm = out[:, 3 + 2 * nh + ns:].reshape(-1, ns, 3)
        return FPointNetOutput(
            seg_logits=logits, mask=mask, mask_count=count, mask_centroid=centroid, object_indices=idx,
            center_delta=delta, stage1_center=stage1, center=out[:, :3] + stage1,
            heading_scores=out[:, 3:3 + nh], heading_residuals_normalized=h_norm,
            heading_residuals=h_norm * (np.pi / nh),
            size_scores=out[:, 3 + 2 * nh:3 + 2 * nh + ns], size_residuals_normalized=s_norm,
            size_residuals=s_norm * self.mean_sizes[None].to(s_norm.dtype),
        )


class TorchFrustumStages:
    """:class:`~robustbench3d.victims.fpointnet.glue.FrustumStages` of an eval-mode network:
    numpy float32 in, numpy float32 out, no autograd.

    The networks as defined, the reference of the faster
    :class:`~robustbench3d.victims.fpointnet.distinct_stages.DistinctPointStages` (the victims' default,
    equal bit for bit at one intra-op thread). The T-Net and the box net run one frustum per call: their
    fully connected layers give results that depend (in the last bits) on a row's position in a batched
    matrix product, which would make a frustum's box depend on the other frustums of its batch. The
    segmentation net runs batched (at one intra-op thread its 1x1 convolutions give each frustum the bits
    of a one-frustum batch for batches up to 8; not at two threads, nor at 40 frustums).
    """

    def __init__(self, model: FrustumPointNetV1):
        self.model = model.eval()

    @staticmethod
    def _run(module: nn.Module, points: np.ndarray, one_hot: np.ndarray) -> np.ndarray:
        with torch.inference_mode():
            return module(torch.from_numpy(np.ascontiguousarray(points, dtype=np.float32)),
                          torch.from_numpy(np.ascontiguousarray(one_hot, dtype=np.float32))).numpy()

    def _per_frustum(self, module: nn.Module, points: np.ndarray, one_hot: np.ndarray) -> np.ndarray:
        return np.concatenate([self._run(module, points[i:i + 1], one_hot[i:i + 1]) for i in range(len(points))])

    def segmentation(self, points: np.ndarray, one_hot: np.ndarray) -> np.ndarray:
        return self._run(self.model.seg, points, one_hot)

    def center_delta(self, object_points: np.ndarray, one_hot: np.ndarray) -> np.ndarray:
        return self._per_frustum(self.model.tnet, object_points, one_hot)

    def box_output(self, object_points: np.ndarray, one_hot: np.ndarray) -> np.ndarray:
        return self._per_frustum(self.model.box, object_points, one_hot)


def set_bn_momentum(model: nn.Module, momentum: float) -> None:
    """Set the PyTorch momentum (= 1 − TF decay) of every BatchNorm layer."""
    for m in model.modules():
        if isinstance(m, nn.modules.batchnorm._BatchNorm):
            m.momentum = momentum


def bn_momentum_at(samples_seen: int, init: float = 0.5, decay_rate: float = 0.5,
                   decay_step: int = 800_000, minimum: float = 0.01) -> float:
    """TF schedule (§1.8): momentum = max(minimum, init·rate^⌊samples/step⌋) (decay ≤ 0.99)."""
    return max(minimum, init * decay_rate ** (samples_seen // decay_step))


def count_parameters(module: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)


def build_model(cfg: FPointNetConfig | str = "full", seed: int = 0) -> FrustumPointNetV1:
    """A freshly initialised network; weights drawn from a torch RNG seeded with ``seed``
    (the global RNG state is left untouched)."""
    if isinstance(cfg, str):
        cfg = CONFIGS[cfg]
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return FrustumPointNetV1(cfg)


def rotate_to_frustum_torch(points: torch.Tensor, rot_angle: float | torch.Tensor) -> torch.Tensor:
    """Differentiable twin of :func:`~robustbench3d.victims.fpointnet.frustum.rotate_to_frustum`:
    rotate (…, ≥3) rect points about y by ``rot_angle`` (rad); other channels pass through."""
    a = torch.as_tensor(rot_angle, dtype=points.dtype, device=points.device)
    c, s = torch.cos(a), torch.sin(a)
    x, y, z = points[..., 0], points[..., 1], points[..., 2]
    return torch.cat([torch.stack([c * x - s * z, y, s * x + c * z], dim=-1), points[..., 3:]], dim=-1)
