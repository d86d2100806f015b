"""LiDAR rendering of meshes into scans: the generator's beam pattern, culled casting against an Embree
brute force over every ray of the pattern, occlusion both ways on a hand-built scan, reflectance,
noise, gradients, and a real KITTI scan."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from embreex import rtcore, rtcore_scene
from embreex.mesh_construction import TriangleMesh

from robustbench3d.sensors import lidar_model as lm
from robustbench3d.sensors import lidar_render as lr
from robustbench3d.sensors.lidar_beams import AZIMUTH_STEP_DEG, BeamPattern, estimate_pattern, scan_ring_ids
from robustbench3d.sensors.lidar_render import prepare_scan, render_lidar, render_lidar_torch, trace_meshes
from robustbench3d.sensors.materials import REFLECTIVITY, Mat
from robustbench3d.sensors.mesh import face_normals, icosphere

torch.set_num_threads(1)
ROOF_Z = -1.73 + 1.50  # roof of a 1.50 m high car in the velodyne frame
EMPTY = np.zeros((0, 4), dtype=np.float32)


def _object(x: float, y: float = 0.3, level: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """A smoothly deformed 0.40 m icosphere resting on a roof at (x, y)."""
    v, f = icosphere(level, 0.4)
    r = 1 + 0.15 * np.sin(3 * v[:, 0] / 0.4 + 0.5) * np.cos(2 * v[:, 1] / 0.4)
    v = v * r[:, None]
    return v + np.array([x, y, ROOF_Z - v[:, 2].min()]), f


#: The two faces of a quadrilateral (vertices in order around it).
QUAD = np.array([[0, 1, 2], [0, 2, 3]])


def _plate(x: float, y: float) -> np.ndarray:
    """A 0.4 m square at (x, y), z from -0.5 to -0.1 m, facing the sensor along x (velodyne frame)."""
    return np.array([[x, y - 0.2, -0.5], [x, y + 0.2, -0.5], [x, y + 0.2, -0.1], [x, y - 0.2, -0.1]])


def _embree(v: np.ndarray, f: np.ndarray, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    scene = rtcore_scene.EmbreeScene(rtcore.EmbreeDevice())
    TriangleMesh(scene, np.ascontiguousarray(v, dtype=np.float32), np.ascontiguousarray(f, dtype=np.int32))
    out = scene.run(np.ascontiguousarray(origins, np.float32), np.ascontiguousarray(dirs, np.float32), output=1)
    return out["primID"], out["tfar"].astype(np.float64)


def test_generator_pattern_is_the_generators_rays():
    from robustbench3d.synth.lidar import _base_rays

    phase = 0.0312
    rays = BeamPattern.generator(phase).rays
    base = _base_rays()
    c, s = np.cos(np.radians(phase)), np.sin(np.radians(phase))
    bx, by, bz = base.direction_rows
    gen = np.stack([c * bx - s * by, s * bx + c * by, bz], 1)  # as in synth.lidar.simulate_scan
    assert len(rays) == len(gen)
    np.testing.assert_allclose(rays.directions, gen, atol=1e-12)
    np.testing.assert_allclose(rays.origins, base.origins, atol=1e-6)


def test_pattern_and_rings_recovered_from_a_generated_scan():
    from robustbench3d.synth.frame import frame_generators
    from robustbench3d.synth.layout import sample_scene
    from robustbench3d.synth.lidar import simulate_scan
    from robustbench3d.synth.raytrace import SceneGeometry

    scene_rng, lidar_rng, _ = frame_generators(11, 0)
    frame_phase = frame_generators(11, 0)[1].uniform(0.0, 0.045)  # simulate_scan's first draw
    scene = sample_scene(scene_rng)
    scan, _ = simulate_scan(scene, SceneGeometry(scene), lidar_rng)
    prep = prepare_scan(scan)
    truth = BeamPattern.generator(frame_phase)
    assert prep.pattern.shift_deg == pytest.approx(frame_phase, abs=1e-6)
    np.testing.assert_allclose(prep.pattern.phases_deg, truth.phases_deg, atol=1e-6)
    # every point lies on a ray of its own laser, at that ray's azimuth
    assert (prep.point_ray >= 0).all()
    rays = prep.pattern.rays
    assert (rays.ring[prep.point_ray] == prep.ring).all()
    az = np.degrees(np.arctan2(scan[:, 1], scan[:, 0])) % 360
    dev = (az - rays.azimuth_deg[prep.point_ray] + 180) % 360 - 180
    assert np.abs(dev).max() < 1e-3
    # ... at the range along that ray from that laser's origin
    p = rays.origins[prep.point_ray] + prep.range_m[:, None] * rays.directions[prep.point_ray]
    np.testing.assert_allclose(p, scan[:, :3], atol=2e-4)
    # the cone fallback (for scans without all 64 lasers) agrees with the wrap heuristic
    np.testing.assert_array_equal(scan_ring_ids(scan[scan[:, 0] > 0][::-1]), prep.ring[scan[:, 0] > 0][::-1])


@pytest.mark.parametrize("distance", [1.3, 5.0, 20.0, 80.0])
def test_culled_hits_equal_embree_brute_force_over_every_ray(distance):
    pattern = BeamPattern.generator(0.0231)
    v, f = _object(distance, y=0.3 if distance > 2 else 0.0)
    prep = prepare_scan(EMPTY, pattern=pattern, ring_ids=np.zeros(0, dtype=np.int64))
    vt = torch.tensor(v, requires_grad=True)
    tr = trace_meshes(prep, [(vt, f, None)])
    (tr.t.sum() + tr.u.sum() + tr.v.sum()).backward()
    assert torch.isfinite(vt.grad).all() and torch.isfinite(tr.t).all()
    rays = pattern.rays
    prim, tfar = _embree(v, f, rays.origins, rays.directions)
    ref = np.flatnonzero(prim >= 0)
    assert len(ref) > {1.3: 3000, 5.0: 500, 20.0: 40, 80.0: 1}[distance]
    np.testing.assert_array_equal(tr.ray, ref)  # exactly the same rays hit
    ours = rays.origins[tr.ray] + tr.t.detach().numpy()[:, None] * rays.directions[tr.ray]
    theirs = rays.origins[ref] + tfar[ref, None] * rays.directions[ref]
    # Embree works in float32 (an ulp of 80 m is 7.6e-6 m), so the 1e-5 m bound is checked against the
    # float64 plane intersection of each ray with the triangle Embree reports; Embree itself is held to
    # its own float32 accuracy
    tri = v[f[prim[ref]]]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    o, d = rays.origins[ref], rays.directions[ref]
    t_exact = np.einsum("ij,ij->i", normal, tri[:, 0] - o) / np.einsum("ij,ij->i", normal, d)
    exact = o + t_exact[:, None] * d
    assert np.abs(ours - exact).max() < 1e-5
    assert np.abs(theirs - exact).max() < 1e-6 + 4e-7 * distance
    brute = len(rays) * len(f)
    if distance >= 5.0:
        assert tr.tests <= 0.01 * brute
    # the render adds exactly the in-range hits (nothing hides them in an empty scan)
    res = render_lidar(prep, [(v, f, None)])
    gate = lm.in_range(tfar[ref])
    np.testing.assert_array_equal(res.ray_index, ref[gate])
    np.testing.assert_allclose(res.added[:, :3], theirs[gate], atol=2e-5)
    assert res.tests == tr.tests and len(res.removed_index) == 0


def test_sensor_inside_a_mesh_and_a_mesh_out_of_sight():
    pattern = BeamPattern.generator(0.04)
    v, f = icosphere(2, 3.0)
    prep = prepare_scan(EMPTY, pattern=pattern, ring_ids=np.zeros(0, dtype=np.int64))
    tr = trace_meshes(prep, [(v + np.array([0.2, 0.0, 0.1]), f, None)])
    assert len(tr.ray) == len(pattern.rays)  # every laser, every azimuth
    t = tr.t.numpy()
    assert np.isfinite(t).all() and (t > 2.5).all() and (t < 3.6).all()
    above = trace_meshes(prep, [(icosphere(1, 0.4)[0] + np.array([0.0, 0.0, 5.0]), icosphere(1, 0.4)[1], None)])
    assert len(above.ray) == 0 and above.tests == 0  # straight above the sensor: no laser's cone reaches it


def test_two_meshes_in_one_beam_nearest_wins():
    pattern = BeamPattern.generator(0.01)
    near, f = _object(8.0)
    far = near + np.array([3.0, 0.5, 0.1])  # behind the near one, partly covered by it
    prep = prepare_scan(EMPTY, pattern=pattern, ring_ids=np.zeros(0, dtype=np.int64))
    res = render_lidar(prep, [(far, f, None), (near, f, None)])
    rays = pattern.rays
    both = np.concatenate([far, near])
    prim, tfar = _embree(both, np.concatenate([f, f + len(far)]), rays.origins, rays.directions)
    ref = np.flatnonzero(prim >= 0)
    np.testing.assert_array_equal(res.ray_index, ref)
    np.testing.assert_array_equal(res.object_index, (prim[ref] >= len(f)).astype(np.int64))
    assert (res.object_index == 0).sum() > 0 and (res.object_index == 1).sum() > 0
    theirs = rays.origins[ref] + tfar[ref, None] * rays.directions[ref]
    assert np.abs(res.added[:, :3] - theirs).max() < 2e-5


def test_occlusion_both_ways_on_a_hand_built_scan():
    pattern = BeamPattern(np.zeros(64))
    v, f = _object(10.0, y=0.0)
    empty = prepare_scan(EMPTY, pattern=pattern, ring_ids=np.zeros(0, dtype=np.int64))
    tr = trace_meshes(empty, [(v, f, None)])
    rays = pattern.rays
    hit_rays, t = tr.ray, tr.t.detach().numpy()
    assert len(hit_rays) > 100
    behind, front = hit_rays[0::3], hit_rays[1::3]
    t_behind, t_front = t[0::3], t[1::3]
    # the object straddles azimuth 0: its rays sit at both ends of each laser's sweep
    assert (rays.azimuth_deg[hit_rays] < 5).any() and (rays.azimuth_deg[hit_rays] > 355).any()
    miss_ray = pattern.ring_start[rays.ring[hit_rays[0]]] + 100  # same laser, 18 deg aside: never hit
    assert miss_ray not in set(hit_rays)
    pts = np.concatenate([
        rays.origins[behind] + (t_behind + 5.0)[:, None] * rays.directions[behind],  # removed
        rays.origins[front] + (t_front - 2.0)[:, None] * rays.directions[front],  # hide the object there
        rays.origins[[miss_ray]] + 30.0 * rays.directions[[miss_ray]],  # kept
    ])
    ring = np.concatenate([rays.ring[behind], rays.ring[front], rays.ring[[miss_ray]]])
    # a point 0.04 deg off a hit ray (its own beam), beyond the object: removed too
    k = hit_rays[2 * len(hit_rays) // 3 + 1]
    a = np.radians(rays.azimuth_deg[k] + 0.04)
    phi = np.radians(pattern.sensor.elevation_deg[rays.ring[k]])
    d = np.array([np.cos(phi) * np.cos(a), np.cos(phi) * np.sin(a), np.sin(phi)])
    pts = np.concatenate([pts, (rays.origins[k] + 40.0 * d)[None]])
    ring = np.concatenate([ring, [rays.ring[k]]])
    scan = np.concatenate([pts, np.full((len(pts), 1), 0.2)], 1).astype(np.float32)
    res = render_lidar(scan, [(v, f, None)], ring_ids=ring)
    n_b, n_f = len(behind), len(front)
    expect_removed = np.concatenate([np.arange(n_b), [len(pts) - 1]])
    np.testing.assert_array_equal(res.removed_index, expect_removed)
    assert not np.isin(res.ray_index, front).any()  # hidden behind nearer returns
    expected_added = np.setdiff1d(hit_rays, front)
    np.testing.assert_array_equal(res.ray_index, expected_added)
    kept = np.setdiff1d(np.arange(len(pts)), expect_removed)
    np.testing.assert_array_equal(res.scan[: len(kept)], scan[kept])
    np.testing.assert_array_equal(res.scan[len(kept):], res.added)
    assert len(res.scan) == len(pts) - n_b - 1 + len(expected_added)
    assert n_f > 0


def test_reflectance_follows_the_generators_model_and_is_deterministic():
    pattern = BeamPattern.generator(0.0)
    v, f = _object(12.0)
    prep = prepare_scan(EMPTY, pattern=pattern, ring_ids=np.zeros(0, dtype=np.int64))
    white = render_lidar(prep, [(v, f, np.ones_like(v))])
    black = render_lidar(prep, [(v, f, np.zeros_like(v))])
    grey = render_lidar(prep, [(v, f, None)])
    assert np.array_equal(white.added, render_lidar(prep, [(v, f, np.ones_like(v))]).added)
    assert (white.added[:, 3] > black.added[:, 3]).all()
    # hand computation for white paint: rho = 0.42 * (0.55 + 0.9), times (0.55 + 0.45 |cos|), range < 20 m
    rays = pattern.rays
    n = face_normals(v, f[white.face_index])
    cos = np.abs((n * rays.directions[white.ray_index]).sum(1))
    rho = min(REFLECTIVITY[Mat.PAINT] * 1.45, 0.98)
    expect = np.floor(rho * (0.55 + 0.45 * cos) * 100) / 100
    np.testing.assert_allclose(white.added[:, 3], expect, atol=0.0100001)
    assert np.mean(np.isclose(white.added[:, 3], expect, atol=1e-6)) > 0.95  # floor at a boundary: 0.01 off
    assert black.added[:, 3].max() < grey.added[:, 3].min() + 0.2


def test_noise_and_dropout_draw_only_from_the_given_rng():
    pattern = BeamPattern.generator(0.0)
    v, f = _object(10.0)
    prep = prepare_scan(EMPTY, pattern=pattern, ring_ids=np.zeros(0, dtype=np.int64))
    clean = render_lidar(prep, [(v, f, None)])
    a = render_lidar(prep, [(v, f, None)], rng=np.random.default_rng(4), range_noise_m=0.02, dropout=0.3)
    b = render_lidar(prep, [(v, f, None)], rng=np.random.default_rng(4), range_noise_m=0.02, dropout=0.3)
    np.testing.assert_array_equal(a.scan, b.scan)
    assert 0.55 < len(a.added) / len(clean.added) < 0.85
    assert np.isin(a.ray_index, clean.ray_index).all()
    # range noise moves the point along its ray only, by at most 3 sd
    rays = pattern.rays
    o, d = rays.origins[a.ray_index], rays.directions[a.ray_index]
    rel = a.added[:, :3] - o
    assert np.abs(np.cross(rel, d)).max() < 1e-4
    base = clean.added[np.searchsorted(clean.ray_index, a.ray_index), :3]
    shift = np.linalg.norm(a.added[:, :3] - base, axis=1)
    assert shift.max() <= 0.06 + 1e-5 and shift.std() > 0.005
    with pytest.raises(ValueError, match="field 'rng'"):
        render_lidar(prep, [(v, f, None)], dropout=0.1)
    with pytest.raises(ValueError, match="field 'meshes\\[0\\]'"):
        render_lidar(prep, [(v, f[:, :2], None)])


def test_torch_points_have_finite_difference_gradients():
    pattern = BeamPattern.generator(0.02)
    v, f = _object(6.0, level=1)
    ring = np.zeros(0, dtype=np.int64)
    prep = prepare_scan(EMPTY, pattern=pattern, ring_ids=ring)
    v0 = torch.tensor(v, requires_grad=True)
    pts, mesh = render_lidar_torch(prep, [(v0, f, None)])
    assert len(pts) > 100 and (mesh == 0).all()
    np.testing.assert_allclose(pts.detach().numpy(), render_lidar(prep, [(v, f, None)]).added[:, :3], atol=1e-5)
    n = len(pts)

    def fn(vert: torch.Tensor) -> torch.Tensor:
        p, _ = render_lidar_torch(prep, [(vert, f, None)])
        assert len(p) == n
        return p[::7]

    assert torch.autograd.gradcheck(fn, (v0,), eps=1e-7, atol=1e-6, rtol=1e-4)
    pts.pow(2).sum().backward()
    assert torch.isfinite(v0.grad).all() and v0.grad.abs().sum() > 0


def test_real_kitti_scan(kitti_samples):
    from robustbench3d.kitti.velodyne import read_scan

    scan = read_scan(kitti_samples / "training" / "velodyne" / "000000.bin")
    prep = prepare_scan(scan)
    assert prep.ring.max() == 63 and prep.pattern.shift_deg == 0.0
    assert np.mean(prep.point_ray >= 0) > 0.97  # real firings sit on the per-laser phase grid
    # an object resting on the road 9 m ahead (velodyne x forward)
    v, f = _object(9.0, y=0.0)
    v = v + np.array([0.0, 0.0, -1.73 - ROOF_Z])
    res = render_lidar(prep, [(v, f, np.full_like(v, 0.6))])
    assert len(res.added) > 150 and np.isfinite(res.added).all()
    assert len(res.removed_index) > 50  # ground returns behind the object on its beams
    rays = prep.pattern.rays
    hit_t = dict(zip(res.ray_index.tolist(), np.linalg.norm(res.added[:, :3] - rays.origins[res.ray_index], axis=1),
                     strict=True))
    for i in res.removed_index:
        assert prep.point_ray[i] in hit_t and prep.range_m[i] > hit_t[prep.point_ray[i]]
        dev = (np.degrees(np.arctan2(scan[i, 1], scan[i, 0])) - rays.azimuth_deg[prep.point_ray[i]] + 180) % 360
        assert abs(dev - 180) <= AZIMUTH_STEP_DEG / 2
    # no kept point lies on a hit ray beyond the object
    kept = np.setdiff1d(np.arange(len(scan)), res.removed_index)
    on = np.isin(prep.point_ray[kept], res.ray_index)
    for i in kept[on]:
        assert prep.range_m[i] < hit_t[prep.point_ray[i]]
    assert len(res.scan) == len(scan) - len(res.removed_index) + len(res.added)
    # estimating the pattern again from the attacked scan keeps the per-laser phases close
    again = estimate_pattern(res.scan, scan_ring_ids(res.scan))
    d_phase = (again.phases_deg - prep.pattern.phases_deg + 0.045) % 0.09 - 0.045
    assert np.abs(d_phase).max() < 0.01


def _pattern_scan(phase: float = 0.021) -> np.ndarray:
    """A KITTI-ordered scan with one return per ray of the generator's pattern, 5-40 m, azimuth jitter 0.03 deg."""
    rays = BeamPattern.generator(phase).rays
    rng = np.random.default_rng(3)
    az = np.radians(rays.azimuth_deg + rng.uniform(-0.03, 0.03, len(rays)))
    phi = np.arcsin(rays.directions[:, 2])
    d = np.stack([np.cos(phi) * np.cos(az), np.cos(phi) * np.sin(az), np.sin(phi)], 1)
    xyz = rays.origins + rng.uniform(5.0, 40.0, len(rays))[:, None] * d
    return np.concatenate([xyz, np.full((len(xyz), 1), 0.3)], 1).astype(np.float32)


def test_culled_preparation_and_lazy_rays_match_the_full_ones_bit_for_bit():
    scan = _pattern_scan()
    ring = scan_ring_ids(scan)
    full = prepare_scan(scan, ring)
    lazy = estimate_pattern(scan, ring)
    idx = np.sort(np.random.default_rng(0).choice(len(full.pattern.rays), 500, replace=False))
    o, d = lazy.ray_geometry(idx)
    assert "rays" not in lazy.__dict__  # answered without building every ray
    assert o.tobytes() == full.pattern.rays.origins[idx].tobytes()
    assert d.tobytes() == full.pattern.rays.directions[idx].tobytes()
    cull = full.pattern.cull(np.array([12.0, 3.0, -0.1]), 0.5)
    part = prepare_scan(scan, ring, full.pattern, cull)
    on = np.isin(full.point_ray, cull)
    assert on.sum() > 50
    np.testing.assert_array_equal(part.point_ray[on], full.point_ray[on])  # every point of the culled rays
    assert part.range_m[on].tobytes() == full.range_m[on].tobytes()
    assert np.all((part.point_ray == -1) | (part.point_ray == full.point_ray))
    assert (part.point_ray >= 0).sum() < len(scan) / 20  # only the points near the culled rays were matched


def test_raw_scan_render_equals_the_prepared_scan_render():
    scan = _pattern_scan()
    meshes = [(*_object(x, y), None) for x, y in ((12.0, 3.0), (12.6, 3.2), (25.0, -4.0), (-9.0, 1.0))]
    a = render_lidar(scan, meshes)
    b = render_lidar(prepare_scan(scan), meshes)
    assert len(a.added) > 20 and len(a.removed_index) > 5 and len(np.unique(a.object_index)) == 4
    assert a.scan.tobytes() == b.scan.tobytes()
    np.testing.assert_array_equal(a.ray_index, b.ray_index)
    np.testing.assert_array_equal(a.removed_index, b.removed_index)


def test_grouped_cast_equals_casting_each_group_alone():
    from robustbench3d.sensors.raycast import cast_rays

    (v1, f1), (v2, f2) = _object(10.0, 0.0), _object(10.5, 0.05)  # overlapping along the rays
    rays = BeamPattern.generator(0.01).rays
    pat = BeamPattern.generator(0.01)
    c1 = pat.cull(0.5 * (v1.min(0) + v1.max(0)), 0.6)
    c2 = pat.cull(0.5 * (v2.min(0) + v2.max(0)), 0.6)
    idx = np.union1d(c1, c2)
    d, h = torch.from_numpy(rays.directions[idx]), torch.from_numpy(rays.origins[idx, 2])
    v = torch.from_numpy(np.concatenate([v1, v2]))
    f = np.concatenate([f1, f2 + len(v1)])
    zero = torch.zeros(3, dtype=torch.float64)
    grouped = cast_rays(v, f, d, zero, h, groups=[(np.searchsorted(idx, c1), 0, len(f1)),
                                                  (np.searchsorted(idx, c2), len(f1), len(f))])
    alone = cast_rays(v, f, d, zero, h)
    assert grouped.hit.sum() > 20
    assert torch.equal(grouped.face, alone.face) and torch.equal(grouped.t, alone.t)
    assert grouped.tests <= alone.tests
    # a group restricts its rays to its faces: only mesh 1's rays, against mesh 1 alone
    only1 = cast_rays(v, f, d, zero, h, groups=[(np.searchsorted(idx, c1), 0, len(f1))])
    first = cast_rays(torch.from_numpy(v1), f1, d, zero, h)
    in1 = torch.from_numpy(np.isin(idx, c1))
    assert torch.equal(only1.face[in1], first.face[in1]) and not bool(only1.hit[~in1].any())
    assert bool((only1.face[only1.hit] < len(f1)).all())
    with pytest.raises(ValueError, match="groups\\[0\\]"):
        cast_rays(v, f, d, zero, h, groups=[(np.array([len(idx)]), 0, len(f1))])


def test_multi_car_frame_equals_brute_force_and_embree():
    from robustbench3d.attacks import create_attack
    from robustbench3d.attacks.base import target_cars
    from robustbench3d.sensors.raycast import cast_rays
    from robustbench3d.synth.frame import generate_frame

    frame = generate_frame(0, 0)
    attack = create_attack("random-shape", seed=0)
    placed = attack.place(target_cars(frame.labels), np.random.default_rng(3))
    meshes = [(frame.calib.rect_to_velo_points(v), attack.obj.faces, attack.obj.colors) for v, _ in placed]
    assert len(meshes) == 22
    prep = prepare_scan(frame.scan)
    tr = trace_meshes(prep, meshes)
    # Reference: every ray of a wide region (3x each mesh's radius, 2 deg of azimuth) cast at all faces of all
    # meshes at once (cast_rays without groups: no per-mesh cull, no per-face pairs).
    pattern = prep.pattern
    wide = np.unique(np.concatenate([pattern.cull(0.5 * (v.min(0) + v.max(0)), 3 * np.abs(v - v.mean(0)).max(), 2.0)
                                     for v, _, _ in meshes]))
    origins, dirs = pattern.ray_geometry(wide)
    v_all = np.concatenate([v for v, _, _ in meshes])
    f_all = np.concatenate([f + k * len(meshes[0][0]) for k, (_, f, _) in enumerate(meshes)])
    brute = cast_rays(torch.from_numpy(v_all), f_all, torch.from_numpy(dirs), torch.zeros(3, dtype=torch.float64),
                      torch.from_numpy(origins[:, 2]))
    hit = brute.hit.numpy()
    assert hit.sum() > 1000 and tr.tests < brute.tests / 2
    np.testing.assert_array_equal(tr.ray, wide[hit])  # the same rays, faces and distances, bit for bit
    n_faces = len(meshes[0][1])
    np.testing.assert_array_equal(tr.mesh * n_faces + tr.face, brute.face.numpy()[hit])
    assert tr.t.numpy().tobytes() == brute.t.numpy()[hit].tobytes()
    # Embree (float32, its own kernel) agrees on the rays and the distances.
    prim, tfar = _embree(v_all, f_all, origins, dirs)
    assert (prim[hit] >= 0).all() and (prim[~hit] < 0).sum() >= (~hit).sum() - 2
    assert np.abs(tfar[hit] - tr.t.numpy()).max() < 1e-4
    # The render adds the in-range hits no original point hides, and keeps the scan's bytes.
    res = render_lidar(frame.scan, meshes)
    shown = ~tr.hidden & lm.in_range(tr.t.numpy())
    np.testing.assert_array_equal(res.ray_index, tr.ray[shown])
    kept = np.delete(frame.scan, res.removed_index, axis=0)
    assert res.scan[:len(kept)].tobytes() == kept.tobytes()  # the original points' bytes, in order
    # noise and dropout: a subset of the same rays, each return moved along its own ray by at most 3 sd
    noisy = render_lidar(frame.scan, meshes, rng=np.random.default_rng(9), range_noise_m=0.02, dropout=0.1)
    assert 0.8 * len(res.added) < len(noisy.added) < len(res.added)
    at = np.searchsorted(res.ray_index, noisy.ray_index)
    np.testing.assert_array_equal(res.ray_index[at], noisy.ray_index)
    moved = np.linalg.norm(noisy.added[:, :3].astype(np.float64) - res.added[at, :3], axis=1)
    assert moved.max() <= 3 * 0.02 + 1e-4 and moved.mean() > 0.005


def test_render_options_are_checked_exactly_and_colours_clipped_per_mesh():
    """Bad noise / dropout values and a missing rng get their exact errors; vertex colours outside [0, 1] give
    the reflectance of the clipped colours, each mesh with its own colours (a grey mesh listed first does not
    stop the next one's), and torch vertices that require grad render like the same numpy vertices."""
    pattern = BeamPattern.generator(0.0)
    v, f = _object(12.0)
    far = v + np.array([0.0, 3.0, 0.0])
    prep = prepare_scan(EMPTY, pattern=pattern, ring_ids=np.zeros(0, dtype=np.int64))
    bad = [(dict(dropout=1.0), "render_lidar: field 'dropout': must be in [0, 1), got 1.0"),
           (dict(dropout=1.5), "render_lidar: field 'dropout': must be in [0, 1), got 1.5"),
           (dict(range_noise_m=-0.1), "render_lidar: field 'range_noise_m': must be >= 0, got -0.1"),
           (dict(range_noise_m=np.inf), "render_lidar: field 'range_noise_m': must be >= 0, got inf"),
           (dict(range_noise_m=0.5), "render_lidar: field 'rng': required when dropout or range_noise_m is on")]
    for kwargs, message in bad:
        with pytest.raises(ValueError) as err:
            render_lidar(prep, [(v, f, None)], **kwargs)
        assert str(err.value) == message
    for over, clipped in ((2.0, 1.0), (-1.0, 0.0)):
        a = render_lidar(prep, [(far, f, None), (v, f, np.full_like(v, over))])
        b = render_lidar(prep, [(far, f, None), (v, f, np.full_like(v, clipped))])
        assert (a.object_index == 1).sum() > 50 and np.array_equal(a.added, b.added)
    white = render_lidar(prep, [(far, f, None), (v, f, np.ones_like(v))])
    grey = render_lidar(prep, [(far, f, None), (v, f, None)])
    own = white.object_index == 1
    assert (white.added[own, 3] > grey.added[own, 3]).all()
    vt = torch.tensor(v, requires_grad=True)
    assert np.array_equal(render_lidar(prep, [(vt, f, None)]).added, render_lidar(prep, [(v, f, None)]).added)


def test_mesh_checks_exactly_float32_vertices_and_returns_within_the_range_gate():
    """Each mesh field check with its exact error (a face index equal to the vertex count is outside);
    float32 vertices render as their float64 values; the result carries the differentiable points and the
    pattern; a mesh around the sensor (every hit nearer than the 1 m gate) adds no point, torch path too."""
    pattern = BeamPattern.generator(0.0)
    v, f = _object(12.0)
    prep = prepare_scan(EMPTY, pattern=pattern, ring_ids=np.zeros(0, dtype=np.int64))
    nan = v.copy()
    nan[5, 1] = np.nan
    bad = [((v, f), "expected (vertices, faces, albedo_rgb or None)"),
           ((v[:, :2], f, None), "vertices must be (V, 3) and faces (F, 3)"),
           ((v, np.where(f == 0, len(v), f), None), f"face indices outside [0, {len(v)})"),
           ((nan, f, None), "vertices contain NaN or inf")]
    for mesh, problem in bad:
        with pytest.raises(ValueError) as err:
            render_lidar(prep, [(v, f, None), mesh])
        assert str(err.value) == f"render_lidar: field 'meshes[1]': {problem}"
    v32 = v.astype(np.float32)
    res = render_lidar(prep, [(torch.from_numpy(v32), f, None)])
    same = render_lidar(prep, [(v32.astype(np.float64), f, None)])
    assert len(res.added) > 50 and np.array_equal(res.added, same.added)
    assert np.array_equal(render_lidar(prep, [(v32, f, None)]).added, same.added)  # a float32 numpy array too
    assert res.pattern is pattern and res.added_torch.dtype == torch.float64
    np.testing.assert_allclose(res.added_torch.numpy(), res.added[:, :3], atol=1e-5)
    vs, fs = icosphere(2, 0.5)
    around = [(vs + np.array([0.2, 0.0, 0.1]), fs, None)]
    assert len(trace_meshes(prep, around).ray) == len(pattern.rays)  # every ray hits, all nearer than 1 m
    pts, mesh = render_lidar_torch(prep, around)
    assert len(render_lidar(prep, around).added) == 0 and pts.shape == (0, 3) and len(mesh) == 0


def test_circular_means_equal_the_per_slice_circular_mean_bit_for_bit():
    """The batched per-laser phases (:func:`_circular_means`) equal :func:`_circular_mean` of each slice
    exactly, for tight clusters (all values pass the second test), clusters wrapping the period, uniform
    spreads and clusters with outliers half a period away (their second pass drops values), and tiny slices."""
    from robustbench3d.sensors.lidar_beams import _circular_mean, _circular_means

    rng = np.random.default_rng(7)
    q = 0.09
    for trial in range(200):
        sizes = rng.integers(1, 300 if trial % 2 else 9, int(rng.integers(1, 70)))
        parts = []
        for s in sizes:
            c, kind = rng.uniform(0.0, q), trial % 5 if trial < 100 else rng.integers(0, 5)
            if kind == 0:
                x = c + rng.normal(0.0, 1e-5, s)
            elif kind == 1:
                x = rng.normal(0.0, 1e-5, s)  # around 0 = q: both ends of [0, q)
            elif kind == 2:
                x = rng.uniform(0.0, q, s)
            elif kind == 3:
                x = c + rng.normal(0.0, 1e-4, s) + (rng.random(s) < 0.2) * q / 2
            else:
                x = np.where(rng.random(s) < 0.5, c, c + q / 4) + rng.normal(0.0, 1e-13, s)
            parts.append(x % q)
        x = np.concatenate(parts)
        hi = np.cumsum(sizes)
        lo = hi - sizes
        got = _circular_means(x, lo, hi, q)
        want = np.array([_circular_mean(x[i:j], q) for i, j in zip(lo, hi, strict=True)])
        assert got.tobytes() == want.tobytes()


def test_batched_albedo_and_culls_equal_the_per_mesh_ones():
    """The stacked-colour interpolation of the hits equals interpolating hit by hit in each mesh's own colours
    (grey meshes, torch colours), a colour table of the wrong length is refused, and the stacked bounding
    spheres cull the same rays as culling each mesh alone."""
    from robustbench3d.sensors.lidar_render import _albedo, _culled_rays, _mesh_tensors

    rng = np.random.default_rng(3)
    pattern = BeamPattern.generator(0.01)
    meshes = []
    for k in range(6):
        v, f = _object(8.0 + 3 * k, y=rng.uniform(-4, 4))
        col = None if k == 2 else (torch.tensor(rng.random(v.shape)) if k == 4 else rng.random(v.shape))
        meshes.append((v, f, col))
    meshes.append((np.zeros((3, 3)), np.zeros((0, 3), dtype=np.int64), None))  # no faces: no rays
    mts = _mesh_tensors(meshes)
    culls = _culled_rays(pattern, mts)
    for (v, f, _), rays in zip(meshes, culls, strict=True):
        alone = pattern.cull(0.5 * (v.min(0) + v.max(0)), float(np.linalg.norm(v - 0.5 * (v.min(0) + v.max(0)),
                                                                                    axis=1).max())) if len(f) else []
        assert np.array_equal(rays, alone)
    n = 500
    mesh = rng.integers(0, 6, n)
    face = rng.integers(0, len(meshes[0][1]), n)
    u, v = rng.random(n) * 0.5, rng.random(n) * 0.5
    counts = [len(m[0]) for m in meshes]
    off = np.cumsum([0, *counts])
    corners = np.stack([np.asarray(meshes[i][1])[j] + off[i] for i, j in zip(mesh, face, strict=True)])
    want = np.full((n, 3), 0.5)
    for h in range(n):  # hit by hit: (1 - u - v) c0 + u c1 + v c2 of the hit face's own vertex colours
        col = meshes[mesh[h]][2]
        if col is not None:
            c = np.asarray(col, dtype=np.float64)[np.asarray(meshes[mesh[h]][1])[face[h]]]
            want[h] = (1 - u[h] - v[h]) * c[0] + u[h] * c[1] + v[h] * c[2]
    got = _albedo(meshes, mesh, u, v, corners, counts)
    assert (got[mesh == 2] == np.float32(0.5)).all()
    np.testing.assert_allclose(got, want.astype(np.float32), rtol=0, atol=1e-7)
    short = [*meshes[:1], (meshes[1][0], meshes[1][1], meshes[1][2][:-1]), *meshes[2:]]
    with pytest.raises(ValueError, match=r"field 'meshes\[1\]': albedo must be \(V, 3\) = \(162, 3\)"):
        render_lidar(prepare_scan(EMPTY, pattern=pattern, ring_ids=np.zeros(0, dtype=np.int64)), short)


def test_nearest_and_near_rays_equal_a_brute_force_over_the_lasers_rays():
    """:meth:`BeamPattern.nearest_ray` equals the argmin of the circular azimuth gap over every ray of the
    point's laser (-1 beyond ``max_deg`` or for an unknown laser), for azimuths across the 0/360 seam and outside
    [0, 360); :meth:`BeamPattern.near_rays` flags exactly the points of a ray's laser within two ``max_deg`` bins
    of its bin (a superset of the points whose nearest ray is one of them), for laser-ordered and unordered
    points."""
    rng = np.random.default_rng(11)
    for shift in (0.0, 0.03):
        pattern = BeamPattern(estimate_pattern(EMPTY, np.zeros(0, dtype=np.int64)).phases_deg + shift, shift)
        ring_all, az_all = pattern.rays.ring, pattern.rays.azimuth_deg
        rays_of = [np.flatnonzero(ring_all == k) for k in range(64)]
        n = 1500
        ring = np.sort(rng.integers(-1, 65, n))
        az = np.concatenate([rng.uniform(-0.3, 0.3, n // 3), rng.uniform(359.7, 360.3, n // 3),
                             rng.uniform(-720.0, 720.0, n - 2 * (n // 3))])
        rng.shuffle(az)
        for max_deg in (AZIMUTH_STEP_DEG / 2, 0.5):
            want = np.full(n, -1)
            for k in range(n):
                if 0 <= ring[k] < 64:
                    rays = rays_of[ring[k]]
                    gap = np.abs((az_all[rays] - az[k] + 180.0) % 360.0 - 180.0)
                    if gap.min() <= max_deg:
                        want[k] = rays[np.argmin(gap)]
            got = pattern.nearest_ray(ring, az, max_deg)
            assert np.array_equal(got, want)
            index = np.unique(rng.choice(want[want >= 0], 40))
            bins = int(np.ceil(360.0 / max_deg))
            ray_bin = np.floor(az_all[index] / max_deg).astype(np.int64)
            point_bin = np.floor((az % 360.0) / max_deg).astype(np.int64) % bins
            near = np.zeros(n, dtype=bool)
            for r, b in zip(ring_all[index], ray_bin, strict=True):
                near |= (ring == r) & (np.abs((point_bin - b + bins // 2) % bins - bins // 2) <= 2)
            assert np.array_equal(pattern.near_rays(index, ring, az, max_deg), near)
            assert near[np.isin(got, index)].all()
            perm = rng.permutation(n)
            assert np.array_equal(pattern.near_rays(index, ring[perm], az[perm], max_deg), near[perm])


def test_pattern_cache_renders_like_no_cache_and_keeps_the_pattern_under_the_scans_key():
    """A raw scan rendered through a :class:`PatternCache` (cold: estimated and stored; warm: from memory) gives
    the scan of the render without one, bit for bit, and the cache then holds the estimate under the key of the
    scan and the ring ids given."""
    from robustbench3d.sensors.pattern_cache import PatternCache

    scan = _pattern_scan()
    ring = scan_ring_ids(scan)
    meshes = [(*_object(x, y), None) for x, y in ((12.0, 3.0), (-9.0, 1.0))]
    ref = render_lidar(scan, meshes, ring_ids=ring)
    cache = PatternCache(None)
    assert cache.lookup(scan, ring)[1] is None
    for _ in ("cold", "warm"):
        got = render_lidar(scan, meshes, ring_ids=ring, patterns=cache)
        assert got.scan.tobytes() == ref.scan.tobytes() and len(got.added) > 20
        np.testing.assert_array_equal(got.removed_index, ref.removed_index)
        kept = cache.lookup(scan, ring)[1]
        assert kept is not None and kept.phases_deg.tobytes() == estimate_pattern(scan, ring).phases_deg.tobytes()
    assert cache.lookup(scan, None)[1] is None  # the derived-ring key is another scan's


def test_no_meshes_leave_a_raw_scan_unchanged():
    scan = _pattern_scan()[::7]
    res = render_lidar(scan, [])
    assert res.scan.tobytes() == scan.tobytes() and len(res.added) == 0 and len(res.removed_index) == 0


def test_dropout_keeps_a_return_whose_draw_equals_the_probability_and_noise_adds_the_clipped_draws():
    """Dropout keeps a return iff its uniform draw is >= ``dropout`` (P(drop) = dropout for draws in [0, 1)):
    a probability equal to one of the draws keeps that return. Range noise adds the clipped N(0, sd) draws to
    each return's range along its ray."""
    pattern = BeamPattern.generator(0.0)
    v, f = _object(10.0)
    prep = prepare_scan(EMPTY, pattern=pattern, ring_ids=np.zeros(0, dtype=np.int64))
    clean = render_lidar(prep, [(v, f, None)])
    n = len(clean.added)
    draws = np.random.default_rng(5).random(n)
    p = float(draws[n // 2])
    drop = render_lidar(prep, [(v, f, None)], rng=np.random.default_rng(5), dropout=p)
    np.testing.assert_array_equal(drop.ray_index, clean.ray_index[draws >= p])
    assert n // 2 in np.flatnonzero(draws >= p)
    sd = 0.05
    noisy = render_lidar(prep, [(v, f, None)], rng=np.random.default_rng(6), range_noise_m=sd)
    noise = np.clip(np.random.default_rng(6).normal(0.0, sd, n), -3 * sd, 3 * sd)
    assert np.abs(noise).max() == 3 * sd  # some draws are clipped
    o, d = pattern.rays.origins[clean.ray_index], pattern.rays.directions[clean.ray_index]
    t_clean = ((clean.added_torch.detach().numpy() - o) * d).sum(1)
    t_noisy = ((noisy.added_torch.detach().numpy() - o) * d).sum(1)
    np.testing.assert_allclose(t_noisy - t_clean, noise, atol=1e-9)


def test_meshes_of_different_vertex_counts_reflect_like_each_alone():
    """Two meshes with different vertex counts (stacked: the second's vertex indices are offset) give each
    return the reflectance it has when its mesh is rendered alone (normals and colours of its own face), with
    colours as numpy or as a torch tensor that requires grad."""
    pattern = BeamPattern.generator(0.0)
    prep = prepare_scan(EMPTY, pattern=pattern, ring_ids=np.zeros(0, dtype=np.int64))
    small = _object(12.0, 3.0, level=1)
    big = _object(12.0, 0.3, level=2)
    assert len(small[0]) != len(big[0])
    rng = np.random.default_rng(8)
    colour = rng.uniform(0.0, 1.0, big[0].shape)
    for col in (colour, torch.tensor(colour, requires_grad=True)):
        both = render_lidar(prep, [(*small, None), (*big, col)])
        for i, alone in enumerate((render_lidar(prep, [(*small, None)]), render_lidar(prep, [(*big, colour)]))):
            own = both.object_index == i
            assert own.sum() > 20
            np.testing.assert_array_equal(both.ray_index[own], alone.ray_index)
            assert both.added[own].tobytes() == alone.added.tobytes()


@pytest.mark.parametrize(("size", "frac"), [(1.0, 1e-5), (3e-8, 0.05)])
def test_a_ray_through_a_face_near_its_farthest_corner_is_a_candidate(size, frac):
    """The per-face cull's sphere holds the whole face: a laser ray crossing a triangle in a plane x = const
    ``frac`` of the way from its corner farthest from the box centre towards the centroid passes just inside
    the radius from the centre (checked here), and must still hit there: a 0.3 m face (within 1/1.001 of the
    radius), and a face of 9e-9 m, whose ray only the sphere's absolute 1e-9 m keeps (1e-3 of its radius is less)."""
    pattern = BeamPattern.generator(0.0)
    prep = prepare_scan(EMPTY, pattern=pattern, ring_ids=np.zeros(0, dtype=np.int64))
    rays = pattern.rays
    near_x = np.flatnonzero(np.abs(rays.azimuth_deg - 1.0) < 0.1)
    k = int(near_x[np.argmin(np.abs(rays.directions[near_x, 2]))])
    o, d = rays.origins[k], rays.directions[k]
    hit = o + (10.0 - o[0]) / d[0] * d
    tri = size * np.array([[0.0, 0.0, 0.0], [0.0, 0.3, 0.0], [0.0, 0.15, 0.27]])
    centre = 0.5 * (tri.min(0) + tri.max(0))
    dist = np.linalg.norm(tri - centre, axis=1)
    far = int(dist.argmax())
    target = tri[far] + frac * (tri.mean(0) - tri[far])
    v = hit + (tri - target)  # the ray meets the face at target, at x = 10
    w = hit - target + centre - o
    closest = np.linalg.norm(w - (w @ d) * d)
    # within the radius, but beyond it shrunk by 1e-3 (0.3 m) or beyond it inflated by 1e-3 less 1e-9 m (tiny)
    assert (dist.max() * (1 + 1e-3) - 1e-9 if size < 1e-6 else dist.max() / 1.001) < closest < dist.max()
    res = render_lidar(prep, [(v, np.array([[0, 1, 2]]), None)])
    assert k in res.ray_index
    at = list(res.ray_index).index(k)
    np.testing.assert_allclose(res.added_torch.detach().numpy()[at], hit, atol=1e-9)


def test_all_pairs_by_hand():
    """The full-scene pairs: every (ray, face), ray-major, in chunks of whole rays (at least one)."""
    def chunks(n_rays: int, n_faces: int, chunk: int) -> list[tuple[list[int], list[int]]]:
        return [(r.tolist(), f.tolist()) for r, f in lr._all_pairs(n_rays, n_faces, chunk)]

    assert chunks(5, 3, 7) == [([0, 0, 0, 1, 1, 1], [0, 1, 2, 0, 1, 2]), ([2, 2, 2, 3, 3, 3], [0, 1, 2, 0, 1, 2]),
                               ([4, 4, 4], [0, 1, 2])]
    assert chunks(2, 3, 2) == [([0, 0, 0], [0, 1, 2]), ([1, 1, 1], [0, 1, 2])]  # a chunk below one ray: one ray
    assert chunks(3, 1, 3) == [([0, 1, 2], [0, 0, 0])]
    assert chunks(0, 3, 7) == []
    assert chunks(2, 0, 1) == [([], []), ([], [])]  # no faces: one empty chunk per ray
    assert all(r.dtype == f.dtype == torch.int64 for r, f in lr._all_pairs(5, 3, 7))


def test_full_scene_cast_tests_every_pair_and_finds_the_culled_hits(monkeypatch):
    """``cull=False`` on an empty prepared scan: every ray of the pattern at every face of two meshes, in
    chunks that do not divide the rays; the same hits as the culled render and as Embree."""
    pattern = BeamPattern.generator(0.0231)
    quad = QUAD
    meshes = [(_plate(6.0, 0.0), quad), (_plate(-9.0, -1.0), quad)]
    prep = prepare_scan(EMPTY, pattern=pattern, ring_ids=np.zeros(0, dtype=np.int64))
    n_rays, n_faces = len(pattern.rays), 4
    monkeypatch.setattr(lr, "FULL_SCENE_CHUNK_PAIRS", 7777 * n_faces + 3)
    assert n_rays % 7777 != 0
    full = render_lidar(prep, [(v, f, None) for v, f in meshes], cull=False)
    culled = render_lidar(prep, [(v, f, None) for v, f in meshes])
    assert full.tests == n_rays * n_faces > 100 * culled.tests
    assert len(culled.ray_index) > 100 and full.scan.tobytes() == culled.scan.tobytes()
    assert np.array_equal(full.ray_index, culled.ray_index) and np.array_equal(full.face_index, culled.face_index)
    v = np.concatenate([_plate(6.0, 0.0), _plate(-9.0, -1.0)])
    prim, tfar = _embree(v, np.concatenate([quad, quad + 4]), pattern.rays.origins, pattern.rays.directions)
    hit = np.flatnonzero(prim >= 0)
    np.testing.assert_array_equal(np.sort(full.ray_index), hit[lm.in_range(tfar[hit])])


def test_given_ring_ids_are_used_not_recovered_from_the_scan():
    """The caller's laser ids decide the pattern of a raw scan (each laser's elevation comes from its id): ids
    shifted by one laser give other rays than the ids recovered from the geometry, in every render path
    (numpy, torch, through a pattern cache), while the recovered ids given explicitly change nothing."""
    from robustbench3d.sensors.pattern_cache import PatternCache

    scan = _pattern_scan()
    ring = scan_ring_ids(scan)
    shifted = (ring + 1) % 64
    meshes = [(*_object(x, y), None) for x, y in ((12.0, 3.0), (-9.0, 1.0))]
    derived = render_lidar(scan, meshes)
    assert render_lidar(scan, meshes, ring_ids=ring).scan.tobytes() == derived.scan.tobytes()
    moved = render_lidar(scan, meshes, ring_ids=shifted)
    assert len(derived.added) > 20 and moved.added.tobytes() != derived.added.tobytes()
    cached = render_lidar(scan, meshes, ring_ids=shifted, patterns=PatternCache(None))
    assert cached.scan.tobytes() == moved.scan.tobytes()
    pts, _ = render_lidar_torch(scan, meshes, ring_ids=shifted)
    np.testing.assert_array_equal(pts.detach().numpy().astype(np.float32), moved.added[:, :3])
    assert not np.array_equal(render_lidar_torch(scan, meshes)[0].detach().numpy().astype(np.float32),
                              moved.added[:, :3])


def test_full_scene_render_of_a_raw_scan_equals_the_culled_one():
    """``cull=False`` on a raw scan (pattern estimated from it, every point matched to its ray, every ray at
    every face): the culled render's scan bit for bit, with noise and dropout, with the ring ids derived or
    given, and through a pattern cache."""
    from robustbench3d.sensors.pattern_cache import PatternCache

    scan = _pattern_scan()
    meshes = [(_plate(12.0, 3.0), QUAD, None), (_plate(-9.0, 1.0), QUAD, None)]
    for ring_ids, patterns in ((None, None), (scan_ring_ids(scan), None), (None, PatternCache(None))):
        culled, full = (render_lidar(scan, meshes, rng=np.random.default_rng(3), range_noise_m=0.02, dropout=0.05,
                                     ring_ids=ring_ids, patterns=patterns, cull=cull) for cull in (True, False))
        assert len(culled.added) > 20 and len(culled.removed_index) > 5
        assert full.scan.tobytes() == culled.scan.tobytes() and full.tests == len(full.pattern.rays) * 4
        np.testing.assert_array_equal(full.removed_index, culled.removed_index)


def test_raw_scan_through_a_warm_pattern_cache_with_a_mesh_out_of_sight_and_one_laser():
    """A raw laser-ordered scan rendered through a warm pattern cache (azimuths computed only for the lasers the
    meshes can reach): a mesh no ray reaches leaves the scan unchanged with no test made, and a strip only one
    laser crosses renders (hits and the returns it removes) as without the cache."""
    from robustbench3d.sensors.pattern_cache import PatternCache

    scan = _pattern_scan()
    pattern = estimate_pattern(scan, scan_ring_ids(scan))
    above = [(_plate(0.0, 0.0) + np.array([0.0, 0.0, 80.0]), QUAD, None)]  # straight up: beyond every laser
    elevation = float(pattern.sensor.elevation_deg[40])
    z = 10.0 * np.tan(np.radians(elevation)) + pattern.sensor.origin_z[40]
    strip = [(np.array([[10.0, -1.0, z - 0.004], [10.0, 1.0, z - 0.004], [10.0, 1.0, z + 0.004],
                        [10.0, -1.0, z + 0.004]]), QUAD, None)]
    cache = PatternCache(None)
    render_lidar(scan, above, patterns=cache)  # cold: estimates and keeps the pattern
    for meshes in (above, strip):
        plain, warm = render_lidar(scan, meshes), render_lidar(scan, meshes, patterns=cache)
        assert warm.scan.tobytes() == plain.scan.tobytes() and warm.tests == plain.tests
        np.testing.assert_array_equal(warm.removed_index, plain.removed_index)
    assert len(plain.added) > 5 and len(plain.removed_index) > 0  # the strip's
    assert set(pattern.ray_rings(plain.ray_index)) == {40}
    gone = render_lidar(scan, above, patterns=cache)
    assert gone.scan.tobytes() == scan.tobytes() and gone.tests == 0 and len(gone.added) == 0


def test_a_scan_of_the_wrong_shape_is_refused_naming_the_field():
    mesh = [(_plate(10.0, 0.0), QUAD, None)]
    for bad in (np.zeros((5, 3), np.float32), np.zeros(8, np.float32)):
        with pytest.raises(ValueError) as err:
            render_lidar(bad, mesh)
        assert str(err.value) == f"render_lidar: field 'scan': expected shape (N, 4), got {bad.shape}"


def test_cull_and_sphere_rays_hold_every_ray_within_the_radius_down_to_nanometre_spheres():
    """Brute force over every ray of the pattern: each ray passing within a sphere (distance from the centre to
    the half-line, float64) is in :meth:`BeamPattern.cull` and :meth:`BeamPattern.sphere_rays`, for spheres of
    1e-9 m to 1 m centred 0.999 r beside a ray 1-80 m out (a sphere seen under 1e-11 rad: the cone test's cos
    rounds to 1)."""
    pattern = BeamPattern.generator(0.013)
    rays = pattern.rays
    rng = np.random.default_rng(7)
    for k in rng.choice(len(rays.origins), 40, replace=False):
        o, d = rays.origins[k], rays.directions[k]
        r = 10.0 ** rng.uniform(-9, 0)
        side = np.cross(d, rng.normal(size=3))
        c = o + rng.uniform(1.0, 80.0) * d + 0.999 * r * side / np.linalg.norm(side)
        w = c - rays.origins
        t = np.maximum((w * rays.directions).sum(1), 0.0)
        within = np.flatnonzero(np.linalg.norm(w - t[:, None] * rays.directions, axis=1) <= r * (1 - 1e-6))
        assert k in within
        assert np.isin(within, pattern.cull(c, r)).all()
        _, near = pattern.sphere_rays(c[None], np.array([r]), np.array([0]), np.array([pattern.sensor.num_lasers - 1]))
        assert np.isin(within, near).all()


def test_prepare_scan_keeps_the_given_ring_ids_refuses_a_wrong_count_and_does_not_copy_a_float32_scan():
    """``prepare_scan`` uses the caller's laser ids (not the recovered ones), a wrong number of ids gets the exact
    error naming the render (through ``prepare_scan`` and ``render_lidar``), and a float32 scan is used as it is
    (no copy of the ~2 MB array), a float64 one converted to float32."""
    scan = _pattern_scan()
    ring = scan_ring_ids(scan)
    shifted = (ring + 1) % 64
    np.testing.assert_array_equal(prepare_scan(scan, shifted).ring, shifted)
    message = f"render_lidar: field 'ring_ids': {len(scan) - 1} ids for {len(scan)} points"
    for call in (lambda: prepare_scan(scan, ring[1:]),
                 lambda: render_lidar(scan, [(_plate(10.0, 0.0), QUAD, None)], ring_ids=ring[1:])):
        with pytest.raises(ValueError) as err:
            call()
        assert str(err.value) == message
    prep = prepare_scan(scan, ring)
    assert prep.scan is scan or np.shares_memory(prep.scan, scan)
    wide = prepare_scan(scan.astype(np.float64), ring)
    assert wide.scan.dtype == np.float32 and wide.scan.tobytes() == scan.tobytes()


def test_prepared_scan_ranges_ray_order_and_points_on_by_hand():
    """Per point (scan order shuffled, three returns on each of 12 rays, lasers 0 and 63 among them): its ray and
    its range sqrt(x^2 + y^2 + (z - h0)^2) from its own laser's origin (0, 0, h0); a laser id the sensor does
    not have (ids are not checked: -100, -1, 64, 200) gets no ray and the range from the velodyne origin
    (h0 = 0). ``by_ray`` is np.argsort(point_ray, kind="stable") (no ray first, each ray's points in scan
    order), ``sorted_ray`` = point_ray[by_ray], and ``points_on`` gives the brute-force (ray, point) pairs;
    also when the matching is restricted to a few rays (most points then have no ray) or to none. The sensor's
    lasers all sit at different heights here (the HDL-64E's first two and last two share theirs)."""
    from robustbench3d.sensors.hdl64e import HDL64E

    pattern = BeamPattern(BeamPattern.generator(0.0).phases_deg, 0.0, HDL64E(origin_z=np.linspace(0.25, 0.1, 64)))
    rays = pattern.rays
    rng = np.random.default_rng(2)
    on = np.concatenate([pattern.ring_start[[0, 63]] + [5, 9], rng.choice(len(rays), 10, replace=False)])
    ray_of = np.repeat(on, 3)
    t = np.tile([5.0, 12.0, 30.0], len(on))
    pts = rays.origins[ray_of] + t[:, None] * rays.directions[ray_of]
    unknown = np.array([-100, -1, 64, 200])
    pts = np.concatenate([pts, rng.uniform(-20.0, 20.0, (len(unknown), 3))])
    ring = np.concatenate([rays.ring[ray_of], unknown])
    want_ray = np.concatenate([ray_of, np.full(len(unknown), -1)])
    perm = rng.permutation(len(pts))
    pts, ring, want_ray = pts[perm], ring[perm], want_ray[perm]
    scan = np.concatenate([pts, np.full((len(pts), 1), 0.3)], 1).astype(np.float32)
    x, y, z = scan[:, :3].astype(np.float64).T
    known = (ring >= 0) & (ring < 64)
    h0 = np.where(known, pattern.sensor.origin_z[np.where(known, ring, 0)], 0.0)
    want_range = np.sqrt(x ** 2 + y ** 2 + (z - h0) ** 2)
    assert {0, 63} <= set(ring[known].tolist())
    for rays_given in (None, on[[0, 1, 4]]):
        prep = prepare_scan(scan, ring, pattern, rays_given)
        matched = want_ray >= 0 if rays_given is None else np.isin(want_ray, rays_given)
        np.testing.assert_array_equal(prep.point_ray[matched], want_ray[matched])
        assert (prep.point_ray[~known] == -1).all() and (prep.point_ray[~matched] == -1).all()
        ranged = matched | ~known if rays_given is None else matched  # the others: NaN (not near the rays)
        np.testing.assert_allclose(prep.range_m[ranged], want_range[ranged], rtol=1e-15, atol=0)
        assert prep.by_ray.dtype == prep.sorted_ray.dtype == prep.point_ray.dtype == np.int64
        np.testing.assert_array_equal(prep.by_ray, np.argsort(prep.point_ray, kind="stable"))
        np.testing.assert_array_equal(prep.sorted_ray, prep.point_ray[prep.by_ray])
        query = np.concatenate([on, [on[0], len(rays) - 1]])  # a ray asked twice, one without points
        owner, point = prep.points_on(query)
        want = sorted((i, p) for i, r in enumerate(query) for p in np.flatnonzero(prep.point_ray == r))
        assert sorted(zip(owner.tolist(), point.tolist(), strict=True)) == want
        assert len(want) == 3 * (len(on) if rays_given is None else 3) + 3
    none = prepare_scan(scan, ring, pattern, [])  # no rays (a plain empty list): no point matched
    assert (none.point_ray == -1).all() and np.isnan(none.range_m).all() and (none.sorted_ray == -1).all()


def test_a_mesh_no_ray_reaches_traces_to_empty_fields_of_the_documented_dtypes_and_renders_nothing():
    """A mesh straight above the sensor (no laser's cone reaches it): :func:`trace_meshes` gives K = 0 hits in the
    documented dtypes (int64 rays, meshes, faces and removed points, torch float64 t, u, v, bool hidden), and
    listed with a visible mesh (first or second) it changes nothing of that mesh's render."""
    pattern = BeamPattern.generator(0.0)
    prep = prepare_scan(EMPTY, pattern=pattern, ring_ids=np.zeros(0, dtype=np.int64))
    above = (_plate(0.0, 0.0) + np.array([0.0, 0.0, 80.0]), QUAD, None)
    tr = trace_meshes(prep, [above])
    for a in (tr.ray, tr.mesh, tr.face, tr.removed_index):
        assert a.shape == (0,) and a.dtype == np.int64
    for a in (tr.t, tr.u, tr.v):
        assert isinstance(a, torch.Tensor) and a.shape == (0,) and a.dtype == torch.float64
    assert tr.hidden.shape == (0,) and tr.hidden.dtype == bool and tr.tests == 0
    seen = (_plate(10.0, 0.0), QUAD, None)
    alone = render_lidar(prep, [seen])
    assert len(alone.added) > 20
    for meshes, index in (([seen, above], 0), ([above, seen], 1)):
        res = render_lidar(prep, meshes)
        assert res.added.tobytes() == alone.added.tobytes() and res.tests == alone.tests
        assert (res.object_index == index).all()


def test_a_scan_return_exactly_at_the_mesh_hit_is_kept_and_the_mesh_shown():
    """The occlusion rules at their boundary (module docstring): a scan point on a hit ray is removed only when
    farther than the hit and hides the mesh only when nearer, so at exactly the hit's range (a plate moved by
    ulps until the cast's t equals the point's float64 range bit for bit) the point is kept and the mesh's
    return added; the nearest plate positions on either side give the other two cases."""
    pattern = BeamPattern.generator(0.0)
    rays = pattern.rays
    k = int(pattern.ring_start[20] + 3)
    o, d = rays.origins[k], rays.directions[k]
    point = (o + 10.0 * d).astype(np.float32)
    scan = np.append(point, np.float32(0.3))[None]
    prep = prepare_scan(scan, ring_ids=rays.ring[[k]], pattern=pattern)
    px, py, pz = point.astype(np.float64)
    rp = float(np.sqrt(px ** 2 + py ** 2 + (pz - o[2]) ** 2))
    assert prep.point_ray[0] == k and prep.range_m[0] == rp

    def plate_at(x):
        return np.array([[x, -1.0, -2.0], [x, 1.0, -2.0], [x, 1.0, 2.0], [x, -1.0, 2.0]])

    def t_of(x):
        tr = trace_meshes(prep, [(plate_at(x), QUAD, None)])
        return float(tr.t.numpy()[list(tr.ray).index(k)])

    x = o[0] + rp * d[0]  # the plate x = const through the point, up to rounding
    for _ in range(50):
        t = t_of(x)
        if t == rp:
            break
        x = np.nextafter(x, np.inf if t < rp else -np.inf)
    assert t == rp
    found = {0.0: x}
    for side, towards in ((-1.0, -np.inf), (1.0, np.inf)):
        y = np.nextafter(x, towards)
        for _ in range(50):
            if t_of(y) != rp:
                break
            y = np.nextafter(y, towards)
        found[side] = y
        assert np.sign(t_of(y) - rp) == side
    for side, removed, shown in ((-1.0, [0], True), (0.0, [], True), (1.0, [], False)):
        res = render_lidar(prep, [(plate_at(found[side]), QUAD, None)])
        assert list(res.removed_index) == removed and (k in res.ray_index) == shown


def test_mesh_arrays_of_other_dtypes_and_list_colours_render_as_their_float64_int64_values():
    """Mesh inputs are converted, not trusted: numpy vertices of any real dtype (float16, longdouble; here
    exactly representable values) render as the same float64 vertices, reflectance included; faces of another
    integer dtype (int32, uint64) as int64 faces; colours given as nested lists as the same numpy colours. A
    colour table of the wrong length is refused with its shape as a plain tuple, for a torch table too."""
    pattern = BeamPattern.generator(0.0)
    prep = prepare_scan(EMPTY, pattern=pattern, ring_ids=np.zeros(0, dtype=np.int64))
    v, f = _object(12.0)
    v = v.astype(np.float16).astype(np.float64)  # values every dtype below holds exactly
    colour = np.random.default_rng(4).uniform(0.0, 1.0, v.shape)
    ref = render_lidar(prep, [(v, f, colour)])
    assert len(ref.added) > 100
    for vv, ff, cc in ((v.astype(np.float16), f, colour), (v.astype(np.longdouble), f, colour),
                       (v, f.astype(np.int32), colour), (v, f.astype(np.uint64), colour), (v, f, colour.tolist())):
        res = render_lidar(prep, [(vv, ff, cc)])
        assert res.added.tobytes() == ref.added.tobytes()
        np.testing.assert_array_equal(res.face_index, ref.face_index)
    for bad in (colour[:-1], torch.tensor(colour[:-1]), colour[:-1].tolist()):
        with pytest.raises(ValueError) as err:
            render_lidar(prep, [(v, f, bad)])
        assert str(err.value) == (f"render_lidar: field 'meshes[0]': albedo must be (V, 3) = ({len(v)}, 3) "
                                  f"(one colour per vertex), got ({len(v) - 1}, 3)")


def test_albedo_interpolates_each_hits_vertex_colours_in_float32_by_hand():
    """:func:`_albedo` by hand for two hits on a coloured triangle and one on a grey mesh: (1 - u - v) c0 + u c1
    + v c2, clipped to [0, 1], as the documented (K, 3) float32."""
    from robustbench3d.sensors.lidar_render import _albedo

    col = np.array([[0.2, 0.4, 0.6], [1.0, 0.0, 0.5], [0.0, 1.0, 2.0]])
    meshes = [(np.zeros((3, 3)), np.array([[0, 1, 2]]), None), (np.zeros((3, 3)), np.array([[0, 1, 2]]), col)]
    got = _albedo(meshes, np.array([1, 0, 1]), np.array([0.25, 0.5, 0.0]), np.array([0.5, 0.5, 1.0]),
                  np.array([[3, 4, 5], [0, 1, 2], [3, 4, 5]]), [3, 3])
    want = np.array([[0.25 * 0.2 + 0.25 * 1.0, 0.25 * 0.4 + 0.5, 0.25 * 0.6 + 0.25 * 0.5 + 0.5 * 2.0],
                     [0.5, 0.5, 0.5], [0.0, 1.0, 2.0]]).clip(0.0, 1.0)
    assert got.dtype == np.float32 and got.shape == (3, 3)
    np.testing.assert_array_equal(got, want.astype(np.float32))


def test_warm_pattern_cache_renders_like_no_cache_on_an_unordered_scan_and_one_starting_with_another_laser():
    """Through a warm pattern cache the azimuths are computed only over the span of the lasers the meshes reach,
    which needs a laser-ordered scan: a shuffled scan whose first point has the lowest laser id (ordered-looking
    from its first row) and a laser-ordered scan of one point of laser 54 then all of lasers 55-63, with a strip
    (at azimuth 90 deg, where the lowest lasers fire) only lasers 55-63 reach (the span then starts at row 1 and
    runs to the end), render as without the cache."""
    from robustbench3d.sensors.pattern_cache import PatternCache

    full = _pattern_scan()
    full_ring = scan_ring_ids(full)
    pattern = estimate_pattern(full, full_ring)
    top = 10.0 * np.tan(np.radians(pattern.sensor.elevation_deg[55])) + pattern.sensor.origin_z[55] + 0.02
    strip = [(np.array([[-0.2, 10.0, -4.7], [0.2, 10.0, -4.7], [0.2, 10.0, top], [-0.2, 10.0, top]]), QUAD, None)]
    rng = np.random.default_rng(6)
    perm = np.concatenate([[0], 1 + rng.permutation(len(full) - 1)])  # row 0 is laser 0's
    last = np.concatenate([np.flatnonzero(full_ring == 54)[:1], np.flatnonzero(full_ring >= 55)])
    for scan, ring in ((full[perm], full_ring[perm]), (full[last], full_ring[last])):
        cache = PatternCache(None)
        render_lidar(scan, strip, ring_ids=ring, patterns=cache)  # cold: estimates and keeps the pattern
        plain, warm = render_lidar(scan, strip, ring_ids=ring), render_lidar(scan, strip, ring_ids=ring, patterns=cache)
        assert len(plain.added) > 20 and len(plain.removed_index) > 5
        assert set(plain.pattern.ray_rings(plain.ray_index)) == set(range(55, 64))
        assert warm.scan.tobytes() == plain.scan.tobytes()
        np.testing.assert_array_equal(warm.removed_index, plain.removed_index)
    assert ring[0] == 54 and ring[1] == 55 and (np.diff(ring) >= 0).all()
    corners = strip[0][0]
    cull = pattern.cull(0.5 * (corners.min(0) + corners.max(0)), np.linalg.norm(corners[0] - corners[2]) / 2)
    assert set(pattern.ray_rings(cull)) <= set(range(55, 64))  # the lasers of the cull: 55 is the lowest id


def test_face_pairs_are_the_face_sphere_rays_within_the_mesh_cull():
    """The cast tests exactly the pairs of :func:`_face_pairs`' definition: each face with the rays of its mesh's
    cull that can pass through the face's sphere (box centre, corner radius inflated by 1e-3, +1e-9 m;
    :meth:`BeamPattern.sphere_rays` over the cull's lasers). A single 2 m triangle, whose sphere is the mesh's
    own inflated, placed so that laser 20's cone barely enters the mesh's sphere: the face's sphere then reaches
    rays of that laser beyond the cull's azimuth margin, which are not cast; the hits are Embree's."""
    pattern = BeamPattern.generator(0.0)
    prep = prepare_scan(EMPTY, pattern=pattern, ring_ids=np.zeros(0, dtype=np.int64))
    rho, a = 6.0, 1.0
    r = a * np.sqrt(2.0)
    phi, h = np.radians(pattern.sensor.elevation_deg[20]), pattern.sensor.origin_z[20]
    zc = h + (r * (1 - 1e-4) + rho * np.sin(phi)) / np.cos(phi)  # laser 20 passes 1e-4 r inside the sphere
    v = np.array([[rho, -a, zc - a], [rho, a, zc - a], [rho, 0.0, zc + a]])
    f = np.array([[0, 1, 2]])
    centre = 0.5 * (v.min(0) + v.max(0))
    assert np.linalg.norm(v - centre, axis=1).max() == pytest.approx(r, rel=1e-12)
    cull = pattern.cull(centre, r)
    rings = pattern.ray_rings(cull)
    assert rings.max() == 20
    _, near = pattern.sphere_rays(centre[None], np.array([r * (1 + 1e-3) + 1e-9]), np.array([rings.min()]),
                                  np.array([rings.max()]))
    assert len(np.setdiff1d(near, cull)) >= 2  # face-sphere rays outside the cull
    tr = trace_meshes(prep, [(v, f, None)])
    assert tr.tests == np.isin(near, cull).sum()
    prim, _ = _embree(v, f, pattern.rays.origins, pattern.rays.directions)
    np.testing.assert_array_equal(tr.ray, np.flatnonzero(prim >= 0))
