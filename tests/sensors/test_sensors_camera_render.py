"""Camera rendering of meshes into the image (robustbench3d.sensors.camera_render) against hand cases."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from robustbench3d.kitti.calib import Calibration
from robustbench3d.sensors import camera_model as cm
from robustbench3d.sensors.camera_depth import DepthMap
from robustbench3d.sensors.camera_model import Lighting
from robustbench3d.sensors.camera_render import (
    camera_ray_tests,
    mesh_box,
    render_camera,
    render_camera_crop_torch,
    render_camera_torch,
)
from robustbench3d.sensors.camera_shade import rect_lighting as _rect_lighting
from robustbench3d.sensors.camera_shade import shade
from robustbench3d.sensors.mesh import icosphere
from robustbench3d.synth.calibs import DAY_0926

# velodyne (x fwd, y left, z up) -> rect (x right, y down, z fwd), no offsets
_PERM = np.array([[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [1.0, 0.0, 0.0, 0.0]])


def small_calib(f: float = 20.0, cu: float = 20.0, cv: float = 15.0) -> Calibration:
    p2 = np.array([[f, 0.0, cu, 0.0], [0.0, f, cv, 0.0], [0.0, 0.0, 1.0, 0.0]])
    return Calibration(P0=p2, P1=p2, P2=p2, P3=p2, R0_rect=np.eye(3), Tr_velo_to_cam=_PERM,
                       Tr_imu_to_velo=np.eye(3, 4))


#: Lighting under which a fronto-parallel face (normal along rect -z, n.up = 0) has radiance = albedo:
#: ambient * 0.6 * sky = 1, no sun, no haze, exposure 1.
FLAT = Lighting(sun_direction=np.array([0.0, 0.0, 1.0]), sun_color=np.zeros(3), sky_zenith=np.ones(3),
                sky_horizon=np.ones(3), ambient=1 / 0.6, haze_distance=1e30, exposure=1.0)

# A triangle at z = 5 in front of the 40x30 camera: projects to (10, 3), (10, 27), (32, 15) px
TRI = np.array([[-2.5, -3.0, 5.0], [-2.5, 3.0, 5.0], [3.0, 0.0, 5.0]])
TRI_FACES = np.array([[0, 1, 2]])


def display(albedo: np.ndarray) -> np.ndarray:
    return cm.tone_curve(np.asarray(albedo, np.float64))


def test_hand_triangle_colours_alpha_and_antialiased_edge():
    calib = small_calib()
    black = np.zeros((30, 40, 3), np.uint8)
    c = np.array([0.2, 0.5, 0.8])
    res = render_camera(black, calib, [(TRI, TRI_FACES, np.tile(c, (3, 1)))], supersample=4, lighting=FLAT)
    assert res.status == ["rendered"] and res.boxes == [(10, 3, 33, 28)]
    assert res.alpha[15, 20] == 1.0 and res.alpha[15, 9] == 0.0 and res.alpha[2, 20] == 0.0
    # the edge u = 10 splits pixel 10 (footprint [9.5, 10.5]): 8 of its 16 samples are inside
    assert res.alpha[15, 10] == 0.5
    np.testing.assert_array_equal(res.image[15, 20], np.round(255 * display(c)))
    np.testing.assert_array_equal(res.image[15, 10], np.round(0.5 * 255 * display(c)))
    np.testing.assert_array_equal(res.image[15, 9], [0, 0, 0])
    # over a grey photo: alpha * object + (1 - alpha) * photo
    grey = np.full((30, 40, 3), 100, np.uint8)
    res = render_camera(grey, calib, [(TRI, TRI_FACES, np.tile(c, (3, 1)))], supersample=4, lighting=FLAT)
    np.testing.assert_array_equal(res.image[15, 10], np.round(255 * (0.5 * display(c) + 0.5 * 100 / 255)))
    outside = np.ones((30, 40), bool)
    outside[3:28, 10:33] = False
    assert (res.image[outside] == 100).all()


def test_hand_triangle_barycentric_vertex_colours():
    """Fronto-parallel triangle: the barycentrics of a pixel centre are its 2D barycentrics in the image."""
    calib = small_calib()
    cols = np.eye(3)
    out = render_camera_torch(torch.zeros(30, 40, 3, dtype=torch.float64), calib, [(TRI, TRI_FACES, cols)],
                              supersample=1, lighting=FLAT).numpy()
    a, b, c = np.array([10.0, 3.0]), np.array([10.0, 27.0]), np.array([32.0, 15.0])
    for u, v in [(20, 15), (12, 10), (25, 16), (30, 15), (11, 25)]:
        m = np.column_stack([b - a, c - a])
        lb, lc = np.linalg.solve(m, np.array([u, v]) - a)
        expect = display((1 - lb - lc) * cols[0] + lb * cols[1] + lc * cols[2])
        np.testing.assert_allclose(out[v, u], expect, atol=1e-12)


def test_shading_matches_the_generator_camera_model():
    """The torch shading equals camera_model's diffuse_faces -> aerial_perspective -> tone_curve."""
    calib = DAY_0926.calib
    rng = np.random.default_rng(3)
    light = Lighting(sun_direction=np.array([0.3, -0.5, 0.81]) / np.linalg.norm([0.3, -0.5, 0.81]),
                     sun_color=np.array([2.6, 2.5, 2.2]), sky_zenith=np.array([0.18, 0.32, 0.75]),
                     sky_horizon=np.array([0.62, 0.72, 0.86]), ambient=0.4, haze_distance=300.0, exposure=1.1)
    n_velo = rng.normal(size=(50, 3))
    n_velo /= np.linalg.norm(n_velo, axis=1, keepdims=True)
    albedo = rng.random((50, 3))
    dist = rng.uniform(1, 200, 50)
    ref = cm.diffuse_faces(albedo.astype(np.float32), n_velo.astype(np.float32), light.sun_direction.astype(np.float32),
                           light.sun_color, light.ambient, light.sky_zenith, light.sky_horizon).lit
    ref = cm.aerial_perspective(ref.T.astype(np.float64), dist, light.sky_horizon, light.haze_distance).T
    ref = cm.tone_curve(ref * light.exposure)
    n_rect = n_velo @ calib.velo_to_rect[:3, :3].T
    got = shade(torch.tensor(albedo), torch.tensor(n_rect), torch.tensor(dist),
                _rect_lighting(light, calib, torch.float64)).numpy()
    np.testing.assert_allclose(got, ref, atol=2e-5)  # float32 reference, rotation rounding of the calib


def test_mesh_box_by_hand():
    calib = small_calib()
    assert mesh_box(calib, TRI, (40, 30)) == ((10, 3, 33, 28), "rendered")
    assert mesh_box(calib, TRI * [1, 1, -1], (40, 30)) == (None, "behind")
    assert mesh_box(calib, TRI + np.array([30.0, 0, 0]), (40, 30)) == (None, "outside")  # u >= 40 everywhere
    assert mesh_box(calib, TRI + np.array([0, 0, -5.0 + 1e-9]), (40, 30)) == (None, "behind")  # in the camera plane
    straddling = np.array([[-1.0, -1.0, -0.5], [1.0, -1.0, 0.5], [0.0, 1.0, 1.0]])
    assert mesh_box(calib, straddling, (40, 30)) == ((0, 0, 40, 30), "rendered")


def _sphere(centre, radius=0.4, seed=0):
    v, f = icosphere(2, radius)
    return v + np.asarray(centre, np.float64), f, np.random.default_rng(seed).random((len(v), 3))


def test_crop_render_equals_full_image_render():
    calib = DAY_0926.calib
    w, h = DAY_0926.image_size
    photo = np.random.default_rng(1).integers(0, 256, (h, w, 3), dtype=np.uint8)
    meshes = [_sphere([1.0, 0.0, 10.0]), _sphere([1.3, 0.2, 12.0], seed=1), _sphere([-7.55, 0.5, 9.0], seed=2)]
    crop = render_camera(photo, calib, meshes, supersample=2)
    full = render_camera(photo, calib, meshes, supersample=2, full_image=True)
    assert crop.boxes[2][0] == 0  # the third sphere is cut by the image border
    np.testing.assert_array_equal(crop.image, full.image)
    np.testing.assert_array_equal(crop.alpha, full.alpha)
    changed = np.argwhere((crop.image != photo).any(axis=2))
    inside = np.zeros((h, w), bool)
    for u0, v0, u1, v1 in crop.boxes:
        inside[v0:v1, u0:u1] = True
    assert len(changed) > 2000 and inside[changed[:, 0], changed[:, 1]].all()
    photo_t = torch.as_tensor(photo, dtype=torch.float64) / 255
    a = render_camera_torch(photo_t, calib, meshes, supersample=2)
    b = render_camera_torch(photo_t, calib, meshes, supersample=2, full_image=True)
    assert torch.equal(a, b)


def test_crop_equals_full_with_faces_crossing_the_camera_plane():
    """Faces with a vertex behind the camera get the whole region as their box: still the full-image result."""
    calib = small_calib()
    photo = np.random.default_rng(4).integers(0, 256, (30, 40, 3), dtype=np.uint8)
    wall = np.array([[-2.0, -1.0, -0.5], [2.0, -1.0, 2.5], [0.0, 2.0, 2.5]])  # one vertex behind the camera
    meshes = [(wall, TRI_FACES, np.eye(3)), _sphere([0.3, -0.2, 2.0], radius=0.5, seed=3)]
    crop = render_camera(photo, calib, meshes, supersample=2)
    full = render_camera(photo, calib, meshes, supersample=2, full_image=True)
    alone = render_camera(photo, calib, meshes[:1], supersample=2)
    assert crop.boxes[0] == (0, 0, 40, 30) and (alone.alpha > 0).sum() > 300
    np.testing.assert_array_equal(crop.image, full.image)
    np.testing.assert_array_equal(crop.alpha, full.alpha)


def test_gradients_match_finite_differences():
    calib = small_calib(f=10.0, cu=6.0, cv=5.0)
    rng = np.random.default_rng(7)
    verts = torch.tensor([[-0.8, -0.7, 2.0], [0.9, -0.5, 2.3], [0.1, 0.9, 1.9], [0.6, 0.4, 2.6]], dtype=torch.float64,
                         requires_grad=True)
    faces = np.array([[0, 1, 2], [1, 3, 2]])
    colors = torch.tensor(rng.random((4, 3)), requires_grad=True)
    photo = torch.tensor(rng.random((10, 12, 3)), requires_grad=True)
    light = Lighting(sun_direction=np.array([-0.6, 0.3, 0.74]) / np.linalg.norm([-0.6, 0.3, 0.74]),
                     sun_color=np.array([1.5, 1.4, 1.2]), sky_zenith=np.array([0.2, 0.3, 0.7]),
                     sky_horizon=np.array([0.6, 0.7, 0.8]), ambient=0.5, haze_distance=3.0, exposure=0.8)

    def fn(v, c, p):
        return render_camera_torch(p, calib, [(v, faces, c)], supersample=2, lighting=light)

    out = fn(verts, colors, photo)
    out.sum().backward()
    assert verts.grad.abs().sum() > 0 and colors.grad.abs().sum() > 0
    # the photo shows through by 1 - alpha: 1 outside, 0 inside, in between on the anti-aliased edge pixels
    alpha = 1.0 - photo.grad[..., 0]
    assert (alpha == 0).any() and (alpha == 1).any() and ((alpha > 0) & (alpha < 1)).any()
    # every vertex and colour coordinate by central differences; the photo (360 inputs, on which the image
    # depends linearly) by random projections (gradcheck's fast mode)
    still = photo.detach()
    assert torch.autograd.gradcheck(lambda v, c: fn(v, c, still), (verts, colors), eps=1e-6, atol=1e-7, rtol=1e-5)
    assert torch.autograd.gradcheck(lambda p: fn(verts.detach(), colors.detach(), p), (photo,), eps=1e-6,
                                    atol=1e-7, rtol=1e-5, fast_mode=True)


def test_scene_depth_hides_exactly_where_nearer():
    calib = small_calib()
    grey = np.full((30, 40, 3), 90, np.uint8)
    mesh = (TRI, TRI_FACES, np.tile([0.9, 0.1, 0.1], (3, 1)))
    plain = render_camera(grey, calib, [mesh], supersample=2, lighting=FLAT)
    dmap = np.full((30, 40), np.inf)
    dmap[:, :20] = 4.0  # nearer than the triangle (z = 5) left of column 20
    hidden = render_camera(grey, calib, [mesh], supersample=2, lighting=FLAT, scene_depth=DepthMap(dmap))
    assert (hidden.image[:, :20] == 90).all() and (hidden.alpha[:, :20] == 0).all()
    np.testing.assert_array_equal(hidden.image[:, 20:], plain.image[:, 20:])
    far = np.full((30, 40), 6.0)
    behind = render_camera(grey, calib, [mesh], supersample=2, lighting=FLAT, scene_depth=DepthMap(far))
    np.testing.assert_array_equal(behind.image, plain.image)


def test_two_objects_overlapping_resolve_by_depth():
    calib = small_calib()
    black = np.zeros((30, 40, 3), np.uint8)
    red, green = np.tile([0.9, 0.0, 0.0], (3, 1)), np.tile([0.0, 0.9, 0.0], (3, 1))
    big = TRI * [1.6, 1.6, 1.6]  # same projection as TRI, at z = 8
    for near, far, want in (((TRI, red), (big, green), red), ((TRI * [2, 2, 2], red), (big, green), green)):
        res = render_camera(black, calib, [(near[0], TRI_FACES, near[1]), (far[0], TRI_FACES, far[1])],
                            supersample=1, lighting=FLAT)
        np.testing.assert_array_equal(res.image[15, 20], np.round(255 * display(want[0])))
        res = render_camera(black, calib, [(far[0], TRI_FACES, far[1]), (near[0], TRI_FACES, near[1])],
                            supersample=1, lighting=FLAT)
        np.testing.assert_array_equal(res.image[15, 20], np.round(255 * display(want[0])))


@pytest.mark.parametrize("centre", [[0.0, 0.3, 1.0], [0.5, 0.5, 80.0], [-6.0, 0.0, 8.0], [0.0, 0.0, 0.2]])
def test_no_nan_near_far_partly_outside_and_straddling(centre):
    straddles = centre[2] < 0.4  # whole image rendered: use the small camera
    calib = small_calib() if straddles else DAY_0926.calib
    w, h = (40, 30) if straddles else DAY_0926.image_size
    v, f, c = _sphere(centre)
    vt = torch.tensor(v, requires_grad=True)
    ct = torch.tensor(c, requires_grad=True)
    out = render_camera_torch(torch.full((h, w, 3), 0.5, dtype=torch.float64), calib, [(vt, f, ct)], supersample=1)
    assert torch.isfinite(out).all()
    out.sum().backward()
    assert torch.isfinite(vt.grad).all() and torch.isfinite(ct.grad).all() and ct.grad.abs().sum() > 0
    assert (out != 0.5).any()


def test_behind_camera_and_outside_are_not_rendered():
    calib = DAY_0926.calib
    w, h = DAY_0926.image_size
    photo = np.random.default_rng(2).integers(0, 256, (h, w, 3), dtype=np.uint8)
    res = render_camera(photo, calib, [_sphere([0.0, 0.0, -5.0]), _sphere([40.0, 0.0, 10.0])])
    assert res.boxes == [None, None] and res.status == ["behind", "outside"]
    np.testing.assert_array_equal(res.image, photo)
    assert not res.alpha.any()


def test_bad_input_names_the_field():
    calib = small_calib()
    black = np.zeros((30, 40, 3), np.uint8)
    with pytest.raises(ValueError, match="field 'meshes\\[0\\]'"):
        render_camera(black, calib, [(TRI, np.array([[0, 1, 3]]), np.ones((3, 3)))])
    with pytest.raises(ValueError, match="field 'meshes\\[0\\]'"):
        render_camera(black, calib, [(TRI * np.nan, TRI_FACES, np.ones((3, 3)))])
    with pytest.raises(ValueError, match="field 'supersample'"):
        render_camera(black, calib, [(TRI, TRI_FACES, np.ones((3, 3)))], supersample=0)
    with pytest.raises(ValueError, match="field 'image'"):
        render_camera(black.astype(np.float32), calib, [])
    ok = (TRI, TRI_FACES, np.ones((3, 3)))
    exact = [([(TRI, TRI_FACES)], "field 'meshes[0]': expected (vertices, faces, colors)"),
             ([ok, (TRI, np.array([[0, 1, 2, 0]]), np.ones((3, 3)))],
              "field 'meshes[1]': faces must be (F, 3) indices into 3 vertices"),
             ([(TRI, TRI_FACES, np.ones((2, 3)))], "field 'meshes[0]': vertices (3, 3) and colors (2, 3) must both "
                                                   "be (V, 3)")]
    for meshes, message in exact:
        with pytest.raises(ValueError) as err:
            render_camera(black, calib, meshes)
        assert str(err.value) == f"render_camera: {message}"
    for bad in (True, 2.0, "3", -1):
        with pytest.raises(ValueError) as err:
            render_camera(black, calib, [ok], supersample=bad)
        assert str(err.value) == f"render_camera: field 'supersample': must be an integer >= 1, got {bad!r}"
    assert render_camera(black, calib, [ok], supersample=np.int64(2)).boxes == [(10, 3, 33, 28)]
    with pytest.raises(ValueError) as err:
        mesh_box(calib, TRI * np.nan, (40, 30))
    assert str(err.value) == "render_camera: field 'vertices': empty, NaN or inf"


def test_mesh_box_outside_above_and_exactly_at_the_camera_plane():
    """A mesh wholly above or left of the image is 'outside' (no box); one with a vertex exactly at the near
    plane (depth 1e-6 m) straddles it: the whole image."""
    calib = small_calib()
    assert mesh_box(calib, TRI + np.array([0.0, -7.5, 0.0]), (40, 30)) == (None, "outside")  # v in [-27, -3]
    assert mesh_box(calib, TRI + np.array([-9.0, 0.0, 0.0]), (40, 30)) == (None, "outside")  # u in [-26, -4]
    near = TRI.copy()
    near[2, 2] = 1e-6
    assert mesh_box(calib, near, (40, 30)) == ((0, 0, 40, 30), "rendered")


def test_colours_of_another_dtype_render_in_the_vertices_dtype():
    """Colour tensors in float32 beside float64 vertices are taken in float64 (as numpy colours are)."""
    calib = small_calib()
    grey = torch.full((30, 40, 3), 0.4, dtype=torch.float64)
    cols = np.array([[0.9, 0.2, 0.1], [0.1, 0.8, 0.3], [0.2, 0.3, 0.9]], np.float32)
    ref = render_camera_torch(grey, calib, [(TRI, TRI_FACES, cols.astype(np.float64))], supersample=2)
    got = render_camera_torch(grey, calib, [(torch.tensor(TRI), TRI_FACES, torch.from_numpy(cols))], supersample=2)
    assert got.dtype == torch.float64 and torch.equal(got, ref)


def test_candidate_pair_chunks_equal_one_pass_and_lie_in_the_face_spans():
    """Chunked candidate pairs (two meshes: a masked region) concatenate to the one-pass pairs, every chunk
    within its bound unless one span is larger, and each pair's sample lies in its face's span."""
    from robustbench3d.sensors.camera_cull import candidate_pairs as _candidate_pairs
    from robustbench3d.sensors.camera_render import _check_meshes, _Geometry, _pixel_set

    calib = DAY_0926.calib
    v, f = icosphere(2, 0.4)
    meshes = _check_meshes([(v + np.array([-2.0, 0.0, 10.0]), f, np.full_like(v, 0.5)),
                            (v + np.array([1.0, -0.6, 14.0]), f, np.full_like(v, 0.5))])
    region, _, _ = _pixel_set(calib, meshes, DAY_0926.image_size, False)
    assert not region.mask.all()
    s = 3
    spans = _Geometry.of(meshes, calib).cull.spans(s, region.rect)
    (one_s, one_f), = list(_candidate_pairs(spans, region, s))
    chunks = list(_candidate_pairs(spans, region, s, 1000))
    assert len(chunks) > 5
    assert all(len(c[0]) <= 1000 for c in chunks)
    assert np.array_equal(np.concatenate([c[0] for c in chunks]), one_s)
    assert np.array_equal(np.concatenate([c[1] for c in chunks]), one_f)
    # sample k of pixel region.pixels[k // s^2], sub-pixel (i, j) = divmod(k % s^2, s) -> absolute sample grid
    pv, pu = np.divmod(region.pixels[one_s // (s * s)], DAY_0926.image_size[0])
    i, j = np.divmod(one_s % (s * s), s)
    col, row = pu * s + j, pv * s + i
    face, srow, c0, c1 = spans
    key = face * 10**6 + srow  # one span per (face, row)
    assert len(np.unique(key)) == len(key)
    at = np.searchsorted(key, one_f * 10**6 + row)
    assert np.array_equal(key[at], one_f * 10**6 + row)
    assert np.all((col >= c0[at]) & (col < c1[at]))
    assert len(one_s) == len(np.unique(one_s * 1000 + one_f)) > 1000


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("distance", [4.0, 10.0, 35.0, 80.0])
def test_scanline_cull_is_conservative(dtype, distance):
    """The crop (box + scanline cull of the projected triangles) renders exactly like the full image (every
    sample near the mesh's bounding sphere against every face), for deformed objects from 4 m to 80 m, seen
    obliquely, in float64 and float32 (whose rounding the cull's margin must cover)."""
    from robustbench3d.attacks.object import random_shape

    calib = DAY_0926.calib
    w, h = DAY_0926.image_size
    photo = torch.as_tensor(np.random.default_rng(5).random((h, w, 3)), dtype=torch.float32)
    obj = random_shape(seed=int(distance * 10), amplitude=0.45)
    meshes = []
    for k, (x, y) in enumerate([(0.3, 0.1), (-0.35 * distance, 0.4), (0.25 * distance, -0.1)]):
        yaw = 0.7 * k
        rot = np.array([[np.cos(yaw), 0.0, np.sin(yaw)], [0.0, 1.0, 0.0], [-np.sin(yaw), 0.0, np.cos(yaw)]])
        verts = obj.vertices() @ rot.T + np.array([x, y, distance + 0.5 * k])
        meshes.append((torch.as_tensor(verts, dtype=dtype), obj.faces, torch.tensor(obj.colors, dtype=dtype)))
    crop = render_camera_torch(photo, calib, meshes, supersample=3)
    full = render_camera_torch(photo, calib, meshes, supersample=3, full_image=True)
    assert (crop != photo).any()
    assert torch.equal(crop, full)


def test_interior_pixels_take_one_sample_edges_s_squared():
    """Adaptive sampling by hand: a pixel whose 8 neighbours' centres show the same mesh as its own is the
    colour at its centre (one sample, alpha 1); a silhouette pixel is the mean of its s x s samples."""
    calib = small_calib()
    black = torch.zeros(30, 40, 3, dtype=torch.float64)
    cols = np.eye(3)
    one = render_camera_torch(black, calib, [(TRI, TRI_FACES, cols)], supersample=1, lighting=FLAT)
    four = render_camera_torch(black, calib, [(TRI, TRI_FACES, cols)], supersample=4, lighting=FLAT)
    # (20, 15) and (14, 12) are deep inside the triangle: one centre sample, as with s = 1
    for u, v in [(20, 15), (14, 12), (25, 15)]:
        assert torch.equal(four[v, u], one[v, u])
    # pixel (10, 15) lies on the edge u = 10: half its 16 samples are inside, their mean is not the centre's
    a, b, c = np.array([10.0, 3.0]), np.array([10.0, 27.0]), np.array([32.0, 15.0])
    expect = np.zeros(3)
    for dv in (np.arange(4) + 0.5) / 4 - 0.5:
        for du in (np.arange(4) + 0.5) / 4 - 0.5:
            lb, lc = np.linalg.solve(np.column_stack([b - a, c - a]), np.array([10 + du, 15 + dv]) - a)
            if lb >= 0 and lc >= 0 and lb + lc <= 1:
                expect += display((1 - lb - lc) * cols[0] + lb * cols[1] + lc * cols[2]) / 16
    np.testing.assert_allclose(four[15, 10].numpy(), expect, atol=1e-12)
    assert not torch.allclose(four[15, 10], one[15, 10])


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_numpy_pair_search_equals_the_pair_casters_bit_for_bit(dtype):
    """The crop's numpy search of candidate pairs (_search_pairs) against PairCaster.search (the torch kernel it
    replaces): the same hitting rays, nearest faces, t (bit for bit) and pair count, for the crop's own candidate
    pairs of deformed objects near and far plus random pairs in several chunks, and with every face doubled
    (equal t everywhere: the smaller face index must win)."""
    from robustbench3d.attacks.object import random_shape
    from robustbench3d.sensors.camera_cull import candidate_pairs as _candidate_pairs
    from robustbench3d.sensors.camera_depth import camera_centre_rect, pixel_rays_rect
    from robustbench3d.sensors.camera_render import _check_meshes, _Geometry, _pixel_set, _search_pairs
    from robustbench3d.sensors.pair_search import PairTable
    from robustbench3d.sensors.raycast import PairCaster

    calib = DAY_0926.calib
    rng = np.random.default_rng(11)
    for k, distance in enumerate([3.0, 10.0, 40.0]):
        obj = random_shape(seed=k, amplitude=0.45)
        verts = obj.vertices() + np.array([0.3, 0.1, distance])
        for faces in (obj.faces, np.concatenate([obj.faces, obj.faces])):
            meshes = _check_meshes([(torch.as_tensor(verts, dtype=dtype), faces, np.full_like(verts, 0.5))])
            region = _pixel_set(calib, meshes, DAY_0926.image_size, False)[0]
            g = _Geometry.of(meshes, calib)
            caster = PairCaster(g.verts, torch.from_numpy(g.faces),
                                torch.as_tensor(camera_centre_rect(calib), dtype=dtype))
            table = PairTable.of(g.verts.numpy(), g.faces, camera_centre_rect(calib))
            assert np.array_equal(table.table, caster.table.numpy()) and table.tol == caster.tol
            s = 3
            pv, pu = np.divmod(region.pixels, DAY_0926.image_size[0])
            off = (np.arange(s) + 0.5) / s - 0.5
            dirs = pixel_rays_rect(calib, (pu[:, None] + np.tile(off, s)).reshape(-1),
                                   (pv[:, None] + np.repeat(off, s)).reshape(-1))
            chunks = list(_candidate_pairs(g.cull.spans(s, region.rect), region, s, 5000))
            n_extra = 20000
            chunks.append((rng.integers(0, len(dirs), n_extra), rng.integers(0, len(g.faces), n_extra)))
            d = dirs.astype(np.float32 if dtype == torch.float32 else np.float64)
            ray, face, t, tests = _search_pairs(table, np.ascontiguousarray(d.T), iter(chunks))
            ray_t, face_t, t_t, tests_t = caster.search(torch.from_numpy(dirs),
                                                        [(torch.from_numpy(a), torch.from_numpy(b)) for a, b in chunks])
            assert tests == tests_t == sum(len(a) for a, _ in chunks)
            assert len(ray) > 1000
            assert np.array_equal(ray, ray_t.numpy()) and np.array_equal(face, face_t.numpy())
            assert t.dtype == t_t.numpy().dtype and np.array_equal(t, t_t.numpy())
            if len(faces) > len(obj.faces):
                assert face.max() < len(obj.faces)  # every doubled face ties with its copy: the first wins


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_compiled_region_walk_equals_the_numpy_spans_and_pair_search_bit_for_bit(dtype):
    """kernels.nearest_in_region (the compiled walk of each face's box and scanline spans) against its numpy
    reference, _FaceCull.spans -> _candidate_pairs -> _search_pairs: the same nearest face and t per sample (bit
    for bit) and the same pair count, for one box (every pixel rendered) and a masked region restricted to the
    faces touching it (two meshes, the second pass of a render), deformed objects from 0.6 m (faces crossing the
    camera plane) to 60 m, s = 1 and 3, and every face doubled (equal t: the smaller face index must win)."""
    from robustbench3d.attacks.object import random_shape
    from robustbench3d.sensors.camera_cull import Region as _Region
    from robustbench3d.sensors.camera_cull import candidate_pairs as _candidate_pairs
    from robustbench3d.sensors.camera_cull import nearest_in_region
    from robustbench3d.sensors.camera_depth import camera_centre_rect, pixel_rays_rect
    from robustbench3d.sensors.camera_render import _check_meshes, _Geometry, _pixel_set, _search_pairs
    from robustbench3d.sensors.pair_search import PairTable

    calib = DAY_0926.calib
    w, h = DAY_0926.image_size
    rng = np.random.default_rng(4)
    checked = 0
    for k, distance in enumerate([0.6, 8.0, 60.0]):
        obj = random_shape(seed=10 + k, amplitude=0.45)
        v = obj.vertices() + np.array([0.1, 0.05, distance])
        for faces in (obj.faces, np.concatenate([obj.faces, obj.faces])):
            meshes = _check_meshes([(torch.as_tensor(v, dtype=dtype), faces, np.full_like(v, 0.5)),
                                    (torch.as_tensor(v + np.array([1.5, 0.3, 4.0]), dtype=dtype), faces,
                                     np.full_like(v, 0.5))][:1 if distance < 1 else 2])
            whole = _pixel_set(calib, meshes, (w, h), False)[0]
            g = _Geometry.of(meshes, calib)
            table = PairTable.of(g.verts.numpy(), g.faces, camera_centre_rect(calib))
            sparse = whole.mask & (rng.random(whole.mask.shape) < 0.3)
            lv, lu = np.nonzero(sparse)
            masked = _Region(whole.rect, sparse, (lv + whole.rect[1]) * w + lu + whole.rect[0])
            for region, faces_in in ((whole, None), (masked, g.cull.touching(masked))):
                for s in (1, 3):
                    pv, pu = np.divmod(region.pixels, w)
                    off = (np.arange(s) + 0.5) / s - 0.5
                    dirs = pixel_rays_rect(calib, (pu[:, None] + np.tile(off, s)).reshape(-1),
                                           (pv[:, None] + np.repeat(off, s)).reshape(-1))
                    d = np.ascontiguousarray(dirs.T.astype(g.np_dtype))
                    pairs = _candidate_pairs(g.cull.spans(s, region.rect, faces_in), region, s, 5000)
                    ray, face, t, tests = _search_pairs(table, d, pairs)
                    near, best, tests_c = nearest_in_region(g.cull, faces_in, table.table, d, region.mask,
                                                            region.rect, s, table.t_min, table.tol)
                    assert tests_c == tests > 0
                    assert np.array_equal(np.flatnonzero(near >= 0), ray) and np.array_equal(near[ray], face)
                    assert best.dtype == t.dtype == g.np_dtype and np.array_equal(best[ray], t)
                    assert np.all(np.isinf(np.delete(best, ray)))
                    checked += len(ray)
            if len(faces) > len(obj.faces):
                assert np.all(face % len(faces) < len(obj.faces))  # each face ties with its copy: the first wins
    assert checked > 20000


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_visible_hits_search_in_the_geometry_dtype_like_a_brute_force_cast(dtype):
    """_visible_hits (no scene depth, s = 2) against the PairCaster's search of every sample x every face: the
    same hit samples and nearest faces, and hit directions in the geometry's dtype (a float32 render searches
    in float32, as the PairCaster it must agree with)."""
    from robustbench3d.attacks.object import random_shape
    from robustbench3d.sensors.camera_depth import camera_centre_rect, pixel_rays_rect
    from robustbench3d.sensors.camera_render import _check_meshes, _Geometry, _pixel_set, _visible_hits
    from robustbench3d.sensors.pair_search import PairTable
    from robustbench3d.sensors.raycast import PairCaster

    calib = DAY_0926.calib
    obj = random_shape(seed=3, amplitude=0.45)
    verts = obj.vertices() + np.array([-0.4, 0.2, 25.0])
    meshes = _check_meshes([(torch.as_tensor(verts, dtype=dtype), obj.faces, np.full_like(verts, 0.5))])
    w = DAY_0926.image_size[0]
    region = _pixel_set(calib, meshes, DAY_0926.image_size, False)[0]
    g = _Geometry.of(meshes, calib)
    caster = PairCaster(g.verts, torch.from_numpy(g.faces), torch.as_tensor(camera_centre_rect(calib), dtype=dtype))
    hits = _visible_hits(calib, g, PairTable.of(g.verts.numpy(), g.faces, camera_centre_rect(calib)), region, w, 2,
                         None, False)
    pv, pu = np.divmod(region.pixels, w)
    off = np.array([-0.25, 0.25])
    dirs = pixel_rays_rect(calib, (pu[:, None] + np.tile(off, 2)).reshape(-1),
                           (pv[:, None] + np.repeat(off, 2)).reshape(-1))
    n, f = len(dirs), len(obj.faces)
    ray, face, _, _ = caster.search(torch.from_numpy(dirs), [(torch.arange(n).repeat_interleave(f),
                                                              torch.arange(f).repeat(n))])
    assert hits.cast == n and len(hits.sample) > 500
    assert np.array_equal(hits.sample, ray.numpy()) and np.array_equal(hits.face, face.numpy())
    assert hits.dirs.dtype == g.np_dtype == (np.float32 if dtype == torch.float32 else np.float64)
    np.testing.assert_array_equal(hits.dirs, dirs[hits.sample].astype(g.np_dtype))


def test_scanline_edge_functions_are_barycentrics_plus_the_hand_computed_margin():
    """_FaceCull's edge functions of one face by hand: a x + b y + c over twice the projected area is the 2D
    barycentric of the opposite vertex plus delta_f = SPAN_MARGIN + 64 eps cond, cond = |ray| / (min edge * cos),
    for v0 (0, 0, 10), v1 (1, 0, 10), v2 (0, 1, 11) seen from the origin (float32 ray test): normal (0, -1, 1),
    ray to the centroid (1, 1, 31) / 3, cos = 10 / sqrt(2 * 107), shortest edge 1: cond = sqrt(22898) / 10."""
    from robustbench3d.sensors.camera_cull import SPAN_MARGIN
    from robustbench3d.sensors.camera_cull import FaceCull as _FaceCull

    calib = DAY_0926.calib
    verts = np.array([[0.0, 0.0, 10.0], [1.0, 0.0, 10.0], [0.0, 1.0, 11.0]])
    fc = _FaceCull.of(calib, verts, np.array([[0, 1, 2]]), None, torch.float32, centre=np.zeros(3))
    delta = SPAN_MARGIN + 64 * float(np.finfo(np.float32).eps) * np.sqrt(22898.0) / 10
    uv, _ = calib.rect_to_image(verts)
    (x1, y1), (x2, y2) = uv[1] - uv[0], uv[2] - uv[0]
    area2 = abs(x1 * y2 - y1 * x2)
    assert fc.tight[0] and not fc.crossing[0] and not fc.unreachable[0]
    values = fc.edge[0] @ np.column_stack([uv, np.ones(3)]).T / area2  # (edge k, at vertex j)
    np.testing.assert_allclose(values, np.eye(3) + delta, rtol=0, atol=1e-9)


def test_cached_rays_and_edge_pixels_equal_their_references():
    """The crop's helpers against plain references: rays through image positions with a cached K^-1 equal
    pixel_rays_rect bit for bit, and the edge pixels (3 x 3 min != max) equal a loop over each pixel's 8
    neighbours on random masked regions."""
    from robustbench3d.sensors.camera_cull import Region as _Region
    from robustbench3d.sensors.camera_depth import pixel_ray_components, pixel_rays_rect
    from robustbench3d.sensors.camera_render import _edge_pixels
    from robustbench3d.sensors.camera_shade import camera_constants as _constants

    rng = np.random.default_rng(4)
    calib = DAY_0926.calib
    u, v = rng.uniform(-50, 1300, 20000), rng.uniform(-50, 420, 20000)
    assert np.array_equal(pixel_ray_components(_constants(calib).kinv, u, v).T, pixel_rays_rect(calib, u, v))
    for _ in range(200):
        mh, mw = rng.integers(1, 12, 2)
        mask = rng.random((mh, mw)) < rng.uniform(0.3, 1.0)
        shows = rng.integers(-1, 3, int(mask.sum()))
        grid = np.full((mh, mw), -1)
        grid[mask] = shows
        want = np.zeros((mh, mw), bool)
        for r in range(mh):
            for c in range(mw):
                for dr in (-1, 0, 1):
                    for dc in (-1, 0, 1):
                        rr, cc = r + dr, c + dc
                        other = grid[rr, cc] if 0 <= rr < mh and 0 <= cc < mw else -1
                        want[r, c] |= other != grid[r, c]
        got = _edge_pixels(_Region((0, 0, int(mw), int(mh)), mask, np.flatnonzero(mask)), shows)
        assert np.array_equal(got, want[mask])


def test_ray_test_counts_by_hand():
    """``camera_ray_tests`` (the benchmark's counts) on the hand triangle: one sample per pixel of its box,
    plus s x s on each silhouette pixel (a pixel centre inside the triangle with a neighbour's outside, or the
    other way round; s > 1); a (sample, face) pair for each sample in the triangle, up to the cull's margin."""
    calib = small_calib()
    mesh = (TRI, TRI_FACES, np.eye(3))
    a, b, c = np.array([10.0, 3.0]), np.array([10.0, 27.0]), np.array([32.0, 15.0])

    def inside(px: np.ndarray, tol: float) -> np.ndarray:
        lam = np.linalg.solve(np.column_stack([b - a, c - a]), (px - a).T).T
        return (lam >= -tol).all(axis=1) & (lam.sum(axis=1) <= 1 + tol)

    assert mesh_box(calib, TRI, (40, 30))[0] == (10, 3, 33, 28)
    uu, vv = np.meshgrid(np.arange(10, 33), np.arange(3, 28))
    centres = np.stack([uu.ravel(), vv.ravel()], axis=1).astype(np.float64)
    shows = inside(centres, 0.0).reshape(uu.shape)
    padded = np.pad(shows, 1)
    edge = np.zeros_like(shows)
    for dv in (-1, 0, 1):
        for du in (-1, 0, 1):
            edge |= padded[1 + dv:1 + dv + shows.shape[0], 1 + du:1 + du + shows.shape[1]] != shows
    assert (shows.size, edge.sum(), shows.sum()) == (575, 154, 279)
    assert camera_ray_tests(calib, [mesh], (40, 30), 1) == (575, 279)
    for s in (2, 3, 4):
        offsets = (np.arange(s) + 0.5) / s - 0.5
        grid = np.array([[du, dv] for dv in offsets for du in offsets])
        subs = (centres[edge.ravel()][:, None, :] + grid[None]).reshape(-1, 2)
        samples, pairs = camera_ray_tests(calib, [mesh], (40, 30), s)
        assert samples == shows.size + s * s * edge.sum()
        assert shows.sum() + inside(subs, 0.0).sum() <= pairs <= shows.sum() + inside(subs, 0.02).sum()
    assert camera_ray_tests(calib, [], (40, 30), 3) == (0, 0)
    assert camera_ray_tests(calib, [(TRI * [1, 1, -1], TRI_FACES, np.eye(3))], (40, 30), 3) == (0, 0)  # behind
    with pytest.raises(ValueError, match="field 'supersample': must be an integer >= 1, got 0"):
        camera_ray_tests(calib, [mesh], (40, 30), 0)


#: Lighting with a sun and sky shading (normals matter), without haze (distance does not).
SUNNY = Lighting(sun_direction=np.array([-0.6, 0.3, 0.74]) / np.linalg.norm([-0.6, 0.3, 0.74]),
                 sun_color=np.array([1.5, 1.4, 1.2]), sky_zenith=np.array([0.2, 0.3, 0.7]),
                 sky_horizon=np.array([0.6, 0.7, 0.8]), ambient=0.5, haze_distance=1e30, exposure=0.8)


def test_a_scene_scaled_about_the_camera_renders_the_same_and_winding_does_not_shade():
    """Without haze the image depends on directions only: the hand triangle tilted and scaled by 0.05 about the
    camera centre (0.3 m faces, 0.25 m away) renders as at full size; and shading is two-sided per face: two
    triangles of one mesh, wound the same way or opposite ways, render the same."""
    calib = small_calib()
    grey = torch.full((30, 40, 3), 0.4, dtype=torch.float64)
    tilt = TRI * [1.0, 1.0, 1.0] + np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.5], [0.0, 0.0, -1.0]])
    cols = np.array([[0.9, 0.2, 0.1], [0.1, 0.8, 0.3], [0.2, 0.3, 0.9]])
    big = render_camera_torch(grey, calib, [(tilt, TRI_FACES, cols)], supersample=2, lighting=SUNNY)
    small = render_camera_torch(grey, calib, [(0.05 * tilt, TRI_FACES, cols)], supersample=2, lighting=SUNNY)
    assert (big != grey).any()
    torch.testing.assert_close(small, big, rtol=0, atol=1e-12)
    # a second, smaller triangle beside it in the same mesh, wound one way or the other
    quad = np.concatenate([tilt, tilt[:, :] * [0.3, 0.3, 1.0] + np.array([-1.2, 0.0, 0.0])])
    cols2 = np.concatenate([cols, cols[::-1]])
    same = render_camera_torch(grey, calib, [(quad, np.array([[0, 1, 2], [3, 4, 5]]), cols2)], supersample=2,
                               lighting=SUNNY)
    flipped = render_camera_torch(grey, calib, [(quad, np.array([[0, 1, 2], [3, 5, 4]]), cols2)], supersample=2,
                                  lighting=SUNNY)
    assert (same != big).any()
    torch.testing.assert_close(flipped, same, rtol=0, atol=1e-12)


def test_defaults_and_nothing_to_render():
    """``render_camera``'s default sampling is 3 x 3; no meshes, or meshes out of view, leave the image bit for
    bit with zero coverage, and give an empty crop (composited: the image)."""
    calib = small_calib()
    rng = np.random.default_rng(2)
    photo = rng.integers(0, 256, (30, 40, 3), dtype=np.uint8)
    mesh = (TRI, TRI_FACES, np.eye(3))
    default = render_camera(photo, calib, [mesh], lighting=FLAT)
    assert np.array_equal(default.image, render_camera(photo, calib, [mesh], supersample=3, lighting=FLAT).image)
    assert not np.array_equal(default.image, render_camera(photo, calib, [mesh], supersample=4, lighting=FLAT).image)
    behind = (TRI * [1, 1, -1], TRI_FACES, np.eye(3))
    for meshes in ([], [behind]):
        res = render_camera(photo, calib, meshes)
        assert np.array_equal(res.image, photo) and res.alpha.shape == (30, 40) and not res.alpha.any()
        assert res.alpha.dtype == np.float32
        image = torch.tensor(photo, dtype=torch.float64) / 255
        crop = render_camera_crop_torch(image, calib, meshes)
        assert crop.pixels.shape == (0,) and crop.values.shape == (0, 3) and crop.rect is None
        assert crop.values.dtype == image.dtype and torch.equal(crop.composite(image), image)


def test_srgb_tone_curve_equals_the_generator_curve_on_its_toe_breakpoint_and_clips():
    """srgb_tone_curve against camera_model.tone_curve (its numpy original) where the linear toe 12.92 x applies
    (x <= 0.0031308, dark haze-free pixels), exactly at the breakpoint (where the two branches differ by 3e-8:
    the toe is taken), and its documented clip to [0, 1] below 0 and above the shoulder."""
    from robustbench3d.sensors.camera_shade import srgb_tone_curve

    at = 0.003133252396650859  # x / (1 + x / 4) == 0.0031308 exactly
    assert at / (1.0 + 0.25 * at) == 0.0031308
    exposed = np.array([-0.5, -1e-3, 0.0, 1e-6, 4e-4, 1.5e-3, 0.0031, at, np.nextafter(at, 1.0), 0.01, 0.3, 2.0,
                        5.0, 100.0])
    got = srgb_tone_curve(torch.tensor(exposed)).numpy()
    np.testing.assert_allclose(got, cm.tone_curve(exposed), rtol=0, atol=1e-15)
    assert got[7] == 12.92 * 0.0031308 and got[0] == got[1] == 0.0 and got[-1] == 1.0
    np.testing.assert_allclose(got[3:6], 12.92 * exposed[3:6] / (1 + 0.25 * exposed[3:6]), rtol=1e-15)


def test_sample_offsets_are_the_sub_pixel_centres():
    """The s x s samples of a pixel sit at the centres of its s x s sub-pixels, (i + 1/2) / s - 1/2, sample k at
    (row, column) = divmod(k, s): by hand for s = 1..4 (the uncached helper, and the cached per-sample table)."""
    from robustbench3d.sensors.camera_render import _sample_offsets, _sub_sample_offsets

    hand = {1: [0.0], 2: [-0.25, 0.25], 3: [-1 / 3, 0.0, 1 / 3], 4: [-0.375, -0.125, 0.125, 0.375]}
    for s, want in hand.items():
        np.testing.assert_allclose(_sample_offsets(s), want, rtol=0, atol=1e-15)
    col, row = _sub_sample_offsets(2)
    np.testing.assert_array_equal(col, [-0.25, 0.25, -0.25, 0.25])
    np.testing.assert_array_equal(row, [-0.25, -0.25, 0.25, 0.25])


def test_float32_geometry_gradients_do_not_depend_on_the_photo_dtype():
    """The geometry runs in the vertices' dtype: with float32 vertices and colours, a float64 photo (of the same
    float32-exact values) gives the same vertex and colour gradients, bit for bit, as a float32 photo; and the
    float64 photo's own gradient is 1 - alpha with the coverage alpha summed in float32 (k samples of weight
    float32(1/9), s = 3) and not rounded again to float32."""
    calib = small_calib()
    cols = np.array([[0.9, 0.2, 0.1], [0.1, 0.8, 0.3], [0.2, 0.3, 0.9]])
    grads = {}
    for pd in (torch.float32, torch.float64):
        v = torch.tensor(TRI, dtype=torch.float32, requires_grad=True)
        c = torch.tensor(cols, dtype=torch.float32, requires_grad=True)
        p = torch.full((30, 40, 3), 0.375, dtype=pd, requires_grad=True)
        out = render_camera_torch(p, calib, [(v, TRI_FACES, c)], supersample=3, lighting=SUNNY)
        out.sum().backward()
        grads[pd] = (out.detach(), v.grad, c.grad, p.grad)
    (o32, v32, c32, _), (o64, v64, c64, p64) = grads[torch.float32], grads[torch.float64]
    assert o64.dtype == p64.dtype == torch.float64 and torch.equal(o64, o32.double())
    assert v64.dtype == torch.float32 and torch.equal(v64, v32) and torch.equal(c64, c32)
    w = np.float32(1 / 9)
    alpha32 = [np.float32(0.0)]
    for _ in range(9):
        alpha32.append(np.float32(alpha32[-1] + w))
    k = torch.round((1 - p64[..., 0]) * 9).long()
    edge = (k > 0) & (k < 9)
    assert edge.sum() > 20 and ((k > 0) & (k < 5)).sum() > 5
    want = 1.0 - torch.tensor([float(a) for a in alpha32], dtype=torch.float64)[k[edge]]
    for ch in range(3):
        assert torch.equal(p64[..., ch][edge], want)


def test_ray_test_counts_of_a_face_kept_whole_box_rows():
    """A face whose vertex depths differ by more than SPAN_DEPTH_RATIO skips the scanline cull and keeps its
    whole box: with one sample per pixel its candidate pairs are exactly the pixel centres inside its projected
    vertices' box widened by BOX_MARGIN_PX (by hand; the box's last row and column included, nothing beyond),
    fewer than the rendered pixels (footprints overlapping the box). The default sampling is 3 x 3."""
    from robustbench3d.sensors.camera_cull import BOX_MARGIN_PX, SPAN_DEPTH_RATIO

    calib = small_calib()
    # depths 0.2 and 5 (ratio 25): projected to (20.0, 15.0), (12.6, 7.6) and (30.7, 22.6)
    steep = np.array([[0.0, 0.0, 0.2], [-1.85, -1.85, 5.0], [2.675, 1.9, 5.0]])
    assert SPAN_DEPTH_RATIO < 5.0 / 0.2
    uv, _ = calib.rect_to_image(steep)
    np.testing.assert_allclose(uv, [[20.0, 15.0], [12.6, 7.6], [30.7, 22.6]], atol=1e-12)
    lo, hi = uv.min(axis=0) - BOX_MARGIN_PX, uv.max(axis=0) + BOX_MARGIN_PX
    centres = np.prod(np.floor(hi) - np.ceil(lo) + 1)  # columns 13..30, rows 8..22
    assert centres == 18 * 15
    mesh = (steep, TRI_FACES, np.eye(3))
    assert mesh_box(calib, steep, (40, 30))[0] == (13, 8, 32, 24)
    assert camera_ray_tests(calib, [mesh], (40, 30), 1) == (19 * 16, centres)
    hand = (TRI, TRI_FACES, np.eye(3))
    assert camera_ray_tests(calib, [hand], (40, 30)) == camera_ray_tests(calib, [hand], (40, 30), 3)
    assert camera_ray_tests(calib, [hand], (40, 30), 3) != camera_ray_tests(calib, [hand], (40, 30), 4)


def test_candidate_pair_chunks_of_long_spans_hold_one_span_each():
    """Chunks of whole spans, at most ``chunk`` pairs each unless one span alone is longer: then that span is a
    chunk by itself (never two spans over the bound); together still the one-pass pairs."""
    from robustbench3d.sensors.camera_cull import candidate_pairs as _candidate_pairs
    from robustbench3d.sensors.camera_render import _check_meshes, _Geometry, _pixel_set

    calib = small_calib()
    meshes = _check_meshes([(TRI, TRI_FACES, np.eye(3))])
    region = _pixel_set(calib, meshes, (40, 30), False)[0]
    s = 2
    spans = _Geometry.of(meshes, calib).cull.spans(s, region.rect)
    lengths = list(spans[3] - spans[2])
    assert min(lengths) < 5 < max(lengths)
    chunks = list(_candidate_pairs(spans, region, s, 5))
    at = 0
    for samples, _ in chunks:  # the spans each chunk consists of, in order
        n, size = 0, 0
        while size < len(samples):
            size, n, at = size + lengths[at], n + 1, at + 1
        assert size == len(samples) and (size <= 5 or n == 1)
    assert at == len(lengths) and len(chunks) > 40
    (one_s, one_f), = list(_candidate_pairs(spans, region, s))
    assert np.array_equal(np.concatenate([c[0] for c in chunks]), one_s)
    assert np.array_equal(np.concatenate([c[1] for c in chunks]), one_f)


def test_full_image_reference_of_one_mesh_reaches_its_farthest_vertices():
    """The full-image reference for a single mesh equals the crop, for a triangle whose three vertices (all
    at the radius of its bounding sphere about its box centre) lie on pixel-centre rays almost along the view
    direction: those rays pass 0.9996 radii from the centre, inside the reference's inflated sphere, and hit.
    Likewise a 0.1 um triangle with a vertex on the optical axis (the ray passes one radius from the centre:
    the absolute 1e-9 m of the inflation keeps it, where 1e-3 of the radius is far below 1e-9 m)."""
    calib = small_calib(f=1000.0, cu=40.0, cv=30.0)
    tri = np.array([[0.2, 0.2, 10.0], [-0.2, 0.2, 10.0], [-0.2, -0.2, 10.0]])  # at (60, 50), (20, 50), (20, 10)
    tiny = np.array([[0.0, 0.0, 0.01], [1e-7, 0.0, 0.01], [1e-7, 1e-7, 0.01]])  # 1 cm away, a vertex at (40, 30)
    photo = np.random.default_rng(6).integers(0, 256, (60, 80, 3), dtype=np.uint8)
    for verts, lit in ((tri, [(50, 60), (50, 20), (10, 20)]), (tiny, [(30, 40)])):
        mesh = (verts, TRI_FACES, np.tile([0.9, 0.5, 0.1], (3, 1)))
        crop = render_camera(photo, calib, [mesh], supersample=1, lighting=FLAT)
        full = render_camera(photo, calib, [mesh], supersample=1, lighting=FLAT, full_image=True)
        assert all(crop.alpha[v, u] == 1.0 for v, u in lit)
        np.testing.assert_array_equal(full.alpha, crop.alpha)
        np.testing.assert_array_equal(full.image, crop.image)


def test_colours_are_checked_in_the_geometry_dtype():
    """Colour tensors are taken in the vertices' dtype before the finiteness check: float64 colours beyond
    float32's range beside float32 vertices are inf where the render uses them, and are refused."""
    calib = small_calib()
    cols = torch.tensor([[0.5, 0.5, 0.5], [0.5, 1e39, 0.5], [0.5, 0.5, 0.5]], dtype=torch.float64)
    with pytest.raises(ValueError) as err:
        render_camera(np.zeros((30, 40, 3), np.uint8), calib, [(torch.tensor(TRI, dtype=torch.float32), TRI_FACES,
                                                                cols)])
    assert str(err.value) == "render_camera: field 'meshes[0]': NaN or inf in vertices or colors"


def test_render_camera_image_check_and_empty_result_lists():
    """render_camera refuses an image that is not (H, W, 3) uint8 by its exact message, and with no meshes returns
    empty per-mesh lists (one entry per mesh, as for meshes out of view)."""
    calib = small_calib()
    for bad in (np.zeros((30, 40, 4), np.uint8), np.zeros((30, 40), np.uint8), np.zeros((30, 40, 3), np.int16)):
        with pytest.raises(ValueError) as err:
            render_camera(bad, calib, [])
        assert str(err.value) == (f"render_camera: field 'image': expected (H, W, 3) uint8, got {bad.shape} "
                                  f"{bad.dtype}")
    photo = np.zeros((30, 40, 3), np.uint8)
    res = render_camera(photo, calib, [])
    assert res.boxes == [] and res.status == []
    res = render_camera(photo, calib, [(TRI * [1, 1, -1], TRI_FACES, np.eye(3))])
    assert res.boxes == [None] and res.status == ["behind"]


def test_lighting_defaults_to_the_depth_sources():
    """Without a lighting argument the depth source's own lighting (a scene's, like SceneRayDepth.lighting) is
    used, else DEFAULT_LIGHTING; an explicit lighting wins."""

    class Open:
        """No occluder anywhere, lit like the scene it came from."""

        def __init__(self, lighting):
            self.lighting = lighting

        def depth(self, u, v):
            return np.full(np.shape(u), np.inf)

    calib = small_calib()
    photo = np.full((30, 40, 3), 60, np.uint8)
    mesh = (TRI, TRI_FACES, np.tile([0.2, 0.5, 0.8], (3, 1)))
    flat = render_camera(photo, calib, [mesh], lighting=FLAT).image
    default = render_camera(photo, calib, [mesh]).image
    assert not np.array_equal(flat, default)
    np.testing.assert_array_equal(render_camera(photo, calib, [mesh], scene_depth=Open(FLAT)).image, flat)
    np.testing.assert_array_equal(render_camera(photo, calib, [mesh], scene_depth=Open(None)).image, default)
    np.testing.assert_array_equal(render_camera(photo, calib, [mesh], scene_depth=Open(SUNNY), lighting=FLAT).image,
                                  flat)
    np.testing.assert_array_equal(render_camera_crop_torch(torch.tensor(photo / 255.0), calib, [mesh],
                                                           scene_depth=Open(FLAT)).values.numpy(),
                                  render_camera_crop_torch(torch.tensor(photo / 255.0), calib, [mesh],
                                                           lighting=FLAT).values.numpy())


def test_a_face_over_one_pixel_centre_is_one_pair_and_hidden_by_a_nearer_scene_depth():
    """A small triangle at z = 5 around pixel (20, 15) (projected to (19.8, 14.8), (20.3, 14.8), (20.0, 15.3)):
    with one sample per pixel its one sample row is one span holding one candidate pair, the pixel centre, which
    it covers; a scene depth of 4 everywhere (nearer) hides that single hit, one of 6 (farther) does not."""
    calib = small_calib()
    tiny = np.array([[-0.05, -0.05, 5.0], [0.075, -0.05, 5.0], [0.0, 0.075, 5.0]])
    uv, _ = calib.rect_to_image(tiny)
    np.testing.assert_allclose(uv, [[19.8, 14.8], [20.3, 14.8], [20.0, 15.3]], atol=1e-12)
    mesh = (tiny, TRI_FACES, np.tile([0.2, 0.5, 0.8], (3, 1)))
    assert mesh_box(calib, tiny, (40, 30))[0] == (20, 15, 21, 16)
    assert camera_ray_tests(calib, [mesh], (40, 30), 1) == (1, 1)
    grey = np.full((30, 40, 3), 90, np.uint8)
    shown = render_camera(grey, calib, [mesh], supersample=1, lighting=FLAT)
    assert shown.alpha[15, 20] == 1.0 and shown.alpha.sum() == 1.0
    np.testing.assert_array_equal(shown.image[15, 20], np.round(255 * display([0.2, 0.5, 0.8])))
    hidden = render_camera(grey, calib, [mesh], supersample=1, lighting=FLAT,
                           scene_depth=DepthMap(np.full((30, 40), 4.0)))
    np.testing.assert_array_equal(hidden.image, grey)
    assert not hidden.alpha.any()
    behind = render_camera(grey, calib, [mesh], supersample=1, lighting=FLAT,
                           scene_depth=DepthMap(np.full((30, 40), 6.0)))
    np.testing.assert_array_equal(behind.image, shown.image)
    # the torch render takes the scene depth too
    photo = torch.full((30, 40, 3), 0.4, dtype=torch.float64)
    out = render_camera_torch(photo, calib, [mesh], supersample=1, lighting=FLAT,
                              scene_depth=DepthMap(np.full((30, 40), 4.0)))
    assert torch.equal(out, photo)


def test_a_tilted_face_is_shaded_with_its_own_unit_normal_by_hand():
    """One tilted triangle under a sun and sky: an interior pixel is tone(E c (a (0.6 + 0.4 n.up) sky + max(n.l, 0)
    sun)), n its unit normal turned towards the camera, computed here by hand (numpy cross product, the lighting's
    velodyne directions rotated to rect by the calibration's Tr_velo_to_cam)."""
    calib = small_calib()
    tilt = TRI + np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.5], [0.0, 0.0, -1.0]])
    c = np.array([0.5, 0.4, 0.3])
    photo = torch.zeros((30, 40, 3), dtype=torch.float64)
    out = render_camera_torch(photo, calib, [(tilt, TRI_FACES, np.tile(c, (3, 1)))], supersample=1, lighting=SUNNY)
    n = np.cross(tilt[1] - tilt[0], tilt[2] - tilt[0])
    n /= np.linalg.norm(n)
    n = -n if n @ tilt[0] > 0 else n  # towards the camera at the origin
    rot = _PERM[:, :3]
    sun, up = rot @ SUNNY.sun_direction, rot @ np.array([0.0, 0.0, 1.0])
    sky = 0.5 * (SUNNY.sky_zenith + SUNNY.sky_horizon)
    irr = SUNNY.ambient * (0.6 + 0.4 * (n @ up)) * sky + max(n @ sun, 0.0) * SUNNY.sun_color
    assert abs(n[0]) > 0.1 and abs(n[1]) > 0.1  # tilted: no component is the whole normal
    np.testing.assert_allclose(out[15, 20].numpy(), display(SUNNY.exposure * c * irr), rtol=0, atol=1e-9)


def test_an_edge_on_face_renders_nothing_without_warnings():
    """A face in a plane through the camera centre (x = 0) projects onto the column u = 20 (zero projected area,
    an exactly zero cos to its centroid ray): its box is searched, nothing is hit, no division warns."""
    import warnings

    calib = small_calib()
    edge_on = np.array([[0.0, 0.0, 5.0], [0.0, 1.0, 5.0], [0.0, 2.0, 6.0]])
    grey = np.full((30, 40, 3), 90, np.uint8)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = render_camera(grey, calib, [(edge_on, TRI_FACES, np.eye(3))], supersample=3, lighting=FLAT)
        assert res.status == ["rendered"] and res.boxes == [(20, 15, 21, 23)]
        np.testing.assert_array_equal(res.image, grey)
        assert not res.alpha.any()
        assert camera_ray_tests(calib, [(edge_on, TRI_FACES, np.eye(3))], (40, 30), 1)[0] == 8


def test_a_face_with_one_vertex_just_in_front_of_the_camera_renders_like_the_full_image():
    """A face with one vertex at depth 0.5 and two behind the camera (depth -1): its part in front (depths in
    (0, 0.5]) is rendered, as the full-image reference (every sample against every face) finds it."""
    calib = small_calib()
    near = np.array([[0.1, 0.05, 0.5], [-2.0, -1.0, -1.0], [2.0, -1.5, -1.0]])
    mesh = (near, TRI_FACES, np.tile([0.7, 0.6, 0.2], (3, 1)))
    grey = np.full((30, 40, 3), 90, np.uint8)
    crop = render_camera(grey, calib, [mesh], supersample=2, lighting=FLAT)
    full = render_camera(grey, calib, [mesh], supersample=2, lighting=FLAT, full_image=True)
    assert full.alpha.sum() > 10
    np.testing.assert_array_equal(crop.image, full.image)
    np.testing.assert_array_equal(crop.alpha, full.alpha)


def test_a_vertex_exactly_at_the_near_depth_makes_the_face_crossing():
    """A vertex at camera depth exactly 1e-6 (_NEAR, included): the mesh box is the whole 40 x 30 image and the
    face a crossing one (whichever of its vertices it is), paired with every sample of it (one per pixel), not
    only those of its projected box."""
    from robustbench3d.sensors.camera_cull import FaceCull as _FaceCull

    calib = small_calib()
    verts = np.array([[0.0, 0.0, 1e-6], [-1.0, -1.0, 2.0], [1.0, -1.0, 2.0]])
    assert mesh_box(calib, verts, (40, 30))[0] == (0, 0, 40, 30)
    for faces in ([[0, 1, 2]], [[1, 2, 0]], [[2, 0, 1]]):  # the near vertex first, last, second
        faces = np.array(faces)
        assert _FaceCull.of(calib, verts, faces, None, torch.float64).crossing.tolist() == [True]
        assert camera_ray_tests(calib, [(verts, faces, np.eye(3))], (40, 30), 1) == (1200, 1200)


def test_scanline_margin_uses_the_shortest_edge_of_a_face_of_edges_2_and_more():
    """As the hand case above, scaled: v0 (0, 0, 10), v1 (2, 0, 10), v2 (0, 2, 12), float32 ray test: normal
    (0, -1, 1), ray (2, 2, 32) / 3, |ray|^2 = 1032 / 9, cos = 30 / sqrt(2064), shortest edge 2:
    cond = |ray| / (2 cos) = sqrt(1032 * 2064) / 180."""
    from robustbench3d.sensors.camera_cull import SPAN_MARGIN
    from robustbench3d.sensors.camera_cull import FaceCull as _FaceCull

    calib = DAY_0926.calib
    verts = np.array([[0.0, 0.0, 10.0], [2.0, 0.0, 10.0], [0.0, 2.0, 12.0]])
    fc = _FaceCull.of(calib, verts, np.array([[0, 1, 2]]), None, torch.float32, centre=np.zeros(3))
    delta = SPAN_MARGIN + 64 * float(np.finfo(np.float32).eps) * np.sqrt(1032.0 * 2064.0) / 180
    uv, _ = calib.rect_to_image(verts)
    (x1, y1), (x2, y2) = uv[1] - uv[0], uv[2] - uv[0]
    area2 = abs(x1 * y2 - y1 * x2)
    assert fc.tight[0]
    values = fc.edge[0] @ np.column_stack([uv, np.ones(3)]).T / area2
    np.testing.assert_allclose(values, np.eye(3) + delta, rtol=0, atol=1e-9)


def test_culled_back_faces_cost_no_ray_tests():
    """A closed sphere (level-1 icosphere, radius 1, 6 m ahead) culls its back faces: its candidate pairs are
    exactly those of its front faces alone (faces whose outward normal points towards the camera, by hand), an
    open mesh that culls nothing; the image is the same."""
    calib = small_calib()
    v, f = icosphere(1)
    v = v + np.array([0.0, 0.0, 6.0])
    cen = v[f].mean(axis=1)
    outward = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    front = np.einsum("ij,ij->i", outward, cen) < 0
    assert 0 < front.sum() < len(f)
    cols = np.tile([0.3, 0.6, 0.9], (len(v), 1))
    assert camera_ray_tests(calib, [(v, f, cols)], (40, 30), 2) == camera_ray_tests(calib, [(v, f[front], cols)],
                                                                                    (40, 30), 2)


def test_the_lighting_cache_evicts_and_each_lighting_still_renders_its_own_exposure():
    """More lightings than the per-calibration cache holds (_MAX_LIGHTS), each rendered once and the first again
    after its eviction: the fronto-parallel face shows tone(exposure * albedo) for each (FLAT, by hand)."""
    import dataclasses

    from robustbench3d.sensors.camera_shade import MAX_LIGHTS as _MAX_LIGHTS

    calib = small_calib()
    c = np.array([0.2, 0.5, 0.8])
    black = np.zeros((30, 40, 3), np.uint8)
    lights = [dataclasses.replace(FLAT, exposure=0.5 + 0.1 * k) for k in range(_MAX_LIGHTS + 2)]
    for light in lights + lights[:1]:
        res = render_camera(black, calib, [(TRI, TRI_FACES, np.tile(c, (3, 1)))], supersample=1, lighting=light)
        np.testing.assert_array_equal(res.image[15, 20], np.round(255 * display(light.exposure * c)))


def test_fused_shading_equals_shade_at_the_hits_of_an_independent_cast():
    """The fused numpy recompute + shading (_ShadeHits) against the torch reference :func:`shade` evaluated at
    the hits of cast_rays (the torch kernel) of every pixel centre: vertex colours interpolated at (u, v), the
    face's unit normal turned towards the camera, the distance t; one sample per pixel, so each covered pixel
    shows exactly that colour (a random-shape object at 6 m, float64)."""
    from robustbench3d.attacks.object import random_shape
    from robustbench3d.sensors.camera_depth import camera_centre_rect, pixel_rays_rect
    from robustbench3d.sensors.raycast import cast_rays

    calib = DAY_0926.calib
    obj = random_shape(seed=5, amplitude=0.4)
    verts = obj.vertices() + np.array([0.3, 0.1, 6.0])
    cols = np.random.default_rng(8).random((len(verts), 3))
    w, h = DAY_0926.image_size
    photo = torch.zeros((h, w, 3), dtype=torch.float64)
    crop = render_camera_crop_torch(photo, calib, [(verts, obj.faces, cols)], supersample=1, lighting=SUNNY)
    pv, pu = np.divmod(crop.pixels.numpy(), w)
    origin = camera_centre_rect(calib)
    hits = cast_rays(torch.tensor(verts), torch.tensor(obj.faces), torch.tensor(pixel_rays_rect(calib, pu, pv)),
                     torch.tensor(origin))
    k = hits.hit.numpy()
    assert k.sum() > 1000
    f = obj.faces[hits.face.numpy()[k]]
    u, v, t = (x.detach().numpy()[k] for x in (hits.u, hits.v, hits.t))
    albedo = (1 - u - v)[:, None] * cols[f[:, 0]] + u[:, None] * cols[f[:, 1]] + v[:, None] * cols[f[:, 2]]
    n = np.cross(verts[f[:, 1]] - verts[f[:, 0]], verts[f[:, 2]] - verts[f[:, 0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n *= np.where(((verts[f[:, 0]] - origin) * n).sum(1) > 0, -1.0, 1.0)[:, None]
    want = shade(torch.tensor(albedo), torch.tensor(n), torch.tensor(t), _rect_lighting(SUNNY, calib, torch.float64))
    np.testing.assert_allclose(crop.values.detach().numpy()[k], want.numpy(), rtol=0, atol=1e-12)
    assert not crop.values.detach().numpy()[~k].any()  # the uncovered pixels keep the black photo


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_compiled_face_cull_equals_the_numpy_reference_bit_for_bit(dtype):
    """_FaceCull.of (kernels.face_cull) against the numpy code it replaced: every field bit for bit, for
    deformed objects ahead, straddling the camera plane and behind it, with skipped faces, a degenerate face
    (two equal vertices) and a sliver."""
    from robustbench3d.attacks.object import random_shape
    from robustbench3d.sensors.camera_cull import FaceCull as _FaceCull
    from robustbench3d.sensors.camera_depth import camera_centre_rect

    calib = DAY_0926.calib
    centre = camera_centre_rect(calib)
    rng = np.random.default_rng(8)
    for k, z in enumerate([0.15, 0.9, 6.0, 45.0, -3.0]):
        obj = random_shape(seed=20 + k, amplitude=0.45)
        v = obj.vertices() + np.array([0.2, 0.1, z])
        v = np.concatenate([v, [[0.0, 0.0, 5.0], [1.0, 0.0, 5.0], [2.0, 1e-9, 5.0]]])
        n = len(obj.vertices())
        faces = np.concatenate([obj.faces, [[n, n + 1, n + 1], [n, n + 1, n + 2]]])
        skip = rng.random(len(faces)) < 0.2
        for sk in (None, skip):
            got = _FaceCull.of(calib, v, faces, sk, dtype, centre)
            want = _face_cull_reference(calib, v, faces, sk, dtype, centre)
            for name, a in zip(("lo", "hi", "crossing", "unreachable", "edge", "tight"), want, strict=True):
                b = getattr(got, name)
                assert b.dtype == a.dtype and np.array_equal(b, a, equal_nan=True), name
        plain = _FaceCull.of(calib, v, faces, None, dtype, centre)
        if 0 < z < 0.4:
            assert plain.crossing.any() and plain.unreachable.any()
        if z > 1:
            assert plain.tight.sum() > 250 and not plain.tight[-2:].any()
        if z < 0:
            assert plain.unreachable[:-2].all() and not plain.unreachable[-2:].any()


def test_compiled_touching_equals_its_numpy_reference():
    """_FaceCull.touching (compiled) against ``compiled=False`` (the summed-area table in numpy) on sparse and
    dense masks of two deformed objects, near (faces crossing the camera plane) and far, and a one-pixel mask
    at the region's corner."""
    from robustbench3d.attacks.object import random_shape
    from robustbench3d.sensors.camera_cull import Region as _Region
    from robustbench3d.sensors.camera_render import _check_meshes, _Geometry, _pixel_set

    calib = DAY_0926.calib
    w, h = DAY_0926.image_size
    rng = np.random.default_rng(12)
    for k, z in enumerate([0.3, 3.0, 10.0, 40.0]):
        obj = random_shape(seed=30 + k, amplitude=0.4)
        v = obj.vertices() + np.array([0.2, 0.1, z])
        meshes = _check_meshes([(torch.tensor(v), obj.faces, np.full_like(v, 0.5)),
                                (torch.tensor(v + np.array([1.5, 0.2, 3.0])), obj.faces, np.full_like(v, 0.5))])
        region = _pixel_set(calib, meshes, (w, h), False)[0]
        g = _Geometry.of(meshes, calib)
        for share in (0.002, 0.05, 0.5, 1.0):
            mask = region.mask & (rng.random(region.mask.shape) < share)
            sub = _Region(region.rect, mask, np.zeros(int(mask.sum()), np.int64))
            got, want = g.cull.touching(sub), g.cull.touching(sub, compiled=False)
            assert got.dtype == bool and np.array_equal(got, want)
            assert got.any() or not mask.any()
    corner = np.zeros_like(region.mask)
    corner[0, 0] = True
    sub = _Region(region.rect, corner, np.zeros(1, np.int64))
    assert np.array_equal(g.cull.touching(sub), g.cull.touching(sub, compiled=False))


def _face_cull_reference(calib, vertices, faces, skip, dtype, centre):
    """The numpy _FaceCull.of that kernels.face_cull replaced (its arithmetic, array by array)."""
    from robustbench3d.sensors.camera_cull import BOX_MARGIN_PX, SPAN_DEPTH_RATIO, SPAN_MARGIN
    from robustbench3d.sensors.camera_cull import NEAR_DEPTH_M as _NEAR
    from robustbench3d.sensors.mesh import cross_rows, dot3

    uv, depth = calib.rect_to_image(vertices)
    p, fd = uv[faces], depth[faces]  # (F, 3, 2), (F, 3)
    # reductions over the 3 vertices written out: numpy's reductions along a short axis cost far more, and
    # min / max / any / all are exact, sums are (x0 + x1) + x2 as numpy's (see raycast.dot3)
    d0, d1, d2 = fd[:, 0], fd[:, 1], fd[:, 2]
    unreachable = (d0 <= 0) & (d1 <= 0) & (d2 <= 0)
    if skip is not None:
        unreachable |= skip
    crossing = ((d0 <= _NEAR) | (d1 <= _NEAR) | (d2 <= _NEAR)) & ~unreachable
    fuv = np.where(crossing[:, None, None] | unreachable[:, None, None], 0.0, p)
    f0, f1, f2 = fuv[:, 0], fuv[:, 1], fuv[:, 2]  # min / max over the 3 vertices (exact either way)
    lo, hi = np.minimum(np.minimum(f0, f1), f2), np.maximum(np.maximum(f0, f1), f2)
    extent = hi - lo
    margin = BOX_MARGIN_PX + 1e-5 * np.maximum(extent[:, 0], extent[:, 1])[:, None]
    # the scanline cull (see spans), for the faces in front of the camera: delta_f and where it applies
    edge_fn = np.zeros((len(faces), 3, 3))
    tight = np.zeros(len(faces), bool)
    ahead = np.flatnonzero(~crossing & ~unreachable)
    q, v3 = p[ahead], vertices[faces[ahead]]
    edge = q[:, [2, 0, 1]] - q[:, [1, 2, 0]]  # edge k runs from vertex (k+1) % 3 to (k+2) % 3
    area2 = edge[:, 1, 0] * edge[:, 2, 1] - edge[:, 1, 1] * edge[:, 2, 0]  # (p1 - p0) x (p2 - p0)
    e3 = v3[:, [2, 0, 1]] - v3[:, [1, 2, 0]]
    n3 = cross_rows(e3[:, 2], -e3[:, 1])
    ray = (v3[:, 0] + v3[:, 1] + v3[:, 2]) / 3 - centre
    with np.errstate(divide="ignore", invalid="ignore"):
        ray2 = dot3(ray, ray)
        cos = np.abs(dot3(n3, ray)) / np.sqrt(dot3(n3, n3) * ray2)
        e3sq = dot3(e3, e3)
        cond = np.sqrt(ray2 / np.minimum(np.minimum(e3sq[:, 0], e3sq[:, 1]), e3sq[:, 2])) / cos
        delta = SPAN_MARGIN + 64 * float(torch.finfo(dtype).eps) * cond
        fa0, fa1, fa2 = d0[ahead], d1[ahead], d2[ahead]
        e2d = edge * edge
        e2d = e2d[:, :, 0] + e2d[:, :, 1]
        ok = ((np.maximum(np.maximum(fa0, fa1), fa2) <= SPAN_DEPTH_RATIO * np.minimum(np.minimum(fa0, fa1), fa2))
              & (np.abs(area2) > 1e-6 * np.maximum(np.maximum(e2d[:, 0], e2d[:, 1]), e2d[:, 2]))
              & np.isfinite(delta))
    sign = np.sign(area2)[:, None]
    start = q[:, [1, 2, 0]]
    edge_fn[ahead] = np.stack([-edge[:, :, 1] * sign, edge[:, :, 0] * sign,  # a x + b y + c, positive inside
                               (edge[:, :, 1] * start[:, :, 0] - edge[:, :, 0] * start[:, :, 1]) * sign
                               + (np.where(ok, delta, 0.0) * np.abs(area2))[:, None]], axis=2)
    tight[ahead] = ok
    return lo - margin, hi + margin, crossing, unreachable, edge_fn, tight
