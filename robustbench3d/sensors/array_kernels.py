"""Compiled (numba) array primitives the renderers share: sums of rows by an index, row-wise cross products, and
the index checks every kernel wrapper makes.

The conventions of every compiled module of this package (``array_kernels``, ``ray_kernels``, ``camera_kernels``,
``lidar_kernels``, ``lidar_table_kernels``): a render of one car tests a few thousand (ray, face) pairs and shades a
few thousand hits; in numpy each step costs tens of operations on small arrays, which was most of a render's time.
Each kernel does exactly the arithmetic of the numpy code it replaces, in the same order and dtype (numba compiles
without fast-math: no operation is reassociated or contracted; constants are cast to the arrays' dtype as numpy
casts Python floats; exp, power and matrix products stay numpy's), so the results are the same bits;
``tests/sensors/test_sensors_kernels.py``, ``tests/sensors/test_sensors_lidar_fast_paths.py`` and the camera tests
compare each
with its numpy reference (named in its docstring; it lives beside the Python code that calls the kernel). Compiled
code does not check bounds: the Python wrappers check the indices they pass (pairs, owners, slots, faces, with
:func:`checked_faces` and :func:`checked_index`). Kernels compile on first use and are cached (``cache=True``:
the package's ``__pycache__``, or numba's user cache directory). A compiled function calls only compiled functions
of its own module (numba keys a cached kernel on its own file, so a helper it inlines from another file could be
edited without the cache noticing).

Here: :func:`scatter_rows` sums rows by an index in float64, in order (``np.bincount``'s arithmetic);
:func:`scatter_add` in the values' dtype, in order (``np.add.at``'s); :func:`cross_rows_float` is
:func:`robustbench3d.sensors.mesh.cross_rows` of float32 / float64 rows; :func:`column_stats` the per-column minimum,
maximum and sum of a float64 array (numpy's bits).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _scatter_rows(index: np.ndarray, rows: np.ndarray, n: int) -> np.ndarray:  # pragma: no cover - compiled
    out = np.zeros((n, rows.shape[1]))
    for k in range(len(index)):
        i = index[k]
        for c in range(rows.shape[1]):
            out[i, c] += rows[k, c]
    return out


@njit(cache=True, nogil=True)
def _scatter_add(index: np.ndarray, values: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover - compiled
    for k in range(len(index)):
        i = index[k]
        for c in range(values.shape[0]):
            out[c, i] += values[c, k]


def checked_faces(faces: np.ndarray, n_vertices: int, name: str) -> np.ndarray:
    """(F, 3) int64 contiguous ``faces``, every index in [0, n_vertices) (the kernels read vertices by them)."""
    faces = np.ascontiguousarray(faces, np.int64)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"{name}: field 'faces': expected (F, 3), got {faces.shape}")
    if faces.size and (int(faces.min()) < 0 or int(faces.max()) >= n_vertices):
        raise ValueError(f"{name}: field 'faces': indices must lie in [0, {n_vertices})")
    return faces


def checked_index(index: np.ndarray, k: int, n: int, name: str) -> np.ndarray:
    index = np.ascontiguousarray(index, np.int64)
    if index.ndim != 1 or len(index) != k:
        raise ValueError(f"{name}: field 'index': expected ({k},), got {index.shape}")
    if k and (int(index.min()) < 0 or int(index.max()) >= n):
        raise ValueError(f"{name}: field 'index': entries must lie in [0, {n})")
    return index


def scatter_rows(index: np.ndarray, rows: np.ndarray, n: int) -> np.ndarray:
    """(n, C) float64 sums of the rows (K, C) by ``index`` (K,) in [0, n): each entry converted to float64 and
    added in order, as ``np.bincount(index, weights=rows[:, c], minlength=n)`` for each column c."""
    rows = np.ascontiguousarray(rows)
    return _scatter_rows(checked_index(index, len(rows), n, "scatter_rows"), rows, n)


def scatter_add(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """(C, n) sums of the columns of ``values`` (C, K) by ``index`` (K,) in [0, n), in the values' dtype, added
    in order: ``np.add.at(out.T, index, values.T)`` on zeros."""
    values = np.ascontiguousarray(values)
    out = np.zeros((values.shape[0], n), values.dtype)
    _scatter_add(checked_index(index, values.shape[1], n, "scatter_add"), values, out)
    return out


@njit(cache=True, nogil=True)
def _cross_rows(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover - compiled
    for i in range(a.shape[0]):
        out[i, 0] = a[i, 1] * b[i, 2] - a[i, 2] * b[i, 1]
        out[i, 1] = a[i, 2] * b[i, 0] - a[i, 0] * b[i, 2]
        out[i, 2] = a[i, 0] * b[i, 1] - a[i, 1] * b[i, 0]


def cross_rows_float(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise a x b of two (N, 3) float32 or float64 arrays (any strides: copied contiguous), in numpy's result
    dtype (a float32 operand of a float64 product is widened first, as numpy does): the components of np.cross,
    the same bits (the caller checks the shapes and dtypes)."""
    out = np.empty(a.shape, np.result_type(a.dtype, b.dtype))
    _cross_rows(np.ascontiguousarray(a), np.ascontiguousarray(b), out)  # one compiled layout per dtype pair
    return out


@njit(cache=True, nogil=True)
def _column_stats(a: np.ndarray) -> tuple:  # pragma: no cover - compiled
    n, m = a.shape
    lo, hi, total = np.empty(m, a.dtype), np.empty(m, a.dtype), np.zeros(m, a.dtype)
    for c in range(m):
        lo[c] = hi[c] = a[0, c]
    for i in range(n):
        for c in range(m):
            x = a[i, c]
            lo[c] = min(lo[c], x)
            hi[c] = max(hi[c], x)
            total[c] += x
    return lo, hi, total


def column_stats(a: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(min, max, sum) per column (C,) of a finite float64 (N, C) array, N >= 1: ``a.min(axis=0)``,
    ``a.max(axis=0)`` (exact) and ``a.sum(axis=0)`` (the rows added in order, as numpy adds along a non-contiguous
    axis), the same values, in one pass (numpy's reductions along axis 0 of a few columns cost tens of times more)."""
    a = np.ascontiguousarray(a, np.float64)
    if a.ndim != 2 or len(a) == 0:
        raise ValueError(f"column_stats: field 'a': expected (N >= 1, C), got {a.shape}")
    return _column_stats(a)
