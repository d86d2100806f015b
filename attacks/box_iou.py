"""Differentiable bird's-eye-view IoU of two rotated boxes (torch), for the box term of the LiDAR loss.

A box is ``(x, z, l, w, ry)`` in the rect frame (m, rad), its footprint the rectangle of
:func:`robustbench3d.eval.iou.footprint_corners` (the evaluator's, which is the reference the tests compare
against). The intersection is box A's footprint clipped by each edge of box B's (Sutherland-Hodgman; both
are convex and counter-clockwise), its area the shoelace sum. Coordinates are taken relative to B's centre
so precision does not depend on the distance from the sensor. Every division is guarded, so the value and
its gradient are finite for any finite boxes (zero-size, coincident or touching ones included); where the
clipped polygon changes its vertex set the IoU is continuous and the gradient one-sided.
"""

from __future__ import annotations

import torch


def footprint_torch(x: torch.Tensor, z: torch.Tensor, length: torch.Tensor, width: torch.Tensor,
                    ry: torch.Tensor) -> list[torch.Tensor]:
    """The four (2,) footprint corners (x, z), counter-clockwise, as the evaluator orders them."""
    c, s = torch.cos(ry), torch.sin(ry)
    hl, hw = length.abs() / 2, width.abs() / 2
    return [torch.stack([x + c * u + s * v, z - s * u + c * v])
            for u, v in ((hl, hw), (-hl, hw), (-hl, -hw), (hl, -hw))]


def _cross(o: torch.Tensor, a: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """z of (a - o) x (p - o): > 0 when p lies left of the directed edge o -> a."""
    return (a[0] - o[0]) * (p[1] - o[1]) - (a[1] - o[1]) * (p[0] - o[0])


def _clip(poly: list[torch.Tensor], a: torch.Tensor, b: torch.Tensor) -> list[torch.Tensor]:
    """The part of convex ``poly`` on the left of (or on) the directed line a -> b."""
    out: list[torch.Tensor] = []
    n = len(poly)
    for i in range(n):
        p, q = poly[i], poly[(i + 1) % n]
        dp, dq = _cross(a, b, p), _cross(a, b, q)
        if dp >= 0:
            out.append(p)
        if (dp >= 0) != (dq >= 0):
            den = dp - dq  # nonzero: dp and dq straddle 0 (an absolute floor would break boxes of ~1e-6 m)
            den = torch.where(den != 0, den, torch.ones_like(den))
            out.append(p + (q - p) * (dp / den))
    return out


def _area(poly: list[torch.Tensor]) -> torch.Tensor:
    total = poly[0].new_zeros(())
    for i in range(len(poly)):
        p, q = poly[i], poly[(i + 1) % len(poly)]
        total = total + p[0] * q[1] - p[1] * q[0]
    return total / 2


def bev_iou_torch(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """BEV IoU (scalar) of boxes ``a`` and ``b``, each (5,) ``x, z, l, w, ry`` (rect frame, m, rad);
    differentiable in both (module doc)."""
    if a.shape != (5,) or b.shape != (5,):
        raise ValueError(f"boxes must be (5,) x, z, l, w, ry; got {tuple(a.shape)} and {tuple(b.shape)}")
    b = b.to(a.dtype)
    origin = b[:2]
    pa = footprint_torch(a[0] - origin[0], a[1] - origin[1], a[2], a[3], a[4])
    pb = footprint_torch(b[0] - origin[0], b[1] - origin[1], b[2], b[3], b[4])
    poly = pa
    for i in range(4):
        if len(poly) < 3:
            break
        poly = _clip(poly, pb[i], pb[(i + 1) % 4])
    # the clipped polygon's area is >= 0; on slivers (aspect 1e9) its rounding (~eps x long side^2) can dip below
    inter = _area(poly).clamp_min(0.0) if len(poly) >= 3 else a.new_zeros(())
    union = (a[2] * a[3]).abs() + (b[2] * b[3]).abs() - inter
    ok = union > 0
    return torch.where(ok, inter / torch.where(ok, union, torch.ones_like(union)), torch.zeros_like(union))
