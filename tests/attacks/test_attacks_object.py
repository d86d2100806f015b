"""The roof object: template, box constraint (tanh and projection), uniform Laplacian, the controls' objects."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from robustbench3d.attacks.object import (
    NEUTRAL_GREY,
    TANH_EPS,
    RoofObject,
    benign_sphere,
    clamp_to_box,
    laplacian_smoothness,
    laplacian_smoothness_torch,
    random_shape,
    tanh_vertices,
    template_faces,
    template_vertices,
    to_file_precision,
    uniform_laplacian,
)
from robustbench3d.sensors.mesh import icosphere

B = np.array([0.4, 0.4, 0.4])
finite = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False, allow_infinity=False)


def brute_force_laplacian(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Mean over vertices of |mean of neighbours - vertex|, neighbours collected face by face."""
    neighbours: dict[int, set[int]] = {i: set() for i in range(len(vertices))}
    for a, b, c in faces.tolist():
        for i, j in ((a, b), (b, c), (c, a)):
            neighbours[i].add(j)
            neighbours[j].add(i)
    total = 0.0
    for i, ring in neighbours.items():
        mean = sum(vertices[j] for j in ring) / len(ring)
        total += float(np.sqrt(((mean - vertices[i]) ** 2).sum()))
    return total / len(vertices)


def test_template_is_the_level_2_icosphere_of_radius_040():
    v, f = template_vertices(), template_faces()
    ref_v, ref_f = icosphere(2, 0.40)
    assert v.shape == (162, 3) and f.shape == (320, 3)
    assert np.array_equal(f, ref_f)
    assert np.max(np.abs(v - ref_v)) < 1e-7  # float32 precision of the file format
    assert np.array_equal(v.astype(np.float32).astype(np.float64), v)
    assert np.all(np.abs(v) <= 0.4)


def test_benign_sphere_is_undeformed_and_grey():
    obj = benign_sphere()
    assert np.array_equal(obj.displacement, np.zeros((162, 3)))
    assert np.array_equal(obj.vertices(), template_vertices())
    assert np.all(obj.colors == NEUTRAL_GREY) and NEUTRAL_GREY == 128 / 255
    assert np.array_equal(obj.faces, template_faces())


def test_object_refuses_vertices_outside_the_box_and_bad_colours():
    v = template_vertices().copy()
    v[7] = [0.41, 0.0, 0.0]
    with pytest.raises(ValueError, match=r"field 'vertices': 1 vertices outside the box.*vertex 7"):
        RoofObject.from_vertices(v)
    d = np.zeros((162, 3))
    d[3, 2] = np.nan
    with pytest.raises(ValueError, match=r"field 'vertices': non-finite value \(NaN or inf\) at vertex 3"):
        RoofObject(d)
    c = np.full((162, 3), 0.5)
    c[9, 1] = 1.01
    with pytest.raises(ValueError, match=r"field 'colors': 1 colours outside \[0, 1\].*vertex 9"):
        RoofObject(colors=c)
    with pytest.raises(ValueError, match=r"field 'displacement': expected shape \(162, 3\)"):
        RoofObject(np.zeros((42, 3)))
    with pytest.raises(ValueError, match="field 'bounds'"):
        RoofObject(bounds=(0.4, -0.1, 0.4))


@settings(max_examples=200, deadline=None)
@given(arrays(np.float64, (5, 3), elements=st.floats(-0.4, 0.4)))
def test_file_precision_never_moves_a_vertex_outwards(v):
    q = to_file_precision(v)
    assert np.all(np.abs(q) <= np.abs(v))
    assert np.all(np.abs(q - v) <= np.abs(v) * 2.0 ** -23 + 2.0 ** -149)  # one float32 step
    assert np.array_equal(q.astype(np.float32).astype(np.float64), q)


@settings(max_examples=300, deadline=None)
@given(arrays(np.float64, (162, 3), elements=finite))
def test_tanh_path_never_leaves_the_box(delta):
    v = tanh_vertices(torch.from_numpy(delta)).numpy()
    assert np.all(np.isfinite(v)) and np.all(np.abs(v) <= B)
    obj = RoofObject.from_vertices(v)  # accepted by the object (no projection needed)
    assert np.all(np.abs(obj.vertices()) <= B)


@settings(max_examples=300, deadline=None)
@given(arrays(np.float64, (162, 3), elements=finite))
def test_projection_path_never_leaves_the_box_and_keeps_inside_points(displacement):
    v = clamp_to_box(template_vertices() + displacement)
    assert np.all(np.abs(v) <= B)
    inside = np.abs(template_vertices() + displacement) <= B
    assert np.array_equal(v[inside], (template_vertices() + displacement)[inside])
    vt = clamp_to_box(torch.from_numpy(template_vertices() + displacement))
    assert np.array_equal(vt.numpy(), v)
    RoofObject.from_vertices(v)


def test_tanh_path_hand_values_and_gradients():
    # delta = 0: b * tanh(atanh((1 - eps) v0 / b)) = (1 - eps) v0
    v = tanh_vertices(torch.zeros(162, 3, dtype=torch.float64)).numpy()
    assert np.allclose(v, (1 - TANH_EPS) * template_vertices(), rtol=0, atol=1e-15)
    # a huge delta saturates at the box face, never beyond it
    big = torch.full((162, 3), 1e3, dtype=torch.float64)
    assert np.array_equal(tanh_vertices(big).numpy(), np.broadcast_to(B, (162, 3)))
    # dv/ddelta = b (1 - tanh^2): finite and positive
    delta = torch.zeros(162, 3, dtype=torch.float64, requires_grad=True)
    tanh_vertices(delta).sum().backward()
    x = np.arctanh((1 - TANH_EPS) * template_vertices() / B)
    assert np.allclose(delta.grad.numpy(), B * (1 - np.tanh(x) ** 2), rtol=1e-12)


def test_torch_vertices_start_at_the_object_and_stay_in_the_box():
    obj = random_shape(4)
    assert np.allclose(obj.torch_vertices().numpy(), (1 - TANH_EPS) * obj.vertices(), atol=1e-15)
    delta = torch.tensor(np.random.default_rng(0).normal(0, 5, (162, 3)), requires_grad=True)
    v = obj.torch_vertices(delta)
    assert torch.all(v.abs() <= torch.tensor(B))
    v.sum().backward()
    assert torch.all(torch.isfinite(delta.grad)) and delta.grad.abs().sum() > 0


def test_laplacian_hand_computed_on_one_triangle():
    v = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    f = np.array([[0, 1, 2]])
    # vertex 0: |(0.5, 0.5, 0)| ; vertices 1 and 2: |(-1, 0.5, 0)|
    expected = (np.sqrt(0.5) + 2 * np.sqrt(1.25)) / 3
    assert laplacian_smoothness(v, f) == pytest.approx(expected, rel=1e-15)
    lap = uniform_laplacian(f, 3)
    assert np.array_equal(lap, np.array([[-1, 0.5, 0.5], [0.5, -1, 0.5], [0.5, 0.5, -1]]))


def test_laplacian_matches_a_brute_force_neighbour_loop():
    rng = np.random.default_rng(1)
    f = template_faces()
    for v in (template_vertices(), random_shape(2).vertices(), rng.normal(0, 0.3, (162, 3))):
        assert laplacian_smoothness(v) == pytest.approx(brute_force_laplacian(v, f), rel=1e-12)
        t = laplacian_smoothness_torch(torch.tensor(v))
        assert float(t) == pytest.approx(brute_force_laplacian(v, f), rel=1e-12)
    lap = uniform_laplacian(f, 162)
    assert np.allclose(lap.sum(axis=1), 0) and np.all(np.diag(lap) == -1)
    assert sorted(set(np.count_nonzero(lap, axis=1) - 1)) == [5, 6]  # icosphere valences
    v = rng.normal(0, 0.3, (162, 3))  # translation invariant
    assert laplacian_smoothness(v + np.array([1.0, -2.0, 3.0])) == pytest.approx(laplacian_smoothness(v), rel=1e-12)


def test_torch_laplacian_gradient_matches_finite_differences():
    v = torch.tensor(random_shape(3).vertices(), requires_grad=True)
    assert torch.autograd.gradcheck(laplacian_smoothness_torch, (v,), eps=1e-6, atol=1e-7, rtol=1e-5)
    # by hand: central differences of the numpy version on a few coordinates
    laplacian_smoothness_torch(v).backward()
    base = v.detach().numpy()
    for i, k in ((0, 0), (17, 1), (161, 2)):
        plus, minus = base.copy(), base.copy()
        plus[i, k] += 1e-6
        minus[i, k] -= 1e-6
        fd = (laplacian_smoothness(plus) - laplacian_smoothness(minus)) / 2e-6
        assert float(v.grad[i, k]) == pytest.approx(fd, rel=1e-5, abs=1e-9)


def test_torch_laplacian_gradient_is_finite_at_a_flat_vertex():
    v = np.array([[0.0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]])  # vertex 0 is its ring's mean
    f = np.array([[0, 1, 3], [0, 3, 2], [0, 2, 4], [0, 4, 1]])
    t = torch.tensor(v, requires_grad=True)
    laplacian_smoothness_torch(t, f).backward()
    assert torch.all(torch.isfinite(t.grad))


def test_random_shape_is_seeded_smooth_nontrivial_and_inside_the_box():
    a, b, c = random_shape(7), random_shape(7), random_shape(8)
    assert a == b and not np.array_equal(a.vertices(), c.vertices())
    for obj in (a, c, random_shape(0)):
        v = obj.vertices()
        assert np.all(np.abs(v) <= B)
        assert np.abs(obj.displacement).max() > 0.05  # really deformed
        # smooth: far smoother than independent per-vertex noise of the same size
        noise = template_vertices() + np.random.default_rng(0).normal(0, obj.displacement.std(), (162, 3))
        assert laplacian_smoothness(v) < 0.5 * laplacian_smoothness(noise)
        assert np.all((obj.colors >= 0) & (obj.colors <= 1)) and obj.colors.std() > 0.1
    with pytest.raises(ValueError, match="field 'seed'"):
        random_shape(-1)
