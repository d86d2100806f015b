"""One synthetic KITTI frame as a pure function of (seed, frame index)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from robustbench3d.kitti.calib import Calibration
from robustbench3d.kitti.labels import Labels
from robustbench3d.synth.annotate import ObjectAnnotation, annotate
from robustbench3d.synth.camera import render_image
from robustbench3d.synth.layout import sample_scene
from robustbench3d.synth.lidar import simulate_scan
from robustbench3d.synth.raytrace import SceneGeometry
from robustbench3d.synth.scene import Scene


@dataclass(frozen=True, eq=False)
class SynthFrame:
    """A generated frame: the four KITTI files' contents plus the ground truth behind them.

    Attributes:
        image: (H, W, 3) uint8 camera-2 image.
        scan: (N, 4) float32 velodyne scan (x, y, z in m, reflectance), KITTI ring order.
        calib: the frame's calibration.
        labels: KITTI labels (rect frame), DontCare lines last.
        scene: the scene the sensors saw (meshes in the velodyne frame).
        object_id: (H, W) int32 index into ``scene.objects`` seen at each pixel (-1 sky).
        point_object: (N,) int32 index into ``scene.objects`` of each scan point.
        annotations: the annotator's record for every object of a labelled kind.
    """

    image: np.ndarray
    scan: np.ndarray
    calib: Calibration
    labels: Labels
    scene: Scene
    object_id: np.ndarray
    point_object: np.ndarray
    annotations: list[ObjectAnnotation]


def frame_generators(seed: int, index: int) -> tuple[np.random.Generator, np.random.Generator, np.random.Generator]:
    """Independent Generators (scene, LiDAR, camera) of frame ``index``, seeded from [seed, index]."""
    children = np.random.SeedSequence([int(seed), int(index)]).spawn(3)
    scene_rng, lidar_rng, camera_rng = (np.random.default_rng(c) for c in children)
    return scene_rng, lidar_rng, camera_rng


def generate_frame(seed: int, index: int) -> SynthFrame:
    """Generate frame ``index`` of the dataset with ``seed`` (deterministic, independent of other frames)."""
    scene_rng, lidar_rng, camera_rng = frame_generators(seed, index)
    scene = sample_scene(scene_rng)
    geometry = SceneGeometry(scene)
    scan, point_object = simulate_scan(scene, geometry, lidar_rng)
    image, object_id = render_image(scene, geometry, camera_rng)
    labels, records = annotate(scene, geometry, object_id, point_object)
    return SynthFrame(image, scan, scene.calib, labels, scene, object_id, point_object, records)
