"""Exact camera-2 scene depth of the embedded (procedural) dataset, for the camera renderer's occlusion.

A :class:`robustbench3d.sensors.camera_depth.DepthSource` (see that module for the depth convention):
the frame's scene is rebuilt from the generator's seed and frame index (:func:`synth_scene_depth`;
:func:`dataset_scene_depth` reads the seed from the dataset's ``synth_manifest.json``) and each query
position gets its own Embree ray from the camera-2 centre, exactly as the generator's camera casts them
(float32 Embree, so depths agree to about 1e-5 relative). It lives in synth (which may import sensors)
because it needs the generator's scene.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from robustbench3d.errors import DataFormatError
from robustbench3d.kitti.calib import Calibration
from robustbench3d.sensors.camera_depth import camera_centre_rect, pixel_rays_rect

if TYPE_CHECKING:
    from robustbench3d.synth.raytrace import SceneGeometry
    from robustbench3d.synth.scene import Scene


class SceneRayDepth:
    """Exact camera-2 depth of a procedural scene: one Embree ray per query (see the module docstring).

    Attributes:
        lighting: the scene's sun and sky (:class:`robustbench3d.sensors.camera_model.Lighting`), used by the
            camera renderer to shade objects like the scene.
    """

    def __init__(self, scene: Scene, geometry: SceneGeometry | None = None):
        from robustbench3d.synth.raytrace import SceneGeometry

        self.scene = scene
        self.calib: Calibration = scene.calib
        self.lighting = scene.lighting
        self.geometry = geometry if geometry is not None else SceneGeometry(scene)
        self._origin_velo = self.calib.rect_to_velo_points(camera_centre_rect(self.calib)[None])[0]

    def depth(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        calib = self.calib
        d = pixel_rays_rect(calib, u, v) @ calib.rect_to_velo[:3, :3].T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        hits = self.geometry.intersect(self._origin_velo, d, 2000.0)
        out = np.full(len(d), np.inf)
        hit = hits.hit
        p = self._origin_velo + hits.t[hit, None].astype(np.float64) * d[hit]
        out[hit] = calib.rect_to_image(calib.velo_to_rect_points(p))[1]
        return out


def synth_scene_depth(seed: int, index: int) -> SceneRayDepth:
    """The exact depth source of frame ``index`` of the procedural dataset generated with ``seed``."""
    from robustbench3d.synth.frame import frame_generators
    from robustbench3d.synth.layout import sample_scene

    scene_rng, _, _ = frame_generators(seed, index)
    return SceneRayDepth(sample_scene(scene_rng))


def dataset_scene_depth(root: str | Path, frame_id: str) -> SceneRayDepth:
    """:func:`synth_scene_depth` of frame ``frame_id`` ('000123') of the generated dataset in ``root``.

    The seed comes from ``root/synth_manifest.json``, which must come from this generator version; the
    rebuilt scene must match the frame's files where they exist (calib P2; every label's box location).
    """
    from robustbench3d.kitti.calib import read_calibration
    from robustbench3d.kitti.labels import read_labels
    from robustbench3d.synth.writer import GENERATOR_VERSION, MANIFEST

    root = Path(root)
    path = root / MANIFEST
    if not path.is_file():
        raise DataFormatError(path, "not found: exact scene depth needs a dataset made by 'robustbench3d data synth'")
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataFormatError(path, f"not valid JSON ({exc})") from None
    if not isinstance(manifest, dict) or manifest.get("generator") != "robustbench3d.synth":
        raise DataFormatError(path, "not a robustbench3d.synth manifest", field="generator")
    if manifest.get("version") != GENERATOR_VERSION:
        raise DataFormatError(path, f"generator version {manifest.get('version')!r}, this robustbench3d "
                              f"rebuilds version {GENERATOR_VERSION}", field="version")
    seed = manifest.get("seed")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise DataFormatError(path, f"expected a non-negative integer, got {seed!r}", field="seed")
    if not (isinstance(frame_id, str) and frame_id.isdigit()):
        raise ValueError(f"dataset_scene_depth: field 'frame_id': expected digits like '000123', got {frame_id!r}")
    source = synth_scene_depth(seed, int(frame_id))
    train = root / "training"
    calib_path = train / "calib" / f"{frame_id}.txt"
    if calib_path.is_file() and not np.allclose(read_calibration(calib_path).P2, source.calib.P2, rtol=1e-9, atol=1e-9):
        raise DataFormatError(calib_path, f"P2 differs from the scene rebuilt from seed {seed}", field="P2")
    label_path = train / "label_2" / f"{frame_id}.txt"
    if label_path.is_file():
        labels = read_labels(label_path)
        boxes = np.array([o.location for o in source.scene.objects if o.labelled]).reshape(-1, 3)
        for i in np.flatnonzero(labels.type != "DontCare"):
            if not len(boxes) or np.abs(boxes - labels.location[i]).max(axis=1).min() > 0.006:
                raise DataFormatError(label_path, f"no object of the scene rebuilt from seed {seed} is at "
                                      f"{labels.location[i].tolist()}", i + 1, "location")
    return source
