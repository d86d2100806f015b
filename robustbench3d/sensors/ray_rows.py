"""The recompute of t, u, v with gradients on the (ray, face) pairs a search kept (module docstring of
:mod:`robustbench3d.sensors.raycast`, step 2).

:class:`FaceRows` holds Möller–Trumbore's per-face rows of the faces hit and their hand-written chain rule, in
numpy (compiled for one float dtype by :mod:`robustbench3d.sensors.ray_kernels`: :func:`face_rows`,
:func:`pair_tuv`, :func:`scatter_pair_grads`, the same arithmetic; the numpy code beside each call is the
reference and the path of mixed dtypes); :func:`recompute_tuv` applies it as a torch autograd function
(:class:`_RecomputeTUV`) for :mod:`~robustbench3d.sensors.raycast`'s casts. A car's or a crop's few hundred to few
thousand pairs would otherwise cost torch's per-op overhead.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from robustbench3d.sensors.array_kernels import scatter_rows
from robustbench3d.sensors.mesh import cross_rows, dot3
from robustbench3d.sensors.ray_faces import one_float_dtype
from robustbench3d.sensors.ray_kernels import face_rows, pair_tuv, scatter_pair_grads


@dataclass(frozen=True, eq=False)
class FaceRows:
    """Möller–Trumbore's per-face rows of the faces ``faces`` (U, 3) of float ``vertices`` (numpy, their dtype):
    the edges e1 = a1 - a0, e2 = a2 - a0, T0 = origin - a0, q0 = T0 x e1, and ``rows`` (10 or 17, U),
    component-major: the det vector e2 x e1, the u*det vector e2 x T0, the v*det vector q0, t*det = e2 . q0, and
    with an offset ``axis`` (ray origins origin + h axis) the slopes in h: e2 x axis, q1 = axis x e1, e2 . q1."""

    faces: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    t0: np.ndarray
    q0: np.ndarray
    axis: np.ndarray | None
    q1: np.ndarray | None
    rows: np.ndarray

    @classmethod
    def of(cls, vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray, axis: np.ndarray | None = None
           ) -> FaceRows:
        if one_float_dtype(vertices, origin, axis):  # compiled, the same arithmetic (the numpy code below)
            e1, e2, t0, q0, q1, rows = face_rows(vertices, faces, origin, axis)
            return cls(faces, e1, e2, t0, q0, axis, q1, rows)
        a0 = vertices[faces[:, 0]]
        e1, e2 = vertices[faces[:, 1]] - a0, vertices[faces[:, 2]] - a0
        t0 = origin - a0
        q0 = cross_rows(t0, e1)
        parts = [cross_rows(e2, e1), cross_rows(e2, t0), q0, dot3(e2, q0)[:, None]]
        q1 = None
        if axis is not None:
            ax = np.broadcast_to(axis, e1.shape)
            q1 = cross_rows(ax, e1)
            parts += [cross_rows(e2, ax), q1, dot3(e2, q1)[:, None]]
        return cls(faces, e1, e2, t0, q0, axis, q1, np.concatenate(parts, axis=1).T.copy())

    def tuv(self, slot: np.ndarray, d: np.ndarray, h: np.ndarray | None = None) -> PairTUV:
        """t, u, v of rays (unit directions ``d`` (K, 3), offsets ``h`` (K,) with an axis) against the faces
        ``slot`` (K,) (positions in :attr:`faces`): t*det / det etc., the division guarded by
        ``where(det != 0, det, 1)``."""
        if one_float_dtype(self.rows, d, h):  # compiled, the same arithmetic (the numpy code below)
            return PairTUV(slot, d, h, *pair_tuv(self.rows, slot, d, h))
        g = self.rows.take(slot, axis=1)
        d0, d1, d2 = d.T
        det = g[0] * d0 + g[1] * d1 + g[2] * d2
        un = g[3] * d0 + g[4] * d1 + g[5] * d2
        vn = g[6] * d0 + g[7] * d1 + g[8] * d2
        tn = g[9]
        if h is not None:
            un = un + h * (g[10] * d0 + g[11] * d1 + g[12] * d2)
            vn = vn + h * (g[13] * d0 + g[14] * d1 + g[15] * d2)
            tn = tn + h * g[16]
        ok = det != 0
        inv = 1.0 / np.where(ok, det, det.dtype.type(1))
        return PairTUV(slot, d, h, ok, inv, tn * inv, un * inv, vn * inv)

    def edge_grads(self, pairs: PairTUV, gt: np.ndarray, gu: np.ndarray, gv: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Gradients (U, 3) float64 w.r.t. e1, e2 and T0 of the loss whose gradients w.r.t. the pairs' t, u, v
        are ``gt``, ``gu``, ``gv`` (K,) (the chain rule through :meth:`tuv` and the rows; for a x b the gradient
        is b x g w.r.t. a and g x a w.r.t. b)."""
        inv = pairs.inv
        gdet = np.where(pairs.ok, -(gt * pairs.t + gu * pairs.u + gv * pairs.v) * inv, 0.0)
        # per face the sums of the columns gdet d, gun d, gvn d, gtn (and, with offsets, those but gdet d times h)
        gm = scatter_pair_grads(pairs.slot, gdet, gu * inv, gv * inv, gt * inv, pairs.d, pairs.h, len(self.faces))
        e1, e2, t0 = self.e1, self.e2, self.t0
        g_det, g_ru = gm[:, 0:3], gm[:, 3:6]
        g_q0 = gm[:, 6:9] + gm[:, 9:10] * e2
        g_e1 = cross_rows(g_det, e2) + cross_rows(g_q0, t0)
        g_e2 = cross_rows(e1, g_det) + cross_rows(t0, g_ru) + gm[:, 9:10] * self.q0
        g_t0 = cross_rows(g_ru, e2) + cross_rows(e1, g_q0)
        if pairs.h is not None:
            ax = np.broadcast_to(self.axis, e1.shape)
            g_q1 = gm[:, 13:16] + gm[:, 16:17] * e2
            g_e1 = g_e1 + cross_rows(g_q1, ax)
            g_e2 = g_e2 + cross_rows(ax, gm[:, 10:13]) + gm[:, 16:17] * self.q1
        return g_e1, g_e2, g_t0

    def vertex_grads(self, g_e1: np.ndarray, g_e2: np.ndarray, g_t0: np.ndarray, n_vertices: int) -> np.ndarray:
        """(V, 3) float64: gradients w.r.t. e1 = a1 - a0, e2 = a2 - a0 and T0 = origin - a0 summed per vertex."""
        rows = np.concatenate([-(g_e1 + g_e2 + g_t0), g_e1, g_e2])
        return scatter_rows(np.concatenate([self.faces[:, 0], self.faces[:, 1], self.faces[:, 2]]), rows, n_vertices)


@dataclass(frozen=True, eq=False)
class PairTUV:
    """:meth:`FaceRows.tuv` of K pairs: their face positions ``slot``, directions ``d``, offsets ``h``, det != 0
    ``ok``, 1 / det (1 where det = 0) ``inv``, and t, u, v (K,)."""

    slot: np.ndarray
    d: np.ndarray
    h: np.ndarray | None
    ok: np.ndarray
    inv: np.ndarray
    t: np.ndarray
    u: np.ndarray
    v: np.ndarray


def face_slots(face: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(used, slot) of int64 indices ``face`` (K,) into range(n): the sorted distinct indices and each index's
    position among them (``np.unique(face, return_inverse=True)`` in O(K + n), without a sort)."""
    present = np.zeros(n, np.int64)
    present[face] = 1
    return present.nonzero()[0], (present.cumsum() - 1)[face]


class _RecomputeTUV(torch.autograd.Function):
    """Differentiable t, u, v (K,) of (ray, face) pairs (:class:`FaceRows`, in numpy in the vertices' dtype);
    backward by hand (:meth:`FaceRows.edge_grads`, checked against finite differences)."""

    @staticmethod
    def forward(ctx: object, vertices: torch.Tensor, faces: np.ndarray, face: np.ndarray, d: np.ndarray,
                origin: np.ndarray, h: np.ndarray | None, axis: np.ndarray | None
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        used, slot = face_slots(face, len(faces))
        fr = FaceRows.of(vertices.detach().numpy(), faces[used], origin, axis)
        pairs = fr.tuv(slot, d, h)
        ctx.fr, ctx.pairs, ctx.n_vertices, ctx.dtype = fr, pairs, len(vertices), vertices.dtype
        return torch.from_numpy(pairs.t), torch.from_numpy(pairs.u), torch.from_numpy(pairs.v)

    @staticmethod
    def backward(ctx: object, gt: torch.Tensor, gu: torch.Tensor, gv: torch.Tensor) -> tuple:
        fr, pairs = ctx.fr, ctx.pairs
        grads = fr.edge_grads(pairs, gt.numpy(), gu.numpy(), gv.numpy())
        gvert = torch.from_numpy(fr.vertex_grads(*grads, ctx.n_vertices)).to(ctx.dtype)
        return gvert, None, None, None, None, None, None


def recompute_tuv(vertices: torch.Tensor, faces_t: torch.Tensor, d: torch.Tensor, origin: torch.Tensor,
                  h: torch.Tensor | None, axis: torch.Tensor, ray: torch.Tensor, face: torch.Tensor
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Differentiable t, u, v (P,) of the (ray, face) pairs (which hit): Möller–Trumbore's per-face rows
    (:class:`FaceRows`, :func:`~robustbench3d.sensors.ray_faces._face_tables`' vectors without the sign fold) of the
    faces of the pairs, then per pair (:class:`_RecomputeTUV`; numpy: a crop's or a car's few hundred pairs cost torch's
    per-op overhead)."""
    return _RecomputeTUV.apply(vertices, faces_t.numpy(), face.numpy(), d.index_select(0, ray).numpy(),
                               origin.numpy(), None if h is None else h.index_select(0, ray).numpy(),
                               None if h is None else axis.numpy())
