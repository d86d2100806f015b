"""YOLO network built from a darknet-style layer list (:mod:`.config`) and its output decoding.

Convolutions are conv-BN-leaky(0.1) without bias; ``HeadConv`` is linear with bias. The network
returns one raw tensor per ``Yolo`` layer, (B, A·(5 + C), H, W), channels per anchor ordered
t_x, t_y, t_w, t_h, t_obj, class logits. :func:`flatten` decodes them (input pixels):
centre = (σ(t_x) + cell_x)·stride, size = anchor·exp(t_w, t_h); objectness and classes are
independent sigmoids, kept as logits. This is the differentiable twin (training, objectness
oracle) of :func:`robustbench3d.victims.yolo.postprocess.decode_heads` (the inference path).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from robustbench3d.victims.yolo.config import (
    CONFIGS,
    Conv,
    HeadConv,
    MaxPool,
    Route,
    Shortcut,
    Upsample,
    Yolo,
    YoloConfig,
)
from robustbench3d.victims.yolo.postprocess import MAX_LOG_SCALE


class _MaxPoolSame(nn.Module):
    """Darknet max-pool with stride 1: pad right/bottom by replication, keeping H x W."""

    def __init__(self, size: int):
        super().__init__()
        self.size = size

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        p = self.size - 1
        return F.max_pool2d(F.pad(x, (0, p, 0, p), mode="replicate"), self.size, 1)


class Darknet(nn.Module):
    """The network of a :class:`YoloConfig`. ``forward(images (B, 3, H, W) in [0, 1])`` returns the
    raw head outputs; attributes ``head_strides`` and ``head_masks`` describe them."""

    def __init__(self, cfg: YoloConfig):
        super().__init__()
        self.cfg = cfg
        self.specs = cfg.layers()
        self.blocks = nn.ModuleList()
        channels: list[int] = []
        strides: list[int] = []
        self.head_strides: list[int] = []
        self.head_masks: list[tuple[int, ...]] = []
        in_ch, stride = 3, 1
        nout = 5 + cfg.num_classes
        for i, spec in enumerate(self.specs):
            block: nn.Module = nn.Identity()
            if isinstance(spec, Conv):
                block = nn.Sequential(
                    nn.Conv2d(in_ch, spec.filters, spec.size, spec.stride, (spec.size - 1) // 2, bias=False),
                    nn.BatchNorm2d(spec.filters), nn.LeakyReLU(0.1))
                in_ch, stride = spec.filters, stride * spec.stride
            elif isinstance(spec, MaxPool):
                block = nn.MaxPool2d(spec.size, spec.stride) if spec.stride > 1 else _MaxPoolSame(spec.size)
                stride *= spec.stride
            elif isinstance(spec, Route):
                idx = [self._absolute(i, j) for j in spec.layers]
                in_ch, stride = sum(channels[j] for j in idx), strides[idx[0]]
            elif isinstance(spec, Upsample):
                block = nn.Upsample(scale_factor=spec.scale, mode="nearest")
                stride //= spec.scale
            elif isinstance(spec, HeadConv):
                nxt = self.specs[i + 1]
                if not isinstance(nxt, Yolo):
                    raise ValueError(f"layer {i}: HeadConv must be followed by a Yolo layer")
                block = nn.Conv2d(in_ch, len(nxt.mask) * nout, 1, bias=True)
                in_ch = len(nxt.mask) * nout
            elif isinstance(spec, Yolo):
                self.head_strides.append(stride)
                self.head_masks.append(spec.mask)
            elif not isinstance(spec, Shortcut):
                raise TypeError(f"unknown layer spec {spec!r}")
            self.blocks.append(block)
            channels.append(in_ch)
            strides.append(stride)
        used = sorted(a for m in self.head_masks for a in m)
        if used != list(range(len(cfg.anchors))):
            raise ValueError(f"Yolo masks {self.head_masks} do not cover the {len(cfg.anchors)} anchors")

    @staticmethod
    def _absolute(i: int, j: int) -> int:
        return i + j if j < 0 else j

    def forward(self, images: torch.Tensor) -> list[torch.Tensor]:
        outputs: list[torch.Tensor] = []
        heads: list[torch.Tensor] = []
        x = images
        for i, (spec, block) in enumerate(zip(self.specs, self.blocks, strict=True)):
            if isinstance(spec, Route):
                x = torch.cat([outputs[self._absolute(i, j)] for j in spec.layers], dim=1)
            elif isinstance(spec, Shortcut):
                x = outputs[i - 1] + outputs[i + spec.source]
            elif isinstance(spec, Yolo):
                heads.append(x)
            else:
                x = block(x)
            outputs.append(x)
        return heads


@dataclass
class YoloPredictions:
    """All priors of all heads, flattened (P priors per image, head by head, then anchor, row, column).

    Attributes:
        boxes: (B, P, 4) decoded cx, cy, w, h in input pixels (differentiable).
        raw: (B, P, 4) t_x, t_y, t_w, t_h.
        obj_logit: (B, P) objectness logits.
        cls_logit: (B, P, C) class logits.
        anchor: (P,) int64 global anchor index; grid: (P, 2) int64 cell (column, row);
        stride: (P,) float stride in pixels; head: (P,) int64 head index.
        layout: per head (stride, grid rows, grid columns, anchor mask, offset of its first prior).
    """

    boxes: torch.Tensor
    raw: torch.Tensor
    obj_logit: torch.Tensor
    cls_logit: torch.Tensor
    anchor: torch.Tensor
    grid: torch.Tensor
    stride: torch.Tensor
    head: torch.Tensor
    layout: list[HeadLayout]


@dataclass(frozen=True)
class HeadLayout:
    stride: int
    rows: int
    cols: int
    mask: tuple[int, ...]
    offset: int


def flatten(heads: list[torch.Tensor], net: Darknet) -> YoloPredictions:
    """Decode raw head outputs of ``net`` into :class:`YoloPredictions`."""
    cfg = net.cfg
    nout = 5 + cfg.num_classes
    parts: list[torch.Tensor] = []
    boxes: list[torch.Tensor] = []
    meta: dict[str, list[torch.Tensor]] = {"anchor": [], "grid": [], "stride": [], "head": []}
    layout: list[HeadLayout] = []
    offset = 0
    for h, (raw, stride, mask) in enumerate(zip(heads, net.head_strides, net.head_masks, strict=True)):
        b, _, gh, gw = raw.shape
        a = len(mask)
        layout.append(HeadLayout(int(stride), gh, gw, tuple(mask), offset))
        offset += a * gh * gw
        p = raw.view(b, a, nout, gh, gw).permute(0, 1, 3, 4, 2).reshape(b, a * gh * gw, nout)
        gy, gx = torch.meshgrid(torch.arange(gh), torch.arange(gw), indexing="ij")
        grid = torch.stack([gx, gy], dim=-1).reshape(1, gh * gw, 2).expand(a, -1, -1).reshape(-1, 2)
        anchors = torch.tensor([cfg.anchors[k] for k in mask], dtype=raw.dtype)
        anc = anchors[:, None, :].expand(-1, gh * gw, -1).reshape(-1, 2)
        xy = (torch.sigmoid(p[..., 0:2]) + grid.to(raw.dtype)) * stride
        wh = anc * torch.exp(p[..., 2:4].clamp(max=MAX_LOG_SCALE))
        boxes.append(torch.cat([xy, wh], dim=-1))
        parts.append(p)
        meta["anchor"].append(torch.tensor(mask, dtype=torch.int64)[:, None].expand(-1, gh * gw).reshape(-1))
        meta["grid"].append(grid)
        meta["stride"].append(torch.full((a * gh * gw,), float(stride)))
        meta["head"].append(torch.full((a * gh * gw,), h, dtype=torch.int64))
    allp = torch.cat(parts, dim=1)
    return YoloPredictions(
        boxes=torch.cat(boxes, dim=1), raw=allp[..., 0:4], obj_logit=allp[..., 4], cls_logit=allp[..., 5:],
        anchor=torch.cat(meta["anchor"]), grid=torch.cat(meta["grid"]), stride=torch.cat(meta["stride"]),
        head=torch.cat(meta["head"]), layout=layout,
    )


def build_model(cfg: YoloConfig | str = "mini", seed: int = 0) -> Darknet:
    """A freshly initialised network, weights drawn from a torch RNG seeded with ``seed``."""
    if isinstance(cfg, str):
        cfg = CONFIGS[cfg]
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return Darknet(cfg)


def conv_layer_count(net: Darknet) -> int:
    """Number of convolution layers (darknet counts the linear head convs too)."""
    return sum(isinstance(m, nn.Conv2d) for m in net.modules())
