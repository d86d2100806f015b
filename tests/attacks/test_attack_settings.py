"""The roof-object attack's settings through every registry factory (``run --attack-arg``), their checks, their
record in describe(), and ``cull=False``: the full-scene render, the same scans and images as the culled one."""

from __future__ import annotations

import inspect
import json
import shutil

import numpy as np
import pytest

from robustbench3d.attacks import ATTACKS, create_attack
from robustbench3d.attacks.base import target_cars
from robustbench3d.attacks.object import benign_sphere
from robustbench3d.attacks.roof import SETTINGS, RoofObjectAttack
from robustbench3d.attacks.shipped import shipped_objects
from robustbench3d.attacks.spec import AttackSpecError
from robustbench3d.errors import RobustBenchError
from robustbench3d.registry import parse_factory_args

#: A value other than the default for every setting.
OTHER = {"eot": True, "position_jitter_m": 0.1, "yaw_jitter_rad": 0.2, "range_noise_m": 0.02, "dropout": 0.05,
         "supersample": 2, "occlusion": "none", "cull": False}
DEFAULTS = {"eot": False, "position_jitter_m": 0.05, "yaw_jitter_rad": np.radians(5.0), "range_noise_m": 0.0,
            "dropout": 0.0, "supersample": 3, "occlusion": "scan", "cull": True}


@pytest.fixture(scope="module")
def factories(tmp_path_factory) -> dict[str, dict]:
    """Attack name -> its own parameters, for every kind of roof-object factory."""
    shipped = shipped_objects()
    path = tmp_path_factory.mktemp("obj") / "my-shape.ply"  # a copy of a shipped object file and its sidecar
    shutil.copyfile(shipped[0].path, path)
    shutil.copyfile(shipped[0].sidecar_path, path.with_suffix(".json"))
    named = ATTACKS.resolve(str(path))  # a .ply given to --attacks
    out = {"benign-sphere": {}, "random-shape": {"seed": 3}, "object-file": {"path": str(path)}, named: {}}
    out.update({entry.name: {} for entry in shipped})
    return out


def test_the_settings_are_the_constructors():
    params = inspect.signature(RoofObjectAttack.__init__).parameters
    assert set(SETTINGS) == set(OTHER) == set(DEFAULTS)
    assert {name: params[name].default for name in SETTINGS} == DEFAULTS


def test_every_roof_object_factory_takes_every_setting(factories):
    assert {"adv-object", "adv-shape", "adv-texture"} <= set(factories)
    for name, own in factories.items():
        attack = create_attack(name, **own, **OTHER)
        assert isinstance(attack, RoofObjectAttack)
        assert {s: getattr(attack, s) for s in SETTINGS} == OTHER, name
        if name in ("random-shape", "object-file"):
            plain = create_attack(name, **own)
            assert {s: getattr(plain, s) for s in SETTINGS} == DEFAULTS, name


def test_attack_args_as_the_command_line_parses_them():
    """``--attack-arg NAME:KEY=VALUE`` values are JSON (true/false, numbers) or strings; one key per option."""
    items = ["adv-object:eot=true", "adv-object:range_noise_m=0.02", "adv-object:dropout=0.05",
             "adv-object:supersample=2", "adv-object:cull=false", "adv-object:occlusion=none",
             "adv-object:position_jitter_m=0", "adv-object:yaw_jitter_rad=0.1"]
    args = parse_factory_args(items, "--attack-arg")["adv-object"]
    attack = create_attack("adv-object", **args)
    assert (attack.eot, attack.range_noise_m, attack.dropout, attack.supersample, attack.cull, attack.occlusion,
            attack.position_jitter_m, attack.yaw_jitter_rad) == (True, 0.02, 0.05, 2, False, "none", 0.0, 0.1)
    assert type(attack.position_jitter_m) is float  # JSON's 0 is an int; stored (and described) as 0.0
    zero = create_attack("adv-object", **parse_factory_args(["adv-object:range_noise_m=0"], "x")["adv-object"])
    assert json.dumps(zero.describe()) == json.dumps(create_attack("adv-object").describe())


def test_defaults_describe_the_attack_as_before():
    """The defaults' description is the one from before these settings existed (run caches stay valid):
    jitter ranges only with EOT, no 'cull' key."""
    d = create_attack("benign-sphere").describe()
    assert set(d) == {"object", "placement", "lidar", "camera"}
    assert d["placement"] == {"rule": "roof-centre", "eot": False}
    assert d["lidar"] == {"range_noise_m": 0.0, "dropout": 0.0}
    assert d["camera"] == {"supersample": 3, "occlusion": "scan"}
    eot = create_attack("benign-sphere", eot=True).describe()
    assert set(eot) == set(d)
    assert eot["placement"] == {"rule": "roof-centre", "eot": True, "position_jitter_m": 0.05,
                                "yaw_jitter_rad": np.radians(5.0)}


def test_every_setting_changes_the_description():
    base = json.dumps(create_attack("benign-sphere").describe(), sort_keys=True)
    described = {base}
    for name, value in OTHER.items():
        d = create_attack("benign-sphere", **{name: value}).describe()
        text = json.dumps(d, sort_keys=True)
        assert text not in described, name
        described.add(text)
        flat = json.dumps(d)
        assert f'"{name}": {json.dumps(value)}' in flat, (name, flat)
    # the jitter ranges without EOT are recorded too (they size the exact-occlusion crops)
    assert create_attack("benign-sphere", yaw_jitter_rad=0.2).describe()["placement"]["yaw_jitter_rad"] == 0.2


BAD = [("eot", "yes", "expected true or false"), ("eot", 1, "expected true or false"),
       ("cull", "false", "expected true or false"), ("position_jitter_m", -0.1, "expected a finite number >= 0"),
       ("yaw_jitter_rad", float("inf"), "expected a finite number >= 0"),
       ("range_noise_m", True, "expected a finite number >= 0"),
       ("range_noise_m", "0.02", "expected a finite number >= 0"),
       ("dropout", 1.0, r"expected a number in \[0, 1\)"), ("dropout", -0.01, r"expected a number in \[0, 1\)"),
       ("supersample", 0, "expected an integer >= 1"), ("supersample", 2.0, "expected an integer >= 1"),
       ("occlusion", "exact", "expected one of scan, none")]


@pytest.mark.parametrize(("field", "value", "problem"), BAD)
def test_bad_values_name_the_field(factories, field, value, problem):
    for name, own in factories.items():
        with pytest.raises(AttackSpecError, match=rf"attack '{name}': field '{field}': {problem}, got"):
            create_attack(name, **own, **{field: value})
    with pytest.raises(ValueError, match=rf"field '{field}': {problem}"):
        RoofObjectAttack(benign_sphere(), **{field: value})


def test_unknown_settings_are_refused(factories):
    assert issubclass(AttackSpecError, RobustBenchError)  # the CLI exits 2 on these
    for name, own in factories.items():
        with pytest.raises(AttackSpecError, match=rf"attack '{name}': invalid parameters .*'range_noise'"):
            create_attack(name, **own, range_noise=0.02)


# -- cull=False: the full-scene reference ------------------------------------------------------------------


def _low_poly_on_roofs(frame, cars: int, level: int = 0) -> list:
    """Velodyne meshes (vertices, faces, colours) of a 0.4 m icosphere of ``level`` on the roofs of the first
    ``cars`` target cars of ``frame``."""
    from robustbench3d.attacks.placement import cars_of, place_on_roof
    from robustbench3d.sensors.mesh import icosphere

    v, f = icosphere(level, 0.4)
    colours = np.random.default_rng(level).uniform(0, 1, (len(v), 3))
    return [(frame.calib.rect_to_velo_points(place_on_roof(v, car)[0]), f, colours)
            for car in cars_of(target_cars(frame.labels))[:cars]]


@pytest.mark.parametrize("index", [0, 2])
def test_full_scene_lidar_equals_the_culled_render(index):
    """Every ray of the pattern at every face gives the culled render's scan, bit for bit (noise and dropout
    on: the same draws), at rays x faces ray-triangle tests."""
    from robustbench3d.sensors.lidar_render import prepare_scan, render_lidar
    from robustbench3d.synth.frame import generate_frame

    frame = generate_frame(0, index)
    meshes = _low_poly_on_roofs(frame, 2)
    culled = render_lidar(frame.scan, meshes, rng=np.random.default_rng(index), range_noise_m=0.02, dropout=0.05)
    full = render_lidar(frame.scan, meshes, rng=np.random.default_rng(index), range_noise_m=0.02, dropout=0.05,
                        cull=False)
    assert len(culled.added) > 30 and len(culled.removed_index) > 0
    assert full.scan.tobytes() == culled.scan.tobytes()
    assert np.array_equal(full.ray_index, culled.ray_index) and np.array_equal(full.face_index, culled.face_index)
    n_rays = int(full.pattern.ring_start[-1])
    assert full.tests == n_rays * sum(len(f) for _, f, _ in meshes) > 100 * culled.tests
    if index == 0:  # a prepared scan (restricted to one mesh's rays) is matched again on every ray
        mesh = meshes[1:2]
        prep = prepare_scan(frame.scan, pattern=full.pattern, rays=full.pattern.cull(mesh[0][0].mean(0), 0.45))
        assert render_lidar(prep, mesh, cull=False).scan.tobytes() == render_lidar(frame.scan, mesh).scan.tobytes()


def test_attack_without_cull_renders_the_full_scene(monkeypatch):
    """``cull=False`` reaches both renderers: every LiDAR ray (render_lidar cull=False) and the whole image
    (render_camera full_image=True); the camera's full image equals the culled one here (the LiDAR's: above)."""
    import robustbench3d.sensors.camera_render as camera_render
    import robustbench3d.sensors.lidar_render as lidar_render
    from robustbench3d.kitti.dataset import Frame
    from robustbench3d.synth.frame import generate_frame

    g = generate_frame(0, 3)
    frame = Frame("000003", g.image, g.scan, g.calib, g.labels)
    targets = target_cars(frame.labels).select(slice(0, 2))
    seen = []
    real_lidar, real_camera = lidar_render.render_lidar, camera_render.render_camera

    def lidar_spy(*args, cull=True, **kwargs):
        seen.append(("lidar", cull))
        return real_lidar(*args, **kwargs)  # the culled render (equal, and 1000x cheaper)

    def camera_spy(*args, full_image=False, **kwargs):
        seen.append(("camera", full_image))
        return real_camera(*args, full_image=full_image, **kwargs)

    monkeypatch.setattr(lidar_render, "render_lidar", lidar_spy)
    monkeypatch.setattr(camera_render, "render_camera", camera_spy)
    images = {}
    for cull in (True, False):
        attacked = create_attack("random-shape", seed=5, cull=cull).apply(frame, targets, np.random.default_rng(9))
        images[cull] = attacked.image
    assert seen == [("lidar", True), ("camera", False), ("lidar", False), ("camera", True)]
    assert np.any(images[True] != frame.image) and images[False].tobytes() == images[True].tobytes()


@pytest.mark.slow
def test_full_scene_attack_equals_the_culled_attack():
    """The whole attack, both sensors, EOT and LiDAR noise on: culled and full scene give the same frames
    (a few minutes: every ray at every face)."""
    from robustbench3d.kitti.dataset import Frame
    from robustbench3d.synth.frame import generate_frame

    for index in (4, 5):
        g = generate_frame(0, index)
        frame = Frame(f"{index:06d}", g.image, g.scan, g.calib, g.labels)
        targets = target_cars(frame.labels).select(slice(0, 3))
        out = {}
        for cull in (True, False):
            attack = create_attack("adv-object", eot=True, range_noise_m=0.02, dropout=0.05, cull=cull)
            attacked = attack.apply(frame, targets, np.random.default_rng(index))
            out[cull] = (attacked.scan.tobytes(), attacked.image.tobytes())
        assert out[False] == out[True]
        assert out[True][0] != frame.scan.tobytes() and out[True][1] != frame.image.tobytes()
