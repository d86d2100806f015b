"""The PointPillars-style network (plain torch, ONNX-exportable): pillar PointNet, BEV scatter, a
three-block 2D backbone with upsampling and concatenation, and a CenterPoint-style centre head.

Input (made by :mod:`.pillars`): pillar features (P, M, 9), pillar coordinates (P, 2) int64 (iy, ix),
the (P, M) valid-point mask, and for a batch the (P,) int64 frame index of each pillar.
Output: a (B, 9, H, W) map at stride ``out_stride`` pillars: channel 0 the Car heatmap logit, then
offset (dx, dy in output cells), z (m, box centre, velodyne), log l, log w, log h (m), sin yaw, cos yaw
(velodyne yaw about z, 0 along +x).
"""

from __future__ import annotations

import torch
from torch import nn

from robustbench3d.victims.pointpillars.config import HEAD_CHANNELS, PointPillarsConfig
from robustbench3d.victims.pointpillars.pillars import NUM_POINT_FEATURES


def _conv(cin: int, cout: int, stride: int = 1) -> list[nn.Module]:
    return [nn.Conv2d(cin, cout, 3, stride, 1, bias=False), nn.BatchNorm2d(cout, eps=1e-3, momentum=0.1),
            nn.ReLU()]


def _block(cin: int, cout: int, layers: int) -> nn.Sequential:
    """A strided 3x3 conv (stride 2) then ``layers - 1`` 3x3 convs, each with BN and ReLU."""
    mods = _conv(cin, cout, 2)
    for _ in range(layers - 1):
        mods += _conv(cout, cout)
    return nn.Sequential(*mods)


def _up(cin: int, cout: int, factor: int) -> nn.Sequential:
    if factor > 1:
        layer: nn.Module = nn.ConvTranspose2d(cin, cout, factor, factor, bias=False)
    else:
        layer = nn.Conv2d(cin, cout, 1, bias=False)
    return nn.Sequential(layer, nn.BatchNorm2d(cout, eps=1e-3, momentum=0.1), nn.ReLU())


class PillarNet(nn.Module):
    """Per-point Linear + BN + ReLU, max over the pillar's valid points: (P, M, 9) -> (P, C)."""

    def __init__(self, channels: int):
        super().__init__()
        self.linear = nn.Linear(NUM_POINT_FEATURES, channels, bias=False)
        self.norm = nn.BatchNorm1d(channels, eps=1e-3, momentum=0.1)

    def forward(self, features: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        p, m, c = features.shape
        x = self.linear(features.reshape(p * m, c))
        x = torch.relu(self.norm(x)).reshape(p, m, -1)
        x = x * mask.unsqueeze(-1).to(x.dtype)  # ReLU >= 0, so masked slots never win the max
        return x.max(dim=1).values


def scatter_to_bev(pillar_feats: torch.Tensor, coords: torch.Tensor, batch_index: torch.Tensor | None,
                   batch_size: int, ny: int, nx: int) -> torch.Tensor:
    """(P, C) pillar features -> (B, C, ny, nx) pseudo-image; empty cells zero.

    A pillar with coordinates (ny, 0) -- one row past the grid, how the ONNX twin pads its fixed pillar
    count -- lands in a spare canvas row that is dropped (batch 1 only)."""
    c = pillar_feats.shape[1]
    flat = coords[:, 0] * nx + coords[:, 1]
    if batch_index is not None:
        flat = flat + batch_index * (ny * nx)
    canvas = torch.zeros(batch_size * ny * nx + 1, c, dtype=pillar_feats.dtype, device=pillar_feats.device)
    canvas = canvas.index_put((flat,), pillar_feats)
    return canvas[:-1].reshape(batch_size, ny, nx, c).permute(0, 3, 1, 2)


class PointPillars(nn.Module):
    """The whole network; see the module doc for inputs and outputs."""

    def __init__(self, cfg: PointPillarsConfig):
        super().__init__()
        self.cfg = cfg
        c1, c2, c3 = cfg.block_channels
        l1, l2, l3 = cfg.block_layers
        self.pillar_net = PillarNet(cfg.pillar_channels)
        self.block1 = _block(cfg.pillar_channels, c1, l1)
        self.block2 = _block(c1, c2, l2)
        self.block3 = _block(c2, c3, l3)
        u = cfg.up_channels
        self.up1, self.up2, self.up3 = _up(c1, u, 1), _up(c2, u, 2), _up(c3, u, 4)
        self.neck = nn.Sequential(*_conv(3 * u, cfg.head_channels))
        self.head = nn.Conv2d(cfg.head_channels, len(HEAD_CHANNELS), 1)
        nn.init.constant_(self.head.bias, 0.0)
        with torch.no_grad():
            self.head.bias[0] = -2.19  # prior 0.1 on the heatmap (focal-loss start)

    def forward(self, features: torch.Tensor, coords: torch.Tensor, mask: torch.Tensor,
                batch_index: torch.Tensor | None = None, batch_size: int = 1) -> torch.Tensor:
        g = self.cfg.grid
        bev = scatter_to_bev(self.pillar_net(features, mask), coords, batch_index, batch_size, g.ny, g.nx)
        x1 = self.block1(bev)
        x2 = self.block2(x1)
        x3 = self.block3(x2)
        up = [self.up1(x1), self.up2(x2), self.up3(x3)]
        h, w = up[0].shape[-2:]
        up = [u[..., :h, :w] for u in up]  # odd sizes: crop the upsampled maps to block 1's
        return self.head(self.neck(torch.cat(up, dim=1)))


def build_model(cfg: PointPillarsConfig, seed: int) -> PointPillars:
    """The network with weights initialised from ``seed`` (torch's default init, seeded locally)."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return PointPillars(cfg)
