"""Camera images (``image_2/*.png``): 8-bit RGB, (H, W, 3) uint8 arrays.

Other pixel formats are converted only where the conversion is exact:

* 16-bit samples keep their high byte, ``v >> 8`` (= floor(v / 256)). Pillow decodes 16-bit
  colour PNGs this way, and grey and colour follow one rule; an 8-bit image widened to 16 bits
  the usual way (``v * 257``) comes back unchanged.
* grey (1-bit, 8-bit, 16-bit) becomes RGB by repeating the channel; a palette is looked up.
* an alpha channel (RGBA, LA, PA, a palette or grey transparency) is dropped when every pixel is
  opaque; a camera image with transparent pixels has no defined colour there and is refused.

Anything else (CMYK, YCbCr, LAB, HSV, float, 32-bit integer beyond 16 bits) is refused with a
:class:`~robustbench3d.errors.DataFormatError` naming the file.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from robustbench3d.errors import DataFormatError
from robustbench3d.fileio import atomic_write_bytes, data_file_errors, read_data_bytes

if TYPE_CHECKING:
    from PIL.Image import Image as PILImage

    from robustbench3d.kitti.calib import Calibration

#: Modes whose pixels are exact 8-bit RGB after Pillow's own conversion (repeat grey, look up palette).
_DIRECT = ("RGB", "L", "1", "P")
#: Modes with an alpha channel: converted as their colour part once every pixel is opaque.
_ALPHA = ("RGBA", "LA", "PA", "La", "RGBa")


def read_image(path: str | Path) -> np.ndarray:
    """Read an image file as (H, W, 3) uint8 RGB (conversions as in the module doc)."""
    path = Path(path)
    return decode_image(read_data_bytes(path), path)


def decode_image(data: bytes, path: str | Path) -> np.ndarray:
    """Decode an image file's bytes as (H, W, 3) uint8 RGB (conversions as in the module doc); ``path``
    names the file in errors."""
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    try:
        im = Image.open(io.BytesIO(data))
        im.load()
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise DataFormatError(path, f"unreadable image ({exc.__class__.__name__}: {exc})") from None
    with im:
        return _to_rgb(im, path)


def read_image_size(path: str | Path) -> tuple[int, int]:
    """(width, height) of an image file from its header alone (the pixels are not decoded)."""
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    with data_file_errors(path):
        f = open(path, "rb")  # noqa: SIM115 - closed below, after Pillow has read the header
    with f:
        try:
            with Image.open(f) as im:
                return int(im.size[0]), int(im.size[1])
        except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
            raise DataFormatError(path, f"unreadable image ({exc.__class__.__name__}: {exc})") from None


def _to_rgb(im: PILImage, path: Path) -> np.ndarray:
    mode = im.mode
    if mode.startswith("I"):  # I;16, I;16B, I;16L, I;16N (16-bit grey) and I (32-bit signed)
        values = np.asarray(im)
        if mode == "I" and values.size and (values.min() < 0 or values.max() > 65535):
            raise DataFormatError(path, f"32-bit integer pixels outside 0..65535 ({values.min()}..{values.max()}) "
                                  "have no exact 8-bit value")
        grey = (values.astype(np.uint32) >> 8).astype(np.uint8)
        return np.repeat(grey[:, :, None], 3, axis=2)
    if mode in ("RGB", "L", "P") and "transparency" in im.info:  # a transparent colour key or palette entries
        im = im.convert("RGBA")
    if im.mode in _ALPHA:
        alpha = np.asarray(im.getchannel("A"))
        if (alpha != 255).any():
            v, u = np.argwhere(alpha != 255)[0]
            raise DataFormatError(path, f"mode {mode} image has transparent pixels (first at x={u}, y={v}, "
                                  f"alpha {alpha[v, u]}); a camera image must be opaque")
        return np.asarray(im.convert("RGB"))
    if mode in _DIRECT:
        return np.asarray(im if mode == "RGB" else im.convert("RGB"))
    raise DataFormatError(path, f"pixel mode {mode} has no exact 8-bit RGB equivalent; save the image as 8-bit RGB")


def check_image_fits_calibration(size: tuple[int, int], calib: Calibration, path: str | Path,
                                 calib_path: str | Path | None = None) -> None:
    """Refuse an image that cannot belong to ``calib``: P2's principal point (c_u, c_v) must lie in
    the middle half of the (width, height) ``size`` (W/4 <= c_u <= 3W/4, H/4 <= c_v <= 3H/4).

    KITTI's images differ slightly in size (1224x370 ... 1242x375) with c_u/W and c_v/H near 0.47;
    a scaled, heavily cropped or foreign image (or a wrong calib file) lands outside the band.
    """
    w, h = size
    _, _, cu, cv = calib.intrinsics
    if not (w / 4 <= cu <= 3 * w / 4 and h / 4 <= cv <= 3 * h / 4):
        which = f" ({Path(calib_path).name})" if calib_path is not None else ""
        raise DataFormatError(path, f"image {w}x{h} does not match its calibration{which}: the principal point "
                              f"(c_u, c_v) = ({cu:.1f}, {cv:.1f}) of P2 must lie in the middle half of the image "
                              f"(c_u in [{w / 4:.1f}, {3 * w / 4:.1f}], c_v in [{h / 4:.1f}, {3 * h / 4:.1f}]); "
                              "wrong image size or wrong calibration file", field="size")


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
