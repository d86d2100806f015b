"""The compiled scatter-adds of robustbench3d.sensors.kernels against numpy's np.bincount and np.add.at (the
arithmetic they replace) bit for bit; the region walk is compared with its numpy reference in
test_sensors_camera_render.py."""

from __future__ import annotations

import numpy as np
import pytest

from robustbench3d.sensors.array_kernels import scatter_add, scatter_rows


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
    from robustbench3d.sensors.ray_kernels import scatter_pair_grads

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
    from robustbench3d.sensors.ray_kernels import star_faces

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


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("offsets", [False, True])
def test_face_rows_and_pair_tuv_equal_their_numpy_formulas_bit_for_bit(dtype, offsets):
    """FaceRows.of / .tuv (compiled when every array has one float dtype) against the formulas written with
    np.cross and element-wise numpy in that dtype: the rows, t, u, v and 1 / det bit for bit, det = 0 (a ray in
    a face's plane) guarded to inv = 1; mixed dtypes take the numpy code and give numpy's promoted result."""
    from robustbench3d.sensors.ray_rows import FaceRows

    rng = np.random.default_rng(3)
    v = rng.standard_normal((40, 3)).astype(dtype)
    f = np.array([rng.permutation(40)[:3] for _ in range(25)])
    f[0] = [5, 5, 9]  # degenerate: e1 = 0, so det = d . (e2 x e1) = 0 exactly
    origin = rng.standard_normal(3).astype(dtype)
    axis = np.array([0.0, 0.0, 1.0], dtype) if offsets else None
    fr = FaceRows.of(v, f, origin, axis)
    a0 = v[f[:, 0]]
    e1, e2 = v[f[:, 1]] - a0, v[f[:, 2]] - a0
    t0 = origin - a0
    q0 = np.cross(t0, e1)
    parts = [np.cross(e2, e1), np.cross(e2, t0), q0, (e2 * q0).sum(1)[:, None]]
    if offsets:
        q1 = np.cross(np.broadcast_to(axis, e1.shape), e1)
        parts += [np.cross(e2, np.broadcast_to(axis, e1.shape)), q1, (e2 * q1).sum(1)[:, None]]
    want = np.concatenate(parts, axis=1).T
    assert fr.rows.dtype == dtype and np.array_equal(fr.rows, want)
    assert np.array_equal(fr.e1, e1) and np.array_equal(fr.e2, e2) and np.array_equal(fr.q0, q0)
    k = 300
    slot = rng.integers(0, len(f), k)
    d = rng.standard_normal((k, 3)).astype(dtype)
    slot[0] = 0
    h = rng.standard_normal(k).astype(dtype) if offsets else None
    p = fr.tuv(slot, d, h)
    g = want[:, slot]
    det = g[0] * d[:, 0] + g[1] * d[:, 1] + g[2] * d[:, 2]
    un = g[3] * d[:, 0] + g[4] * d[:, 1] + g[5] * d[:, 2]
    vn = g[6] * d[:, 0] + g[7] * d[:, 1] + g[8] * d[:, 2]
    tn = g[9]
    if offsets:
        un = un + h * (g[10] * d[:, 0] + g[11] * d[:, 1] + g[12] * d[:, 2])
        vn = vn + h * (g[13] * d[:, 0] + g[14] * d[:, 1] + g[15] * d[:, 2])
        tn = tn + h * g[16]
    inv = 1.0 / np.where(det != 0, det, dtype(1))
    assert np.array_equal(p.ok, slot != 0) and np.all(p.inv[slot == 0] == 1)
    for got, ref in ((p.inv, inv), (p.t, tn * inv), (p.u, un * inv), (p.v, vn * inv)):
        assert got.dtype == dtype and np.array_equal(got, ref)
    mixed = FaceRows.of(v, f, origin.astype(np.float64) + 0.5, axis)  # numpy's promotion: float64 T0
    assert mixed.t0.dtype == np.float64 and np.array_equal(mixed.t0, (origin.astype(np.float64) + 0.5) - a0)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("offsets", [False, True])
def test_face_test_geometry_equals_the_numpy_table_bit_for_bit(dtype, offsets):
    """face_test_geometry (compiled for one float dtype) against raycast._face_tables on the sliver mask written
    in numpy: v0, e1, e2 and every table row bit for bit, with a sliver, a zero-area face, skipped faces and
    (shared origin) a face whose plane holds the origin (never hit: infinite floor)."""
    import torch

    import robustbench3d.sensors.ray_faces as rc

    rng = np.random.default_rng(6)
    v = rng.standard_normal((30, 3)).astype(dtype)
    v[29] = v[3] + (v[4] - v[3]) * dtype(0.5) + dtype(1e-7)  # nearly on the edge 3-4: a sliver
    f = np.array([rng.permutation(29)[:3] for _ in range(40)])
    f[0], f[1] = [3, 4, 29], [6, 6, 7]
    origin = rng.standard_normal(3).astype(dtype)
    v[[10, 11, 12]] = origin + np.array([[1, 0, 0], [0, 1, 0], [1, 1, 0]], dtype)  # a plane through the origin
    f[2] = [10, 11, 12]
    axis = np.array([0.0, 0.0, 1.0], dtype) if offsets else None
    skip = rng.random(len(f)) < 0.2
    got = rc.face_test_geometry(v, f, origin, 1e-3, axis, skip)
    v0, v1, v2 = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    e1, e2 = v1 - v0, v2 - v0
    area2 = np.linalg.norm(np.cross(e1, e2), axis=1)
    longest = np.maximum(np.maximum((e1 * e1).sum(1), (e2 * e2).sum(1)), ((v2 - v1) ** 2).sum(1))
    sliver = rc._SLIVER[torch.float32 if dtype == np.float32 else torch.float64]
    valid = (area2 > sliver * longest) & np.isfinite(area2) & ~skip
    table = rc._face_tables(v0, e1, e2, valid, origin, np.zeros(3, dtype) if axis is None else axis, 1e-3, offsets)
    for a, b in zip(got, (v0, e1, e2, table), strict=True):
        assert a.dtype == dtype and np.array_equal(a, b)
    assert not valid[1] and np.isinf(got[3][10, 1])
    if not offsets:
        assert np.isinf(got[3][10, 2])


def test_compiled_sphere_rays_equal_the_numpy_code_pair_for_pair():
    """BeamPattern.sphere_rays (compiled) against its numpy code (``compiled=False``): the same (sphere, ray)
    pairs in the same order, for random spheres near and far, small and large, across azimuth 0 (wrapped
    ranges), around the sensor's axis (every azimuth) and on restricted laser ranges."""
    from robustbench3d.sensors.lidar_beams import BeamPattern

    pattern = BeamPattern.generator(0.3)
    rng = np.random.default_rng(0)
    total, wrapped, full = 0, 0, 0
    for trial in range(60):
        m = int(rng.integers(1, 40))
        c = rng.uniform(-30.0, 30.0, (m, 3))
        c[:, 2] = rng.uniform(-3.0, 2.0, m)
        if trial % 3 == 0:  # near azimuth 0: ranges wrap
            c[:, 0], c[:, 1] = np.abs(c[:, 0]) + 2.0, rng.uniform(-0.3, 0.3, m)
        if trial % 5 == 0:  # around the axis: every azimuth
            c[:, :2] *= 0.02
        r = rng.uniform(0.01, 1.5, m)
        first = rng.integers(0, 30, m)
        last = first + rng.integers(0, 40, m)
        ref = pattern.sphere_rays(c, r, first, last, compiled=False)
        got = pattern.sphere_rays(c, r, first, last)
        assert got[0].dtype == got[1].dtype == np.int64
        assert np.array_equal(got[0], ref[0]) and np.array_equal(got[1], ref[1])
        total += len(ref[0])
        wrapped += trial % 3 == 0 and len(np.unique(ref[1])) < len(ref[1])
        full += trial % 5 == 0
    assert total > 10**6 and full and wrapped


def test_compiled_cone_cull_equals_the_numpy_cull_many():
    """BeamPattern.cull_many (compiled) against its numpy code (``compiled=False``): the same sorted rays per
    sphere, for spheres near and far, across azimuth 0, around the axis (full lasers, whose three turns coincide),
    holding a laser's apex (inside: every azimuth) and with a margin of 0."""
    from robustbench3d.sensors.lidar_beams import BeamPattern

    pattern = BeamPattern.generator(0.3)
    rng = np.random.default_rng(1)
    total = 0
    for trial in range(80):
        m = int(rng.integers(1, 10))
        c = rng.uniform(-40.0, 40.0, (m, 3))
        c[:, 2] = rng.uniform(-3.0, 2.0, m)
        if trial % 4 == 0:
            c[:, 0], c[:, 1] = np.abs(c[:, 0]) + 2.0, rng.uniform(-0.3, 0.3, m)
        if trial % 5 == 0:
            c[:, :2] *= 0.02
        if trial % 9 == 0:
            c[0] = [0.0, 0.0, pattern.sensor.origin_z[10]]
        r = rng.uniform(0.01, 2.5, m)
        margin = 0.0 if trial % 2 else 0.2
        ref = pattern.cull_many(c, r, margin, compiled=False)
        got = pattern.cull_many(c, r, margin)
        assert len(got) == len(ref) == m
        for a, b in zip(got, ref, strict=True):
            assert a.dtype == b.dtype == np.int64 and np.array_equal(a, b)
        total += sum(len(a) for a in ref)
    assert total > 10**6


@pytest.mark.parametrize(("da", "db"), [(np.float32, np.float32), (np.float64, np.float64),
                                        (np.float32, np.float64), (np.float64, np.float32)])
def test_cross_rows_equals_np_cross_bit_for_bit(da, db):
    """mesh.cross_rows (compiled for float32 / float64 rows) against np.cross: the same bits and numpy's result
    dtype, for contiguous rows, a column slice of a wider array, a broadcast row and an empty array; integer rows
    take numpy's path."""
    from robustbench3d.sensors.mesh import cross_rows

    rng = np.random.default_rng(7)
    a = (rng.standard_normal((500, 3)) * 10.0 ** rng.integers(-4, 5, (500, 1))).astype(da)
    wide = rng.standard_normal((500, 7)).astype(db)
    for b in (rng.standard_normal((500, 3)).astype(db), wide[:, 2:5], np.broadcast_to(np.array([0.3, -1.0, 2.0],
                                                                                                db), (500, 3))):
        got, want = cross_rows(a, b), np.cross(a, b)
        assert got.dtype == want.dtype == np.result_type(da, db) and np.array_equal(got, want)
    assert cross_rows(a[:0], a[:0]).shape == (0, 3)
    ints = rng.integers(-5, 5, (20, 3))
    assert np.array_equal(cross_rows(ints, ints[::-1]), np.cross(ints, ints[::-1]))


def test_kernels_refuse_faces_out_of_range_instead_of_reading_past_the_vertices():
    """The compiled kernels do not check bounds, so their wrappers do: a face index outside the vertices is a
    ValueError naming the field from FaceRows.of, the test table (PairTable.of) and star_faces."""
    from robustbench3d.sensors.pair_search import PairTable
    from robustbench3d.sensors.ray_kernels import star_faces
    from robustbench3d.sensors.ray_rows import FaceRows

    v = np.eye(3)
    bad = np.array([[0, 1, 3]])
    with pytest.raises(ValueError, match=r"face_rows: field 'faces': indices must lie in \[0, 3\)"):
        FaceRows.of(v, bad, np.zeros(3))
    with pytest.raises(ValueError, match=r"face_test_table: field 'faces': indices must lie in \[0, 3\)"):
        PairTable.of(v, bad, np.zeros(3))
    tetra = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
    with pytest.raises(ValueError, match=r"star_faces: field 'faces': indices must lie in \[0, 3\)"):
        star_faces(v, tetra, v.mean(axis=0), np.full(3, 5.0))  # vertex 3 does not exist
