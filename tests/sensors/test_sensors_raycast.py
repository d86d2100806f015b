"""The torch ray/triangle core against hand-computed cases, an independent textbook Möller–Trumbore loop,
float64 finite differences, and the degenerate cases (grazing rays, edges, vertices, zero-area faces, rays
from inside, all-miss)."""

from __future__ import annotations

import itertools
import warnings

import numpy as np
import pytest
import torch

from robustbench3d.sensors.mesh import icosphere
from robustbench3d.sensors.ray_faces import back_faces
from robustbench3d.sensors.raycast import PairCaster, cast_ray_pair_chunks, cast_ray_pairs, cast_rays

torch.set_num_threads(1)
F64 = torch.float64


def _t(a: np.ndarray, dtype: torch.dtype = F64) -> torch.Tensor:
    return torch.as_tensor(np.asarray(a), dtype=dtype)


def _reference(v: np.ndarray, f: np.ndarray, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Nearest t per ray (inf on a miss): the textbook per-ray Möller–Trumbore of reference.md §4.4."""
    best = np.full(len(d), np.inf)
    v0 = v[f[:, 0]]
    e1, e2 = v[f[:, 1]] - v0, v[f[:, 2]] - v0
    for i in range(len(d)):
        p = np.cross(d[i], e2)
        det = (e1 * p).sum(1)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = o[i] - v0
            u = (s * p).sum(1) / det
            q = np.cross(s, e1)
            w = (d[i] * q).sum(1) / det
            t = (e2 * q).sum(1) / det
            ok = (np.abs(det) > 1e-12) & (u >= 0) & (w >= 0) & (u + w <= 1) & (t > 1e-6)
        if ok.any():
            best[i] = t[ok].min()
    return best


def _blob(level: int = 2, centre=(8.0, 0.5, 0.2)) -> tuple[np.ndarray, np.ndarray]:
    v, f = icosphere(level, 0.4)
    r = 1 + 0.2 * np.sin(3 * v[:, 0] / 0.4) * np.cos(2 * v[:, 1] / 0.4)
    return v * r[:, None] + np.asarray(centre), f


def _rays_at(centre: np.ndarray, n: int, spread: float, rng: np.random.Generator):
    az0, el0 = np.arctan2(centre[1], centre[0]), np.arctan2(centre[2], np.hypot(centre[0], centre[1]))
    az = az0 + rng.uniform(-spread, spread, n)
    el = el0 + rng.uniform(-spread, spread, n)
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], 1)


def _every_pair(n_rays: int, n_faces: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(ray, face) int64 indices of every ray x face pair, ray-major."""
    return torch.arange(n_rays).repeat_interleave(n_faces), torch.arange(n_faces).repeat(n_rays)


def test_hand_computed_triangle():
    v = _t([[2.0, 0.0, 0.0], [2.0, 1.0, 0.0], [2.0, 0.0, 1.0]])  # plane x = 2
    f = torch.tensor([[0, 1, 2]])
    d = _t([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    origin = _t([0.0, 0.25, 0.5])
    hits = cast_rays(v, f, d, origin, _t([0.0, -1.0, 0.0, 0.0]), offset_axis=(0.0, 0.0, 1.0))
    # ray 0 hits (2, .25, .5): u = .25 (vertex 1 weight), v = .5; ray 1 starts at z = -0.5: miss;
    # ray 2 points away: miss (t < 0); ray 3 = ray 0
    assert hits.hit.tolist() == [True, False, False, True]
    assert hits.face.tolist() == [0, -1, -1, 0]
    np.testing.assert_allclose(hits.t.numpy(), [2.0, 0.0, 0.0, 2.0], atol=1e-15)
    np.testing.assert_allclose(hits.u.numpy(), [0.25, 0, 0, 0.25], atol=1e-15)
    np.testing.assert_allclose(hits.v.numpy(), [0.5, 0, 0, 0.5], atol=1e-15)
    pts = hits.points(origin + _t([0.0, 0.0, 0.0]), d)
    np.testing.assert_allclose(pts[0].numpy(), [2.0, 0.25, 0.5], atol=1e-15)
    np.testing.assert_array_equal(pts[1].numpy(), [0.0, 0.0, 0.0])


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_matches_textbook_reference_with_laser_heights(dtype):
    rng = np.random.default_rng(3)
    v, f = _blob()
    f = f[:301]  # not a multiple of the cluster size
    d = _rays_at(np.array([8.0, 0.5, 0.2]), 1500, 0.07, rng)
    h = rng.uniform(0.1, 0.21, len(d))
    origin = np.array([0.0, 0.0, 0.0])
    hits = cast_rays(_t(v, dtype), torch.from_numpy(f), _t(d, dtype), _t(origin, dtype), _t(h, dtype))
    o = np.zeros((len(d), 3))
    o[:, 2] = h
    ref = _reference(v, f, o, d)
    assert hits.t.dtype == dtype
    assert 300 < np.isfinite(ref).sum() < 1400
    np.testing.assert_array_equal(hits.hit.numpy(), np.isfinite(ref))
    tol = 1e-12 if dtype == torch.float64 else 2e-5
    np.testing.assert_allclose(hits.t.numpy()[np.isfinite(ref)], ref[np.isfinite(ref)], rtol=0, atol=tol * 10)
    # the recorded face really contains the hit point: barycentrics reproduce it
    k = hits.hit.numpy()
    fa = f[hits.face.numpy()[k]]
    u, w = hits.u.numpy()[k], hits.v.numpy()[k]
    p = (1 - u - w)[:, None] * v[fa[:, 0]] + u[:, None] * v[fa[:, 1]] + w[:, None] * v[fa[:, 2]]
    np.testing.assert_allclose(p, hits.points(_t(o, dtype), _t(d, dtype)).numpy()[k], atol=tol * 100)
    assert hits.tests < len(d) * len(f) / 3  # the cluster spheres skip most pairs


def test_gradients_match_float64_finite_differences():
    v, f = _blob(level=1, centre=(4.0, 0.0, 0.0))
    rng = np.random.default_rng(5)
    d = _t(_rays_at(np.array([4.0, 0.0, 0.0]), 40, 0.06, rng))
    h = _t(rng.uniform(0.1, 0.2, 40))
    ft = torch.from_numpy(f)
    origin = _t([0.0, 0.0, 0.0])
    v0 = _t(v).requires_grad_()
    hits = cast_rays(v0, ft, d, origin, h)
    assert hits.hit.sum() > 20

    def pts(vert: torch.Tensor) -> torch.Tensor:
        r = cast_rays(vert, ft, d, origin, h)
        assert torch.equal(r.face, hits.face)  # the perturbation keeps every ray on its face
        o = origin + h[:, None] * _t([0.0, 0.0, 1.0])
        return torch.cat([r.points(o, d), r.u[:, None], r.v[:, None]], 1)

    assert torch.autograd.gradcheck(pts, (v0,), eps=1e-6, atol=1e-7, rtol=1e-5)


def _finite_grad(hits, vert: torch.Tensor, o: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    loss = hits.points(o, d).pow(2).sum() + hits.u.sum() + hits.v.sum()
    (g,) = torch.autograd.grad(loss, vert, allow_unused=True)
    g = torch.zeros_like(vert) if g is None else g
    assert torch.isfinite(g).all()
    for x in (hits.t, hits.u, hits.v):
        assert torch.isfinite(x).all()
    return g


def test_rays_through_vertices_and_edges_never_leak():
    v, f = icosphere(2, 0.4)
    vert = _t(v).requires_grad_()
    targets = [v, 0.5 * (v[f[:, 0]] + v[f[:, 1]]), 0.5 * (v[f[:, 1]] + v[f[:, 2]])]
    origin = np.array([3.0, -2.0, 1.0])
    for tgt in targets:
        d = tgt - origin
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        hits = cast_rays(vert, torch.from_numpy(f), _t(d), _t(origin))
        _finite_grad(hits, vert, _t(origin), _t(d))
        # rays aimed at a point on the near side (not near the silhouette) must hit at or before it
        facing = ((tgt / np.linalg.norm(tgt, axis=1, keepdims=True)) * -d).sum(1) > 0.05
        assert hits.hit.numpy()[facing].all()
        dist = np.linalg.norm(tgt - origin, axis=1)
        assert (hits.t.detach().numpy()[facing] <= dist[facing] + 1e-9).all()


def test_grazing_and_in_plane_rays_are_rejected_with_finite_gradients():
    v = _t([[2.0, -1.0, -1.0], [2.0, 1.0, -1.0], [2.0, 0.0, 1.0]]).requires_grad_()
    f = torch.tensor([[0, 1, 2]])
    # origin on the plane x = 2: in-plane and nearly in-plane rays through the triangle
    o_on = _t([2.0, -3.0, 0.0])
    d = _t([[0.0, 1.0, 0.0], [1e-9, 1.0, 0.0], [1e-4, 1.0, 0.0]])
    d = d / torch.linalg.norm(d, dim=1, keepdim=True)
    hits = cast_rays(v, f, d, o_on)
    assert not hits.hit.any()  # |cos(incidence)| < 1e-3: no hit
    _finite_grad(hits, v, o_on, d)
    # rays at the interior point (2, 0, 0) from 1 m away, incidence just above / below the cut cos = 1e-3
    for cos_inc, expect in ((2e-3, True), (5e-4, False)):
        di = _t([[cos_inc, 0.0, np.sqrt(1 - cos_inc**2)]])
        oi = _t([2.0, 0.0, 0.0]) - di[0]
        hits = cast_rays(v, f, di, oi)
        assert hits.hit.tolist() == [expect]
        g = _finite_grad(hits, v, oi, di)
        assert g.abs().max() < 2e4  # grows like 1 / cos(incidence), bounded by the cut
        if expect:
            np.testing.assert_allclose(hits.t.detach().numpy(), [1.0], atol=1e-9)


def test_zero_area_faces_inside_rays_and_all_miss():
    v, f = icosphere(2, 0.4)
    # add a collapsed face (three equal vertices), a collinear sliver and a near-collinear one (|e1 x e2| = 2e-14,
    # below 1e-10 of its longest squared edge, 0.04; a ray crosses its edge z = 0) in front of the sphere
    extra = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, -0.1, 0.0], [1.0, 0.0, 0.0],
                      [1.0, 0.1, 0.0], [1.2, -0.1, 0.0], [1.2, 0.1, 0.0], [1.2, 0.0, 1e-13]])
    vv = np.concatenate([v, extra])
    ff = np.concatenate([f, [[162, 163, 164], [165, 166, 167], [168, 169, 170]]])
    vert = _t(vv).requires_grad_()
    origin = _t([3.0, 0.0, 0.0])
    d = _t([[-1.0, 0.0, 0.0], [-1.0, 1e-9, 0.0]])
    d = d / torch.linalg.norm(d, dim=1, keepdim=True)
    hits = cast_rays(vert, torch.from_numpy(ff), d, origin)
    assert hits.hit.all() and (hits.face < 320).all()  # the degenerate faces are never hit
    np.testing.assert_allclose(hits.t.detach().numpy(), 2.6, atol=1e-3)
    _finite_grad(hits, vert, origin, d)
    # from inside: every ray hits the sphere once, at about the radius
    rng = np.random.default_rng(1)
    d = rng.normal(size=(500, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    vert = _t(v).requires_grad_()
    hits = cast_rays(vert, torch.from_numpy(f), _t(d), _t([0.0, 0.0, 0.0]))
    assert hits.hit.all()
    t = hits.t.detach().numpy()
    assert (t > 0.4 * 0.95).all() and (t <= 0.4 + 1e-12).all()
    _finite_grad(hits, vert, _t([0.0, 0.0, 0.0]), _t(d))
    # all miss, and no rays at all
    hits = cast_rays(vert, torch.from_numpy(f), _t(-d[:5] * 0 + [0.0, 0.0, 1.0]), _t([0.0, 0.0, 5.0]))
    assert not hits.hit.any() and (hits.face == -1).all() and (hits.t == 0).all()
    g = _finite_grad(hits, vert, _t([0.0, 0.0, 5.0]), _t(np.tile([0.0, 0.0, 1.0], (5, 1))))
    assert (g == 0).all()
    empty = cast_rays(vert, torch.from_numpy(f), torch.zeros(0, 3, dtype=F64), _t([0.0, 0.0, 0.0]))
    assert empty.hit.shape == (0,) and empty.tests == 0


def test_bad_input_is_reported():
    v, f = icosphere(1, 0.4)
    with pytest.raises(ValueError, match="field 'faces'"):
        cast_rays(_t(v), torch.from_numpy(f + 100), _t([[1.0, 0, 0]]), _t([0.0, 0, 0]))
    bad = v.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="field 'vertices'"):
        cast_rays(_t(bad), torch.from_numpy(f), _t([[1.0, 0, 0]]), _t([0.0, 0, 0]))
    with pytest.raises(ValueError, match="field 'origin_offset'"):
        cast_rays(_t(v), torch.from_numpy(f), _t([[1.0, 0, 0]]), _t([0.0, 0, 0]), _t([0.1, 0.2]))


def test_pairs_entry_point_equals_cast_rays_and_the_textbook_reference():
    """cast_ray_pairs with every (ray, face) pair, or only a subset holding each ray's hit faces, gives
    cast_rays' hits bit for bit (same kernels) and the textbook nearest t; a pair left out is not tested."""
    rng = np.random.default_rng(11)
    v, f = _blob()
    d = _rays_at(np.array([8.0, 0.5, 0.2]), 400, 0.06, rng)
    origin = np.zeros(3)
    vt = torch.tensor(v, requires_grad=True)
    ref = cast_rays(vt, torch.as_tensor(f), _t(d), _t(origin))
    ray_all, face_all = _every_pair(len(d), len(f))
    every = cast_ray_pairs(vt, torch.as_tensor(f), _t(d), _t(origin), ray_all, face_all)
    assert every.tests == len(d) * len(f)
    expect_t = _reference(v, f, origin[None, :].repeat(len(d), 0), d)
    np.testing.assert_allclose(np.where(every.hit.numpy(), every.t.detach().numpy(), np.inf), expect_t, rtol=1e-12)
    # pairs of faces whose vertices all lie on the ray's side of the blob centre (a crude cull holding the hits)
    cand = (v[f].mean(axis=1) - np.array([8.0, 0.5, 0.2])) @ np.array([-1.0, 0.0, 0.0]) > -0.1
    keep = torch.as_tensor(cand)[face_all]
    some = cast_ray_pairs(vt, torch.as_tensor(f), _t(d), _t(origin), ray_all[keep], face_all[keep])
    for got in (every, some):
        assert torch.equal(got.hit, ref.hit) and torch.equal(got.face, ref.face)
        for a, b in ((got.t, ref.t), (got.u, ref.u), (got.v, ref.v)):
            assert torch.equal(a.detach(), b.detach())
        (ga,) = torch.autograd.grad((got.t + got.u).sum(), vt)
        (gb,) = torch.autograd.grad((ref.t + ref.u).sum(), vt, retain_graph=True)
        assert torch.equal(ga, gb)
    # only the far side's faces paired: the rays now hit the back of the blob (larger t) or nothing
    far = cast_ray_pairs(vt, torch.as_tensor(f), _t(d), _t(origin), ray_all[~keep], face_all[~keep])
    both = far.hit & ref.hit
    assert both.any() and (far.t[both] > ref.t[both]).all()
    with pytest.raises(ValueError, match="field 'face_index'"):
        cast_ray_pairs(vt, torch.as_tensor(f), _t(d), _t(origin), ray_all[:3], face_all[:2])
    with pytest.raises(ValueError, match="field 'ray_index'"):
        cast_ray_pairs(vt, torch.as_tensor(f), _t(d), _t(origin), torch.tensor([len(d)]), torch.tensor([0]))


def test_pair_chunks_give_the_hits_of_one_call():
    """The pairs tested in uneven chunks (some empty) give cast_ray_pairs' hits and gradients bit for bit."""
    rng = np.random.default_rng(5)
    v, f = _blob()
    d = _rays_at(np.array([8.0, 0.5, 0.2]), 300, 0.06, rng)
    vt = torch.tensor(v, requires_grad=True)
    ray_all, face_all = _every_pair(len(d), len(f))
    one = cast_ray_pairs(vt, torch.as_tensor(f), _t(d), _t(np.zeros(3)), ray_all, face_all)
    cuts = [0, 7, 7, 5000, len(ray_all) // 2, len(ray_all)]
    chunks = [(ray_all[a:b], face_all[a:b]) for a, b in itertools.pairwise(cuts)]
    many = cast_ray_pair_chunks(vt, torch.as_tensor(f), _t(d), _t(np.zeros(3)), iter(chunks))
    assert one.hit.any() and many.tests == one.tests == len(ray_all)
    assert torch.equal(many.hit, one.hit) and torch.equal(many.face, one.face)
    for a, b in ((many.t, one.t), (many.u, one.u), (many.v, one.v)):
        assert torch.equal(a.detach(), b.detach())
    with pytest.raises(ValueError, match="field 'face_index'"):
        cast_ray_pair_chunks(vt, torch.as_tensor(f), _t(d), _t(np.zeros(3)), [(ray_all[:3], face_all[:2])])

@pytest.mark.parametrize("every", [1, 2])
def test_hits_reduced_between_chunks_keep_the_nearest_and_the_smallest_face_of_a_tie(monkeypatch, every):
    """A long search reduces its hits to each ray's nearest every few chunks (the numpy reference search_pairs_np
    compacts its hit lists; the compiled search_pairs keeps one nearest per ray): the same winners bit for bit,
    also when a face's exact duplicate (equal t, higher index) is tested first."""
    import robustbench3d.sensors.pair_search as rc

    rng = np.random.default_rng(11)
    v, f = _blob()
    d = _rays_at(np.array([8.0, 0.5, 0.2]), 200, 0.06, rng)
    first = cast_rays(_t(v), torch.as_tensor(f), _t(d), _t(np.zeros(3)))
    f = np.roll(f, -int(first.face[first.hit][0]), axis=0)  # face 0 is some ray's nearest (a face id of 0 is kept)
    f2 = np.concatenate([f, f])  # faces F..2F-1 duplicate 0..F-1: every hit is a tie the lower index must win
    vt = torch.tensor(v, requires_grad=True)
    ray_all, face_all = _every_pair(len(d), len(f2))
    one = cast_ray_pairs(vt, torch.as_tensor(f2), _t(d), _t(np.zeros(3)), ray_all, face_all)
    order = torch.argsort(-face_all, stable=True)  # duplicates (high indices) first
    r, fa = ray_all[order], face_all[order]
    cuts = [*range(0, len(r), 997), len(r)]
    monkeypatch.setattr(rc, "_COMPACT_EVERY", every)
    many = cast_ray_pair_chunks(vt, torch.as_tensor(f2), _t(d), _t(np.zeros(3)),
                                ((r[a:b], fa[a:b]) for a, b in itertools.pairwise(cuts)))
    assert one.hit.sum() > 50 and int(one.face[one.hit].max()) < len(f) and (one.face == 0).any()
    assert torch.equal(many.hit, one.hit) and torch.equal(many.face, one.face)
    for a, b in ((many.t, one.t), (many.u, one.u), (many.v, one.v)):
        assert torch.equal(a.detach(), b.detach())
    # the numpy reference (which compacts every `every` chunks) against the compiled search of the same chunks
    table = rc.PairTable.of(v, f2, np.zeros(3)).table
    d_cols = np.ascontiguousarray(d.T)
    chunks = [(r[a:b].numpy(), fa[a:b].numpy()) for a, b in itertools.pairwise(cuts)]
    face_np, best_np, tests_np = rc.search_pairs_np(table, d_cols, None, iter(chunks), 1e-6, 1e-6)
    face_c, best_c, tests_c = rc.search_pairs(table, d_cols, None, iter(chunks), 1e-6, 1e-6)
    assert tests_np == tests_c == len(r) and np.array_equal(face_np, face_c) and np.array_equal(best_np, best_c)
    assert np.array_equal(face_c, one.face.numpy())


def test_pair_caster_searches_then_recomputes_like_cast_ray_pairs():
    """PairCaster (one table, several searches, one recompute of their winners): the hits, t, u, v and
    gradients of cast_ray_pairs bit for bit, with the search's t equal to the recomputed t and misses absent."""
    rng = np.random.default_rng(8)
    v, f = _blob()
    d = _rays_at(np.array([8.0, 0.5, 0.2]), 300, 0.09, rng)
    vt = torch.tensor(v, requires_grad=True)
    ray_all, face_all = _every_pair(len(d), len(f))
    ref = cast_ray_pairs(vt, torch.as_tensor(f), _t(d), _t(np.zeros(3)), ray_all, face_all)
    assert ref.hit.any() and not ref.hit.all()
    caster = PairCaster(vt, torch.as_tensor(f), _t(np.zeros(3)))
    half = len(d) // 2  # two searches over two halves of the rays, one recompute
    parts = [caster.search(_t(d[:half]), [(ray_all[ray_all < half], face_all[ray_all < half])]),
             caster.search(_t(d[half:]), [(ray_all[ray_all >= half] - half, face_all[ray_all >= half])])]
    ray = torch.cat([parts[0][0], parts[1][0] + half])
    face = torch.cat([parts[0][1], parts[1][1]])
    assert parts[0][3] + parts[1][3] == len(ray_all)
    assert torch.equal(ray, torch.nonzero(ref.hit).reshape(-1)) and torch.equal(face, ref.face[ray])
    t, u, w = caster.recompute(_t(d)[ray], face)
    for a, b in ((t, ref.t[ray]), (u, ref.u[ray]), (w, ref.v[ray])):
        assert torch.equal(a.detach(), b.detach())
    np.testing.assert_allclose(torch.cat([parts[0][2], parts[1][2]]).numpy(), t.detach().numpy(), rtol=1e-12)
    (ga,) = torch.autograd.grad((t + 2 * u - w).sum(), vt)
    (gb,) = torch.autograd.grad((ref.t + 2 * ref.u - ref.v).sum(), vt)
    assert torch.equal(ga, gb) and ga.abs().sum() > 0
    empty = caster.recompute(_t(np.zeros((0, 3))), torch.zeros(0, dtype=torch.int64))[0]
    assert empty.shape == (0,) and empty.requires_grad


def test_pair_caster_runs_in_the_vertices_dtype_whatever_the_directions():
    """float32 vertices with float64 (numpy) directions: the search and the recompute run in float32, the same
    as with float32 directions, and differ from a float64 cast."""
    rng = np.random.default_rng(3)
    v, f = _blob()
    d = _rays_at(np.array([8.0, 0.5, 0.2]), 200, 0.06, rng)
    pairs = [_every_pair(len(d), len(f))]
    v32 = torch.tensor(v, dtype=torch.float32)
    caster = PairCaster(v32, torch.as_tensor(f), torch.zeros(3))
    ray, face, t, _ = caster.search(d, pairs)
    ray32, face32, t32, _ = caster.search(torch.tensor(d, dtype=torch.float32), pairs)
    assert len(ray) > 20 and t.dtype == torch.float32
    assert torch.equal(ray, ray32) and torch.equal(face, face32) and torch.equal(t, t32)
    tr, ur, wr = caster.recompute(d[ray.numpy()], face)
    assert tr.dtype == ur.dtype == wr.dtype == torch.float32
    assert torch.equal(tr, caster.recompute(torch.tensor(d[ray.numpy()], dtype=torch.float32), face)[0])
    t64 = PairCaster(torch.tensor(v), torch.as_tensor(f), torch.zeros(3, dtype=torch.float64)).search(d, pairs)[2]
    assert t64.dtype == torch.float64 and not torch.equal(t64.to(torch.float32).double(), t64)


def test_back_faces_hand_computed_tetrahedron():
    """A unit right tetrahedron (outward faces) seen from (2, 2, 2): only the slanted face x + y + z = 1
    faces the origin; the three faces in the coordinate planes are back faces."""
    v = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])  # normals -z, -y, -x, (1, 1, 1)
    assert back_faces(v, f, np.array([2.0, 2.0, 2.0])).tolist() == [True, True, True, False]
    assert back_faces(v, f, np.array([-2.0, 0.2, 0.2])).tolist() == [True, True, False, True]
    assert back_faces(v, f[:, ::-1], np.array([2.0, 2.0, 2.0])) is None  # inward-oriented
    assert back_faces(v, f[:3], np.array([2.0, 2.0, 2.0])) is None  # open
    assert back_faces(v, f, np.array([0.5, 0.5, 0.5])) is None  # origin inside the bounding sphere


def test_back_face_culling_keeps_every_hit_and_refuses_folded_meshes():
    """Culling the back faces of a closed star-shaped blob leaves every ray's nearest hit unchanged (face,
    t, u, v bit for bit); a fold (a vertex pushed through the centre) or a reversed mesh is not culled."""
    rng = np.random.default_rng(5)
    v, f = _blob()
    origin = np.zeros(3)
    d = _rays_at(np.array([8.0, 0.5, 0.2]), 3000, 0.06, rng)
    skip = back_faces(v, f, origin)
    assert skip is not None and 0.4 < skip.mean() < 0.6
    vt = _t(v)
    full = cast_rays(vt, torch.as_tensor(f), _t(d), _t(origin))
    culled = cast_rays(vt, torch.as_tensor(f), _t(d), _t(origin), skip_faces=torch.as_tensor(skip))
    assert full.hit.sum() > 1000 and torch.equal(full.face, culled.face)
    for a, b in ((full.t, culled.t), (full.u, culled.u), (full.v, culled.v)):
        assert torch.equal(a, b)
    assert not skip[full.face[full.hit].numpy()].any()
    folded = v.copy()
    folded[0] = 2 * v.mean(axis=0) - 0.5 * (v[0] - v.mean(axis=0))  # across the centre
    assert back_faces(folded, f, origin) is None
    with pytest.raises(ValueError, match="field 'skip_faces'"):
        cast_rays(vt, torch.as_tensor(f), _t(d), _t(origin), skip_faces=torch.zeros(3, dtype=torch.bool))


@pytest.mark.parametrize("grouped", [False, True])
def test_cluster_sphere_holds_every_vertex_and_counts_its_tests(grouped):
    """One triangle in the plane x = 2: its cluster's bounding sphere has centre (2, .5, .5) and radius
    sqrt(1/2), every vertex on it. A ray along x at y = 1, z = 0 touches the sphere only at the vertex
    (2, 1, 0), so only the sphere's inflation lets it be tested: it hits there (t = 2, u = 1, v = 0). The
    opposite ray (closest approach behind its origin) is not tested: 1 ray-triangle test in all."""
    v = _t([[2.0, 0.0, 0.0], [2.0, 1.0, 0.0], [2.0, 0.0, 1.0]])
    d = _t([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    groups = [(np.array([0, 1]), 0, 1)] if grouped else None
    hits = cast_rays(v, torch.tensor([[0, 1, 2]]), d, _t([0.0, 1.0, 0.0]), groups=groups)
    assert hits.hit.tolist() == [True, False] and hits.face.tolist() == [0, -1] and hits.tests == 1
    np.testing.assert_allclose(hits.t.numpy(), [2.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(hits.u.numpy(), [1.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(hits.v.numpy(), [0.0, 0.0], atol=1e-15)
    # the same at the vertex (2, 0, 1), along x at y = 0, z = 1: it hits with v = 1
    hits = cast_rays(v, torch.tensor([[0, 1, 2]]), d, _t([0.0, 0.0, 1.0]), groups=groups)
    assert hits.hit.tolist() == [True, False] and hits.tests == 1
    np.testing.assert_allclose(hits.v.numpy(), [1.0, 0.0], atol=1e-15)


def test_entry_points_pass_their_options_and_name_their_errors():
    """The triangle in the plane x = 2 again, by hand: the options reach the test (t_min, cos_min, offset_axis,
    skip_faces, t_min's default), misses keep integer faces -1, t = 0 (also for vertices summing to 0) and the
    count of tests made, and every entry point prefixes its errors with its own name."""
    v = _t([[2.0, 0.0, 0.0], [2.0, 1.0, 0.0], [2.0, 0.0, 1.0]])
    f = torch.tensor([[0, 1, 2]])
    x = _t([[1.0, 0.0, 0.0]])
    one = (torch.tensor([0]), torch.tensor([0]))
    o = _t([0.0, 0.25, 0.25])  # along x: hits (2, .25, .25) at t = 2
    assert cast_ray_pairs(v, f, x, o, *one).t.tolist() == [2.0]
    assert not cast_ray_pairs(v, f, x, o, *one, t_min=2.5).hit.any()
    slant = _t([[0.8, 0.6, 0.0]])  # from (0, -1.25, .25) to the same point, t = 2.5, |cos(incidence)| = 0.8
    assert cast_ray_pairs(v, f, slant, _t([0.0, -1.25, 0.25]), *one).t.tolist() == [2.5]
    assert not cast_ray_pairs(v, f, slant, _t([0.0, -1.25, 0.25]), *one, cos_min=0.9).hit.any()
    # the origin moved by 1 along y: (0, -.75, .25) + (0, 1, 0); along the default z axis it would miss
    shifted = cast_ray_pairs(v, f, x, _t([0.0, -0.75, 0.25]), *one, origin_offset=_t([1.0]), offset_axis=(0, 1, 0))
    assert shifted.t.tolist() == [2.0]
    assert cast_ray_pair_chunks(v, f, x, _t([1.5, 0.25, 0.25]), [one]).t.tolist() == [0.5]  # t_min 1e-6
    assert not cast_rays(v, f, x, o, skip_faces=torch.tensor([True])).hit.any()
    assert cast_rays(v, f, x, o, groups=[(np.array([0]), 0, 1), (np.array([0]), 1, 1)]).t.tolist() == [2.0]
    # misses: no faces at all, and a ray through the cluster sphere beside the triangle (tested once)
    none = cast_rays(v, torch.zeros((0, 3), dtype=torch.int64), _t([[1.0, 0, 0], [0, 1.0, 0]]), o)
    assert none.face.dtype == torch.int64 and none.face.tolist() == [-1, -1] and none.tests == 0
    beside = cast_rays(v, f, x, _t([0.0, 0.8, 0.8]))  # (2, .8, .8): u + v = 1.6
    assert beside.tests == 1 and beside.face.tolist() == [-1] and beside.t.tolist() == [0.0]
    centred = _t([[2.0, 1.0, 0.0], [2.0, -1.0, 1.0], [-4.0, 0.0, -1.0]]).requires_grad_()  # vertices sum to 0
    assert cast_rays(centred, f, x, _t([0.0, 5.0, 5.0])).t.tolist() == [0.0]
    none = PairCaster(centred, f, _t([0.0, 5.0, 5.0])).recompute(x[:0], torch.zeros(0, dtype=torch.int64))
    assert all(z.shape == (0,) and z.dtype == torch.float64 and z.requires_grad for z in none)  # connected
    sum(z.sum() for z in none).backward()
    assert torch.equal(centred.grad, torch.zeros(3, 3, dtype=torch.float64))  # a zero gradient, not 0 / 0
    errors = [
        (lambda: cast_rays(v, f + 1, x, o), "cast_rays: field 'faces': indices must lie in [0, 3)"),
        (lambda: cast_ray_pairs(v, f, x, o, torch.tensor([0, 0]), torch.tensor([0])),
         "cast_ray_pairs: field 'face_index': 1 faces for 2 rays"),
        (lambda: cast_ray_pair_chunks(v, f + 1, x, o, [one]), "cast_ray_pair_chunks: field 'faces': indices must "
                                                             "lie in [0, 3)"),
        (lambda: cast_ray_pair_chunks(v, f, x, o, [(torch.tensor([1]), torch.tensor([0]))]),
         "cast_ray_pair_chunks: field 'ray_index': pairs must index 1 rays and 1 faces"),
        (lambda: PairCaster(v * np.nan, f, o), "PairCaster: field 'vertices': contains NaN or inf"),
        (lambda: PairCaster(v, f, o).search(x, [(torch.tensor([0]), torch.tensor([1]))]),
         "PairCaster: field 'ray_index': pairs must index 1 rays and 1 faces"),
        (lambda: cast_rays(v.to(torch.float16), f, x, o),
         "cast_rays: field 'vertices': dtype must be float32 or float64, got torch.float16"),
    ]
    for call, message in errors:
        with pytest.raises(ValueError) as err:
            call()
        assert str(err.value) == message


def test_groups_of_different_sizes_empty_groups_and_a_near_origin():
    """Grouped casts equal the plain cast: a 1-face group before an 8-face group (two cluster counts: the
    ray's face is the 8th, in the second cluster), groups without rays or faces, and rays starting 0.5 m
    before the triangle (closer to its cluster's centre than the radius)."""
    tri = np.array([[2.0, 0.0, 0.0], [2.0, 1.0, 0.0], [2.0, 0.0, 1.0]])
    # 9 triangles: the one above, then 8 copies 3 m along y and 0.1 ... 0.8 m behind it
    v = _t(np.concatenate([tri] + [tri + np.array([0.1 * k, 3.0, 0.0]) for k in range(1, 9)]))
    f = torch.arange(27).reshape(9, 3)
    d = _t([[1.0, 0.0, 0.0]] * 2)
    o = _t([0.0, 3.25, 0.25])  # along x both rays meet the copies at x = 2.1 ... 2.8: the first is face 1
    plain = cast_rays(v, f, d, o)
    assert plain.face.tolist() == [1, 1] and plain.t.tolist() == pytest.approx([2.1, 2.1])
    late = _t(np.concatenate([tri] + [tri + np.array([3.0 - 0.1 * k, 3.0, 0.0]) for k in range(1, 9)]))  # 8 nearest
    for verts, want in ((v, 1), (late, 8)):
        ref = cast_rays(verts, f, d, o)
        got = cast_rays(verts, f, d, o, groups=[(np.array([0, 1]), 0, 1), (np.array([0, 1]), 1, 9)])
        assert ref.face.tolist() == got.face.tolist() == [want, want] and torch.equal(ref.t, got.t)
    # groups of 1 and 2 clusters batched apart whatever their first faces: 4 and 5 faces, 4 faces from face 4
    for groups in ([(np.array([0, 1]), 0, 4), (np.array([0, 1]), 4, 9)], [(np.array([0, 1]), 4, 8),
                                                                        (np.array([0, 1]), 1, 9)]):
        assert cast_rays(late, f, d, o, groups=groups).face.tolist() == [8, 8]
    empty = cast_rays(v, f, d, o, groups=[(np.zeros(0, dtype=np.int64), 0, 9), (np.array([0]), 3, 3)])
    assert empty.face.dtype == torch.int64 and empty.face.tolist() == [-1, -1] and empty.tests == 0
    near = cast_rays(v[:3], f[:1], d[:1], _t([1.5, 0.25, 0.25]), groups=[(np.array([0]), 0, 1)])
    assert near.t.tolist() == [0.5]


def test_later_ray_chunks_are_searched_and_open_spheres_are_not_culled():
    """1280 faces make a search chunk of 1048576 // 1280 = 819 rays: the first chunk's rays all point away
    (no candidate pair), the last 181 rays point at the sphere and must still hit it. A sphere missing one
    of its 320 faces is open (its solid angles still sum to almost 4 pi): no back-face culling."""
    v, f = icosphere(3, 0.4)
    assert len(f) == 1280
    d = np.tile([[-1.0, 0.0, 0.0]], (1000, 1))
    d[819:] = [1.0, 0.0, 0.0]
    hits = cast_rays(_t(v + np.array([8.0, 0.0, 0.0])), torch.from_numpy(f), _t(d), _t([0.0, 0.0, 0.0]))
    assert not hits.hit[:819].any() and hits.hit[819:].all()
    np.testing.assert_allclose(hits.t[819:].numpy(), 7.6, atol=1e-3)
    v2, f2 = icosphere(2, 0.4)
    assert back_faces(v2, f2, np.array([3.0, 0.0, 0.0])) is not None
    assert back_faces(v2, f2[1:], np.array([3.0, 0.0, 0.0])) is None


def test_cluster_sphere_tests_exactly_the_rays_within_its_inflated_radius():
    """The cull's definition, counted in ``RayHits.tests``: the 3-4-5 triangle (-3, -4), (3, -4), (-3, 4) in a
    plane x = const has its box centre at (x, 0, 0) and every vertex at 5 from it, so its cluster sphere has
    radius R = 5 (1 + 1e-3) + 1e-9. A ray is tested iff it passes within R of the centre and its closest
    approach is more than R behind its origin: with laser offsets (h along z) too."""
    tri = np.array([[0.0, -3.0, -4.0], [0.0, 3.0, -4.0], [0.0, -3.0, 4.0]])
    f = torch.tensor([[0, 1, 2]])
    x = _t([[1.0, 0.0, 0.0]])
    radius = 5.0 * (1 + 1e-3) + 1e-9
    far = _t(tri + np.array([10.0, 0.0, 0.0]))
    for z, tested in ((6.0, 0), (5.006, 0), (4.9, 1), (-3.9, 1)):
        # the same ray from (0, 0, z) with no offset and as (0, 0, z - 3) + 3 along z
        assert cast_rays(far, f, x, _t([0.0, 0.0, z])).tests == tested
        assert cast_rays(far, f, x, _t([0.0, 0.0, z - 3.0]), origin_offset=_t([3.0])).tests == tested
    hit = cast_rays(far, f, x, _t([0.0, -2.0, -3.0]), origin_offset=_t([2.0]))  # from (0, -2, -1)
    assert hit.tests == 1 and hit.face.tolist() == [0] and hit.t.tolist() == [10.0]
    # the triangle in x = 0, rays along +x from (R, 0, 0): the closest approach is exactly R behind the origin
    # (not tested), from just inside the sphere it is less (tested; both miss: the triangle is behind them)
    at = _t(tri)
    assert cast_rays(at, f, x, _t([radius, 0.0, 0.0])).tests == 0
    inside = cast_rays(at, f, x, _t([np.nextafter(radius, 0.0), 0.0, 0.0]))
    assert inside.tests == 1 and inside.face.tolist() == [-1]


def test_cull_keeps_the_hits_of_tiny_faces_and_of_a_needle_in_a_cluster():
    """Two clusters whose bounding spheres must hold every corner exactly: a 1e-7 m triangle hit through its
    vertex from 1e-5 m (the sphere's absolute inflation exceeds the rounding there), and a cluster of a long
    triangle through the box centre plus three tiny ones near it, hit 0.78 from the centre (inside the true
    radius 0.866, outside a radius measured per axis), equal to the textbook reference."""
    s = 1e-7
    tiny = np.array([[2.0, 0.0, 0.0], [2.0, s, 0.0], [2.0, 0.0, s]])
    o = np.array([2.0 - 1e-5, s, 0.0])
    d = np.array([[1.0, 0.0, 0.0]])
    hits = cast_rays(_t(tiny), torch.tensor([[0, 1, 2]]), _t(d), _t(o))
    assert hits.face.tolist() == [0] and hits.tests == 1
    np.testing.assert_allclose(hits.t.numpy(), [1e-5], rtol=1e-9)  # by hand (the reference's det floor is absolute)
    np.testing.assert_allclose(hits.u.numpy(), [1.0], atol=1e-6)
    a, b, c = np.array([0.5, 0.5, 0.5]), np.array([-0.5, -0.5, -0.5]), np.array([0.1, -0.1, 0.0])
    small = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.0, 0.01, 0.0]])
    v = np.concatenate([[a, b, c], small, small + 0.01, small - 0.01])
    f = np.arange(12).reshape(4, 3)
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n)
    p = 0.95 * a + 0.05 * b  # on face 0, |p| = 0.779; its plane holds the centre, so the ray passes at |p|
    for sign in (1.0, -1.0):
        origin = p + 2.0 * sign * n
        dirs = -sign * n[None]
        hits = cast_rays(_t(v), torch.from_numpy(f), _t(dirs), _t(origin))
        assert hits.face.tolist() == [0]
        np.testing.assert_allclose(hits.t.numpy(), _reference(v, f, origin[None], dirs), rtol=1e-12)


def test_grouped_casts_accept_int32_rays_and_an_empty_group_first():
    """Group rays given as int32 (numpy or torch) and a group without rays before the others give the hits of
    the plain cast."""
    v = _t([[2.0, 0.0, 0.0], [2.0, 1.0, 0.0], [2.0, 0.0, 1.0]])
    f = torch.tensor([[0, 1, 2]])
    d = _t([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    o = _t([0.0, 0.25, 0.25])
    for groups in ([(np.array([0, 1], dtype=np.int32), 0, 1)], [(torch.tensor([1, 0], dtype=torch.int32), 0, 1)],
                   [(np.zeros(0, dtype=np.int64), 0, 1), (np.array([0, 1]), 0, 1)],
                   [(np.array([0]), 0, 0), (np.array([1, 0]), 0, 1)]):
        hits = cast_rays(v, f, d, o, groups=groups)
        assert hits.face.tolist() == [0, 0] and hits.t.tolist() == [2.0, 2.0] and hits.tests == 2


def test_pair_caster_search_without_check_trusts_the_pairs():
    """``check=False`` skips the range check: in-range pairs give the checked result, and a ray index out of
    range reaches torch's own indexing error instead of the check's ValueError."""
    v = _t([[2.0, 0.0, 0.0], [2.0, 1.0, 0.0], [2.0, 0.0, 1.0]])
    caster = PairCaster(v, torch.tensor([[0, 1, 2]]), _t([0.0, 0.25, 0.25]))
    x = _t([[1.0, 0.0, 0.0]])
    one = [(torch.tensor([0]), torch.tensor([0]))]
    checked, unchecked = caster.search(x, one), caster.search(x, one, check=False)
    assert [r.tolist() for r in checked[:3]] == [r.tolist() for r in unchecked[:3]] == [[0], [0], [2.0]]
    with pytest.raises(ValueError, match="pairs must index"):
        caster.search(x, [(torch.tensor([1]), torch.tensor([0]))])
    with pytest.raises((IndexError, RuntimeError)) as err:
        caster.search(x, [(torch.tensor([1]), torch.tensor([0]))], check=False)
    assert not isinstance(err.value, ValueError)


def test_skip_faces_and_groups_are_checked_also_without_rays_or_faces():
    """A wrong ``skip_faces`` length or a group outside the rays / faces is an error whatever the counts: also
    with no rays or no faces, where nothing is cast (all misses, 0 tests, on valid input)."""
    v = _t([[2.0, 0.0, 0.0], [2.0, 1.0, 0.0], [2.0, 0.0, 1.0]])
    f = torch.tensor([[0, 1, 2]])
    o = _t([0.0, 0.25, 0.25])
    no_rays, no_faces = _t(np.zeros((0, 3))), torch.zeros((0, 3), dtype=torch.int64)
    for faces, rays in ((f, no_rays), (no_faces, _t([[1.0, 0.0, 0.0]])), (no_faces, no_rays)):
        with pytest.raises(ValueError, match=f"cast_rays: field 'skip_faces': 2 flags for {len(faces)} faces"):
            cast_rays(v, faces, rays, o, skip_faces=torch.zeros(2, dtype=torch.bool))
        ok = cast_rays(v, faces, rays, o, skip_faces=torch.zeros(len(faces), dtype=torch.bool),
                       groups=[(np.zeros(0, dtype=np.int64), 0, len(faces))])
        assert ok.face.tolist() == [-1] * len(rays) and ok.tests == 0
    with pytest.raises(ValueError, match=r"field 'groups\[0\]': rays must index 0 rays"):
        cast_rays(v, f, no_rays, o, groups=[(np.array([0]), 0, 1)])
    with pytest.raises(ValueError, match=r"field 'groups\[1\]': .* faces \[0, 1\) lie in \[0, 0\]"):
        cast_rays(v, no_faces, _t([[1.0, 0.0, 0.0]]), o, groups=[(np.array([0]), 0, 0), (np.array([0]), 0, 1)])


def test_offset_axis_other_than_z_matches_the_textbook_reference():
    """Laser offsets along a slanted axis (0.6, 0, 0.8), rays mostly along z (their z component weighs the axis'
    cross terms that vanish for the default z axis): hits, t and the barycentric points equal the textbook
    reference from the per-ray origins origin + h a."""
    rng = np.random.default_rng(21)
    centre = np.array([0.5, 0.3, 6.0])
    v, f = _blob(centre=tuple(centre))
    d = _rays_at(centre, 1500, 0.07, rng)
    h = rng.uniform(0.1, 0.21, len(d))
    axis = np.array([0.6, 0.0, 0.8])
    hits = cast_rays(_t(v), torch.from_numpy(f), _t(d), _t(np.zeros(3)), _t(h), offset_axis=tuple(axis))
    o = h[:, None] * axis
    ref = _reference(v, f, o, d)
    assert 300 < np.isfinite(ref).sum() < 1400
    np.testing.assert_array_equal(hits.hit.numpy(), np.isfinite(ref))
    k = hits.hit.numpy()
    np.testing.assert_allclose(hits.t.numpy()[k], ref[k], rtol=0, atol=1e-11)
    fa = f[hits.face.numpy()[k]]
    u, w = hits.u.numpy()[k], hits.v.numpy()[k]
    p = (1 - u - w)[:, None] * v[fa[:, 0]] + u[:, None] * v[fa[:, 1]] + w[:, None] * v[fa[:, 2]]
    np.testing.assert_allclose(p, o[k] + hits.t.numpy()[k, None] * d[k], atol=1e-10)


def test_hit_test_boundaries_at_their_exact_values():
    """The triangle in the plane x = 2 seen along +x from (0, y, z): det = 1, u = y, v = z, t = 2, all exact. Rays
    exactly at the barycentric tolerance 1e-6 outside an edge (u = -1e-6, v = -1e-6, u + v = 1 + 1e-6) still hit
    (the float64 tolerance of the module docstring); twice as far out they miss. A hit at exactly t = t_min or at
    exactly |cos(incidence)| = cos_min is ignored (documented: t <= t_min, |cos| <= cos_min); just inside, it is not."""
    v = _t([[2.0, 0.0, 0.0], [2.0, 1.0, 0.0], [2.0, 0.0, 1.0]])
    f = torch.tensor([[0, 1, 2]])
    x = _t([[1.0, 0.0, 0.0]])
    tol = 1e-6
    edge = 1.0 + tol  # det + tol * det as the test rounds it
    for y, z in ((-tol, 0.5), (0.5, -tol), (edge, 0.0), (0.5, edge - 0.5)):
        hits = cast_rays(v, f, x, _t([0.0, y, z]))
        assert hits.face.tolist() == [0] and hits.t.tolist() == [2.0]
        assert hits.u.tolist() == [y] and hits.v.tolist() == [z]
    for y, z in ((-2 * tol, 0.5), (0.5, -2 * tol), (1.0 + 2 * tol, 0.0)):
        assert cast_rays(v, f, x, _t([0.0, y, z])).face.tolist() == [-1]
    o = _t([0.0, 0.25, 0.25])
    assert not cast_rays(v, f, x, o, t_min=2.0).hit.any()
    assert cast_rays(v, f, x, o, t_min=np.nextafter(2.0, 0.0)).t.tolist() == [2.0]
    # |cos| = 0.5 exactly: det = 0.5 d_x = 0.5 and the floor cos_min |n| = 0.5; the ray from (1.5, -0.7, 0.25)
    # meets the plane at t = 1 inside the triangle
    slant = _t([[0.5, np.sqrt(0.75), 0.0]])
    assert not cast_rays(v, f, slant, _t([1.5, -0.7, 0.25]), cos_min=0.5).hit.any()
    kept = cast_rays(v, f, slant, _t([1.5, -0.7, 0.25]), cos_min=np.nextafter(0.5, 0.0))
    assert kept.face.tolist() == [0] and kept.t.tolist() == [1.0]


def test_a_ray_starting_in_a_face_plane_never_hits_that_face():
    """t > 0 always (the test folds in the sign that makes t positive): rays starting inside a triangle, in its
    plane z = 1, do not hit it at t = 0 whichever way they point, whatever t_min (also t_min <= 0), from a shared
    origin or raised onto the plane by a laser offset; from below the same rays hit it at t = 1 and 1.25."""
    v = _t([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0]])
    f = torch.tensor([[0, 1, 2]])
    d = _t([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [0.6, 0.0, 0.8]])
    below = _t([0.1, 0.1, 0.0])
    for t_min in (1e-6, 0.0, -1.0):
        assert not cast_rays(v, f, d, _t([0.1, 0.1, 1.0]), t_min=t_min).hit.any()
        assert not cast_rays(v, f, d, below, _t([1.0, 1.0, 1.0]), t_min=t_min).hit.any()
        pairs = cast_ray_pairs(v, f, d, below, torch.arange(3), torch.zeros(3, dtype=torch.int64), _t([1.0] * 3),
                               t_min=t_min)
        assert not pairs.hit.any()
        hits = cast_rays(v, f, d, below, t_min=t_min)
        assert hits.hit.tolist() == [True, False, True]
        np.testing.assert_allclose(hits.t.numpy(), [1.0, 0.0, 1.25], atol=1e-15)


def test_cull_tests_a_ray_passing_exactly_at_the_inflated_radius():
    """The 3-4-5 triangle (-3, -4, 0), (3, -4, 0), (-3, 4, 0): its cluster sphere has centre 0 and radius
    R = 5 (1 + 1e-3) + 1e-9. A ray along x from (0, 0, R) passes exactly R from the centre (its closest approach
    is its origin): it is tested (within R includes R, exact here: |(0, 0, R)|^2 is R^2 rounded as R ** 2); from
    the next float above R it is not. Plain and grouped casts."""
    tri = _t([[-3.0, -4.0, 0.0], [3.0, -4.0, 0.0], [-3.0, 4.0, 0.0]])
    f = torch.tensor([[0, 1, 2]])
    x = _t([[1.0, 0.0, 0.0]])
    radius = 5.0 * (1 + 1e-3) + 1e-9
    for z, tested in ((radius, 1), (np.nextafter(radius, np.inf), 0)):
        for groups in (None, [(np.array([0]), 0, 1)]):
            hits = cast_rays(tri, f, x, _t([0.0, 0.0, z]), groups=groups)
            assert hits.tests == tested and hits.face.tolist() == [-1]


def test_degenerate_faces_are_judged_by_their_own_longest_edge():
    """The sliver rule (|e1 x e2| <= 1e-10 x the face's longest squared edge: never hit) per face: a 1 mm triangle
    beside a 1 km one is hit. 20 m slivers whose longest edge is v1 -> v2 (apex v0 at height h, |e1 x e2| = 20 h
    against 1e-10 x 400): h = 1e-8 is hit, h = 1e-9 is degenerate; a face exactly at the threshold (|e1 x e2| =
    1e-10 = 1e-10 x 1, exact) is degenerate. A skip_faces mask that skips nothing changes none of this."""
    x = _t([[1.0, 0.0, 0.0]])
    small = [[2.0, 0.0, 0.0], [2.0, 1e-3, 0.0], [2.0, 0.0, 1e-3]]
    big = [[-500.0, -500.0, -1.0], [500.0, -500.0, -1.0], [-500.0, 500.0, -1.0]]  # below the ray, parallel to it
    cases = [(small + big, x, [0.0, 2.5e-4, 2.5e-4], True)]
    for h, hit in ((1e-8, True), (1e-9, False)):
        cases.append(([[2.0, 0.0, h], [2.0, -10.0, 0.0], [2.0, 10.0, 0.0]], x, [0.0, 0.0, h / 2], hit))
    at = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, 1e-10, 0.0]]  # e1 x e2 = (0, 0, 1e-10), longest squared edge 1
    cases.append((at, _t([[0.0, 0.0, -1.0]]), [0.5, 0.25e-10, 1.0], False))
    for verts, d, o, hit in cases:
        f = torch.arange(len(verts)).reshape(-1, 3)
        for skip in (None, torch.zeros(len(f), dtype=torch.bool)):
            hits = cast_rays(_t(verts), f, d, _t(o), skip_faces=skip)
            assert hits.face.tolist() == ([0] if hit else [-1])


def test_single_pair_recompute_and_its_gradient_where_det_is_one():
    """PairCaster.recompute of one pair, by hand: the triangle in the plane x = 2 seen along -x from (3, .25, .5),
    where det = d . (e2 x e1) = 1 exactly: t = 1, u = .25, v = .5, and gradients w.r.t. the vertices equal float64
    finite differences."""
    f = torch.tensor([[0, 1, 2]])
    d = _t([[-1.0, 0.0, 0.0]])
    o = _t([3.0, 0.25, 0.5])
    v = _t([[2.0, 0.0, 0.0], [2.0, 1.0, 0.0], [2.0, 0.0, 1.0]]).requires_grad_()
    t, u, w = PairCaster(v, f, o).recompute(d, torch.tensor([0]))
    assert t.tolist() == [1.0] and u.tolist() == [0.25] and w.tolist() == [0.5]
    assert torch.autograd.gradcheck(lambda vert: PairCaster(vert, f, o).recompute(d, torch.tensor([0])), (v,),
                                    eps=1e-6, atol=1e-8, rtol=1e-6)


def test_pair_caster_table_of_a_face_whose_plane_holds_the_origin():
    """PairCaster.table by hand, from the origin 0: the triangle in the plane x = 2 has the column (det vector
    (1, 0, 0), u*det (0, 2, 0), v*det (0, 0, 2), t*det 2, grazing floor 1e-3 |n| = 1e-3) after the sign fold
    (t*det = -2 before it); a triangle in the plane y = 0, which holds the origin, has sign 0: rows 0..9 zero
    (finite, as camera_render's numpy kernel needs) and an infinite floor (never hit)."""
    v = _t([[2.0, 0.0, 0.0], [2.0, 1.0, 0.0], [2.0, 0.0, 1.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0], [1.0, 0.0, 1.0]])
    table = PairCaster(v, torch.arange(6).reshape(2, 3), _t(np.zeros(3))).table
    assert table.shape == (11, 2)
    assert table[:, 0].tolist() == [1.0, 0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 0.0, 2.0, 2.0, 1e-3]
    assert table[:10, 1].tolist() == [0.0] * 10 and table[10, 1].item() == np.inf


def test_inputs_are_cast_to_the_vertices_dtype_and_indices_to_int64():
    """Vertices not given as a tensor (a list of integers, a float32 array) are cast to float64; every other input
    follows the vertices' dtype (float32 vertices with float64 directions, origin and offsets: the all-float32
    cast bit for bit); faces and pair indices of other integer dtypes (uint32, int16, int32) index as int64 does."""
    tri = [[2, 0, 0], [2, 1, 0], [2, 0, 1]]
    f = torch.tensor([[0, 1, 2]])
    x, o = _t([[1.0, 0.0, 0.0]]), _t([0.0, 0.25, 0.5])
    for given in (tri, np.array(tri, np.float32)):
        hits = cast_rays(given, f, x, o)
        assert hits.t.dtype == F64 and hits.t.tolist() == [2.0] and hits.u.tolist() == [0.25]
    rng = np.random.default_rng(4)
    v, fb = _blob()
    d = _rays_at(np.array([8.0, 0.5, 0.2]), 300, 0.06, rng)
    h = rng.uniform(0.1, 0.2, len(d))
    v32, f64 = _t(v, torch.float32), torch.from_numpy(fb)
    ref = cast_rays(v32, f64, _t(d, torch.float32), torch.zeros(3), _t(h, torch.float32))
    got = cast_rays(v32, f64, d, _t(np.zeros(3)), h)
    assert ref.hit.sum() > 50 and got.t.dtype == torch.float32
    assert torch.equal(got.face, ref.face) and torch.equal(got.t, ref.t) and torch.equal(got.u, ref.u)
    ref = cast_rays(_t(v), f64, _t(d), _t(np.zeros(3)))
    for faces in (fb.astype(np.uint32), fb.astype(np.int16)):
        assert torch.equal(cast_rays(_t(v), faces, _t(d), _t(np.zeros(3))).face, ref.face)
    ray_all, face_all = _every_pair(len(d), len(fb))
    for ri, fi in ((ray_all.int(), face_all.int()), (ray_all.numpy().astype(np.uint32), face_all.numpy())):
        pairs = cast_ray_pairs(_t(v), f64, _t(d), _t(np.zeros(3)), ri, fi)
        assert torch.equal(pairs.face, ref.face) and torch.equal(pairs.t, ref.t)


def test_vertices_of_a_wrong_shape_are_named():
    """Vertices of shape (3, 4) are refused with the field, the expected and the given shape."""
    with pytest.raises(ValueError) as err:
        cast_rays(torch.zeros(3, 4, dtype=F64), torch.tensor([[0, 1, 2]]), _t([[1.0, 0.0, 0.0]]), _t(np.zeros(3)))
    assert str(err.value) == "cast_rays: field 'vertices': expected shape (V, 3), got (3, 4)"


def test_read_only_numpy_inputs_are_accepted_without_warnings():
    """Read-only numpy arrays (e.g. views of a cache) as faces, directions, origin and offsets: no warning (torch
    warns about sharing non-writable memory, once per process unless told to warn always) and the same hits."""
    v = _t([[2.0, 0.0, 0.0], [2.0, 1.0, 0.0], [2.0, 0.0, 1.0]])
    arrays = [np.array([[0, 1, 2]]), np.array([[1.0, 0.0, 0.0]]), np.array([0.0, 0.25, 0.25]), np.array([0.25])]
    for a in arrays:
        a.setflags(write=False)
    always = torch.is_warn_always_enabled()
    torch.set_warn_always(True)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            hits = cast_rays(v, *arrays)
    finally:
        torch.set_warn_always(always)
    assert hits.face.tolist() == [0] and hits.t.tolist() == [2.0] and hits.v.tolist() == [0.5]


def test_pair_casts_where_no_ray_hits():
    """Pair casts where nothing hits: cast_ray_pairs reports faces -1 and t = 0; a PairCaster search returns empty
    rays, faces and t, its t in the vertices' dtype (float64), with and without pairs."""
    v = _t([[2.0, 0.0, 0.0], [2.0, 1.0, 0.0], [2.0, 0.0, 1.0]])
    f = torch.tensor([[0, 1, 2]])
    d = _t([[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # away from the triangle, and beside it
    o = _t([0.0, 0.25, 0.25])
    pairs = (torch.tensor([0, 1]), torch.tensor([0, 0]))
    miss = cast_ray_pairs(v, f, d, o, *pairs)
    assert miss.face.tolist() == [-1, -1] and miss.t.tolist() == [0.0, 0.0] and miss.tests == 2
    caster = PairCaster(v, f, o)
    for chunks in ([pairs], []):
        ray, face, t, tests = caster.search(d, chunks)
        assert ray.tolist() == face.tolist() == t.tolist() == [] and tests == (2 if chunks else 0)
        assert ray.dtype == face.dtype == torch.int64 and t.dtype == F64


def _octahedron() -> tuple[np.ndarray, np.ndarray]:
    """Vertices (+-1, 0, 0), (0, +-2, 0), (0, 0, +-1) (box centre 0, bounding radius 2; all exact) and its 8 faces,
    outward."""
    v = np.array([[1.0, 0, 0], [-1, 0, 0], [0, 2, 0], [0, -2, 0], [0, 0, 1], [0, 0, -1]])
    f = np.array([[0, 2, 4], [0, 5, 2], [0, 4, 3], [0, 3, 5], [1, 4, 2], [1, 2, 5], [1, 3, 4], [1, 5, 3]])
    return v, f


def _facing_away(v: np.ndarray, f: np.ndarray, o: np.ndarray) -> np.ndarray:
    """(o - V0) . ((V1 - V0) x (V2 - V0)) <= 0 per face (back_faces' documented condition), directly."""
    return ((o - v[f[:, 0]]) * np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])).sum(1) <= 0


def test_back_faces_outside_test_at_its_margin_and_the_culled_condition_inclusive():
    """The octahedron's bounding sphere (centre of its box, 0; radius 2): an origin at 2 (1 + 1e-6) exactly is
    not outside (no culling), the next float beyond it is; origins at 3.5 on the y axis and at (0.5, 0, 2.1)
    (off the box's centre line) are outside. A face seen exactly edge-on ((o - V0) . n = 0, exact) is culled
    (documented: <= 0). Integer faces of another dtype and an origin given as a column give the same mask."""
    v, f = _octahedron()
    margin = 2.0 * (1 + 1e-6)
    assert back_faces(v, f, np.array([0.0, margin, 0.0])) is None
    for o in ([0.0, np.nextafter(margin, np.inf), 0.0], [0.0, 3.5, 0.0], [0.5, 0.0, 2.1], [3.0, 0.0, -2.0]):
        o = np.array(o)
        mask = back_faces(v, f, o)
        assert mask is not None and mask.tolist() == _facing_away(v, f, o).tolist()
    o = np.array([3.0, 0.0, -2.0])  # in the plane x + y / 2 + z = 1 of face 0
    mask = back_faces(v, f, o)
    assert mask[0] and not mask[1]  # edge-on: culled; the neighbour across its edge (1, 0, 0)-(0, 2, 0) faces o
    assert back_faces(v, f.astype(np.int32), o).tolist() == mask.tolist()
    assert back_faces(v, f, o.reshape(3, 1)).tolist() == mask.tolist()


def test_back_faces_of_float32_vertices_agree_with_exact_arithmetic():
    """float32 vertices, origins 1e-9 in front of or behind a face's plane, 3 m from its vertex: the face's flag
    is the exact (rational) sign of (o - V0) . (e1 x e2) <= 0 of the float32 values."""
    from fractions import Fraction

    v, f = icosphere(1, 1.0)
    v32 = v.astype(np.float32)
    vx = v32.astype(np.float64)
    rng = np.random.default_rng(0)
    for k in rng.choice(len(f), 24, replace=False):
        p0, p1, p2 = vx[f[k]]
        n = np.cross(p1 - p0, p2 - p0)
        n /= np.linalg.norm(n)
        side = np.cross(n, rng.normal(size=3))
        o = p0 + 3.0 * side / np.linalg.norm(side) + rng.choice([-1e-9, 1e-9]) * n
        q = [[Fraction(float(c)) for c in p] for p in (p0, p1, p2, o)]
        e1, e2, r = ([a - b for a, b in zip(q[i], q[0], strict=True)] for i in (1, 2, 3))
        cross = [e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0]]
        mask = back_faces(v32, f, o)
        assert mask is not None and bool(mask[k]) == (sum(a * b for a, b in zip(r, cross, strict=True)) <= 0)


def test_back_faces_refuses_a_degenerate_face_and_an_empty_mesh_and_accepts_perturbed_icosahedra():
    """A closed, consistently oriented tetrahedron with one edge split by its midpoint and closed by a zero-area
    face (vertex centroid 0, exact: that face's (V0 - c) . n = 0, not > 0) does not qualify; nor does a mesh
    without vertices and faces (None, no warning). Radially perturbed icosahedra (star-shaped, one sheet) qualify,
    with the directly computed mask."""
    v = np.array([[2.0, 0, 0], [0, 2, 0], [-1.5, -1.5, 2], [-1.5, -1.5, -2], [1, 1, 0]])
    f = np.array([[0, 4, 2], [4, 1, 2], [1, 4, 0], [0, 3, 1], [0, 2, 3], [1, 3, 2]])
    o = np.array([5.0, 5.0, 5.0])
    assert back_faces(v, f, o) is None
    assert back_faces(v[:4], np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]]), o) is not None  # unsplit
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert back_faces(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), o) is None
    v0, f0 = icosphere(0, 1.0)
    for seed in range(12):
        vv = v0 * np.random.default_rng(seed).uniform(0.8, 1.2, (len(v0), 1))
        mask = back_faces(vv, f0, o)
        assert mask is not None and mask.tolist() == _facing_away(vv, f0, o).tolist()


@pytest.mark.parametrize("offsets", [False, True])
def test_face_rows_tuv_and_gradients_against_a_linear_solve_with_autograd(offsets):
    """FaceRows (the numpy recompute and its hand-written backward) against an independent reference: t, u, v
    of each (ray, face) pair from torch.linalg.solve of o + t d = a0 + u e1 + v e2 (float64), and the vertex
    gradients of a random linear loss on t, u, v by autograd through that solve; rays from an origin offset
    along an axis (the LiDAR's lasers) or from one shared origin (the camera)."""
    from robustbench3d.sensors.ray_rows import FaceRows, face_slots

    rng = np.random.default_rng(11)
    v, f = _blob(level=1, centre=(5.0, -0.4, 0.6))
    face = rng.integers(0, len(f), 300)
    used, slot = face_slots(face, len(f))
    centre = v[f[face]].mean(1) + rng.normal(0, 0.05, (300, 3))  # aimed near each face, hit or miss
    origin = np.array([0.2, -0.1, 0.3])
    axis = np.array([0.0, 0.6, 0.8])
    h = rng.uniform(-0.5, 0.5, 300) if offsets else None
    start = origin + (h[:, None] * axis if offsets else 0.0)
    d = centre - start
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    fr = FaceRows.of(v, f[used], origin, axis if offsets else None)
    pairs = fr.tuv(slot, d, h)

    vt = torch.tensor(v, requires_grad=True)
    a0, a1, a2 = vt[f[face, 0]], vt[f[face, 1]], vt[f[face, 2]]
    system = torch.stack([-torch.from_numpy(d), a1 - a0, a2 - a0], dim=2)  # [-d | e1 | e2] (t, u, v) = o - a0
    tuv = torch.linalg.solve(system, (torch.from_numpy(start) - a0)[..., None])[..., 0]
    np.testing.assert_allclose(np.stack([pairs.t, pairs.u, pairs.v], 1), tuv.detach().numpy(), rtol=1e-9, atol=1e-9)
    g = rng.normal(size=(300, 3))
    (tuv * torch.from_numpy(g)).sum().backward()
    grads = fr.edge_grads(pairs, g[:, 0], g[:, 1], g[:, 2])
    np.testing.assert_allclose(fr.vertex_grads(*grads, len(v)), vt.grad.numpy(), rtol=1e-7, atol=1e-8)
    assert fr.rows.shape == (17 if offsets else 10, len(used))
