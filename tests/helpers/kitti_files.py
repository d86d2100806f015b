"""KITTI files of a dataset read with plain Python and numpy, independently of the library."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def label_rows(dataset: Path, frame_id: str) -> list[list[str]]:
    """The label file's rows as tokens."""
    text = (dataset / "training" / "label_2" / f"{frame_id}.txt").read_text()
    return [line.split() for line in text.splitlines() if line.strip()]


def calib_p2(dataset: Path, frame_id: str) -> np.ndarray:
    """The calibration file's 3x4 ``P2``."""
    for line in (dataset / "training" / "calib" / f"{frame_id}.txt").read_text().splitlines():
        if line.startswith("P2:"):
            return np.array([float(v) for v in line.split()[1:]]).reshape(3, 4)
    raise AssertionError("no P2")


def image_size(dataset: Path, frame_id: str) -> tuple[int, int]:
    """(width, height) of the frame's PNG, from its IHDR chunk."""
    head = (dataset / "training" / "image_2" / f"{frame_id}.png").read_bytes()[16:24]
    return int.from_bytes(head[:4], "big"), int.from_bytes(head[4:], "big")
