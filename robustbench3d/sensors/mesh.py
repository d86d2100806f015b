"""Mesh primitives the sensor models and the attacks share: the icosphere, per-face normals and row-wise
3-vector arithmetic (:func:`cross_rows`, :func:`dot3`) with numpy's bits.

Units: metres; any right-handed frame (the generator uses object-local or velodyne coordinates).
Winding: a face (a, b, c) is counter-clockwise seen from the side its normal (b - a) x (c - a) points to.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from robustbench3d.sensors.array_kernels import cross_rows_float

_FLOATS = (np.dtype(np.float32), np.dtype(np.float64))

#: The 12 vertices of the base icosahedron (before normalisation), with t the golden ratio.
_T = (1 + 5 ** 0.5) / 2
_ICOSAHEDRON_VERTICES = [[-1, _T, 0], [1, _T, 0], [-1, -_T, 0], [1, -_T, 0], [0, -1, _T], [0, 1, _T], [0, -1, -_T],
                         [0, 1, -_T], [_T, 0, -1], [_T, 0, 1], [-_T, 0, -1], [-_T, 0, 1]]
#: Its 20 faces, wound counter-clockwise seen from outside.
_ICOSAHEDRON_FACES = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
                      [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5],
                      [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]]


@lru_cache(maxsize=4)
def _unit_icosphere(level: int) -> tuple[np.ndarray, np.ndarray]:
    """Read-only (vertices, faces) of the unit icosphere of subdivision ``level``."""
    verts = [np.array(p, dtype=np.float64) / np.linalg.norm(p) for p in _ICOSAHEDRON_VERTICES]
    faces = _ICOSAHEDRON_FACES
    for _ in range(level):
        midpoint: dict[tuple[int, int], int] = {}
        new = []
        for tri in faces:
            ids = []
            for i, j in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])):
                key = (min(i, j), max(i, j))
                if key not in midpoint:
                    p = verts[i] + verts[j]
                    verts.append(p / np.linalg.norm(p))
                    midpoint[key] = len(verts) - 1
                ids.append(midpoint[key])
            ab, bc, ca = ids
            a, b, c = tri
            new += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
        faces = new
    v, f = np.array(verts), np.array(faces, dtype=np.int64)
    v.flags.writeable = f.flags.writeable = False
    return v, f


def icosphere(level: int, radius: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Geodesic sphere centred at the origin: the icosahedron with each face split ``level`` times into four.

    Level L has 10 * 4^L + 2 vertices and 20 * 4^L faces (level 1: 42 / 80, level 2: 162 / 320).
    Vertex order is stable: the 12 icosahedron vertices first, then each subdivision appends the
    midpoints of the edges in the order they are met walking the previous level's faces in order
    (edges (a, b), (b, c), (c, a) of each), every vertex pushed out onto the sphere. Face k of level
    L - 1 becomes faces 4k..4k+3 of level L: its three corner triangles (at a, b, c) and the centre one.
    All faces are wound counter-clockwise seen from outside (right-hand normals point outwards).

    Args:
        level: subdivision level, >= 0.
        radius: sphere radius, m (> 0).
    Returns:
        vertices (V, 3) float64, m, all at distance ``radius`` from the origin (to rounding), and
        faces (F, 3) int64 vertex indices; both fresh arrays the caller may modify.
    """
    if isinstance(level, bool) or not isinstance(level, (int, np.integer)) or level < 0:
        raise ValueError(f"icosphere: field 'level': must be an integer >= 0, got {level!r}")
    if not np.isfinite(radius) or radius <= 0:
        raise ValueError(f"icosphere: field 'radius': must be a finite number > 0, got {radius!r}")
    v, f = _unit_icosphere(int(level))
    return v * radius, f.copy()


def cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise a x b of (N, 3) arrays: np.cross's components (the same bits), without its per-call overhead
    (float32 or float64 arrays: compiled, :func:`robustbench3d.sensors.array_kernels.cross_rows_float`)."""
    if a.dtype in _FLOATS and b.dtype in _FLOATS and a.shape == b.shape and a.ndim == 2 and a.shape[1] == 3:
        return cross_rows_float(a, b)
    return np.stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                     a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]], axis=1)


def dot3(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Dot products over a last axis of 3, summed as ((x0 y0 + x1 y1) + x2 y2): the order numpy's
    ``(x * y).sum(-1)`` adds them in (the same bits), without the cost of a reduction along a short axis."""
    return x[..., 0] * y[..., 0] + x[..., 1] * y[..., 1] + x[..., 2] * y[..., 2]


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3) unit normals (b - a) x (c - a) / |...| of the faces (a, b, c), in the vertices' dtype (the
    renderers pass float64); (0, 0, 0) for a degenerate face. ``vertices`` (V, 3) in any frame, ``faces``
    (F, 3) indices. The sensor models are two-sided (they use |n . d| or flip n towards the viewer), so
    only the direction of the plane matters."""
    v0, v1, v2 = (np.take(vertices, faces[:, k], axis=0) for k in range(3))
    a, b = v1 - v0, v2 - v0
    n = cross_rows(a, b)
    length = np.sqrt(n[:, 0] * n[:, 0] + n[:, 1] * n[:, 1] + n[:, 2] * n[:, 2])  # = np.linalg.norm(n, axis=1)
    return n / np.maximum(length, 1e-12)[:, None]
