"""Placement of the roof object on a car: hand-computed poses, resting on the roof, jitter, frames."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from robustbench3d.attacks.object import benign_sphere, random_shape
from robustbench3d.attacks.placement import Car, Placement, cars_of, place_on_roof, rect_to_velo, sample_jitter
from robustbench3d.kitti.labels import Labels
from robustbench3d.testing import SIMPLE_CALIB

CAR = Car(location=(2.0, 1.6, 10.0), dimensions=(1.5, 1.6, 4.0), rotation_y=math.pi / 2)


def test_hand_computed_placement_of_three_vertices():
    # object frame: x along the car, y down; lowest point y = 0.3
    v = np.array([[0.4, 0.0, 0.0], [0.0, 0.3, 0.0], [0.0, -0.2, 0.1]])
    placed, pose = place_on_roof(v, CAR)
    # roof centre (2, 1.6 - 1.5, 10) = (2, 0.1, 10); centre lifted by 0.3: (2, -0.2, 10)
    assert np.allclose(pose.roof_centre, [2.0, 0.1, 10.0], atol=1e-15)
    assert np.allclose(pose.centre, [2.0, -0.2, 10.0], atol=1e-15)
    # ry = pi/2: x' = cos x + sin z = z, z' = -sin x + cos z = -x
    expected = np.array([[2.0, -0.2, 10.0 - 0.4], [2.0, 0.1, 10.0], [2.0 + 0.1, -0.4, 10.0]])
    assert np.allclose(placed, expected, atol=1e-12)
    assert pose.yaw == math.pi / 2


def test_general_yaw_rotates_a_known_vertex_by_hand():
    ry = 0.3
    car = Car(location=(-3.0, 1.7, 20.0), dimensions=(1.4, 1.7, 4.2), rotation_y=ry)
    obj = benign_sphere().vertices()
    placed, _ = place_on_roof(obj, car)
    lowest = obj[:, 1].max()
    for k in (0, 5, 100):
        x, y, z = obj[k]
        by_hand = np.array([math.cos(ry) * x + math.sin(ry) * z - 3.0,
                            y + (1.7 - 1.4) - lowest,
                            -math.sin(ry) * x + math.cos(ry) * z + 20.0])
        assert np.allclose(placed[k], by_hand, atol=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_object_rests_on_the_roof_centre(seed):
    rng = np.random.default_rng(seed)
    obj = random_shape(seed).vertices()
    car = Car(location=tuple(rng.uniform(-10, 30, 3)), dimensions=tuple(rng.uniform(1.3, 4.5, 3)),
              rotation_y=float(rng.uniform(-math.pi, math.pi)))
    placed, pose = place_on_roof(obj, car)
    roof_y = car.location[1] - car.dimensions[0]
    assert placed[:, 1].max() == pytest.approx(roof_y, abs=1e-12)  # lowest point touches the roof plane
    # the object's centre is straight above the roof centre (same x, z), by the lowest point's offset
    assert np.allclose(pose.centre[[0, 2]], [car.location[0], car.location[2]], atol=1e-12)
    assert pose.centre[1] == pytest.approx(roof_y - obj[:, 1].max(), abs=1e-12)
    # rigid: distances to the centre are kept
    assert np.allclose(np.linalg.norm(placed - pose.centre, axis=1), np.linalg.norm(obj, axis=1), atol=1e-12)


def test_jitter_moves_along_the_car_and_adds_yaw():
    v = np.array([[0.4, 0.0, 0.0], [0.0, 0.3, 0.0]])
    base, _ = place_on_roof(v, CAR)
    moved, pose = place_on_roof(v, CAR, Placement(forward=0.05, lateral=0.02, yaw=0.0))
    # local (0.05, 0, 0.02) at ry = pi/2 -> rect (0.02, 0, -0.05)
    assert np.allclose(moved - base, [[0.02, 0.0, -0.05]] * 2, atol=1e-12)
    turned, pose = place_on_roof(v, CAR, Placement(yaw=-math.pi / 2))
    assert pose.yaw == pytest.approx(0.0)
    assert np.allclose(turned[0], [2.0 + 0.4, -0.2, 10.0], atol=1e-12)  # yaw 0: x stays x


def test_sample_jitter_is_seeded_and_within_its_ranges():
    draws = [sample_jitter(np.random.default_rng(9), 0.05, 0.1) for _ in range(2)]
    assert draws[0] == draws[1]
    rng = np.random.default_rng(1)
    many = [sample_jitter(rng, 0.05, 0.1) for _ in range(500)]
    fwd, lat, yaw = (np.array([getattr(p, k) for p in many]) for k in ("forward", "lateral", "yaw"))
    assert np.all(np.abs(fwd) <= 0.05) and np.all(np.abs(lat) <= 0.05) and np.all(np.abs(yaw) <= 0.1)
    assert fwd.std() > 0.02 and yaw.std() > 0.04  # actually spread over the range
    rng = np.random.default_rng(3)
    sample_jitter(rng)
    assert rng.bit_generator.state == _after_three_draws(3)


def _after_three_draws(seed: int) -> dict:
    rng = np.random.default_rng(seed)
    rng.uniform(size=2)
    rng.uniform()
    return rng.bit_generator.state


def test_torch_placement_equals_numpy_and_is_differentiable():
    obj = random_shape(5).vertices()
    jitter = Placement(0.01, -0.03, 0.05)
    placed_np, pose_np = place_on_roof(obj, CAR, jitter)
    v = torch.tensor(obj, requires_grad=True)
    placed_t, pose_t = place_on_roof(v, CAR, jitter)
    assert np.allclose(placed_t.detach().numpy(), placed_np, atol=1e-14)
    assert np.allclose(pose_t.centre, pose_np.centre, atol=1e-14)
    velo_t = rect_to_velo(placed_t, SIMPLE_CALIB)
    assert np.allclose(velo_t.detach().numpy(), SIMPLE_CALIB.rect_to_velo_points(placed_np), atol=1e-12)
    velo_t[:, 0].sum().backward()
    assert torch.all(torch.isfinite(v.grad)) and v.grad.abs().sum() > 0


def test_rect_to_velo_puts_the_object_above_the_car_in_the_velodyne_frame():
    placed, _ = place_on_roof(benign_sphere().vertices(), CAR)
    velo = rect_to_velo(placed, SIMPLE_CALIB)
    # SIMPLE_CALIB: rect (x, y, z) = (-y_v, -z_v - 0.08, x_v - 0.27) -> velodyne z = -(y + 0.08)
    assert np.allclose(velo[:, 2], -(placed[:, 1] + 0.08), atol=1e-12)
    assert np.allclose(velo[:, 0], placed[:, 2] + 0.27, atol=1e-12)


def test_cars_of_reads_label_rows():
    labels = Labels(type=np.array(["Car", "Car"], dtype=object), truncated=np.zeros(2), occluded=np.zeros(2, int),
                    alpha=np.zeros(2), bbox=np.zeros((2, 4)), dimensions=np.array([[1.5, 1.6, 4.0], [1.4, 1.7, 3.9]]),
                    location=np.array([[2.0, 1.6, 10.0], [1.0, 1.7, 30.0]]), rotation_y=np.array([math.pi / 2, 0.1]))
    cars = cars_of(labels)
    assert cars[0] == CAR
    assert np.allclose(cars[1].roof_centre, [1.0, 0.3, 30.0])
