"""KITTI object calibration (``calib/*.txt``) and the frame transforms it defines.

Frames (all metric, right-handed):
    velodyne: x forward, y left, z up; origin at the LiDAR.
    rect: rectified camera 0; x right, y down, z forward. Labels live here.
    image: image-2 pixels, u right, v down; P2 maps rect to image 2 (the colour images).

velodyne -> rect: ``R0_rect @ (Tr_velo_to_cam @ [x; 1])``; rect -> image: ``P2 @ [x; 1]``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from robustbench3d.errors import DataFormatError
from robustbench3d.fileio import atomic_write_text, read_data_text

#: Matrices of an object calib file, in file order, with their shapes.
CALIB_KEYS: dict[str, tuple[int, int]] = {
    "P0": (3, 4), "P1": (3, 4), "P2": (3, 4), "P3": (3, 4),
    "R0_rect": (3, 3), "Tr_velo_to_cam": (3, 4), "Tr_imu_to_velo": (3, 4),
}


def _homogeneous(m: np.ndarray) -> np.ndarray:
    """Pad a 3x3 or 3x4 matrix to 4x4 with a 1 in the corner."""
    out = np.eye(4)
    out[: m.shape[0], : m.shape[1]] = m
    return out


def _read_only(m: np.ndarray) -> np.ndarray:
    m.setflags(write=False)
    return m


@dataclass(frozen=True, eq=False)
class Calibration:
    """The seven matrices of a KITTI object calib file (float64).

    Treat the matrices as read-only: the derived transforms are computed once and cached.
    """

    P0: np.ndarray
    P1: np.ndarray
    P2: np.ndarray
    P3: np.ndarray
    R0_rect: np.ndarray
    Tr_velo_to_cam: np.ndarray
    Tr_imu_to_velo: np.ndarray

    def __post_init__(self) -> None:
        for key, shape in CALIB_KEYS.items():
            m = np.asarray(getattr(self, key), dtype=np.float64)
            if m.shape != shape:
                raise ValueError(f"Calibration.{key} has shape {m.shape}, expected {shape}")
            object.__setattr__(self, key, m)

    # ---- derived matrices -------------------------------------------------------------
    @cached_property
    def velo_to_rect(self) -> np.ndarray:
        """4x4 homogeneous transform velodyne -> rect."""
        return _read_only(_homogeneous(self.R0_rect) @ _homogeneous(self.Tr_velo_to_cam))

    @cached_property
    def rect_to_velo(self) -> np.ndarray:
        """4x4 homogeneous transform rect -> velodyne (exact rigid inverse)."""
        m = self.velo_to_rect
        r, t = m[:3, :3], m[:3, 3]
        # R0_rect is a rotation up to rounding in the file; invert the full 3x3 to stay exact.
        r_inv = np.linalg.inv(r)
        out = np.eye(4)
        out[:3, :3] = r_inv
        out[:3, 3] = -r_inv @ t
        return _read_only(out)

    @cached_property
    def velo_to_image(self) -> np.ndarray:
        """3x4 projection velodyne -> image-2 pixels (homogeneous)."""
        return _read_only(self.P2 @ self.velo_to_rect)

    @property
    def intrinsics(self) -> tuple[float, float, float, float]:
        """(f_u, f_v, c_u, c_v) of camera 2 in pixels."""
        return float(self.P2[0, 0]), float(self.P2[1, 1]), float(self.P2[0, 2]), float(self.P2[1, 2])

    # ---- point transforms ------------------------------------------------------------
    def velo_to_rect_points(self, pts: np.ndarray) -> np.ndarray:
        """(N, 3) velodyne points -> (N, 3) rect points."""
        m = self.velo_to_rect
        return np.asarray(pts, dtype=np.float64)[:, :3] @ m[:3, :3].T + m[:3, 3]

    def rect_to_velo_points(self, pts: np.ndarray) -> np.ndarray:
        """(N, 3) rect points -> (N, 3) velodyne points."""
        m = self.rect_to_velo
        return np.asarray(pts, dtype=np.float64)[:, :3] @ m[:3, :3].T + m[:3, 3]

    def rect_to_image(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project (N, 3) rect points with P2.

        Returns (uv, depth): (N, 2) pixel coordinates and (N,) depth (rect z minus camera-2
        offset). Points with depth <= 0 are behind the camera; their uv is meaningless.
        """
        pts = np.asarray(pts, dtype=np.float64)[:, :3]
        h = pts @ self.P2[:, :3].T + self.P2[:, 3]
        depth = h[:, 2]
        safe = np.where(np.abs(depth) > 1e-12, depth, 1e-12)
        return h[:, :2] / safe[:, None], depth

    def image_to_rect(self, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Back-project pixels at rect depth z (m) to (N, 3) rect points (inverse of P2)."""
        fu, fv, cu, cv = self.intrinsics
        bx = -self.P2[0, 3] / fu
        by = -self.P2[1, 3] / fv
        uv = np.asarray(uv, dtype=np.float64)
        z = np.asarray(depth, dtype=np.float64)
        # P2 rows: u*(z + tz) = fu*x + cu*z + P2[0,3]; with tz = P2[2,3] (0 in KITTI).
        zz = z + self.P2[2, 3]
        x = (uv[:, 0] * zz - cu * z) / fu + bx
        y = (uv[:, 1] * zz - cv * z) / fv + by
        return np.stack([x, y, z], axis=1)

    # ---- IO -------------------------------------------------------------------------
    def to_text(self) -> str:
        """Calib-file text in the KITTI layout (``%.12e``, final blank line)."""
        lines = []
        for key in CALIB_KEYS:
            vals = getattr(self, key).reshape(-1)
            lines.append(f"{key}: " + " ".join(f"{v:.12e}" for v in vals))
        return "\n".join(lines) + "\n\n"


def parse_calibration(text: str, path: str | Path = "<string>") -> Calibration:
    """Parse calib-file text; every matrix of :data:`CALIB_KEYS` must be present exactly once."""
    path = Path(path)
    found: dict[str, np.ndarray] = {}
    for lineno, raw in enumerate(text.split("\n"), start=1):
        line = raw.strip()
        if not line:
            continue
        key, sep, rest = line.partition(":")
        key = key.strip()
        if not sep:
            raise DataFormatError(path, "expected 'KEY: v1 v2 ...'", lineno)
        if key not in CALIB_KEYS:
            raise DataFormatError(path, f"unknown calibration matrix; expected one of {', '.join(CALIB_KEYS)}",
                                  lineno, key)
        if key in found:
            raise DataFormatError(path, "matrix given twice", lineno, key)
        shape = CALIB_KEYS[key]
        toks = rest.split()
        if len(toks) != shape[0] * shape[1]:
            raise DataFormatError(path, f"expected {shape[0] * shape[1]} values, got {len(toks)}", lineno, key)
        try:
            vals = np.array([float(t) for t in toks], dtype=np.float64)
        except ValueError:
            bad = next(t for t in toks if not _is_float(t))
            raise DataFormatError(path, f"expected a number, got {bad!r}", lineno, key) from None
        if not np.all(np.isfinite(vals)):
            raise DataFormatError(path, "non-finite value", lineno, key)
        found[key] = vals.reshape(shape)
    missing = [k for k in CALIB_KEYS if k not in found]
    if missing:
        raise DataFormatError(path, f"missing calibration matrix {', '.join(missing)}", field=missing[0])
    return Calibration(**found)


def _is_float(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def read_calibration(path: str | Path) -> Calibration:
    path = Path(path)
    return parse_calibration(read_data_text(path), path)


def write_calibration(path: str | Path, calib: Calibration) -> None:
    atomic_write_text(path, calib.to_text())
