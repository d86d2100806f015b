"""Scene building blocks: vehicle meshes, size statistics, road coordinates, annotation rules."""

from __future__ import annotations

import numpy as np
import pytest

from robustbench3d.kitti import Labels, parse_labels
from robustbench3d.synth import materials as mt
from robustbench3d.synth.annotate import difficulty, occlusion_level
from robustbench3d.synth.layout import car_style_for, sample_car_size, sample_scene
from robustbench3d.synth.materials import Mat
from robustbench3d.synth.road import sample_road
from robustbench3d.synth.vehicles import CAR_STYLES, car_mesh
from robustbench3d.synth.writer import label_text


def _volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    return abs(np.einsum("ij,ij->i", a, np.cross(b, c)).sum()) / 6.0


@pytest.mark.parametrize("style", CAR_STYLES)
def test_car_mesh_fills_its_box_and_has_a_car_silhouette(style):
    rng = np.random.default_rng(3)
    l, w, h = 4.1, 1.7, 1.5
    m = car_mesh(l, w, h, style, mt.pick(rng, mt.CAR_PAINT), rng)
    lo, hi = m.bounds()
    np.testing.assert_array_equal(lo, [-l / 2, -w / 2, 0.0])
    np.testing.assert_array_equal(hi, [l / 2, w / 2, h])
    body = m.material != Mat.TYRE
    # not a box: the body (without wheels) fills well under the box volume
    assert _volume(m.vertices, m.faces[body & (m.material != Mat.RIM)]) < 0.8 * l * w * h
    v = m.vertices
    front = v[:, 0] > 0.45 * l
    top = v[:, 2] > 0.97 * h
    assert v[front, 2].max() < 0.8 * h  # hood / nose well below the roof
    assert np.abs(v[top, 1]).max() < 0.45 * w  # the cabin narrows towards the roof
    for mat in (Mat.GLASS, Mat.TYRE, Mat.HEADLIGHT, Mat.TAILLIGHT):
        assert (m.material == mat).any()
    assert np.all(m.color[m.material == Mat.TYRE].max(axis=1) < 0.05)  # dark wheels and windows
    assert np.all(m.color[m.material == Mat.GLASS].max(axis=1) < 0.05)


def test_car_sizes_follow_kitti_statistics():
    rng = np.random.default_rng(0)
    lwh = np.array([sample_car_size(rng) for _ in range(20000)])
    np.testing.assert_allclose(lwh.mean(axis=0), [3.88, 1.63, 1.53], atol=0.02)
    np.testing.assert_allclose(lwh.std(axis=0), [0.40, 0.10, 0.14], atol=0.02)
    styles = [car_style_for(x, rng) for x in lwh[:2000]]
    assert set(styles) == set(CAR_STYLES)


def test_road_coordinates_round_trip():
    rng = np.random.default_rng(5)
    for _ in range(20):
        road = sample_road(rng)
        s = rng.uniform(-40, 100, 200)
        d = rng.uniform(-25, 25, 200)
        x, y, _ = road.to_velo(s, d)
        s2, d2 = road.to_road(x, y)
        np.testing.assert_allclose(s2, s, atol=1e-6)
        np.testing.assert_allclose(d2, d, atol=1e-6)
        # the sensor stands at the ego offset, 1.73 m above the ground
        s0, d0 = road.to_road(np.zeros(1), np.zeros(1))
        assert s0[0] == pytest.approx(0, abs=1e-9) and d0[0] == pytest.approx(road.ego_offset)
        assert road.ground_z(np.zeros(1), np.zeros(1))[0] == pytest.approx(-1.73)


def test_difficulty_groups_follow_the_kitti_rules():
    #                      easy   mod(h) mod(occ) mod(tr) hard(occ) hard(tr) ign(h) ign(tr) edge-easy
    height = np.array([50.0, 30.0, 45.0, 45.0, 45.0, 45.0, 24.9, 45.0, 40.0])
    occluded = np.array([0, 0, 1, 0, 2, 0, 0, 0, 0])
    truncated = np.array([0.0, 0.0, 0.0, 0.2, 0.0, 0.4, 0.0, 0.6, 0.15])
    assert list(difficulty(height, occluded, truncated)) == [0, 1, 1, 1, 2, 2, 3, 3, 0]


def test_occlusion_levels():
    assert [occlusion_level(f) for f in (0.0, 0.099, 0.1, 0.49, 0.5, 0.99)] == [0, 0, 1, 1, 2, 2]


def test_label_text_is_kitti_formatted():
    labels = Labels(
        type=np.array(["Car", "DontCare"], dtype=object), truncated=np.array([0.12, -1.0]),
        occluded=np.array([1, -1]), alpha=np.array([-1.57, -10.0]),
        bbox=np.array([[10.0, 20.5, 100.25, 80.0], [503.89, 169.71, 590.61, 190.13]]),
        dimensions=np.array([[1.5, 1.6, 3.9], [-1, -1, -1]]), location=np.array([[1.0, 1.7, 20.0], [-1000] * 3]),
        rotation_y=np.array([-1.52, -10.0]))
    text = label_text(labels)
    assert text.splitlines() == [
        "Car 0.12 1 -1.57 10.00 20.50 100.25 80.00 1.50 1.60 3.90 1.00 1.70 20.00 -1.52",
        "DontCare -1 -1 -10 503.89 169.71 590.61 190.13 -1 -1 -1 -1000 -1000 -1000 -10",
    ]
    back = parse_labels(text)
    assert np.array_equal(back.bbox, labels.bbox) and list(back.type) == ["Car", "DontCare"]


def test_scene_contents_are_varied_and_headings_mostly_road_aligned():
    kinds: dict[str, int] = {}
    aligned = []
    for i in range(3):
        scene = sample_scene(np.random.default_rng([99, i]))
        for o in scene.objects:
            kinds[o.kind] = kinds.get(o.kind, 0) + 1
        road = scene.road
        for o in scene.objects:
            if o.kind == "Car":
                x, y = o.mesh.vertices[:, :2].mean(axis=0)
                s, _ = road.to_road(np.array([x]), np.array([y]))
                _, _, road_yaw = road.to_velo(s, np.zeros(1))
                fwd = scene.calib.rect_to_velo[:3, :3] @ np.array([np.cos(o.rotation_y), 0, -np.sin(o.rotation_y)])
                diff = np.arctan2(fwd[1], fwd[0]) - road_yaw[0]
                aligned.append(abs(np.sin(diff)) < np.sin(np.radians(15)))
    for kind in ("Car", "building", "tree", "pole", "ground", "sidewalk"):
        assert kinds.get(kind, 0) > 0, kind
    assert kinds["Car"] >= 30
    assert np.mean(aligned) > 0.6
