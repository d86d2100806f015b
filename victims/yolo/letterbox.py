"""Letterboxing camera images to the network input size, differentiably.

The image (H, W) is scaled by s = min(W_in/W, H_in/H) to (round(H·s), round(W·s)) with
antialiased bilinear interpolation and centred on a canvas of the input size filled with a
constant. Pixel coordinates map as x_in = x·(W'/W) + pad_x (and likewise y), exactly matching
the interpolation grid; gradients flow from the network input back to the image.

This is the differentiable twin (training data, attacks) of the numpy
:func:`~robustbench3d.victims.yolo.preprocess.letterbox_image` used on the inference path; the
geometry (:class:`Letterbox`, :func:`letterbox_geometry`) is shared.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from robustbench3d.victims.yolo.preprocess import Letterbox, letterbox_geometry


def letterbox(images: torch.Tensor, input_size: tuple[int, int], fill: float = 0.5) -> tuple[torch.Tensor, Letterbox]:
    """(B, 3, H, W) float images in [0, 1] -> ((B, 3, H_in, W_in), geometry)."""
    x, geo = resize_for_letterbox(images, input_size)
    return letterbox_window(x, geo, ((0, input_size[1]), (0, input_size[0])), fill), geo


def resize_for_letterbox(images: torch.Tensor, input_size: tuple[int, int]) -> tuple[torch.Tensor, Letterbox]:
    """(B, 3, H, W) images resized to the letterbox's (B, 3, H', W') (unchanged if the size is kept), geometry."""
    geo = letterbox_geometry((images.shape[-1], images.shape[-2]), input_size)
    rw, rh = geo.resized
    if (rw, rh) == geo.image_size:
        return images, geo
    return F.interpolate(images, size=(rh, rw), mode="bilinear", align_corners=False, antialias=True), geo


def letterbox_window(resized: torch.Tensor, geo: Letterbox, window: tuple[tuple[int, int], tuple[int, int]],
                     fill: float = 0.5) -> torch.Tensor:
    """The rows [r0, r1) and columns [c0, c1) (``window``, input pixels) of the letterboxed input made from the
    resized images of :func:`resize_for_letterbox`: the part of them inside the window, padded with ``fill``."""
    (r0, r1), (c0, c1) = window
    (px, py), (rw, rh) = geo.pad, geo.resized
    top, left = min(max(0, py - r0), r1 - r0), min(max(0, px - c0), c1 - c0)
    y0, y1 = min(max(r0 - py, 0), rh), min(max(r1 - py, 0), rh)
    x0, x1 = min(max(c0 - px, 0), rw), min(max(c1 - px, 0), rw)
    part = resized if (y0, y1, x0, x1) == (0, rh, 0, rw) else resized[..., y0:y1, x0:x1]
    return F.pad(part, (left, (c1 - c0) - left - (x1 - x0), top, (r1 - r0) - top - (y1 - y0)), value=fill)


def image_to_tensor(image: np.ndarray) -> torch.Tensor:
    """(H, W, 3) uint8 RGB -> (1, 3, H, W) float32 in [0, 1]."""
    return torch.from_numpy(np.array(image, dtype=np.uint8, copy=True)).permute(2, 0, 1)[None].float() / 255.0


__all__ = ["Letterbox", "image_to_tensor", "letterbox", "letterbox_geometry", "letterbox_window",
           "resize_for_letterbox"]
