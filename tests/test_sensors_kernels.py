"""The compiled scatter-adds of robustbench3d.sensors.kernels against numpy's np.bincount and np.add.at (the
arithmetic they replace) bit for bit; the region walk is compared with its numpy reference in
test_sensors_camera_render.py."""

from __future__ import annotations

import numpy as np
import pytest

from robustbench3d.sensors.kernels import scatter_add, scatter_rows


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_scatter_rows_equals_bincount_per_column_bit_for_bit(dtype):
    """Float64 sums in order, as np.bincount(index, weights=column, minlength=n): magnitudes spread over 1e-8 to
    1e8 make the summation order visible (a pairwise or reordered sum gives other bits)."""
    rng = np.random.default_rng(0)
    k, n = 5000, 37
    index = rng.integers(0, n - 2, k)  # the last two rows get nothing: zeros
    rows = (rng.standard_normal((k, 7)) * 10.0 ** rng.integers(-8, 9, (k, 7))).astype(dtype)
    want = np.stack([np.bincount(index, weights=rows[:, c], minlength=n) for c in range(7)], axis=1)
    got = scatter_rows(index, rows, n)
    assert got.dtype == np.float64 and got.shape == (n, 7)
    assert np.array_equal(got, want) and not got[-2:].any()
    reordered = scatter_rows(index[::-1], rows[::-1], n)
    assert not np.array_equal(reordered, got)  # the order is part of the contract (and of the bits above)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_scatter_add_equals_add_at_in_the_values_dtype_bit_for_bit(dtype):
    rng = np.random.default_rng(1)
    k, n = 4000, 50
    index = rng.integers(0, n, k)
    values = (rng.standard_normal((3, k)) * 10.0 ** rng.integers(-6, 7, (3, k))).astype(dtype)
    want = np.zeros((3, n), dtype)
    np.add.at(want.T, index, values.T)
    got = scatter_add(index, values, n)
    assert got.dtype == dtype and np.array_equal(got, want)
    assert np.array_equal(scatter_add(index[:0], values[:, :0], n), np.zeros((3, n), dtype))


def test_scatters_refuse_an_index_out_of_range_or_of_the_wrong_length():
    rows = np.ones((3, 2))
    with pytest.raises(ValueError, match=r"scatter_rows: field 'index': entries must lie in \[0, 4\)"):
        scatter_rows(np.array([0, 4, 1]), rows, 4)
    with pytest.raises(ValueError, match=r"scatter_rows: field 'index': entries must lie in \[0, 4\)"):
        scatter_rows(np.array([0, -1, 1]), rows, 4)
    with pytest.raises(ValueError, match=r"scatter_add: field 'index': expected \(2,\)"):
        scatter_add(np.array([0, 1, 2]), np.ones((3, 2)), 4)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("offsets", [False, True])
def test_scatter_pair_grads_equals_the_stacked_columns_summed_by_bincount(dtype, offsets):
    """The columns FaceRows.edge_grads sums per face (gdet d, gun d, gvn d, gtn; with offsets h also those but
    gdet d times h), formed in the arrays' dtype and summed by np.bincount: the same bits."""
    from robustbench3d.sensors.kernels import scatter_pair_grads

    rng = np.random.default_rng(2)
    k, n = 3000, 41
    slot = rng.integers(0, n, k)
    gdet, gun, gvn, gtn, h = (rng.standard_normal(k).astype(dtype) * 10.0 ** rng.integers(-5, 6, k) for _ in range(5))
    d = rng.standard_normal((k, 3)).astype(dtype)
    cols = [gdet * d[:, 0], gdet * d[:, 1], gdet * d[:, 2], gun * d[:, 0], gun * d[:, 1], gun * d[:, 2],
            gvn * d[:, 0], gvn * d[:, 1], gvn * d[:, 2], gtn]
    if offsets:
        cols += [x * h for x in cols[3:]]
    want = np.stack([np.bincount(slot, weights=c, minlength=n) for c in cols], axis=1)
    got = scatter_pair_grads(slot, gdet, gun, gvn, gtn, d, h if offsets else None, n)
    assert got.shape == (n, 17 if offsets else 10) and np.array_equal(got, want)


def test_star_faces_against_the_per_face_formulas_in_numpy():
    """kernels.star_faces on a deformed sphere: the triple products' sign, the solid-angle sum (4 pi for one
    sheet seen from inside, to rounding) and the cull mask (o - c - a) . (e1 x e2) <= 0, bit for bit."""
    from robustbench3d.attacks.object import random_shape
    from robustbench3d.sensors.kernels import star_faces

    obj = random_shape(seed=1, amplitude=0.3)
    v, f = obj.vertices() + np.array([0.2, -0.1, 7.0]), obj.faces
    c = v.sum(axis=0) / len(v)
    o = np.array([0.5, -1.0, 0.0])
    a, b, cc = v[f[:, 0]] - c, v[f[:, 1]] - c, v[f[:, 2]] - c
    normal = np.cross(b - a, cc - a)
    triple = (a * normal).sum(1)
    la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, cc))
    den = la * lb * lc + (a * b).sum(1) * lc + (a * cc).sum(1) * lb + (b * cc).sum(1) * la
    positive, angle, mask = star_faces(v, f, c, o)
    assert positive == bool(np.all(triple > 0)) and positive
    assert angle == pytest.approx(2.0 * np.arctan2(triple, den).sum(), rel=1e-12)
    assert angle == pytest.approx(4.0 * np.pi, rel=1e-12)
    assert np.array_equal(mask, ((o - c - a) * normal).sum(1) <= 0) and 0 < mask.sum() < len(f)
    flipped = f[:, [0, 2, 1]]  # inward-oriented: every triple product negative, solid angles sum to -4 pi
    positive, angle, _ = star_faces(v, flipped, c, o)
    assert not positive and angle == pytest.approx(-4.0 * np.pi, rel=1e-12)
