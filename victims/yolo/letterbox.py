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
    geo = letterbox_geometry((images.shape[-1], images.shape[-2]), input_size)
    rw, rh = geo.resized
    x = images
    if (rw, rh) != geo.image_size:
        x = F.interpolate(images, size=(rh, rw), mode="bilinear", align_corners=False, antialias=True)
    wi, hi = input_size
    px, py = geo.pad
    x = F.pad(x, (px, wi - rw - px, py, hi - rh - py), value=fill)
    return x, geo


def image_to_tensor(image: np.ndarray) -> torch.Tensor:
    """(H, W, 3) uint8 RGB -> (1, 3, H, W) float32 in [0, 1]."""
    return torch.from_numpy(np.array(image, dtype=np.uint8, copy=True)).permute(2, 0, 1)[None].float() / 255.0


__all__ = ["Letterbox", "image_to_tensor", "letterbox", "letterbox_geometry"]
