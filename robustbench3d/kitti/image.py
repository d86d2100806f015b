"""Camera images (``image_2/*.png``): 8-bit RGB, (H, W, 3) uint8 arrays."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from robustbench3d.errors import DataFormatError
from robustbench3d.fileio import atomic_write_bytes


def read_image(path: str | Path) -> np.ndarray:
    """Read an image file as (H, W, 3) uint8 RGB."""
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if not path.is_file():
        raise DataFormatError(path, "file not found")
    try:
        with Image.open(path) as im:
            im.load()
            return np.asarray(im.convert("RGB"))
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise DataFormatError(path, f"unreadable image ({exc.__class__.__name__}: {exc})") from None


def image_size(path: str | Path) -> tuple[int, int]:
    """(width, height) from the image header without decoding the pixels."""
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    try:
        with Image.open(path) as im:
            return im.size
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise DataFormatError(path, f"unreadable image ({exc.__class__.__name__}: {exc})") from None


def encode_png(image: np.ndarray, compress_level: int = 6, strategy: int | None = None) -> bytes:
    """PNG bytes of an (H, W, 3) uint8 image (deterministic for identical input).

    ``strategy`` is a zlib strategy (e.g. ``zlib.Z_HUFFMAN_ONLY``); None keeps zlib's default.
    """
    from PIL import Image

    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"image must be (H, W, 3) uint8, got {image.shape} {image.dtype}")
    buf = io.BytesIO()
    options = {} if strategy is None else {"compress_type": strategy}
    Image.fromarray(np.ascontiguousarray(image), "RGB").save(buf, format="PNG", compress_level=compress_level,
                                                           **options)
    return buf.getvalue()


def write_image(path: str | Path, image: np.ndarray, compress_level: int = 6, strategy: int | None = None) -> None:
    """Write an (H, W, 3) uint8 image as PNG, atomically (see :func:`encode_png`)."""
    atomic_write_bytes(path, encode_png(image, compress_level, strategy))
