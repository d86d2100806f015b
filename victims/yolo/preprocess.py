"""Letterboxing in numpy: the 2D stage's pre-processing on the inference path (torch and ONNX).

The image (H, W) is scaled by s = min(W_in/W, H_in/H) to (round(H·s), round(W·s)) and centred on a
canvas of the input size filled with a constant. The resize is PyTorch's antialiased bilinear
interpolation (``F.interpolate(..., mode="bilinear", align_corners=False, antialias=True)``,
itself PIL's triangle filter) written as separable taps: width first, then height, float32 with
fused multiply-adds. :func:`letterbox_image` therefore agrees with the differentiable
:func:`~robustbench3d.victims.yolo.letterbox.letterbox` (training data, attacks) to float32
rounding, bit for bit on CPUs where torch uses FMA. Pixel coordinates map as
x_in = x·(W'/W) + pad_x (and likewise y).

Imports numpy and numba only (no torch): the ONNX victim runs it. The taps run in one compiled pass
(:func:`_resize_last_axis`) with the arithmetic of :func:`_resize_axis_numpy`, kept as its reference
(tests/victims/test_yolo_preprocess_compiled.py compares them bit for bit).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numba import njit


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

    def _affine(self) -> tuple[list[float], list[float]]:
        sx, sy = self.scale
        return [sx, sy, sx, sy], [float(self.pad[0]), float(self.pad[1]), float(self.pad[0]), float(self.pad[1])]

    def to_input(self, boxes: Any) -> Any:
        """xyxy boxes in original pixels -> input pixels (numpy float64, or a torch tensor)."""
        scale, off = self._affine()
        if _is_tensor(boxes):
            return boxes * boxes.new_tensor(scale) + boxes.new_tensor(off)
        return np.asarray(boxes, dtype=np.float64) * np.array(scale) + np.array(off)

    def to_image(self, boxes: Any) -> Any:
        """xyxy boxes in input pixels -> original pixels (numpy float64, or a torch tensor)."""
        scale, off = self._affine()
        if _is_tensor(boxes):
            return (boxes - boxes.new_tensor(off)) / boxes.new_tensor(scale)
        return (np.asarray(boxes, dtype=np.float64) - np.array(off)) / np.array(scale)

    def mirror_x(self, x: Any) -> Any:
        """Input-pixel x of the mirrored image's letterbox -> x in this letterbox (the original image
        mirrored about its vertical centre line, x_img -> W - x_img; numpy or torch)."""
        return (self.resized[0] + 2 * self.pad[0]) - x


def _is_tensor(x: Any) -> bool:
    """True for torch tensors, detected without importing torch."""
    return not isinstance(x, np.ndarray) and hasattr(x, "new_tensor")


def letterbox_geometry(image_size: tuple[int, int], input_size: tuple[int, int]) -> Letterbox:
    """Letterbox of an image of (W, H) pixels into an input of (W_in, H_in)."""
    w, h = image_size
    wi, hi = input_size
    s = min(wi / w, hi / h)
    rw, rh = min(wi, max(1, round(w * s))), min(hi, max(1, round(h * s)))
    return Letterbox((w, h), (rw, rh), ((wi - rw) // 2, (hi - rh) // 2))


def resize_taps(in_size: int, out_size: int) -> tuple[np.ndarray, np.ndarray]:
    """Taps of PyTorch's antialiased bilinear resize along one axis, bit for bit.

    Returns (index (out_size, K) int64, weight (out_size, K) float32): output sample i is
    Σ_k weight[i, k]·input[index[i, k]]; unused taps have weight 0 and index 0. Scale = in/out;
    when downscaling the triangle filter is widened by the scale (antialiasing). The float32 /
    float64 roundings follow the reference CPU kernel, so the weights are identical to torch's.
    """
    f32 = np.float32
    scale = f32(in_size) / f32(out_size)
    support = scale if scale >= 1.0 else f32(1.0)
    invscale = f32(1.0) / scale if scale >= 1.0 else f32(1.0)
    centers = (float(scale) * (np.arange(out_size) + 0.5)).astype(f32)
    xmin = np.maximum((centers.astype(np.float64) - float(support) + 0.5).astype(np.int64), 0)
    xmax = np.minimum((centers.astype(np.float64) + float(support) + 0.5).astype(np.int64), in_size)
    k = int((xmax - xmin).max())
    index = xmin[:, None] + np.arange(k)[None, :]
    valid = index < xmax[:, None]
    arg = (index.astype(f32) - centers[:, None]).astype(f32)
    arg = ((arg.astype(np.float64) + 0.5) * float(invscale)).astype(f32)
    weight = np.where(valid, np.maximum(f32(0.0), f32(1.0) - np.abs(arg)), f32(0.0)).astype(f32)
    total = np.zeros(out_size, dtype=f32)
    for j in range(k):  # sequential float32 sum, as the kernel
        total += weight[:, j]
    safe = np.where(total != 0, total, f32(1.0))
    weight = np.where(total[:, None] != 0, weight / safe[:, None], f32(0.0)).astype(f32)
    return np.where(valid, index, 0), weight


@njit(cache=True, nogil=True)
def _resize_last_axis(x: np.ndarray, index: np.ndarray, weight: np.ndarray) -> np.ndarray:  # pragma: no cover
    """(R, N) float32 rows -> (R, M) with the taps ``index``/``weight`` (M, K): each output the float32
    rounding of the float64 multiply-add of the previous one and the next tap, as :func:`_resize_axis_numpy`."""
    rows, m_out, k_taps = x.shape[0], index.shape[0], index.shape[1]
    out = np.empty((rows, m_out), dtype=np.float32)
    for r in range(rows):
        for m in range(m_out):
            acc = np.float32(np.float64(x[r, index[m, 0]]) * np.float64(weight[m, 0]))
            for k in range(1, k_taps):
                acc = np.float32(np.float64(acc) + np.float64(x[r, index[m, k]]) * np.float64(weight[m, k]))
            out[r, m] = acc
    return out


def _resize_axis(x: np.ndarray, axis: int, out_size: int) -> np.ndarray:
    """Resize float32 ``x`` along ``axis`` (compiled; the bits of :func:`_resize_axis_numpy`)."""
    index, weight = resize_taps(x.shape[axis], out_size)
    moved = np.ascontiguousarray(np.moveaxis(np.asarray(x, dtype=np.float32), axis, -1))
    out = _resize_last_axis(moved.reshape(-1, moved.shape[-1]), np.ascontiguousarray(index, dtype=np.int64),
                            np.ascontiguousarray(weight, dtype=np.float32))
    return np.moveaxis(out.reshape(*moved.shape[:-1], out_size), -1, axis)


def _resize_axis_numpy(x: np.ndarray, axis: int, out_size: int) -> np.ndarray:
    """Resize float32 ``x`` along ``axis``; taps are accumulated in order with one rounding per
    multiply-add (a fused multiply-add, exact here: float32 products are exact in float64)."""
    index, weight = resize_taps(x.shape[axis], out_size)
    moved = np.moveaxis(x, axis, -1)
    acc = (moved[..., index[:, 0]].astype(np.float64) * weight[:, 0]).astype(np.float32)
    for k in range(1, index.shape[1]):
        acc = (acc + moved[..., index[:, k]].astype(np.float64) * weight[:, k]).astype(np.float32)
    return np.moveaxis(acc, -1, axis)


def letterbox_image(image: np.ndarray, input_size: tuple[int, int], fill: float = 0.5) -> tuple[np.ndarray, Letterbox]:
    """(H, W, 3) uint8 RGB -> ((3, H_in, W_in) float32 in [0, 1], geometry)."""
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ValueError(f"expected an (H, W, 3) uint8 image, got {img.dtype} {img.shape}")
    geo = letterbox_geometry((img.shape[1], img.shape[0]), input_size)
    x = np.ascontiguousarray(img.transpose(2, 0, 1), dtype=np.float32) / np.float32(255.0)
    rw, rh = geo.resized
    if (rw, rh) != geo.image_size:
        x = _resize_axis(_resize_axis(x, 2, rw), 1, rh)
    wi, hi = input_size
    px, py = geo.pad
    canvas = np.full((3, hi, wi), fill, dtype=np.float32)
    canvas[:, py:py + rh, px:px + rw] = x
    return canvas, geo
