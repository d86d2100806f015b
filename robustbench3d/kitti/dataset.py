"""Lazy access to a dataset in the KITTI object layout (real KITTI or the embedded generator's output).

    ROOT/ImageSets/{train,val,...}.txt
    ROOT/training/{image_2/NNNNNN.png, velodyne/NNNNNN.bin, calib/NNNNNN.txt, label_2/NNNNNN.txt}
"""

from __future__ import annotations

import os
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from robustbench3d.errors import DataFormatError
from robustbench3d.fileio import read_data_bytes
from robustbench3d.kitti.calib import Calibration, read_calibration
from robustbench3d.kitti.image import check_image_fits_calibration, decode_image, read_image, read_image_size
from robustbench3d.kitti.labels import Labels, read_labels
from robustbench3d.kitti.splits import read_split
from robustbench3d.kitti.velodyne import read_scan

SUBDIRS = {"image": ("image_2", ".png"), "scan": ("velodyne", ".bin"),
           "calib": ("calib", ".txt"), "labels": ("label_2", ".txt")}


@dataclass(frozen=True, eq=False)
class Frame:
    """One KITTI frame.

    Attributes:
        frame_id: 6-digit id.
        image: (H, W, 3) uint8 RGB of camera 2.
        scan: (N, 4) float32 x, y, z (velodyne frame, m), reflectance.
        calib: the frame's calibration.
        labels: ground-truth objects (rect frame), or None where the split has no labels.
    """

    frame_id: str
    image: np.ndarray
    scan: np.ndarray
    calib: Calibration
    labels: Labels | None

    @property
    def image_size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return int(self.image.shape[1]), int(self.image.shape[0])


class DeferredImageError(RuntimeError):
    """Making the image of a :class:`LazyImageFrame` failed (the cause is chained)."""


@dataclass(frozen=True, eq=False)
class MadeOnce:
    """A ``make_image`` callable run at most once, its image kept (what a :class:`LazyImageFrame` holds):
    nothing but the callable and its image."""

    make: Callable[[], np.ndarray]
    made: list[np.ndarray] = field(default_factory=list, repr=False)

    def __call__(self) -> np.ndarray:
        if not self.made:
            self.made.append(self.make())
        return self.made[0]


@dataclass(frozen=True, eq=False)
class LazyImageFrame(Frame):
    """A :class:`Frame` whose image is made on first access of ``image`` and kept (e.g. an attacked
    frame: its camera render is skipped when no consumer reads the image, as a victim given
    ground-truth 2D boxes does).

    Constructed as ``LazyImageFrame(frame_id, scan, calib, labels, size, make_image)``; ``image_size``
    is ``size`` and never makes the image. ``make_image`` is wrapped (:class:`MadeOnce`) so that it runs
    at most once for this frame and every copy of it (``dataclasses.replace`` keeps the laziness; it
    cannot set ``image``); its errors are raised as :class:`DeferredImageError`.

    A victim is handed such frames (with ``labels=None``) and can reach everything ``make_image`` holds
    (a closure's cells, an object's attributes): it must hold data the victim may see (arrays, a
    calibration, numbers), never labels, file paths or harness objects -- e.g. a frozen dataclass with
    ``__call__`` (:class:`~robustbench3d.attacks.roof.CameraRender`, :class:`EncodedImage`), not a closure.

    Attributes:
        size: (width, height) of the image in pixels.
        make_image: returns the (H, W, 3) uint8 image.
    """

    image: np.ndarray = field(init=False, repr=False)
    size: tuple[int, int]
    make_image: Callable[[], np.ndarray] = field(repr=False)

    def __post_init__(self) -> None:
        if not isinstance(self.make_image, MadeOnce):  # copies share the wrapper, hence one image
            object.__setattr__(self, "make_image", MadeOnce(self.make_image))

    def __getattr__(self, name: str) -> np.ndarray:  # only called while ``image`` is not yet set
        if name != "image":
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
        try:
            image = self.make_image()
        except Exception as exc:
            raise DeferredImageError(f"frame {self.frame_id}: making its image failed: "
                                     f"{type(exc).__name__}: {exc}") from exc
        if (image.ndim != 3 or image.shape[2] != 3
                or (int(image.shape[1]), int(image.shape[0])) != tuple(self.size)):
            raise DeferredImageError(f"frame {self.frame_id}: made an image of shape {image.shape}, "
                                     f"expected (H, W, 3) for (W, H) = {tuple(self.size)}")
        object.__setattr__(self, "image", image)
        return image

    @property
    def image_size(self) -> tuple[int, int]:
        """(width, height) in pixels, without making the image."""
        return int(self.size[0]), int(self.size[1])


#: The file each :class:`EncodedImage` was read from, to name it in errors; kept here rather than in the
#: object so that a frame hands a victim no path.
_IMAGE_FILES: weakref.WeakKeyDictionary[EncodedImage, Path] = weakref.WeakKeyDictionary()


@dataclass(frozen=True, eq=False)
class EncodedImage:
    """An image file's bytes, decoded on the first call and kept (the ``make_image`` of a
    :class:`FileImageFrame`): the bytes, the header's (width, height) and the decoded image, no path.

    A file that cannot be decoded, or whose pixels are not the header's size, raises
    :class:`DataFormatError` naming the file (:meth:`KittiDataset.lazy_frame` notes it)."""

    data: bytes
    size: tuple[int, int]
    decoded: list[np.ndarray] = field(default_factory=list, repr=False)

    def __call__(self) -> np.ndarray:
        if not self.decoded:
            path = _IMAGE_FILES.get(self, Path("<image bytes>"))
            image = decode_image(self.data, path)
            if (int(image.shape[1]), int(image.shape[0])) != tuple(self.size):
                raise DataFormatError(path, f"decoded size {image.shape[1]}x{image.shape[0]} differs from "
                                      f"the header's {self.size[0]}x{self.size[1]}")
            self.decoded.append(image)
        return self.decoded[0]


@dataclass(frozen=True, eq=False)
class FileImageFrame(LazyImageFrame):
    """A :class:`LazyImageFrame` whose image is a dataset file decoded on first access
    (:meth:`KittiDataset.lazy_frame`). Its size comes from the file's header; a file that cannot be
    decoded raises :class:`DataFormatError` naming it, as an eager read does (bad input, not a
    deferred failure). ``make_image`` is an :class:`EncodedImage` (the file's bytes, read with the
    header), which decodes once for the frame and its copies; it holds no path, so nothing but the
    frame's data is reachable through it (a victim must not find the dataset's paths there)."""

    def __post_init__(self) -> None:
        pass

    def __getattr__(self, name: str) -> np.ndarray:  # only called while ``image`` is not yet set
        if name != "image":
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
        image = self.make_image()
        object.__setattr__(self, "image", image)
        return image


class KittiDataset:
    """Frames of ``root/<subset>`` listed by ``root/ImageSets/<split>.txt`` (or every frame found).

    Nothing but the split list is read at construction; each accessor reads only its own file.
    """

    def __init__(self, root: str | Path, split: str | None = "val", subset: str = "training"):
        self.root = Path(root)
        self.split = split
        self.subset = subset
        self.dir = self.root / subset
        if not self.dir.is_dir():
            raise DataFormatError(self.dir, "not a directory; expected the KITTI layout ROOT/training/...")

    @cached_property
    def frame_ids(self) -> list[str]:
        if self.split is not None:
            return read_split(self.root / "ImageSets" / f"{self.split}.txt")
        labels_dir = self.dir / SUBDIRS["calib"][0]
        return sorted(p.stem for p in labels_dir.glob("*.txt"))

    def __len__(self) -> int:
        return len(self.frame_ids)

    def path(self, kind: str, frame_id: str) -> Path:
        """Path of one file: kind is 'image', 'scan', 'calib' or 'labels'."""
        sub, ext = SUBDIRS[kind]
        return self.dir / sub / f"{frame_id}{ext}"

    def image(self, frame_id: str) -> np.ndarray:
        """The frame's image, refused when its size does not fit the frame's calibration
        (see :func:`~robustbench3d.kitti.image.check_image_fits_calibration`)."""
        return self._image(frame_id)[0]

    def _image(self, frame_id: str) -> tuple[np.ndarray, Calibration]:
        """The frame's image, checked against its calibration, and the calibration."""
        path = self.path("image", frame_id)
        image = read_image(path)
        calib = self.calib(frame_id)
        check_image_fits_calibration((image.shape[1], image.shape[0]), calib, path, self.path("calib", frame_id))
        return image, calib

    def image_size(self, frame_id: str) -> tuple[int, int]:
        """(width, height) of the frame's image from its file header (no pixel is decoded)."""
        return read_image_size(self.path("image", frame_id))

    def lazy_frame(self, frame_id: str, labels: Labels | None) -> FileImageFrame:
        """The frame with ``labels``: scan, calibration and the image file's bytes read now, the image
        decoded on first access (a consumer that never reads it, like a victim given ground-truth 2D
        boxes, never pays for it). The header's size is checked against the calibration now, as
        :meth:`image` does."""
        path, calib = self.path("image", frame_id), self.calib(frame_id)
        size = read_image_size(path)
        check_image_fits_calibration(size, calib, path, self.path("calib", frame_id))
        encoded = EncodedImage(read_data_bytes(path), size)
        _IMAGE_FILES[encoded] = path
        return FileImageFrame(frame_id, self.scan(frame_id), calib, labels, size, encoded)

    def scan(self, frame_id: str) -> np.ndarray:
        return read_scan(self.path("scan", frame_id))

    def calib(self, frame_id: str) -> Calibration:
        return read_calibration(self.path("calib", frame_id))

    def labels(self, frame_id: str) -> Labels | None:
        """The frame's ground truth; None only when there is no label file (a symlink loop, a
        directory or an unreadable file is an error, not a frame without labels)."""
        path = self.path("labels", frame_id)
        try:
            os.lstat(path)
        except FileNotFoundError:
            return None
        except OSError:
            pass  # read_labels reports it, naming the file
        return read_labels(path, scored=False)

    def frame(self, frame_id: str) -> Frame:
        image, calib = self._image(frame_id)
        return Frame(frame_id, image, self.scan(frame_id), calib, self.labels(frame_id))

    def __getitem__(self, index: int) -> Frame:
        return self.frame(self.frame_ids[index])

    def __iter__(self):
        for fid in self.frame_ids:
            yield self.frame(fid)
