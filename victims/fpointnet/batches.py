"""Training batches of F-PN v1 drawn by tensor indexing on the training device.

:class:`TensorFrustums` holds a :class:`~robustbench3d.victims.fpointnet.data.FrustumSet` once,
already rotated to the frustum frame, with its fixed targets (size class and residual, one-hot,
centre, heading), as tensors on the training device. :meth:`TensorFrustums.batch` then draws what
:func:`~robustbench3d.victims.fpointnet.data.make_item` draws — N points uniformly with
replacement, the flip (p = 0.5: x, centre x and heading π − h) and the shift — with a
``torch.Generator`` on that device, in a handful of tensor operations for the whole batch. Same
distribution as ``make_item``, other random streams.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from robustbench3d.victims.fpointnet.box_coding import HEADING_BIN_WIDTH, NUM_HEADING_BIN, one_hot, size_to_class
from robustbench3d.victims.fpointnet.data import FrustumSet, ShiftMode
from robustbench3d.victims.fpointnet.losses import FPointNetTargets


def angle_to_class_torch(angle: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Torch twin of :func:`~robustbench3d.victims.fpointnet.box_coding.angle_to_class` (float64)."""
    two_pi = 2 * np.pi
    a = torch.remainder(angle.double(), two_pi)
    shifted = torch.remainder(a + HEADING_BIN_WIDTH / 2, two_pi)
    cls = torch.clamp(torch.floor(shifted / HEADING_BIN_WIDTH), max=NUM_HEADING_BIN - 1).long()
    return cls, shifted - (cls.double() * HEADING_BIN_WIDTH + HEADING_BIN_WIDTH / 2)


@dataclass
class TensorFrustums:
    """F frustums on one device: points (T, 4) float32 in each frustum's frame, seg (T,) uint8,
    start (F,) and count (F,) int64, center (F, 3) float64 (frustum frame), heading (F,) float64
    (ry − rot), size_class (F,) int64, size_residual (F, 3) float32, one_hot (F, 3) float32."""

    points: torch.Tensor
    seg: torch.Tensor
    start: torch.Tensor
    count: torch.Tensor
    center: torch.Tensor
    heading: torch.Tensor
    size_class: torch.Tensor
    size_residual: torch.Tensor
    one_hot: torch.Tensor

    def __len__(self) -> int:
        return len(self.start)

    @classmethod
    def from_set(cls, fs: FrustumSet, device: torch.device | str = "cpu") -> TensorFrustums:
        counts = np.diff(fs.offsets)
        if len(counts) and counts.min() < 1:
            raise ValueError("cannot train on an empty frustum")
        rot = np.repeat(fs.rot_angle, counts)
        c, s = np.cos(rot), np.sin(rot)
        x, z = fs.points[:, 0].astype(np.float64), fs.points[:, 2].astype(np.float64)
        pts = np.stack([c * x - s * z, fs.points[:, 1], s * x + c * z, fs.points[:, 3]], axis=1).astype(np.float32)
        cr, sr = np.cos(fs.rot_angle), np.sin(fs.rot_angle)
        cx, cz = fs.center[:, 0], fs.center[:, 2]
        center = np.stack([cr * cx - sr * cz, fs.center[:, 1], sr * cx + cr * cz], axis=1)
        size_cls = np.zeros(len(fs), np.int64)
        size_res = np.zeros((len(fs), 3))
        for t in np.unique(fs.types):
            sel = fs.types == t
            size_cls[sel], size_res[sel] = size_to_class(fs.size_lwh[sel], [str(t)] * int(sel.sum()))
        dev = torch.device(device)

        def put(a: np.ndarray, dtype: torch.dtype) -> torch.Tensor:
            return torch.as_tensor(np.ascontiguousarray(a)).to(device=dev, dtype=dtype)

        return cls(points=put(pts, torch.float32), seg=put(fs.seg, torch.uint8),
                   start=put(fs.offsets[:-1], torch.int64), count=put(counts, torch.int64),
                   center=put(center, torch.float64), heading=put(fs.ry - fs.rot_angle, torch.float64),
                   size_class=put(size_cls, torch.int64), size_residual=put(size_res, torch.float32),
                   one_hot=put(one_hot(fs.types) if len(fs) else np.zeros((0, 3)), torch.float32))

    def batch(self, indices: np.ndarray | torch.Tensor, num_points: int, generator: torch.Generator,
              flip: bool = False, shift: ShiftMode = "off") -> tuple[torch.Tensor, torch.Tensor, FPointNetTargets]:
        """(points (B, N, 4), one_hot (B, 3), targets) of frustums ``indices``, augmentations drawn
        from ``generator`` (on this set's device)."""
        dev = self.points.device
        i = torch.as_tensor(np.asarray(indices), dtype=torch.int64).to(dev)
        b = len(i)
        u = torch.rand((b, num_points), generator=generator, device=dev, dtype=torch.float64)
        count = self.count[i]
        local = torch.minimum((u * count[:, None]).long(), count[:, None] - 1)
        idx = self.start[i][:, None] + local
        points = self.points[idx]  # (B, N, 4)
        seg = self.seg[idx].long()
        center = self.center[i].clone()
        heading = self.heading[i].clone()
        if flip:
            f = torch.rand(b, generator=generator, device=dev, dtype=torch.float64) > 0.5
            sign = torch.where(f, -1.0, 1.0)
            points = torch.cat([points[..., :1] * sign[:, None, None].float(), points[..., 1:]], dim=-1)
            center[:, 0] = center[:, 0] * sign
            heading = torch.where(f, np.pi - heading, heading)
        if shift != "off":
            d = torch.sqrt(center[:, 0] ** 2 + center[:, 1] ** 2)
            n = torch.randn(b, generator=generator, device=dev, dtype=torch.float64)
            lo, hi = (0.8 * d, 1.2 * d) if shift == "faithful" else (-0.2 * d, 0.2 * d)
            delta = torch.minimum(torch.maximum(n * d * 0.05, lo), hi)
            points = torch.cat([points[..., :2], points[..., 2:3] + delta[:, None, None].float(), points[..., 3:]],
                               dim=-1)
            center[:, 2] = center[:, 2] + delta
        hcls, hres = angle_to_class_torch(heading)
        targets = FPointNetTargets(seg=seg, center=center.float(), heading_class=hcls, heading_residual=hres.float(),
                                   size_class=self.size_class[i], size_residual=self.size_residual[i])
        return points, self.one_hot[i], targets
