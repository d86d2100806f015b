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
hides nothing. A frame without targets is returned as is. ``cull=False`` renders the full scene instead of
the culled rays and pixels (every LiDAR ray at every face, the whole image): the reference the culling is
measured against, the same frame bit for bit at a far higher cost.

Every roof-object factory of the registry takes the attack's settings (:data:`SETTINGS`) as keyword
arguments, through one decorator (:func:`roof_settings`): ``run --attack-arg adv-object:dropout=0.05``.

The attacked frame is a :class:`~robustbench3d.kitti.dataset.LazyImageFrame`: the LiDAR render is done in
:meth:`RoofObjectAttack.apply`, the camera render (and the scene depth it needs) on the first read of its
``image`` (the same bytes as rendering it at once), so a consumer that never reads the image (a victim
given ground-truth 2D boxes) never pays for it.
"""

from __future__ import annotations

import copy
import functools
import inspect
import numbers
from collections.abc import Callable
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
#: The settings of :class:`RoofObjectAttack` (keyword arguments of its constructor) that every roof-object
#: factory also takes (:func:`roof_settings`), in constructor order.
SETTINGS = ("eot", "position_jitter_m", "yaw_jitter_rad", "range_noise_m", "dropout", "supersample", "occlusion",
            "cull")


def check_settings(settings: dict[str, Any]) -> None:
    """Raise ValueError ``field '<name>': <problem>`` for the first setting of ``settings`` (names of
    :data:`SETTINGS`) of the wrong type or out of range (values as JSON gives them: true/false, numbers, strings)."""
    for name, value in settings.items():
        if name in ("eot", "cull"):
            ok, want = isinstance(value, (bool, np.bool_)), "true or false"
        elif name == "supersample":
            ok = isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_)) and value >= 1
            want = "an integer >= 1"
        elif name == "occlusion":
            ok, want = isinstance(value, str) and value in OCCLUSION_MODES, f"one of {', '.join(OCCLUSION_MODES)}"
        elif name in SETTINGS:
            real = isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_)) and np.isfinite(value)
            if name == "dropout":
                ok, want = real and 0 <= value < 1, "a number in [0, 1)"
            else:
                ok, want = real and value >= 0, "a finite number >= 0"
        else:
            raise ValueError(f"field {name!r}: not a setting of the roof-object attack ({', '.join(SETTINGS)})")
        if not ok:
            raise ValueError(f"field {name!r}: expected {want}, got {value!r}")


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
        cull: render only the rays and pixels the objects can reach (default); False: the full-scene reference
            (module doc).

    Settings of the wrong type or out of range raise ValueError naming the field (:func:`check_settings`).
    """

    def __init__(self, obj: RoofObject, *, identity: dict[str, Any] | None = None, sha256: str | None = None,
                 eot: bool = False, position_jitter_m: float = POSITION_JITTER_M,
                 yaw_jitter_rad: float = YAW_JITTER_RAD, range_noise_m: float = 0.0, dropout: float = 0.0,
                 supersample: int = 3, occlusion: str = "scan", cull: bool = True) -> None:
        check_settings({"eot": eot, "position_jitter_m": position_jitter_m, "yaw_jitter_rad": yaw_jitter_rad,
                        "range_noise_m": range_noise_m, "dropout": dropout, "supersample": supersample,
                        "occlusion": occlusion, "cull": cull})
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
        self.cull = bool(cull)
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
                             patterns=default_pattern_cache(), cull=self.cull)
        scan = np.ascontiguousarray(lidar.scan, dtype=frame.scan.dtype)
        rect = [(v, faces, colors) for v, _ in placed]
        settings = copy.copy(self)  # the image is this call's, whatever changes the attack later

        def camera_image() -> np.ndarray:
            return render_camera(frame.image, frame.calib, rect, scene_depth=settings.scene_depth(frame, targets),
                                 supersample=settings.supersample, full_image=not settings.cull).image

        return LazyImageFrame(frame.frame_id, scan, frame.calib, frame.labels, frame.image_size, camera_image)

    def describe(self) -> dict[str, Any]:
        """Object, placement and sensor settings; the jitter ranges appear with EOT on or when not the defaults,
        ``cull`` only when off (so the defaults describe the attack as they did before these settings existed)."""
        jitter = {"position_jitter_m": self.position_jitter_m, "yaw_jitter_rad": self.yaw_jitter_rad}
        return {
            "object": {"ply_sha256": self.sha256, "made_by": self.identity,
                       "bounds": [float(b) for b in self.obj.bounds]},
            "placement": {"rule": PLACEMENT_RULE, "eot": self.eot,
                          **(jitter if self.eot or (self.position_jitter_m, self.yaw_jitter_rad)
                             != (POSITION_JITTER_M, YAW_JITTER_RAD) else {})},
            "lidar": {"range_noise_m": self.range_noise_m, "dropout": self.dropout},
            "camera": {"supersample": self.supersample, "occlusion": self.occlusion},
            **({} if self.cull else {"cull": False}),
        }


def settings_parameters() -> list[inspect.Parameter]:
    """The keyword-only parameters of :data:`SETTINGS`, with :class:`RoofObjectAttack`'s defaults."""
    params = inspect.signature(RoofObjectAttack.__init__).parameters
    return [params[name].replace(kind=inspect.Parameter.KEYWORD_ONLY) for name in SETTINGS]


def roof_settings(factory: Callable[..., RoofObjectAttack]) -> Callable[..., RoofObjectAttack]:
    """Decorator of a registry factory ``(own params, **settings) -> RoofObjectAttack`` that passes the settings
    on to the attack: the signature :meth:`~robustbench3d.attacks.spec.AttackSpec.create` binds gains every
    :data:`SETTINGS` keyword with the constructor's default (other names are refused as unknown parameters), and
    a value of the wrong type or out of range raises :class:`~robustbench3d.attacks.spec.AttackSpecError`
    ``field '<name>': ...`` before the factory runs."""
    from robustbench3d.attacks.spec import AttackSpecError

    own = [p for p in inspect.signature(factory).parameters.values() if p.kind is not inspect.Parameter.VAR_KEYWORD]
    signature = inspect.Signature(own + settings_parameters(), return_annotation="RoofObjectAttack")

    @functools.wraps(factory)
    def wrapper(*args: Any, **kwargs: Any) -> RoofObjectAttack:
        bound = signature.bind(*args, **kwargs)  # TypeError for unknown names, as calling a plain function
        settings = {k: bound.arguments.pop(k) for k in SETTINGS if k in bound.arguments}
        try:
            check_settings(settings)
        except ValueError as exc:
            raise AttackSpecError(str(exc)) from None
        return factory(*bound.args, **bound.kwargs, **settings)

    wrapper.__signature__ = signature  # type: ignore[attr-defined]
    return wrapper
