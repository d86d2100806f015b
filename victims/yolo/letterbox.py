"""Letterboxing camera images to the network input size, differentiably.

The image (H, W) is scaled by s = min(W_in/W, H_in/H) to (round(H·s), round(W·s)) with
antialiased bilinear interpolation and centred on a canvas of the input size filled with a
constant. Pixel coordinates map as x_in = x·(W'/W) + pad_x (and likewise y), exactly matching
the interpolation grid; gradients flow from the network input back to the image.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F


@dataclass(frozen=True)
class Letterbox:
    """Geometry of one letterbox: original (W, H), resized (W', H'), padding (left, top), px."""

    image_size: tuple[int, int]
    resized: tuple[int, int]
    pad: tuple[int, int]

    @property
    def scale(self) -> tuple[float, float]:
        """(sx, sy) = resized / original."""
        return self.resized[0] / self.image_size[0], self.resized[1] / self.image_size[1]

    def to_input(self, boxes: np.ndarray | torch.Tensor) -> np.ndarray | torch.Tensor:
        """xyxy boxes in original pixels -> input pixels."""
        sx, sy = self.scale
        scale = [sx, sy, sx, sy]
        off = [self.pad[0], self.pad[1], self.pad[0], self.pad[1]]
        if isinstance(boxes, torch.Tensor):
            return boxes * boxes.new_tensor(scale) + boxes.new_tensor(off)
        return np.asarray(boxes, dtype=np.float64) * np.array(scale) + np.array(off)

    def to_image(self, boxes: np.ndarray | torch.Tensor) -> np.ndarray | torch.Tensor:
        """xyxy boxes in input pixels -> original pixels."""
        sx, sy = self.scale
        scale = [sx, sy, sx, sy]
        off = [self.pad[0], self.pad[1], self.pad[0], self.pad[1]]
        if isinstance(boxes, torch.Tensor):
            return (boxes - boxes.new_tensor(off)) / boxes.new_tensor(scale)
        return (np.asarray(boxes, dtype=np.float64) - np.array(off)) / np.array(scale)


def letterbox_geometry(image_size: tuple[int, int], input_size: tuple[int, int]) -> Letterbox:
    """Letterbox of an image of (W, H) pixels into an input of (W_in, H_in)."""
    w, h = image_size
    wi, hi = input_size
    s = min(wi / w, hi / h)
    rw, rh = min(wi, max(1, round(w * s))), min(hi, max(1, round(h * s)))
    return Letterbox((w, h), (rw, rh), ((wi - rw) // 2, (hi - rh) // 2))


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
