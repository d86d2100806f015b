"""Attack registry and contract: the "none" control, targets, requirements, parameter checks."""

from __future__ import annotations

import numpy as np
import pytest

from robustbench3d.attacks import ATTACKS, ENTRY_POINT_GROUP, AttackRequirements, AttackSpec, create_attack
from robustbench3d.attacks.base import Attack, target_cars
from robustbench3d.errors import RobustBenchError
from robustbench3d.kitti.calib import Calibration
from robustbench3d.kitti.dataset import Frame
from robustbench3d.kitti.labels import Labels
from robustbench3d.registry import RegistryError, UnknownNameError
from robustbench3d.victims.spec import Capabilities


def random_frame(rng: np.random.Generator) -> Frame:
    """A frame with random image, scan, calibration and three labelled objects (Car, Van, Car)."""
    calib = Calibration(P0=rng.normal(size=(3, 4)), P1=rng.normal(size=(3, 4)), P2=rng.normal(size=(3, 4)),
                        P3=rng.normal(size=(3, 4)), R0_rect=rng.normal(size=(3, 3)),
                        Tr_velo_to_cam=rng.normal(size=(3, 4)), Tr_imu_to_velo=rng.normal(size=(3, 4)))
    n = 3
    labels = Labels(type=np.array(["Car", "Van", "Car"], dtype=object), truncated=rng.random(n),
                    occluded=np.array([0, 1, 2]), alpha=rng.uniform(-3, 3, n), bbox=rng.uniform(0, 300, (n, 4)),
                    dimensions=rng.uniform(1, 4, (n, 3)), location=rng.uniform(-20, 40, (n, 3)),
                    rotation_y=rng.uniform(-3, 3, n))
    image = rng.integers(0, 256, (37, 124, 3), dtype=np.uint8)
    scan = rng.normal(size=(500, 4)).astype(np.float32)
    return Frame("000042", image, scan, calib, labels)


def snapshot(frame: Frame) -> dict[str, bytes]:
    out = {"image": frame.image.tobytes(), "scan": frame.scan.tobytes(), "id": frame.frame_id.encode()}
    for key in ("P0", "P1", "P2", "P3", "R0_rect", "Tr_velo_to_cam", "Tr_imu_to_velo"):
        out[key] = np.asarray(getattr(frame.calib, key)).tobytes()
    for key in ("truncated", "occluded", "alpha", "bbox", "dimensions", "location", "rotation_y"):
        out[key] = getattr(frame.labels, key).tobytes()
    out["type"] = "|".join(frame.labels.type).encode()
    return out


def test_none_attack_leaves_every_array_bit_identical():
    frame = random_frame(np.random.default_rng(3))
    before = snapshot(frame)
    dtypes = (frame.image.dtype, frame.scan.dtype, frame.image.shape, frame.scan.shape)
    attack = create_attack("none")
    out = attack.apply(frame, target_cars(frame.labels), np.random.default_rng(0))
    assert isinstance(out, Frame)
    assert snapshot(out) == before  # the output is the clean frame, bit for bit
    assert snapshot(frame) == before  # and the input was not modified
    assert (out.image.dtype, out.scan.dtype, out.image.shape, out.scan.shape) == dtypes
    assert attack.describe() == {"object": None}


def test_target_cars_are_the_car_rows():
    frame = random_frame(np.random.default_rng(4))
    targets = target_cars(frame.labels)
    assert list(targets.type) == ["Car", "Car"]
    assert np.array_equal(targets.location, frame.labels.location[[0, 2]])
    assert len(target_cars(None)) == 0


def test_registry_lists_none_and_suggests_close_names():
    assert "none" in ATTACKS.names()
    assert ATTACKS.group == ENTRY_POINT_GROUP == "robustbench3d.attacks"
    with pytest.raises(UnknownNameError, match="did you mean 'none'"):
        create_attack("nnoe")


def test_unknown_parameters_are_refused_with_the_attack_name():
    with pytest.raises(RobustBenchError, match=r"attack 'none': invalid parameters \{'radius': 0.4\}"):
        create_attack("none", radius=0.4)


def test_registry_accepts_only_attack_specs_and_factories_must_build_attacks():
    with pytest.raises(RegistryError, match="expected a AttackSpec"):
        ATTACKS.register("test-not-a-spec", object())
    spec = AttackSpec(factory=lambda: object())
    with pytest.raises(RobustBenchError, match="returned a object, not an Attack"):
        spec.create()


def test_attack_base_class_requires_apply_and_describe():
    class Incomplete(Attack):
        def describe(self):
            return {}

    with pytest.raises(TypeError, match="apply"):
        Incomplete()


LIDAR_ONLY = Capabilities(modalities=("lidar",), backend="other", gradients=False, deterministic=True)
FUSION_WHITE_BOX = Capabilities(modalities=("camera", "lidar"), backend="torch", gradients=True, deterministic=True)


def test_requirements_against_victim_capabilities():
    assert AttackRequirements().unmet(LIDAR_ONLY) is None
    assert AttackRequirements(needs_lidar=True).unmet(LIDAR_ONLY) is None
    reason = AttackRequirements(needs_camera=True).unmet(LIDAR_ONLY)
    assert reason == "needs the camera; the victim offers lidar, no gradients"
    reason = AttackRequirements(needs_camera=True, needs_gradients=True).unmet(LIDAR_ONLY)
    assert reason == "needs the camera and gradients (white-box oracles); the victim offers lidar, no gradients"
    assert AttackRequirements(needs_camera=True, needs_lidar=True, needs_gradients=True).unmet(FUSION_WHITE_BOX) is None
