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

The attacked frame is a :class:`~robustbench3d.kitti.dataset.LazyImageFrame`: the LiDAR render and the
camera's occlusion depth (which needs the target cars and the dataset) are done in :meth:`RoofObjectAttack.apply`,
the camera render on the first read of its ``image`` (the same bytes as rendering it at once), so a consumer
that never reads the image (a victim given ground-truth 2D boxes) never pays for it. What the deferred render
holds (:class:`CameraRender`) is data a victim may see -- the clean image, the calibration, the placed
objects' meshes and the occlusion depth at the positions the render can query -- never the labels, the
target cars, a path or the attack: the victim is handed the frame.
"""

from __future__ import annotations

import functools
import inspect
import math
import numbers
from collections.abc import Callable
from dataclasses import dataclass
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
from robustbench3d.attacks.record import ObjectRecord, added_rows, placed_object_boxes, target_rows
from robustbench3d.kitti.dataset import Frame, KittiDataset, LazyImageFrame
from robustbench3d.kitti.labels import Labels

if TYPE_CHECKING:
    from robustbench3d.kitti.calib import Calibration
    from robustbench3d.sensors.camera_depth import DepthSource

OCCLUSION_MODES = ("scan", "none")
#: The settings of :class:`RoofObjectAttack` (keyword arguments of its constructor) that every roof-object
#: factory also takes (:func:`roof_settings`), in constructor order.
SETTINGS = ("eot", "position_jitter_m", "yaw_jitter_rad", "range_noise_m", "dropout", "supersample", "occlusion",
            "cull")


#: The upper end of each numeric setting's range (the lower end is 0, supersample's 1; dropout is in [0, 1)):
#: position_jitter_m 0.5 m: the object's centre stays on the roof of a KITTI car (~1.3 m by ~1.8 m); at 1e9 m
#: it is rendered nowhere near any car and the cell would report a clean result. yaw_jitter_rad pi: +-pi
#: already covers every heading. range_noise_m 0.2 m (standard deviation, clipped at 3 sd): ten times the
#: HDL-64E's 2 cm; more moves the object's returns by more than its own size. supersample 16: 16 x 16
#: samples resolve an edge pixel's coverage to 1/256, the 8-bit image's own step; the cost grows as its
#: square (a frame of 22 cars at 16: ~10 s and 1.4 GB; 100000 would ask for petabytes).
SETTING_MAX = {"position_jitter_m": 0.5, "yaw_jitter_rad": math.pi, "range_noise_m": 0.2, "supersample": 16}
#: (upper end, range) of each numeric setting as messages write them.
_RANGE_TEXT = {"position_jitter_m": ("0.5 m", "[0, 0.5] m"), "yaw_jitter_rad": ("pi rad", "[0, pi] rad"),
               "range_noise_m": ("0.2 m", "[0, 0.2] m"), "supersample": ("16", "[1, 16]")}


def _number_problem(name: str, value: Any) -> str | None:
    """What the numeric setting ``name`` should be when ``value`` is wrong (None: it is right), with its range
    after the value: ``"<want>, got <value> (range [lo, hi] unit)"`` (:data:`SETTING_MAX`)."""
    if name == "dropout":
        return None if _is_real(value) and 0 <= value < 1 else f"a number in [0, 1), got {value!r}"
    top, (top_text, span) = SETTING_MAX[name], _RANGE_TEXT[name]
    if name == "supersample":
        low = isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_)) and value >= 1
        want = "an integer >= 1"
    else:
        low, want = _is_real(value) and value >= 0, "a finite number >= 0"
    if low and value <= top:
        return None
    return f"{f'at most {top_text}' if low else want}, got {value!r} (range {span})"


def _is_real(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_)) and bool(np.isfinite(value))


def check_settings(settings: dict[str, Any]) -> None:
    """Raise ValueError ``field '<name>': expected <what>, got <value> (range ...)`` for the first setting of
    ``settings`` (names of :data:`SETTINGS`) of the wrong type or out of its range (:data:`SETTING_MAX`; values
    as JSON gives them: true/false, numbers, strings). Checked before any frame is rendered."""
    for name, value in settings.items():
        if name in ("eot", "cull"):
            problem = None if isinstance(value, (bool, np.bool_)) else f"true or false, got {value!r}"
        elif name == "occlusion":
            ok = isinstance(value, str) and value in OCCLUSION_MODES
            problem = None if ok else f"one of {', '.join(OCCLUSION_MODES)}, got {value!r}"
        elif name in SETTINGS:
            problem = _number_problem(name, value)
        else:
            raise ValueError(f"field {name!r}: not a setting of the roof-object attack ({', '.join(SETTINGS)})")
        if problem is not None:
            raise ValueError(f"field {name!r}: expected {problem}")


class RoofObjectAttack(Attack):
    """Place ``obj`` on the roof of every target car and render it into both sensors.

    Args:
        obj: the object.
        identity: how the object was made (e.g. ``{"attack": "random-shape", "seed": 0}`` or a file's
            sidecar ``made_by``); part of :meth:`describe`.
        sha256: the object's PLY sha256 (a loaded file's); default: that of its PLY bytes.
        eot: jitter each placement (uniform +-``position_jitter_m`` in [0, 0.5] m along and across the car,
            +-``yaw_jitter_rad`` in [0, pi]), drawn from the frame's generator.
        range_noise_m, dropout: LiDAR realism passed to the renderer (off by default; [0, 0.2] m and [0, 1)).
        supersample: camera samples per pixel side, 1 to 16 (:data:`SETTING_MAX` says why).
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
        """(rect vertices (V, 3), pose) of the object on each target car, in label order (V: the object family's
        vertex count, 162 for the default family)."""
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
        return self.apply_recorded(frame, targets, rng)[0]

    def apply_recorded(self, frame: Frame, targets: Labels, rng: np.random.Generator) -> tuple[Frame, ObjectRecord]:
        """The attacked frame (what :meth:`apply` returns: the one code path) and the record of each placement:
        the image-2 box of the object's bounds box as placed and the rows of the attacked scan the render added
        for that car (:mod:`robustbench3d.attacks.record`). The record is kept apart from the frame."""
        if len(targets) == 0:
            return frame, ObjectRecord.empty()
        from robustbench3d.attacks.depth_cache import depth_for_render
        from robustbench3d.sensors.lidar_render import render_lidar
        from robustbench3d.sensors.pattern_cache import default_pattern_cache

        placed = self.place(targets, rng)
        faces, colors = self.obj.faces.copy(), self.obj.colors.copy()  # writable: the renderers wrap them in torch
        velo = [(frame.calib.rect_to_velo_points(v), faces, colors) for v, _ in placed]
        lidar = render_lidar(frame.scan, velo, rng=rng, range_noise_m=self.range_noise_m, dropout=self.dropout,
                             patterns=default_pattern_cache(), cull=self.cull)
        scan = np.ascontiguousarray(lidar.scan, dtype=frame.scan.dtype)
        vertices = [v for v, _ in placed]
        # The exact depth needs the targets and the dataset: fetched now (a cache file read once warm), and
        # whatever the render can ask beyond its crops is asked now, so the deferred render holds data only.
        depth = depth_for_render(self.scene_depth(frame, targets), frame.calib, vertices, frame.image_size,
                                 self.supersample)
        render = CameraRender(
            photo=frame.make_image if isinstance(frame, LazyImageFrame) else frame.image, calib=frame.calib,
            meshes=tuple((v, faces, colors) for v in vertices), scene_depth=depth, supersample=self.supersample,
            full_image=not self.cull)
        record = ObjectRecord(
            placed_object_boxes(self.obj.bounds, [pose for _, pose in placed], frame.calib, frame.image_size),
            added_rows(len(frame.scan), len(lidar.removed_index), lidar.object_index, len(placed)),
            target_rows(frame.labels, targets))
        return LazyImageFrame(frame.frame_id, scan, frame.calib, frame.labels, frame.image_size, render), record

    def describe(self) -> dict[str, Any]:
        """Object, placement and sensor settings; the jitter ranges appear with EOT on or when not the defaults,
        ``cull`` only when off, the object's family (its template record) only when not the default one (so the
        defaults describe the attack as they did before these settings existed)."""
        jitter = {"position_jitter_m": self.position_jitter_m, "yaw_jitter_rad": self.yaw_jitter_rad}
        family = self.obj.family
        return {
            "object": {"ply_sha256": self.sha256, "made_by": self.identity,
                       "bounds": [float(b) for b in self.obj.bounds],
                       **({} if family.is_default else {"template": {"name": family.name, **family.record()}})},
            "placement": {"rule": PLACEMENT_RULE, "eot": self.eot,
                          **(jitter if self.eot or (self.position_jitter_m, self.yaw_jitter_rad)
                             != (POSITION_JITTER_M, YAW_JITTER_RAD) else {})},
            "lidar": {"range_noise_m": self.range_noise_m, "dropout": self.dropout},
            "camera": {"supersample": self.supersample, "occlusion": self.occlusion},
            **({} if self.cull else {"cull": False}),
        }


@dataclass(frozen=True, eq=False)
class CameraRender:
    """The deferred camera render of an attacked frame (its ``make_image``), holding data only, fixed when the
    frame is attacked (whatever changes the attack later): a victim given the frame can reach all of it.

    Attributes:
        photo: the clean (H, W, 3) uint8 image, or the clean frame's own deferred image (e.g. its
            :class:`~robustbench3d.kitti.dataset.EncodedImage`).
        calib: the frame's calibration.
        meshes: per placed object its rect vertices (V, 3), faces (F, 3) and colours (V, 3).
        scene_depth: the occlusion depth, data only (:func:`~robustbench3d.attacks.depth_cache.depth_for_render`),
            or None (no occlusion).
        supersample, full_image: as :func:`~robustbench3d.sensors.camera_render.render_camera` takes them.
    """

    photo: np.ndarray | Callable[[], np.ndarray]
    calib: Calibration
    meshes: tuple[tuple[np.ndarray, np.ndarray, np.ndarray], ...]
    scene_depth: DepthSource | None
    supersample: int
    full_image: bool

    def __call__(self) -> np.ndarray:
        from robustbench3d.sensors.camera_render import render_camera

        photo = self.photo() if callable(self.photo) else self.photo
        return render_camera(photo, self.calib, list(self.meshes), scene_depth=self.scene_depth,
                             supersample=self.supersample, full_image=self.full_image).image


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
