"""The camera render of a level-4 object family (2562 vertices, 5120 faces) against the full-image reference, and
the per-face setup's edge cases (robustbench3d.sensors.camera_kernels.face_cull reading each face's own vertices,
skipped faces reading none; array_kernels.column_stats; the backward's dtype conversion)."""

from __future__ import annotations

import numpy as np
import torch

from robustbench3d.kitti.calib import Calibration
from robustbench3d.sensors.array_kernels import column_stats
from robustbench3d.sensors.camera_cull import BOX_MARGIN_PX, FaceCull
from robustbench3d.sensors.camera_render import render_camera, render_camera_torch
from robustbench3d.sensors.mesh import icosphere
from robustbench3d.synth.calibs import DAY_0926


def _small_calib() -> Calibration:
    """A 40 x 30 pixel camera, f = 20 px, principal point (20, 15), rect = camera 2 (no offsets)."""
    p2 = np.array([[20.0, 0.0, 20.0, 0.0], [0.0, 20.0, 15.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
    perm = np.array([[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [1.0, 0.0, 0.0, 0.0]])
    return Calibration(P0=p2, P1=p2, P2=p2, P3=p2, R0_rect=np.eye(3), Tr_velo_to_cam=perm,
                       Tr_imu_to_velo=np.eye(3, 4))


def _level4(centre: list[float], seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A level-4 icosphere of radius 0.4 m (a family's template), its vertices jittered by 5 mm, random colours."""
    v, f = icosphere(4, 0.4)
    rng = np.random.default_rng(seed)
    return v + rng.normal(0.0, 0.005, v.shape) + np.asarray(centre), f, rng.random((len(v), 3))


def test_level4_render_and_gradients_equal_the_full_image_reference():
    """Two level-4 objects (one cut by the image's left border, so its faces straddle the crop's edge) rendered as
    a crop equal the full-image reference (every sample near a mesh x every front face, no boxes or spans) bit for
    bit: the uint8 image and alpha, the float64 values and the gradients to vertices, colours and photo."""
    calib = DAY_0926.calib
    w, h = DAY_0926.image_size
    photo = np.random.default_rng(1).integers(0, 256, (h, w, 3), dtype=np.uint8)
    meshes = [_level4([1.0, 0.5, 18.0], 0), _level4([-22.0, 0.6, 26.0], 1)]
    assert len(meshes[0][0]) == 2562 and len(meshes[0][1]) == 5120
    crop = render_camera(photo, calib, meshes, supersample=2)
    full = render_camera(photo, calib, meshes, supersample=2, full_image=True)
    assert crop.boxes[1][0] == 0 and crop.status == ["rendered", "rendered"]  # the second is cut by the border
    np.testing.assert_array_equal(crop.image, full.image)
    np.testing.assert_array_equal(crop.alpha, full.alpha)
    assert (crop.alpha > 0).sum() > 1000

    grads = []
    for full_image in (False, True):
        leaves = [(torch.tensor(v, requires_grad=True), f, torch.tensor(c, requires_grad=True)) for v, f, c in meshes]
        image = torch.tensor(photo / 255.0, requires_grad=True)
        out = render_camera_torch(image, calib, leaves, supersample=2, full_image=full_image)
        weights = torch.linspace(0.5, 1.5, out.numel(), dtype=out.dtype).reshape(out.shape)
        (out * weights).sum().backward()
        grads.append([out.detach(), image.grad] + [t.grad for v, _, c in leaves for t in (v, c)])
    for a, b in zip(*grads, strict=True):
        assert a.dtype == b.dtype and torch.equal(a, b)
    assert all(g.abs().sum() > 0 for g in grads[0][2:])


def test_float32_level4_crop_equals_its_full_image_reference():
    """The float32 geometry (the training renders') of a level-4 object: crop and full-image values and gradients
    equal bit for bit."""
    calib = DAY_0926.calib
    w, h = DAY_0926.image_size
    v, f, c = _level4([0.5, 0.3, 30.0], 2)
    image = torch.tensor(np.random.default_rng(3).random((h, w, 3)), dtype=torch.float32)
    got = []
    for full_image in (False, True):
        vt = torch.tensor(v, dtype=torch.float32, requires_grad=True)
        ct = torch.tensor(c, dtype=torch.float32, requires_grad=True)
        out = render_camera_torch(image, calib, [(vt, f, ct)], supersample=3, full_image=full_image)
        out.sum().backward()
        got.append((out.detach(), vt.grad, ct.grad))
    for a, b in zip(*got, strict=True):
        assert a.dtype == b.dtype == torch.float32 and torch.equal(a, b)
    assert got[0][1].abs().sum() > 0


def test_a_mesh_outside_the_image_and_one_behind_leave_the_photo_untouched():
    """A level-4 object entirely left of the image and one behind the camera: status 'outside' / 'behind', no box,
    the photo unchanged bit for bit, alpha zero, and the gradients reach the photo only (identity)."""
    calib = DAY_0926.calib
    w, h = DAY_0926.image_size
    photo = np.random.default_rng(5).integers(0, 256, (h, w, 3), dtype=np.uint8)
    meshes = [_level4([-40.0, 0.5, 10.0], 4), _level4([0.0, 0.0, -5.0], 5)]
    res = render_camera(photo, calib, meshes)
    assert res.status == ["outside", "behind"] and res.boxes == [None, None]
    np.testing.assert_array_equal(res.image, photo)
    assert not res.alpha.any()
    image = torch.tensor(photo / 255.0, requires_grad=True)
    render_camera_torch(image, calib, [(torch.tensor(v), f, torch.tensor(c)) for v, f, c in meshes]).sum().backward()
    assert torch.equal(image.grad, torch.ones_like(image))


def test_face_cull_of_skipped_edge_on_and_straddling_faces_by_hand():
    """FaceCull.of by hand on a 40 x 30 camera (f = 20 px, centre (20, 15)): a skipped face whose vertices hold
    NaN (never read: unreachable, box 0 -/+ the margin, no edge functions, not tight), an edge-on face (its plane
    holds the camera centre: zero projected area, not tight, its box the column u = 20), a face straddling the
    image's left border (its box reaches past it, u < 0) and a face with every vertex behind the camera."""
    calib = _small_calib()
    verts = np.array([[np.nan, np.nan, np.nan], [0.0, 0.0, 5.0], [0.0, 1.0, 5.0], [0.0, 2.0, 6.0],
                      [-15.0, 0.0, 10.0], [-5.0, 0.0, 10.0], [-10.0, 5.0, 10.0],
                      [0.0, 0.0, -1.0], [1.0, 0.0, -1.0], [0.0, 1.0, -2.0]])
    faces = np.array([[0, 1, 2], [1, 2, 3], [4, 5, 6], [7, 8, 9]])
    skip = np.array([True, False, False, False])
    with np.errstate(invalid="ignore"):
        fc = FaceCull.of(calib, verts, faces, skip, torch.float64, centre=np.zeros(3))
    assert fc.unreachable.tolist() == [True, False, False, True]
    assert fc.crossing.tolist() == [False] * 4
    np.testing.assert_array_equal(fc.lo[0], [-BOX_MARGIN_PX] * 2)
    np.testing.assert_array_equal(fc.hi[0], [BOX_MARGIN_PX] * 2)
    assert not fc.edge[0].any() and not fc.edge[3].any()
    assert fc.tight.tolist() == [False, False, True, False]
    # edge-on: u = 20 for every vertex, v = 15, 19, 15 + 20 * 2 / 6
    v_top = 15.0 + 20.0 * 2.0 / 6.0
    m = BOX_MARGIN_PX + 1e-5 * (v_top - 15.0)  # the margin grows with the box's extent (in v here)
    np.testing.assert_allclose(fc.lo[1], [20.0 - m, 15.0 - m], rtol=0, atol=1e-12)
    np.testing.assert_allclose(fc.hi[1], [20.0 + m, v_top + m], rtol=0, atol=1e-12)
    # straddling: u = 20 + 20 x / 10 in [-10, 10], v = 15 + 2 y in [15, 25]
    m = BOX_MARGIN_PX + 1e-5 * 20.0
    np.testing.assert_allclose(fc.lo[2], [-10.0 - m, 15.0 - m], rtol=0, atol=1e-12)
    np.testing.assert_allclose(fc.hi[2], [10.0 + m, 25.0 + m], rtol=0, atol=1e-12)
    # the straddling face's box is clipped to the region's samples: columns from 0, not below
    box = fc.boxes(1, (0, 0, 40, 30))
    assert box[2].tolist() == [0, 15, 11, 26] and box[0].tolist() == [0, 0, 0, 0] and box[3].tolist() == [0, 0, 0, 0]


def test_a_face_straddling_the_image_border_renders_like_the_full_image():
    """One triangle cut by the left border of a 40 x 30 image: the crop equals the full-image reference (pixels
    and alpha), and it covers pixels in column 0."""
    calib = _small_calib()
    verts = np.array([[-15.0, -3.0, 10.0], [-5.0, 0.0, 10.0], [-10.0, 5.0, 10.0]])
    tri = (verts, np.array([[0, 1, 2]]), np.eye(3))
    photo = np.random.default_rng(6).integers(0, 256, (30, 40, 3), dtype=np.uint8)
    crop = render_camera(photo, calib, [tri], supersample=3)
    full = render_camera(photo, calib, [tri], supersample=3, full_image=True)
    assert crop.boxes[0][0] == 0 and crop.alpha[:, 0].any()
    np.testing.assert_array_equal(crop.image, full.image)
    np.testing.assert_array_equal(crop.alpha, full.alpha)


def test_column_stats_equal_numpys_reductions_bit_for_bit():
    """column_stats against numpy's min / max / sum along axis 0, for shapes from one row to 30000 rows and values
    over twelve orders of magnitude (the sum's order matters at that range)."""
    rng = np.random.default_rng(9)
    for n in (1, 2, 3, 7, 162, 2562, 30000):
        for cols in (2, 3):
            a = rng.normal(size=(n, cols)) * 10.0 ** rng.uniform(-6, 6, size=(n, 1))
            lo, hi, total = column_stats(a)
            assert np.array_equal(lo, a.min(axis=0)) and np.array_equal(hi, a.max(axis=0))
            assert np.array_equal(total, a.sum(axis=0))
    lo, hi, total = column_stats(np.array([[1.0, -2.0], [3.0, 4.0], [-5.0, 0.5]]))
    assert lo.tolist() == [-5.0, -2.0] and hi.tolist() == [3.0, 4.0] and total.tolist() == [-1.0, 2.5]


def test_backward_conversion_equals_torchs_rounding():
    """The shading backward's float64 -> float32 conversion (numpy's) rounds as torch's ``.to``: the same bits on
    values that need rounding, ties, subnormals and overflow to inf."""
    from robustbench3d.sensors.camera_shade import _as_torch

    rng = np.random.default_rng(10)
    x = np.concatenate([rng.normal(size=50000) * 10.0 ** rng.uniform(-40, 40, 50000),
                        [1.0 + 2.0 ** -24, 1.0 + 3 * 2.0 ** -24, 1e-45, 3e38 * 10, -0.0]]).reshape(-1, 5)
    with np.errstate(over="ignore"):
        got = _as_torch(x, torch.float32)
    assert got.dtype == torch.float32 and torch.equal(got, torch.from_numpy(x).to(torch.float32))
    same = _as_torch(x, torch.float64)
    assert same.dtype == torch.float64 and np.shares_memory(same.numpy(), x)
