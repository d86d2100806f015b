"""The LiDAR render's compiled fast paths (issue #34) against their references, bit for bit: the fused face-sphere
search against the pairs it used to form and test, the one-pass ray table against ``HDL64E.ray_azimuths``, the
compiled nearest ray against its numpy code, the scan rows' copy against a mask, the points of the culled rays
against the full preparation, and whole attacked frames (hits, points, gradients) against a brute force cast of
every ray near the cars at every face of every car."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from robustbench3d.sensors import lidar_model as lm
from robustbench3d.sensors import lidar_render as lr
from robustbench3d.sensors.lidar_beams import GENERATOR_FIRING_OFFSETS_DEG, BeamPattern, scan_ring_ids
from robustbench3d.sensors.lidar_kernels import cone_cull, nearest_rays, sphere_pairs_nearest
from robustbench3d.sensors.lidar_table_kernels import cull_runs, rows_but
from robustbench3d.sensors.mesh import icosphere
from robustbench3d.sensors.pair_search import search_pairs
from robustbench3d.sensors.raycast import cast_ray_search, cast_rays

torch.set_num_threads(1)


def _blobs(rng: np.random.Generator, n: int, near_zero: bool = False) -> list[tuple[np.ndarray, np.ndarray, None]]:
    """``n`` deformed 0.4 m icospheres (level 2) 4-40 m away, around azimuth 0 when ``near_zero`` (their ranges
    wrap), some overlapping in azimuth (rays shared between meshes)."""
    v0, f = icosphere(2, 0.4)
    out = []
    for _ in range(n):
        rho = rng.uniform(4.0, 40.0)
        az = rng.uniform(-0.04, 0.04) if near_zero else rng.uniform(-np.pi, np.pi)
        z = rng.uniform(-1.6, 0.5)
        v = v0 * (1 + 0.3 * rng.uniform(-1, 1, (len(v0), 1))) + [rho * np.cos(az), rho * np.sin(az), z]
        out.append((v, f, None))
    return out


def _search_inputs(pattern: BeamPattern, meshes: list) -> tuple:
    """What ``_trace`` gives the cast: checked meshes, culls, their union, stacked geometry, the per-face test table
    (offsets on), directions by component and the rays' apex heights."""
    mts = lr._mesh_tensors(meshes)
    culls = lr._culled_rays(pattern, mts)
    keep = [i for i, (_, fa) in enumerate(mts) if len(fa) and len(culls[i])]
    mts, culls = [mts[i] for i in keep], [culls[i] for i in keep]
    idx = lr._union(pattern, culls)
    v_off = np.cumsum([0] + [len(v) for v, _ in mts])
    vt = torch.cat([v for v, _ in mts])
    fa = np.concatenate([f + v_off[k] for k, (_, f) in enumerate(mts)])
    origins, dirs = pattern.ray_geometry(idx)
    from robustbench3d.sensors.ray_faces import face_test_geometry

    table = face_test_geometry(vt.numpy(), fa, np.zeros(3), 1e-3, np.array([0.0, 0.0, 1.0]))[3]
    return mts, culls, idx, (vt.numpy(), fa), table, dirs.T.copy(), origins[:, 2].copy()


@pytest.mark.parametrize("seed", range(6))
def test_fused_sphere_search_equals_testing_the_formed_pairs_bit_for_bit(seed):
    """``_sphere_search`` (each face's sphere against its mesh's culled rays, tested as found) against
    ``search_pairs`` of the pairs ``_face_pairs`` forms in numpy: the same nearest face and t per ray, bit for bit,
    and the same number of pairs tested; meshes near and far, around azimuth 0 (wrapped ranges), sharing rays."""
    rng = np.random.default_rng(seed)
    pattern = BeamPattern.generator(rng.uniform(0.0, 0.045))
    meshes = _blobs(rng, 6, near_zero=seed % 2 == 0) + _blobs(rng, 3)
    mts, culls, idx, stacked, table, d_cols, h = _search_inputs(pattern, meshes)
    ray, face = lr._face_pairs(pattern, mts, culls, idx, stacked)
    want_face, want_t, want_tests = search_pairs(table, d_cols, h, [(ray, face)], 1e-6, 1e-6)
    got_face, got_t, got_tests = lr._sphere_search(pattern, mts, culls, idx, stacked)(table, d_cols, h, 1e-6, 1e-6)
    assert (want_face >= 0).sum() > 100 and want_tests > 10 * (want_face >= 0).sum()
    assert got_face.tobytes() == want_face.tobytes() and got_t.tobytes() == want_t.tobytes()
    assert got_tests == want_tests == len(ray)


@pytest.mark.parametrize("frame_index", [0, 3])
def test_attacked_frame_hits_points_and_gradients_equal_a_brute_force_cast_bit_for_bit(frame_index):
    """A generated frame with the shipped adv-object on every target car: the traced hits (ray, mesh, face, t, u,
    v) equal ``cast_rays``' (its own torch search: every face of every car against every ray of a wide region
    around the cars), bit for bit, and so do the render's points and the gradients of a weighted sum of them
    w.r.t. each car's vertices (the points o + t d of the same rays from the brute force's t)."""
    from robustbench3d.attacks import create_attack
    from robustbench3d.attacks.base import target_cars
    from robustbench3d.synth.frame import generate_frame

    frame = generate_frame(0, frame_index)
    attack = create_attack("adv-object")
    placed = attack.place(target_cars(frame.labels), np.random.default_rng(frame_index))
    velo = [frame.calib.rect_to_velo_points(v) for v, _ in placed]
    faces = attack.obj.faces
    assert len(velo) >= 5
    res = lr.render_lidar(frame.scan, [(v, faces, attack.obj.colors) for v in velo])
    pattern = res.pattern
    wide = np.unique(np.concatenate([pattern.cull(0.5 * (v.min(0) + v.max(0)), 3 * np.abs(v - v.mean(0)).max(), 2.0)
                                     for v in velo]))
    origins, dirs = pattern.ray_geometry(wide)
    leaves = [torch.tensor(v, requires_grad=True) for v in velo]
    brute = cast_rays(torch.cat(leaves), np.concatenate([faces + k * len(velo[0]) for k in range(len(velo))]),
                      torch.from_numpy(dirs), torch.zeros(3, dtype=torch.float64), torch.from_numpy(origins[:, 2]))
    hit = brute.hit.numpy()
    tr = lr.trace_meshes(lr.prepare_scan(frame.scan, pattern=pattern), [(v, faces, None) for v in velo])
    np.testing.assert_array_equal(tr.ray, wide[hit])
    np.testing.assert_array_equal(tr.mesh * len(faces) + tr.face, brute.face.numpy()[hit])
    for mine, ref in ((tr.t, brute.t), (tr.u, brute.u), (tr.v, brute.v)):
        assert mine.numpy().tobytes() == ref.detach().numpy()[hit].tobytes()
    # the render's points: the in-range hits no scan point hides, o + t d
    shown = ~tr.hidden & lm.in_range(tr.t.numpy())
    at = np.flatnonzero(hit)[shown]
    want = torch.from_numpy(origins[at]) + brute.t[torch.from_numpy(at)][:, None] * torch.from_numpy(dirs[at])
    assert res.added_torch.detach().numpy().tobytes() == want.detach().numpy().tobytes()
    # gradients of a weighted sum of the points w.r.t. each car's vertices
    weights = torch.from_numpy(np.random.default_rng(1).standard_normal(want.shape))
    (want * weights).sum().backward()
    mine = [torch.tensor(v, requires_grad=True) for v in velo]
    pts, _ = lr.render_lidar_torch(frame.scan, [(v, faces, None) for v in mine])
    (pts * weights).sum().backward()
    for a, b in zip(mine, leaves, strict=True):
        assert a.grad.numpy().tobytes() == b.grad.numpy().tobytes()
    assert sum(float(a.grad.abs().sum()) > 0 for a in mine) >= 3


def _numpy_ray_table(pattern: BeamPattern) -> tuple[np.ndarray, np.ndarray]:
    """The rays' (ring int64, azimuth) as ``BeamPattern`` formed them before: ``sensor.ray_azimuths`` in numpy."""
    with np.errstate(invalid="ignore"):
        ring, az = pattern.sensor.ray_azimuths(np.asarray(pattern.phases_deg, dtype=np.float64) - pattern.shift_deg)
        return ring.astype(np.int64), az + pattern.shift_deg


def test_one_pass_ray_table_equals_the_sensors_numpy_rays_bit_for_bit():
    """The compiled ray table (azimuths, lasers' first rays, lowest and highest azimuth) against
    ``HDL64E.ray_azimuths`` turned as before: generator phases, random phases, phases far outside a quantum
    (whole lasers past 360, others cut by the ego sectors at every offset), firings exactly at a sector's bounds,
    a NaN phase (that laser has no rays) and a NaN turn (no rays at all)."""
    rng = np.random.default_rng(0)
    cases = [BeamPattern.generator(rng.uniform(0.0, 0.045)) for _ in range(20)]
    cases += [BeamPattern(rng.uniform(-0.05, 0.1, 64)) for _ in range(20)]
    cases += [BeamPattern(rng.uniform(-400.0, 400.0, 64)) for _ in range(20)]
    bounds = np.array([156.0, 165.0, 197.0, 204.0, 280.0, 300.0, 342.0, 19.0, 14.0, 26.0, 39.0])
    cases += [BeamPattern(bounds[rng.integers(0, len(bounds), 64)] - 0.09 * rng.integers(0, 20, 64))
              for _ in range(20)]
    nan_phase = GENERATOR_FIRING_OFFSETS_DEG.copy()
    nan_phase[3] = np.nan
    cases += [BeamPattern(nan_phase, 0.01), BeamPattern(GENERATOR_FIRING_OFFSETS_DEG, float("nan"))]
    for pattern in cases:
        ring, az = _numpy_ray_table(pattern)
        got_ring, got_az = pattern._ring_azimuth
        assert got_ring.tobytes() == ring.tobytes() and got_az.tobytes() == az.tobytes()
        assert pattern.ring_start.tobytes() == np.searchsorted(ring, np.arange(65)).tobytes()
        lowest, highest = pattern._azimuth_range
        if len(az) == 0:
            assert (lowest, highest) == (np.inf, -np.inf)
        elif np.isnan(az).any():
            assert np.isnan(lowest) and np.isnan(highest)
        else:
            assert (lowest, highest) == (az.min(), az.max())
        assert pattern._keys.tobytes() == (ring * 1000.0 + az).tobytes()
        index = rng.integers(0, max(len(az), 1), 300) if len(az) else np.zeros(0, np.int64)
        np.testing.assert_array_equal(pattern.ray_rings(index), ring[index])
    assert len(cases[-2]._ring_azimuth[0]) < len(cases[0]._ring_azimuth[0]) and len(cases[-1]._ring_azimuth[0]) == 0


def test_ray_rings_outside_the_rays_read_as_numpy_reads_the_lasers():
    pattern = BeamPattern.generator(0.01)
    ring = _numpy_ray_table(pattern)[0]
    np.testing.assert_array_equal(pattern.ray_rings(np.array([-1, 0, len(ring) - 1])), ring[[-1, 0, -1]])
    with pytest.raises(IndexError):
        pattern.ray_rings(np.array([len(ring)]))


@pytest.mark.parametrize("phase", [0.0, 0.017, 0.044])
def test_compiled_nearest_ray_equals_the_numpy_code(phase):
    """Points on every laser and unknown lasers, anywhere in azimuth, within rounding of 0 / 360 and of the
    half-way azimuths between two rays, and NaN: the same ray (or -1) as the numpy code."""
    pattern = BeamPattern.generator(phase)
    ring, az = _numpy_ray_table(pattern)
    rng = np.random.default_rng(int(phase * 1000))
    n = 20000
    pick = rng.integers(0, len(az), n)
    mid = 0.5 * (az[pick] + az[np.minimum(pick + 1, len(az) - 1)])
    pts_az = np.concatenate([rng.uniform(-180.0, 180.0, n), az[pick] + rng.normal(0.0, 0.03, n), mid,
                             np.nextafter(mid, np.inf), rng.uniform(-0.1, 0.1, 2000), 360.0 - rng.uniform(0, 0.1, 2000),
                             [np.nan, np.nan]])
    pts_az = np.where(pts_az > 180.0, pts_az - 360.0, pts_az)
    pts_ring = np.concatenate([rng.integers(-2, 66, n), ring[pick], ring[pick], ring[pick],
                               rng.integers(0, 64, 4000), [3, 70]])
    want = pattern.nearest_ray(pts_ring, pts_az, compiled=False)
    got = pattern.nearest_ray(pts_ring, pts_az)
    assert got.dtype == want.dtype == np.int64 and np.array_equal(got, want)
    assert (want >= 0).sum() > n and (want < 0).sum() > 1000


def test_rows_but_copies_the_kept_rows_bytes_in_order():
    rng = np.random.default_rng(3)
    scan = rng.standard_normal((5000, 4)).astype(np.float32)
    bits = scan.view(np.uint32)
    bits[7, 1] = 0x7FC00123  # a NaN with a payload
    bits[8, 2] = 0x80000000  # -0.0
    for removed in (np.zeros(0, np.int64), np.array([0]), np.array([4999]), np.array([0, 1, 2, 7, 8, 4998, 4999]),
                    np.sort(rng.choice(5000, 900, replace=False)), np.arange(5000)):
        kept = np.ones(len(scan), bool)
        kept[removed] = False
        out = rows_but(scan, removed, 3)
        assert out.shape == (kept.sum() + 3, 4) and out.dtype == np.float32
        assert out[:kept.sum()].tobytes() == scan[kept].tobytes()
    for bad in (np.array([5000]), np.array([-1]), np.array([3, 3]), np.array([4, 2])):
        with pytest.raises(ValueError, match="rows_but: field 'removed'"):
            rows_but(scan, bad)


def test_without_rows_then_added_equals_concatenating_the_kept_rows():
    rng = np.random.default_rng(4)
    scan = rng.standard_normal((300, 4)).astype(np.float32)
    added = rng.standard_normal((5, 4)).astype(np.float32)
    removed = np.array([0, 5, 6, 7, 299])
    kept = np.delete(scan, removed, axis=0)
    assert lr._without_rows(scan, removed, added).tobytes() == np.concatenate([kept, added]).tobytes()
    wide = scan.astype(np.float64)  # other dtypes: numpy's concatenation
    assert lr._without_rows(wide, removed, added).tobytes() == np.concatenate([np.delete(wide, removed, 0),
                                                                              added]).tobytes()


def test_cull_runs_are_the_culls_consecutive_rays_of_one_laser():
    """Runs by brute force: each cull split where the next ray is not the next index or belongs to another
    laser; each run's position is its first ray's in the union."""
    pattern = BeamPattern.generator(0.02)
    ring = _numpy_ray_table(pattern)[0]
    rng = np.random.default_rng(5)
    centres = rng.uniform(-30, 30, (7, 3))
    centres[:, 2] = rng.uniform(-2, 1, 7)
    centres[0] = [20.0, 0.0, -1.0]  # around azimuth 0: two runs per laser
    culls = pattern.cull_many(centres, rng.uniform(0.3, 3.0, 7))
    culls[3] = np.zeros(0, np.int64)
    idx = np.unique(np.concatenate(culls))
    ptr, start, stop, pos = pattern.cull_runs(culls, idx)
    n = 0
    for m, cull in enumerate(culls):
        cut = np.flatnonzero((np.diff(cull) != 1) | (np.diff(ring[cull]) != 0)) + 1
        for run in np.split(cull, cut) if len(cull) else []:
            k = ring[run[0]]
            assert ptr[m * 64 + k] <= n < ptr[m * 64 + k + 1]
            assert (start[n], stop[n], pos[n]) == (run[0], run[-1] + 1, np.searchsorted(idx, run[0]))
            n += 1
    assert n == len(start) == ptr[-1] and n > len(culls) + 5
    with pytest.raises(ValueError, match="cull_runs"):
        cull_runs(np.array([len(ring)]), np.array([1]), pattern.ring_start, idx)


@pytest.mark.parametrize("ordered", [True, False])
def test_points_of_the_culled_rays_equal_the_full_preparation(ordered):
    """``_ray_points`` (only the culled lasers' azimuths, no (N,) arrays) against ``_prepare_rays``: the same points
    on the same rays with the same ranges, bit for bit, for each ray's points in scan order; on a laser-ordered
    scan and a shuffled one."""
    from robustbench3d.synth.frame import generate_frame

    scan = generate_frame(0, 1).scan
    if not ordered:
        scan = scan[np.random.default_rng(0).permutation(len(scan))]
    ring = scan_ring_ids(scan)
    pattern = lr.prepare_scan(generate_frame(0, 1).scan).pattern
    meshes = [(v, f, None) for v, f, _ in _blobs(np.random.default_rng(6), 5)]
    culls = lr._culled_rays(pattern, lr._mesh_tensors(meshes))
    rays = lr._union(pattern, culls)
    full = lr._prepare_rays(scan, ring, pattern, None, rays)
    part = lr._ray_points(scan, ring, pattern, None, rays)
    query = np.concatenate([rays, [0, len(pattern._ring_azimuth[0]) - 1]])
    for a, b in zip(full.ranges_on(query), part.ranges_on(query), strict=True):
        assert a.tobytes() == b.tobytes()
    assert len(part.index) > 200


def test_fast_path_inputs_are_checked():
    pattern = BeamPattern.generator(0.0)
    az, start = pattern._table[:2]
    with pytest.raises(ValueError, match="cone_cull"):
        cone_cull(np.zeros((1, 3)), np.ones(1), np.zeros(64), np.zeros(64), 0.1, az, start[:-1], 1000.0)
    with pytest.raises(ValueError, match="nearest_rays"):
        nearest_rays(np.zeros(3, np.int64), np.zeros(2), start, az, (0.0, 360.0), 0.09, 1000.0)
    runs = (np.zeros(65, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64))
    with pytest.raises(ValueError, match="must be float64"):
        sphere_pairs_nearest(np.zeros((1, 3)), np.ones(1), np.zeros(1, np.int64), runs, np.zeros(64), np.zeros(64),
                             az, 1000.0, np.zeros((18, 1), np.float32), np.zeros((3, 0)), np.zeros(0), 1e-6, 1e-6)
    with pytest.raises(ValueError, match="sphere_pairs_nearest"):
        sphere_pairs_nearest(np.zeros((1, 3)), np.ones(1), np.array([1]), runs, np.zeros(64), np.zeros(64), az,
                             1000.0, np.zeros((18, 1)), np.zeros((3, 0)), np.zeros(0), 1e-6, 1e-6)
    v, f = icosphere(0, 1.0)

    def wrong(table, d_cols, h, t_min, tol):
        return np.zeros(2, np.int64), np.zeros(2), 0

    with pytest.raises(ValueError, match="render_lidar: field 'search'"):
        cast_ray_search(torch.from_numpy(v + 5.0), f, torch.zeros((3, 3), dtype=torch.float64),
                        torch.zeros(3, dtype=torch.float64), wrong, name="render_lidar")


@pytest.mark.parametrize("ordered", [True, False])
def test_compiled_near_rays_equal_the_numpy_code(ordered):
    """Points of every laser at bin boundaries (multiples of 0.09 deg and their neighbours), around 0 / +-180 /
    -0.0, against the culled rays of a few spheres: the same flags as the numpy code; with a NaN or an azimuth
    outside (-360, 360) the numpy code runs (the same flags too)."""
    pattern = BeamPattern.generator(0.013)
    rng = np.random.default_rng(7)
    n = 30000
    ring = np.sort(rng.integers(0, 64, n)) if ordered else rng.integers(0, 64, n)
    edge = 0.09 * rng.integers(-2000, 2000, n)
    az = np.concatenate([rng.uniform(-180.0, 180.0, n // 2), edge[: n // 4],
                         np.nextafter(edge[n // 4: n // 2], rng.choice([-np.inf, np.inf], n // 2 - n // 4))])
    az[:4] = [-0.0, 0.0, 180.0, -180.0]
    centres = np.array([[10.0, 0.2, -1.0], [-8.0, 3.0, -0.5], [0.5, -15.0, 0.0], [30.0, -0.1, -1.5]])
    rays = np.unique(np.concatenate(pattern.cull_many(centres, np.array([1.0, 2.0, 0.7, 3.0]))))
    want = pattern.near_rays(rays, ring, az, compiled=False)
    got = pattern.near_rays(rays, ring, az)
    assert got.dtype == want.dtype == np.bool_ and np.array_equal(got, want) and 100 < want.sum() < n // 2
    for odd in (np.nan, 400.0, -361.0):
        bad = az.copy()
        bad[10] = odd
        with np.errstate(invalid="ignore"):  # numpy's cast of a NaN bin
            np.testing.assert_array_equal(pattern.near_rays(rays, ring, bad),
                                          pattern.near_rays(rays, ring, bad, compiled=False))
