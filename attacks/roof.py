"""The roof-object attack: one :class:`~robustbench3d.attacks.object.RoofObject` on every target car.

Per frame: the object is placed on each target car (:func:`~robustbench3d.attacks.placement.place_on_roof`,
with EOT jitter drawn from the frame's generator when enabled, one draw per car in label order),
rendered into the scan (:func:`robustbench3d.sensors.lidar_render.render_lidar`, velodyne frame; the clean
scan's beam pattern is estimated once per scan and kept, :mod:`robustbench3d.sensors.pattern_cache`) and
into image 2 (:func:`robustbench3d.sensors.camera_render.render_camera`, rect frame); all objects of a
frame are rendered together, so objects overlapping in a beam or a pixel resolve by depth. A car whose
object is behind the camera or projects outside the image gets no camera render but keeps its LiDAR
returns. Camera occlusion by nearer scene geometry (``occlusion="scan"``, the default) is exact on a
dataset made by the procedural generator once :meth:`RoofObjectAttack.bind_dataset` has seen it (its
``synth_manifest.json``): the frame's scene is rebuilt and its depths around the roofs are cached on disk
(:mod:`robustbench3d.attacks.depth_cache`); on any other dataset, or without a bound dataset, it is the
clean scan's depth map (:func:`robustbench3d.sensors.camera_depth.lidar_depth_map`); ``occlusion="none"``
hides nothing. A frame without targets is returned as is.

The attacked frame is a :class:`~robustbench3d.kitti.dataset.LazyImageFrame`: the LiDAR render is done in
:meth:`RoofObjectAttack.apply`, the camera render (and the scene depth it needs) on the first read of its
``image`` (the same bytes as rendering it at once), so a consumer that never reads the image (a victim
given ground-truth 2D boxes) never pays for it.
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from robustbench3d.attacks.base import Attack
from robustbench3d.attacks.object import RoofObject
from robustbench3d.attacks.objectfile import object_sha256
from robustbench3d.attacks.placement import (
    PLACEMENT_RULE,
    POSITION_JITTER_M,
    YAW_JITTER_RAD,
    Pose,
    cars_of,
    place_on_roof,
    sample_jitter,
)
from robustbench3d.kitti.dataset import Frame, KittiDataset, LazyImageFrame
from robustbench3d.kitti.labels import Labels

if TYPE_CHECKING:
    from robustbench3d.sensors.camera_depth import DepthSource

OCCLUSION_MODES = ("scan", "none")


class RoofObjectAttack(Attack):
    """Place ``obj`` on the roof of every target car and render it into both sensors.

    Args:
        obj: the object.
        identity: how the object was made (e.g. ``{"attack": "random-shape", "seed": 0}`` or a file's
            sidecar ``made_by``); part of :meth:`describe`.
        sha256: the object's PLY sha256 (a loaded file's); default: that of its PLY bytes.
        eot: jitter each placement (uniform +-``position_jitter_m`` along and across the car,
            +-``yaw_jitter_rad``), drawn from the frame's generator.
        range_noise_m, dropout: LiDAR realism passed to the renderer (off by default).
        supersample: camera samples per pixel side.
        occlusion: camera occlusion source: "scan" (the clean scan's depth map) or "none".
    """

    def __init__(self, obj: RoofObject, *, identity: dict[str, Any] | None = None, sha256: str | None = None,
                 eot: bool = False, position_jitter_m: float = POSITION_JITTER_M,
                 yaw_jitter_rad: float = YAW_JITTER_RAD, range_noise_m: float = 0.0, dropout: float = 0.0,
                 supersample: int = 3, occlusion: str = "scan") -> None:
        if occlusion not in OCCLUSION_MODES:
            raise ValueError(f"field 'occlusion': expected one of {', '.join(OCCLUSION_MODES)}, got {occlusion!r}")
        for name, value in (("position_jitter_m", position_jitter_m), ("yaw_jitter_rad", yaw_jitter_rad),
                            ("range_noise_m", range_noise_m)):
            if not np.isfinite(value) or value < 0:
                raise ValueError(f"field '{name}': must be a finite number >= 0, got {value!r}")
        if not 0 <= dropout < 1:
            raise ValueError(f"field 'dropout': must be in [0, 1), got {dropout!r}")
        self.obj = obj
        self.identity = dict(identity or {})
        self.sha256 = sha256 or object_sha256(obj)
        self.eot = bool(eot)
        self.position_jitter_m = float(position_jitter_m)
        self.yaw_jitter_rad = float(yaw_jitter_rad)
        self.range_noise_m = float(range_noise_m)
        self.dropout = float(dropout)
        self.supersample = int(supersample)
        self.occlusion = occlusion
        self._vertices = obj.vertices()
        self._dataset: tuple[Path, str] | None = None  # (root, dataset key) of a bound generated dataset

    def bind_dataset(self, kitti: KittiDataset) -> None:
        """Use exact occlusion for ``kitti``'s frames if the procedural generator made it (module doc)."""
        from robustbench3d.attacks.depth_cache import synth_key

        key = synth_key(kitti.root)
        self._dataset = None if key is None else (Path(kitti.root).resolve(), key)

    @property
    def exact_occlusion(self) -> bool:
        """True when camera occlusion uses the rebuilt scene of a bound generated dataset."""
        return self.occlusion == "scan" and self._dataset is not None

    def place(self, targets: Labels, rng: np.random.Generator) -> list[tuple[np.ndarray, Pose]]:
        """(rect vertices (162, 3), pose) of the object on each target car, in label order."""
        placed = []
        for car in cars_of(targets):
            jitter = sample_jitter(rng, self.position_jitter_m, self.yaw_jitter_rad) if self.eot else None
            placed.append(place_on_roof(self._vertices, car, jitter))
        return placed

    def scene_depth(self, frame: Frame, targets: Labels | None = None) -> DepthSource | None:
        """The camera occlusion source of ``frame`` (module doc); ``targets`` (default: the frame's target
        cars) are the cars whose roof crops the exact source caches."""
        if self.occlusion == "none":
            return None
        if self._dataset is not None:
            from robustbench3d.attacks.base import target_cars
            from robustbench3d.attacks.depth_cache import cached_scene_depth

            root, key = self._dataset
            # The crops cover the EOT jitter whether or not it is on, so both share one cache file.
            return cached_scene_depth(root, key, frame.frame_id, frame.calib,
                                      target_cars(frame.labels) if targets is None else targets,
                                      frame.image_size, self.supersample, self.obj.bounds, self.position_jitter_m)
        from robustbench3d.sensors.camera_depth import lidar_depth_map

        return lidar_depth_map(frame.scan, frame.calib, frame.image_size)

    def apply(self, frame: Frame, targets: Labels, rng: np.random.Generator) -> Frame:
        if len(targets) == 0:
            return frame
        from robustbench3d.sensors.camera_render import render_camera
        from robustbench3d.sensors.lidar_render import render_lidar
        from robustbench3d.sensors.pattern_cache import default_pattern_cache

        placed = self.place(targets, rng)
        faces, colors = self.obj.faces.copy(), self.obj.colors.copy()  # writable: the renderers wrap them in torch
        velo = [(frame.calib.rect_to_velo_points(v), faces, colors) for v, _ in placed]
        lidar = render_lidar(frame.scan, velo, rng=rng, range_noise_m=self.range_noise_m, dropout=self.dropout,
                             patterns=default_pattern_cache())
        scan = np.ascontiguousarray(lidar.scan, dtype=frame.scan.dtype)
        rect = [(v, faces, colors) for v, _ in placed]
        settings = copy.copy(self)  # the image is this call's, whatever changes the attack later

        def camera_image() -> np.ndarray:
            return render_camera(frame.image, frame.calib, rect, scene_depth=settings.scene_depth(frame, targets),
                                 supersample=settings.supersample).image

        return LazyImageFrame(frame.frame_id, scan, frame.calib, frame.labels, frame.image_size, camera_image)

    def describe(self) -> dict[str, Any]:
        return {
            "object": {"ply_sha256": self.sha256, "made_by": self.identity,
                       "bounds": [float(b) for b in self.obj.bounds]},
            "placement": {"rule": PLACEMENT_RULE, "eot": self.eot,
                          **({"position_jitter_m": self.position_jitter_m, "yaw_jitter_rad": self.yaw_jitter_rad}
                             if self.eot else {})},
            "lidar": {"range_noise_m": self.range_noise_m, "dropout": self.dropout},
            "camera": {"supersample": self.supersample, "occlusion": self.occlusion},
        }
