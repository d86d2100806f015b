"""The public sensor models (robustbench3d.sensors.{mesh, materials, lidar_model, camera_model}) against
hand-computed values. (That the generator uses exactly these models is proven by test_synth_bytes.py.)"""

from __future__ import annotations

import math

import numpy as np
import pytest

from robustbench3d.sensors import camera_model as cm
from robustbench3d.sensors import lidar_model as lm
from robustbench3d.sensors.materials import MATERIALS, REFLECTIVITY, RETURN_PROB, SPECULAR, TINTED, Mat
from robustbench3d.sensors.mesh import face_normals, icosphere

F32 = np.float32


def _logistic(x: float) -> float:
    return 1.0 / (1.0 + math.exp(-x))


def _srgb(x: float) -> float:
    return 12.92 * x if x <= 0.0031308 else 1.055 * x ** (1 / 2.4) - 0.055


# --- icosphere -------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("level", "nv", "nf"), [(0, 12, 20), (1, 42, 80), (2, 162, 320)])
def test_icosphere_counts_radius_and_topology(level, nv, nf):
    v, f = icosphere(level, 0.2)
    assert v.shape == (nv, 3) and f.shape == (nf, 3) and f.dtype == np.int64
    assert np.allclose(np.linalg.norm(v, axis=1), 0.2, rtol=0, atol=1e-12)
    assert len(np.unique(np.round(v, 9), axis=0)) == nv  # no duplicate vertices
    assert np.array_equal(np.unique(f), np.arange(nv))  # every vertex used
    directed = {(int(a), int(b)) for tri in f for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0]))}
    assert len(directed) == 3 * nf  # no directed edge twice: consistent winding ...
    assert all((b, a) in directed for a, b in directed)  # ... and closed: each edge has its twin
    edges = len(directed) // 2
    assert nv - edges + nf == 2  # Euler characteristic of the sphere


@pytest.mark.parametrize("level", [0, 1, 2])
def test_icosphere_normals_point_outwards(level):
    v, f = icosphere(level, 0.2)
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    centroid = v[f].mean(axis=1)
    cos = np.sum(n * centroid, axis=1) / np.linalg.norm(n, axis=1) / np.linalg.norm(centroid, axis=1)
    assert cos.min() > 0.95


def test_icosphere_vertex_order_is_documented_order():
    v0, f0 = icosphere(0)
    t = (1 + 5 ** 0.5) / 2
    s = math.sqrt(1 + t * t)
    assert np.allclose(v0[0], [-1 / s, t / s, 0]) and np.allclose(v0[11], [-t / s, 0, 1 / s])
    assert f0[0].tolist() == [0, 11, 5]
    v1, f1 = icosphere(1)
    assert np.array_equal(v1[:12], v0)
    # level-0 face (0, 11, 5): midpoints of (0, 11), (11, 5), (5, 0) become vertices 12, 13, 14
    for k, (a, b) in zip((12, 13, 14), ((0, 11), (11, 5), (5, 0)), strict=True):
        m = v0[a] + v0[b]
        assert np.allclose(v1[k], m / np.linalg.norm(m))
    assert f1[:4].tolist() == [[0, 12, 14], [11, 13, 12], [5, 14, 13], [12, 13, 14]]
    v2, f2 = icosphere(2, 0.2)
    assert np.allclose(v2[:42], 0.2 * v1)
    # face k of level 1 splits into faces 4k..4k+3 of level 2, corners first
    assert [f2[4 * 7 + i][0] for i in range(3)] == f1[7].tolist()


def test_icosphere_returns_fresh_arrays_and_rejects_bad_arguments():
    v, f = icosphere(1)
    v[:] = 0.0
    f[:] = 0
    v2, f2 = icosphere(1)
    assert np.allclose(np.linalg.norm(v2, axis=1), 1.0) and f2.max() == 41
    for bad in (-1, 1.5, True, "2"):
        with pytest.raises(ValueError, match="field 'level'"):
            icosphere(bad)  # type: ignore[arg-type]
    for bad in (0.0, -0.2, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="field 'radius'"):
            icosphere(1, bad)


def test_face_normals_by_hand():
    v = np.array([[0.0, 0, 0], [2, 0, 0], [0, 2, 0], [0, 0, 3], [1, 0, 0]])
    f = np.array([[0, 1, 2], [0, 2, 1], [0, 1, 3], [0, 1, 4]])
    n = face_normals(v, f)
    assert np.allclose(n, [[0, 0, 1], [0, 0, -1], [0, -1, 0], [0, 0, 0]])


# --- materials --------------------------------------------------------------------------------------------------


def test_material_tables_follow_the_material_list():
    assert len(REFLECTIVITY) == len(RETURN_PROB) == len(SPECULAR) == len(TINTED) == len(Mat)
    assert REFLECTIVITY[Mat.PAINT] == F32(MATERIALS[Mat.PAINT].reflectivity) == F32(0.42)
    assert RETURN_PROB[Mat.GLASS] == F32(0.75) and SPECULAR[Mat.GLASS] == F32(0.9)
    assert set(np.flatnonzero(TINTED)) == {Mat.PAINT, Mat.FACADE, Mat.WALL, Mat.CLOTH}


# --- LiDAR ------------------------------------------------------------------------------------------------------


def test_sigmoid_and_range_gate():
    x = np.array([-30.0, -2.0, 0.0, 1.0, 30.0])
    assert np.allclose(lm.sigmoid(x), [_logistic(v) for v in x], rtol=0, atol=1e-15)
    t = np.array([0.5, 1.0, 1.001, 50.0, 120.0, 120.01])
    assert lm.in_range(t).tolist() == [False, False, True, True, True, False]


def test_cos_incidence_is_two_sided():
    s60, c60 = math.sin(math.radians(60)), 0.5
    n = np.array([[0.0, 0, 1], [0, 0, 1], [0, 0, -1], [0, 0, 1]])
    d = np.array([[0.0, 0, -1], [1, 0, 0], [s60, 0, -c60], [s60, 0, -c60]])
    assert np.allclose(lm.cos_incidence(n, d), [1.0, 0.0, 0.5, 0.5])


def test_material_reflectivity_by_hand():
    mat = np.array([Mat.GLASS, Mat.PAINT, Mat.PAINT, Mat.PAINT, Mat.SIGN, Mat.TYRE], dtype=np.uint8)
    albedo = np.array([[1, 1, 1], [1, 1, 1], [0, 0, 0], [0.25, 0.25, 0.25], [0, 0, 0], [1, 1, 1]], dtype=F32)
    rho = lm.material_reflectivity(mat, albedo)
    # glass / sign / tyre ignore the albedo; paint is scaled by 0.55 + 0.9 sqrt(luminance)
    assert rho.dtype == F32
    assert np.allclose(rho, [0.08, 0.42 * 1.45, 0.42 * 0.55, 0.42 * 1.0, 0.97, 0.05], atol=1e-6)
    assert np.isclose(lm.albedo_luminance(np.array([[0.0, 1, 0]], F32))[0], 0.7152)


def test_return_probability_at_normal_and_grazing_incidence():
    s0 = lm.SIGNAL_THRESHOLD
    # signal exactly at the threshold: half the material's return probability
    t = math.sqrt(0.39 / s0)
    p = lm.return_probability(np.array([0.97]), np.array([0.39]), np.array([1.0]), np.array([t]))
    assert np.isclose(p[0], 0.97 * 0.5)
    # asphalt (rho 0.3) at 50 m: seen head-on almost surely, at cos 0.05 far less often
    rho, r = 0.3, 50.0
    p = lm.return_probability(np.ones(3), np.full(3, rho), np.array([1.0, 0.05, 0.0]), np.full(3, r))
    expect = [_logistic(math.log(rho * c / r ** 2 / s0) / 0.5) for c in (1.0, 0.05, 0.02)]  # cos floored at 0.02
    assert np.allclose(p, expect, rtol=1e-12)
    assert p[0] > 0.998 and 0.69 < p[1] < 0.71
    assert np.allclose(lm.received_signal(np.array([0.5, 0.5]), np.array([1.0, 0.0]), np.array([10.0, 10.0])),
                       [0.005, 1e-4])


def test_range_noise_statistics():
    e = lm.range_noise(np.random.default_rng(0), 200_000)
    assert np.abs(e).max() <= 0.03 + 1e-15
    assert abs(e.mean()) < 1e-4 and 0.0099 < e.std() < 0.0101
    assert 0.0015 < np.mean(np.abs(e) >= 0.03) < 0.004  # the 3-sigma tails are clipped (0.27 %)


def test_reflectance_by_hand():
    r = np.array([10.0, 20.0, 45.0, 100.0])
    assert np.allclose(lm.range_attenuation(r), [1.0, 1.0, 0.7, 0.3])
    got = lm.reflectance_mean(np.full(3, 0.5), np.array([1.0, 0.0, 1.0]), np.array([10.0, 10.0, 45.0]))
    assert np.allclose(got, [0.5, 0.5 * 0.55, 0.5 * 0.7])
    ln = np.log(lm.reflectance_noise(np.random.default_rng(1), 100_000))
    assert abs(ln.mean()) < 2e-3 and 0.118 < ln.std() < 0.122
    p0 = lm.zero_reflectance_probability(np.array([0.0, 45.0, 100.0]))
    assert np.allclose(p0, [0.04 + 0.9 * _logistic(-9), 0.49, 0.04 + 0.9 * _logistic(11)])
    q = lm.quantize_reflectance(np.array([0.456, 0.999, 1.2, -0.1, 0.5]), np.array([0, 0, 0, 0, 1], bool))
    assert np.allclose(q, [0.45, 0.99, 0.99, 0.0, 0.0])


# --- camera -----------------------------------------------------------------------------------------------------

ZENITH = np.array([0.2, 0.4, 0.8])
HORIZON = np.array([0.6, 0.6, 0.6])


def test_face_toward_turns_normals_to_the_eye():
    n = np.array([[0, 0, 1], [0, 0, 1]], F32)
    anchor = np.zeros((2, 3), F32)
    assert np.array_equal(cm.face_toward(n, anchor, np.array([0, 0, 5], F32)), n)
    assert np.array_equal(cm.face_toward(n, anchor, np.array([0, 0, -5], F32)), -n)


def test_diffuse_shading_of_faces_by_hand():
    s60 = math.sin(math.radians(60))
    normals = np.array([[0, 0, 1], [0, 0, 1], [0, 0, -1]], F32)
    albedo = np.full((3, 3), 0.5, F32)
    sun_colour = np.array([1.0, 1.0, 1.0])
    shade = cm.diffuse_faces(albedo, normals, np.array([0, 0, 1], F32), sun_colour, 0.25, ZENITH, HORIZON)
    sky = np.array([0.4, 0.5, 0.7])  # mean of zenith and horizon
    up = 0.5 * 0.25 * 1.0 * sky  # a face looking up gets the full sky light
    down = 0.5 * 0.25 * 0.2 * sky  # one looking down a fifth
    assert np.allclose(shade.cos_sun, [1, 1, -1])
    assert np.allclose(shade.shadowed, [up, up, down])
    assert np.allclose(shade.lit, [up + 0.5, up + 0.5, down])  # lit head-on: + albedo * sun
    tilted = cm.diffuse_faces(albedo[:1], normals[:1], np.array([s60, 0, 0.5], F32), sun_colour, 0.25, ZENITH,
                              HORIZON)
    assert np.allclose(tilted.lit, up + 0.5 * 0.5)  # Lambert: cos 60 deg
    # shadows are an input mask: points on faces [1, 0, 1], sunlit, sunlit, shadowed
    pts = cm.gather_faces(shade.shadowed, shade.lit, np.array([1, 0, 2]), np.array([True, True, False]))
    assert pts.shape == (3, 3) and np.allclose(pts.T, [up + 0.5, up + 0.5, down])
    o = cm.shadow_ray_origins(np.zeros((3, 1)), np.array([[0.0], [0.0], [1.0]]))
    assert np.allclose(o[:, 0], [0, 0, 0.03])


def test_sky_and_reflection_terms_by_hand():
    g = cm.sky_gradient(np.array([-0.3, 0.0, 0.25, 1.0]), HORIZON, ZENITH)
    assert np.allclose(g.T, [HORIZON, HORIZON, HORIZON + 0.5 * (ZENITH - HORIZON), ZENITH])
    c45 = math.cos(math.radians(45))
    refl, cos_v = cm.mirror_reflection(np.array([[0.0, 0.0], [0, 0], [1, 1]]),
                                       np.array([[0.0, c45], [0, 0], [-1, -c45]]))
    assert np.allclose(refl.T, [[0, 0, 1], [c45, 0, c45]]) and np.allclose(cos_v, [1.0, c45])
    assert np.allclose(cm.schlick_fresnel(np.array([1.0, 0.0, 0.5])), [0.04, 1.0, 0.04 + 0.96 / 32])
    sun = np.array([0.0, 0.0, 1.0])
    r = np.array([[0.0, math.sqrt(1 - 0.81)], [0.0, 0.0], [1.0, 0.9]])
    assert np.allclose(cm.phong_highlight(r, sun), [1.0, 0.9 ** 64])


def test_specular_shading_by_hand():
    sun_colour = np.array([1.0, 0.9, 0.8])
    base = np.full((3, 3), 0.4, F32)
    # point 0: seen head-on from the side (reflection horizontal: env = 0.25 base + 0.02), paint
    # points 1, 2: seen from straight above (reflection up to the zenith, towards the sun), glass, lit / shadowed
    n = np.array([[1, 0, 0], [0, 0, 1], [0, 0, 1]], F32).T
    d = np.array([[-1, 0, 0], [0, 0, -1], [0, 0, -1]], F32).T
    strength = np.array([0.35, 0.9, 0.9], F32)
    out = cm.specular_shading(base, n, d, strength, np.array([False, True, True]), np.array([True, True, False]),
                              np.array([0, 0, 1], F32), sun_colour, HORIZON, ZENITH)
    k0 = 0.35 * 0.08  # Fresnel 0.04 head-on, floored at 0.08
    assert np.allclose(out[:, 0], 0.4 * (1 - k0) + k0 * (0.25 * 0.4 + 0.02), atol=1e-6)
    k1 = 0.9 * 0.28  # glass floor
    assert np.allclose(out[:, 1], 0.4 * (1 - k1) + k1 * ZENITH + 0.9 * sun_colour, atol=1e-6)
    assert np.allclose(out[:, 2], 0.4 * (1 - k1) + k1 * ZENITH, atol=1e-6)  # no highlight in shadow


def test_haze_tone_map_and_noise_by_hand():
    rad = np.array([[1.0, 1.0, 1.0]] * 3, F32)
    hz = cm.aerial_perspective(rad, np.array([0.0, 100.0, 1e6], F32), HORIZON, 100.0)
    assert np.allclose(hz.T, [[1, 1, 1], HORIZON + (1 - HORIZON) / math.e, HORIZON], atol=1e-6)

    x = np.array([0.0, 0.001, 0.5 / 0.875, 4 / 3, 100.0])
    assert np.allclose(cm.tone_curve(x), [0.0, 12.92 * 0.001 / 1.00025, _srgb(0.5), 1.0, 1.0])
    lut = cm.display_lut()
    assert lut.shape == (4096,) and lut[0] == 0 and lut[-1] == 255 and np.all(np.diff(lut) >= 0)
    assert lut[1024] == round(255 * _srgb(0.8))  # exposed radiance 1 -> shoulder 0.8
    scale = cm.exposure_scale(0.5)
    assert scale == F32(512.0)
    assert cm.lut_index(np.array([-1.0, 0.5, 1.0, 0.9999, 100.0], F32), scale).tolist() == [0, 256, 512, 511, 4095]
    assert cm.tone_map(np.array([1.0], F32), 1.0)[0] == lut[1024]

    display = np.array([[[100, 100, 250]]], np.int16)
    for byte, delta in ((0x00, -7), (0xFF, 7), (0x27, 1)):  # 0x27: low bits 7, top bits 1
        got = cm.apply_sensor_noise(display, np.full((1, 1, 3), byte, np.uint8))
        assert got.dtype == np.uint8 and got[0, 0].tolist() == [100 + delta, 100 + delta, min(250 + delta, 255)]
    # over all byte values the noise is centred, on -7..7, sd 3.24 grey levels
    noise = cm.apply_sensor_noise(np.full((1, 256, 1), 100, np.int16), np.arange(256, dtype=np.uint8)[None, :, None])
    e = noise.astype(float) - 100
    assert e.min() == -7 and e.max() == 7 and e.mean() == 0 and np.isclose(e.std(), math.sqrt(2 * 5.25))


def test_optics_blur_is_the_binomial_kernel():
    img = np.zeros((5, 5, 3), np.uint8)
    img[2, 2] = 160
    out = cm.optics_blur(img)
    assert out[2, 2].tolist() == [40] * 3 and out[2, 1, 0] == 20 and out[1, 1, 0] == 10 and out[0, 0, 0] == 0
    flat = np.full((4, 6, 3), 77, np.uint8)
    assert np.array_equal(cm.optics_blur(flat), flat)
