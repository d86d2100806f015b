"""The roof-object attack on a generated frame: identity without cars, where the object shows up in the
scan and the image, cars behind the camera, determinism, the registry entries and ``--attacks FILE.ply``."""

from __future__ import annotations

import json

import numpy as np
import pytest

from robustbench3d.attacks import ATTACKS, create_attack
from robustbench3d.attacks.base import target_cars
from robustbench3d.attacks.object import benign_sphere, random_shape
from robustbench3d.attacks.objectfile import object_sha256, save_object
from robustbench3d.attacks.roof import RoofObjectAttack
from robustbench3d.errors import DataFormatError, RobustBenchError
from robustbench3d.kitti.dataset import Frame
from robustbench3d.kitti.labels import Labels
from robustbench3d.sensors.camera_render import mesh_box


@pytest.fixture(scope="module")
def frame() -> Frame:
    from robustbench3d.synth.frame import generate_frame

    f = generate_frame(0, 0)
    return Frame("000000", f.image, f.scan, f.calib, f.labels)


def _cars(location: list[list[float]], ry: list[float]) -> Labels:
    n = len(location)
    return Labels(type=np.array(["Car"] * n, dtype=object), truncated=np.zeros(n), occluded=np.zeros(n, int),
                  alpha=np.zeros(n), bbox=np.zeros((n, 4)), dimensions=np.tile([1.5, 1.6, 3.9], (n, 1)),
                  location=np.array(location, dtype=np.float64), rotation_y=np.array(ry, dtype=np.float64))


def _snapshot(f: Frame) -> tuple[bytes, bytes]:
    return f.image.tobytes(), f.scan.tobytes()


def _added_rows(clean: np.ndarray, attacked: np.ndarray) -> np.ndarray:
    before = {row.tobytes() for row in clean}
    return np.array([row for row in attacked if row.tobytes() not in before])


def test_frame_without_cars_passes_through_unchanged(frame):
    attack = create_attack("random-shape", seed=0)
    for labels in (Labels.empty(), frame.labels.of_types(["Pedestrian"])):
        out = attack.apply(frame, target_cars(labels), np.random.default_rng(0))
        assert out is frame


def test_object_appears_on_the_cars_in_scan_and_image_only(frame):
    targets = target_cars(frame.labels).select(slice(0, 3))  # the three nearest cars (4-9 m)
    before = _snapshot(frame)
    attack = create_attack("random-shape", seed=1)
    out = attack.apply(frame, targets, np.random.default_rng(0))
    assert _snapshot(frame) == before  # input untouched
    assert out.calib is frame.calib and out.labels is frame.labels and out.frame_id == frame.frame_id
    assert out.scan.dtype == np.float32 and out.image.dtype == np.uint8 and out.image.shape == frame.image.shape
    placed = [v for v, _ in attack.place(targets, np.random.default_rng(0))]
    # LiDAR: every added point lies on one of the placed objects (within its bounding sphere)
    added = _added_rows(frame.scan, out.scan)
    assert len(added) > 100
    centres = [frame.calib.rect_to_velo_points(v).mean(axis=0) for v in placed]
    radius = np.linalg.norm(attack.obj.vertices(), axis=1).max()
    dist = np.min([np.linalg.norm(added[:, :3] - c, axis=1) for c in centres], axis=0)
    assert np.all(dist <= radius + 0.05)
    # camera: pixels change, and only inside the objects' projected boxes
    changed = np.any(out.image != frame.image, axis=2)
    assert changed.sum() > 500
    inside = np.zeros_like(changed)
    boxes = [mesh_box(frame.calib, v, frame.image_size) for v in placed]
    assert [status for _, status in boxes] == ["outside", "rendered", "rendered"]  # car 0: 4 m away, 50 deg right
    for box, _ in boxes[1:]:
        u0, v0, u1, v1 = box
        inside[v0:v1, u0:u1] = True
    assert not np.any(changed & ~inside)


def test_car_behind_the_camera_or_outside_the_image_keeps_its_lidar_returns(frame):
    targets = _cars([[0.0, 1.6, -8.0], [25.0, 1.6, 3.0]], [0.0, 1.0])  # behind; far right of the image
    attack = create_attack("benign-sphere")
    out = attack.apply(frame, targets, np.random.default_rng(0))
    assert out.image.tobytes() == frame.image.tobytes()
    added = _added_rows(frame.scan, out.scan)
    for v, _ in attack.place(targets, np.random.default_rng(0)):
        centre = frame.calib.rect_to_velo_points(v).mean(axis=0)
        assert np.sum(np.linalg.norm(added[:, :3] - centre, axis=1) <= 0.45) > 20


def test_same_seed_gives_the_same_attacked_frame(frame):
    targets = target_cars(frame.labels).select(slice(0, 2))
    attack = create_attack("random-shape", seed=2, eot=True)
    a = attack.apply(frame, targets, np.random.default_rng(11))
    b = attack.apply(frame, targets, np.random.default_rng(11))
    c = attack.apply(frame, targets, np.random.default_rng(12))
    assert _snapshot(a) == _snapshot(b)
    assert a.scan.tobytes() != c.scan.tobytes()  # EOT: another draw, another placement
    plain = create_attack("random-shape", seed=2)  # no EOT, no noise: nothing random
    assert _snapshot(plain.apply(frame, targets, np.random.default_rng(1))) == \
        _snapshot(plain.apply(frame, targets, np.random.default_rng(2)))


def test_describe_identifies_the_object(tmp_path):
    d = create_attack("random-shape", seed=3).describe()
    json.dumps(d)
    assert d["object"]["ply_sha256"] == object_sha256(random_shape(3))
    assert d["object"]["made_by"] == {"attack": "random-shape", "seed": 3}
    assert d["placement"] == {"rule": "roof-centre", "eot": False}
    eot = create_attack("benign-sphere", eot=True).describe()
    assert eot["placement"]["eot"] is True and eot["placement"]["yaw_jitter_rad"] == pytest.approx(np.radians(5))
    assert create_attack("random-shape", seed=4).describe() != d
    path = save_object(tmp_path / "mine.ply", random_shape(3), {"attack": "random-shape", "seed": 3})
    from_file = create_attack("object-file", path=str(path)).describe()
    assert from_file["object"] == d["object"]  # the same object, from its file


def test_registry_entries_and_parameter_errors(tmp_path):
    assert {"benign-sphere", "random-shape", "object-file"} <= set(ATTACKS.names())
    assert isinstance(create_attack("benign-sphere"), RoofObjectAttack)
    assert create_attack("benign-sphere").obj == benign_sphere()
    assert create_attack("random-shape").obj == random_shape(0)
    with pytest.raises(RobustBenchError, match=r"attack 'random-shape': random_shape: field 'seed'"):
        create_attack("random-shape", seed=-3)
    with pytest.raises(DataFormatError, match=r"missing\.ply: object file not found"):
        create_attack("object-file", path=str(tmp_path / "missing.ply"))
    with pytest.raises(ValueError, match="field 'occlusion'"):
        RoofObjectAttack(benign_sphere(), occlusion="exact")


def test_attacks_option_accepts_object_files(tmp_path):
    path = save_object(tmp_path / "My Object.ply", random_shape(6), {"attack": "random-shape", "seed": 6})
    names, args = ATTACKS.resolve_all(["none", str(path)], {str(path): {"eot": True}})
    assert names == ["none", "my-object"] and args == {"my-object": {"eot": True}}
    attack = create_attack("my-object", eot=True)
    assert attack.obj == random_shape(6) and attack.eot
    assert ATTACKS.resolve_all([str(path)], {})[0] == ["my-object"]  # idempotent for the same file
    with pytest.raises(RobustBenchError, match="no such object file"):
        ATTACKS.resolve_all([str(tmp_path / "nope.ply")], {})
    clash = save_object(tmp_path / "sub" / "none.ply", benign_sphere())
    with pytest.raises(RobustBenchError, match="'none' is already a registered attack"):
        ATTACKS.resolve_all([str(clash)], {})
