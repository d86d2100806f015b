"""The F-PN v1 stages run over each frustum's distinct points, bit for bit equal to running them as defined.

Every network of the cascade is a per-point MLP (1x1 convolutions, BatchNorm, ReLU), a max over the points,
and (segmentation) a per-point head on [point feature, max feature, one-hot] or (T-Net, box net) fully
connected layers. The resampling to N points draws with replacement and the object-point gather repeats
masked points, so most frustums hold each point several times; a repeated point gives the same per-point
result and leaves the max unchanged. :class:`DistinctPointStages` therefore runs the per-point layers once
per distinct point (rows compared as bytes), all frustums of a call side by side in one (1, C, L)
convolution, takes each frustum's max over its own columns and scatters the per-point logits back.

Bit-identity with :class:`~robustbench3d.victims.fpointnet.model.TorchFrustumStages` (one intra-op thread,
the runner's setting, tests/victims/test_fpointnet_distinct.py on the shipped weights over val frames) rests on two
measured properties of the CPU convolution kernel, each checked by a test: a point's 1x1-convolution result
does not depend on its column or on the number of columns when that number is a multiple of
:data:`COLUMN_BLOCK` (the kernel treats a ragged last block of columns differently, so the columns are padded),
and a fully connected layer applied to one row (``torch.addmv``) gives the bits of ``nn.Linear`` on a
one-row batch, which is how the reference runs the T-Net and the box net.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from robustbench3d.victims.fpointnet.model import FrustumPointNetV1, TorchFrustumStages

#: Columns of the one-convolution layout are padded to a multiple of this (see the module docstring).
COLUMN_BLOCK = 64


@dataclass(frozen=True)
class DistinctColumns:
    """The distinct rows of B frustums laid side by side: ``columns`` (1, C, L) float32 (L a multiple of
    :data:`COLUMN_BLOCK`, zero padding after the last frustum), frustum b's distinct rows in columns
    ``starts[b]:starts[b + 1]``, and ``inverse`` (B, N): the column of each input row."""

    columns: torch.Tensor
    starts: np.ndarray
    inverse: np.ndarray


def distinct_columns(rows: np.ndarray) -> DistinctColumns:
    """Lay out the distinct rows (compared as bytes) of each frustum of ``rows`` (B, N, C) float32."""
    rows = np.ascontiguousarray(rows, dtype=np.float32)
    b, n, c = rows.shape
    keys = rows.view(np.dtype((np.void, 4 * c))).reshape(b, n)
    firsts, inverse = [], np.empty((b, n), dtype=np.int64)
    starts = np.zeros(b + 1, dtype=np.int64)
    for i in range(b):
        _, first, inv = np.unique(keys[i], return_index=True, return_inverse=True)
        firsts.append(rows[i, first])
        inverse[i] = inv.reshape(-1) + starts[i]
        starts[i + 1] = starts[i] + len(first)
    total = int(starts[-1])
    padded = -(-total // COLUMN_BLOCK) * COLUMN_BLOCK
    columns = np.zeros((c, padded), dtype=np.float32)
    columns[:, :total] = np.concatenate(firsts).T
    return DistinctColumns(torch.from_numpy(columns)[None], starts, inverse)


def segment_max(features: torch.Tensor, starts: np.ndarray) -> torch.Tensor:
    """(B, C) per-frustum max of (1, C, L) ``features`` over each frustum's columns."""
    return torch.stack([features[0, :, starts[i]:starts[i + 1]].amax(dim=1) for i in range(len(starts) - 1)])


def fc_rows(layers: nn.Sequential | nn.Linear, x: torch.Tensor) -> torch.Tensor:
    """Apply fully connected layers to each row of (B, C) ``x`` as to a one-row batch (``addmv`` per row:
    the bits ``nn.Linear`` gives one frustum at a time); BatchNorm (eval) and ReLU act per element."""
    for m in layers if isinstance(layers, nn.Sequential) else (layers,):
        x = torch.stack([torch.addmv(m.bias, m.weight, row) for row in x]) if isinstance(m, nn.Linear) else m(x)
    return x


class DistinctPointStages(TorchFrustumStages):
    """:class:`~robustbench3d.victims.fpointnet.glue.FrustumStages` of an eval-mode float32 network, each
    frustum's per-point layers run once per distinct point (module docstring). A network set to the
    ``"rows"`` layout runs as :class:`TorchFrustumStages` does."""

    def __init__(self, model: FrustumPointNetV1):
        super().__init__(model)
        self.distinct = not (model.seg.rows or model.tnet.rows or model.box.rows)

    def segmentation(self, points: np.ndarray, one_hot: np.ndarray) -> np.ndarray:
        if not self.distinct:
            return super().segmentation(points, one_hot)
        seg = self.model.seg
        lay = distinct_columns(points)
        with torch.inference_mode():
            point_feat = seg.point_mlp(lay.columns)
            glob = segment_max(seg.global_mlp(point_feat), lay.starts)
            glob = torch.cat([glob, torch.from_numpy(np.ascontiguousarray(one_hot, dtype=np.float32))], dim=1)
            owner = np.repeat(np.arange(len(points)), np.diff(lay.starts))
            owner = np.concatenate([owner, np.zeros(point_feat.shape[2] - len(owner), dtype=np.int64)])
            per_column = glob[torch.from_numpy(owner)].T[None]
            logits = seg.classifier(seg.head(torch.cat([point_feat, per_column], dim=1)))[0].T.numpy()
        return logits[lay.inverse]

    def _pointnet(self, net: nn.Module, object_points: np.ndarray, one_hot: np.ndarray) -> np.ndarray:
        """T-Net or box net (per-point ``mlp``, max, ``fc``, ``out``) over distinct object points."""
        lay = distinct_columns(object_points)
        with torch.inference_mode():
            feat = segment_max(net.mlp(lay.columns), lay.starts)
            feat = torch.cat([feat, torch.from_numpy(np.ascontiguousarray(one_hot, dtype=np.float32))], dim=1)
            return fc_rows(net.out, fc_rows(net.fc, feat)).numpy()

    def center_delta(self, object_points: np.ndarray, one_hot: np.ndarray) -> np.ndarray:
        if not self.distinct:
            return super().center_delta(object_points, one_hot)
        return self._pointnet(self.model.tnet, object_points, one_hot)

    def box_output(self, object_points: np.ndarray, one_hot: np.ndarray) -> np.ndarray:
        if not self.distinct:
            return super().box_output(object_points, one_hot)
        return self._pointnet(self.model.box, object_points, one_hot)
