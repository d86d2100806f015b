"""Exact camera occlusion on the embedded dataset, cached per frame on disk.

A frame alone does not say which procedural scene it came from, so :meth:`RoofObjectAttack.bind_dataset
<robustbench3d.attacks.roof.RoofObjectAttack.bind_dataset>` notes the dataset root; when it holds the
generator's ``synth_manifest.json`` the scene of each frame is rebuilt (:func:`dataset_scene_depth`: the
generator's Embree rays from the camera-2 centre, 0.12-0.3 s per frame) instead of approximating it
from the scan. Since the same frame is attacked once per victim x proposals x attack cell (and by
``attack apply``), the exact depths an object can need are computed once and kept in

    <cache>/scene_depth/<dataset key>/<frame id>_s<supersample>_<crop key>.npz

``dataset key`` is the sha256 (16 hex) of the manifest's generator, version and seed (which fix every
scene); ``crop key`` that of the crop geometry below. Each file holds, per target car, the camera-2
depth at every camera sample position (s x s per pixel, as :func:`~robustbench3d.sensors.camera_render.
render_camera` casts them) of a pixel box covering any object that fits the object box (half extents
``bounds``) resting on the car's roof, placed with any EOT jitter up to ``margin_m`` (the box is the
projection of a prism of radius |(b_x, b_z)| + sqrt(2) margin_m around the roof centre, from the roof up
to 2 b_y, clipped to the image), plus the scene's lighting (the renderer shades objects with it). Depths
beyond the prism's farthest camera depth (+1 cm) are stored as +inf: no object sample is that far, so
they hide nothing either way, and the files stay small (16 kB for a frame with 8 cars). Files are written
atomically and read when present. A query outside every cached box (a car straddling the
camera plane, an object larger than its bounds) is answered by the exact provider, built on demand:
the cache changes speed, never values.
"""

from __future__ import annotations

import hashlib
import io
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from robustbench3d.attacks.placement import cars_of
from robustbench3d.errors import DataFormatError
from robustbench3d.fileio import atomic_write_bytes
from robustbench3d.kitti.calib import Calibration
from robustbench3d.kitti.labels import Labels

if TYPE_CHECKING:
    from robustbench3d.sensors.camera_depth import DepthSource
    from robustbench3d.synth.scene import Lighting

CACHE_VERSION = 1
#: Depths farther than the farthest point an object can reach plus this are stored as +inf.
FAR_MARGIN_M = 0.01
#: Crops larger than this many pixels (e.g. a car straddling the camera plane) are not cached.
MAX_CROP_PIXELS = 200_000
_LIGHT_ARRAYS = ("sun_direction", "sun_color", "sky_zenith", "sky_horizon")
_LIGHT_FLOATS = ("ambient", "haze_distance", "exposure")


def synth_key(root: str | Path) -> str | None:
    """The dataset key of a generated dataset (module doc), or None if ``root`` has no generator manifest."""
    from robustbench3d.synth.writer import MANIFEST

    path = Path(root) / MANIFEST
    if not path.is_file():
        return None
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataFormatError(path, f"not valid JSON ({exc})") from None
    if not isinstance(manifest, dict):
        raise DataFormatError(path, "expected a JSON object")
    ident = {k: manifest.get(k) for k in ("generator", "version", "seed")}
    return hashlib.sha256(json.dumps(ident, sort_keys=True).encode()).hexdigest()[:16]


def sample_offsets(supersample: int) -> np.ndarray:
    """Sub-pixel sample offsets of one axis, as the camera renderer places them."""
    return (np.arange(supersample) + 0.5) / supersample - 0.5


def roof_crop(calib: Calibration, roof_centre: np.ndarray, bounds: np.ndarray, margin_m: float,
              image_size: tuple[int, int]) -> tuple[tuple[int, int, int, int], float] | None:
    """Pixel box (u0, v0, u1, v1), half-open, that any object within ``bounds`` on this roof can reach
    (module doc), and the largest camera-2 depth such an object can have; None if the region is behind
    or straddles the camera, misses the image or exceeds :data:`MAX_CROP_PIXELS`."""
    from robustbench3d.sensors.camera_render import mesh_box

    r = float(np.hypot(bounds[0], bounds[2])) + np.sqrt(2.0) * margin_m
    ang = np.linspace(0.0, 2 * np.pi, 16, endpoint=False)
    ring = np.stack([np.cos(ang), np.zeros_like(ang), np.sin(ang)], axis=1) * (r / np.cos(np.pi / 16))
    prism = np.concatenate([roof_centre + ring, roof_centre + ring - [0.0, 2 * float(bounds[1]), 0.0]])
    box, status = mesh_box(calib, prism, image_size)
    if box is None or status != "rendered" or (box[2] - box[0]) * (box[3] - box[1]) > MAX_CROP_PIXELS:
        return None
    depth = calib.rect_to_image(prism)[1]
    if np.any(depth <= 1e-6):
        return None  # straddles the camera plane
    return box, float(depth.max())


@dataclass(eq=False)
class CroppedDepth:
    """A :class:`DepthSource` answering from per-car crops of exact depths (module doc).

    Attributes:
        supersample: samples per pixel side the crops hold.
        boxes: (K, 4) int64 crop boxes (u0, v0, u1, v1), farthest +inf cut first (a query reads the first
            box holding it).
        depths: per box a ((v1 - v0) * s, (u1 - u0) * s) float64 array: row v0 * s + i holds sample row i.
        lighting: the scene's lighting (used by the renderer for shading).
        exact: builds the exact provider for queries outside the crops.
    """

    supersample: int
    boxes: np.ndarray
    depths: list[np.ndarray]
    lighting: Lighting
    exact: Any
    _fallback: DepthSource | None = field(default=None, repr=False)

    def depth(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        u, v = np.asarray(u, np.float64), np.asarray(v, np.float64)
        s = self.supersample
        # Sample grid index: position p = pixel + offset, offset = (j + 0.5) / s - 0.5 -> p * s + (s - 1) / 2.
        gu, gv = u * s + (s - 1) / 2, v * s + (s - 1) / 2
        iu, iv = np.rint(gu).astype(np.int64), np.rint(gv).astype(np.int64)
        on_grid = (np.abs(gu - iu) < 1e-6) & (np.abs(gv - iv) < 1e-6)
        out = np.full(len(u), np.nan)
        todo = np.flatnonzero(on_grid)  # queries still without a depth (the boxes shrink it)
        for (u0, v0, u1, v1), d in zip(self.boxes, self.depths, strict=True):
            tu, tv = iu[todo], iv[todo]
            k = (tu >= u0 * s) & (tu < u1 * s) & (tv >= v0 * s) & (tv < v1 * s)
            got = d[tv[k] - v0 * s, tu[k] - u0 * s]
            out[todo[k]] = got
            left = ~k
            left[k] = np.isnan(got)
            todo = todo[left]
        missing = np.isnan(out)
        if missing.any():
            if self._fallback is None:
                self._fallback = self.exact()
            out[missing] = self._fallback.depth(u[missing], v[missing])
        return out


def _encode(boxes: np.ndarray, depths: list[np.ndarray], lighting: Lighting, supersample: int) -> bytes:
    arrays: dict[str, np.ndarray] = {"version": np.array(CACHE_VERSION), "supersample": np.array(supersample),
                                     "boxes": boxes.reshape(-1, 4).astype(np.int64)}
    arrays.update({f"depth_{i}": d for i, d in enumerate(depths)})
    arrays.update({f"light_{k}": np.asarray(getattr(lighting, k), np.float64) for k in _LIGHT_ARRAYS + _LIGHT_FLOATS})
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


def _decode(path: Path) -> tuple[int, np.ndarray, list[np.ndarray], Lighting] | None:
    """The cached crops of ``path``, or None if the file is unreadable or of another cache version."""
    from robustbench3d.synth.scene import Lighting

    try:
        with np.load(path) as z:
            if int(z["version"]) != CACHE_VERSION:
                return None
            boxes = z["boxes"]
            depths = [z[f"depth_{i}"] for i in range(len(boxes))]
            light = Lighting(**{k: z[f"light_{k}"] for k in _LIGHT_ARRAYS},
                             **{k: float(z[f"light_{k}"]) for k in _LIGHT_FLOATS})
            return int(z["supersample"]), boxes, depths, light
    except (OSError, KeyError, ValueError):
        return None


def crop_key(bounds: np.ndarray, margin_m: float) -> str:
    """Key of the crop geometry (module doc)."""
    text = json.dumps({"bounds": [round(float(b), 9) for b in bounds], "margin_m": round(float(margin_m), 9)})
    return hashlib.sha256(text.encode()).hexdigest()[:8]


def cached_scene_depth(root: Path, dataset_key: str, frame_id: str, calib: Calibration, targets: Labels,
                       image_size: tuple[int, int], supersample: int, bounds: np.ndarray, margin_m: float,
                       cache_root: Path | None = None) -> CroppedDepth:
    """The exact scene depth of frame ``frame_id`` around its target cars' roofs, from the cache or
    computed (one scene rebuild) and cached (module doc)."""
    from robustbench3d.paths import cache_dir

    base = (cache_root or cache_dir()) / "scene_depth" / dataset_key
    path = base / f"{frame_id}_s{supersample}_{crop_key(bounds, margin_m)}.npz"
    exact = _ExactFactory(root, frame_id)
    found = _decode(path) if path.is_file() else None
    if found is not None and found[0] == supersample:
        return CroppedDepth(supersample, found[1], found[2], found[3], exact)
    source = exact()
    off = sample_offsets(supersample)
    boxes, depths, fars = [], [], []
    for car in cars_of(targets):
        crop = roof_crop(calib, car.roof_centre, bounds, margin_m, image_size)
        if crop is None:
            continue
        box, far = crop
        u0, v0, u1, v1 = box
        su = (np.arange(u0, u1)[:, None] + off[None, :]).reshape(-1)
        sv = (np.arange(v0, v1)[:, None] + off[None, :]).reshape(-1)
        gu, gv = np.meshgrid(su, sv)
        d = source.depth(gu.reshape(-1), gv.reshape(-1)).reshape(gv.shape)
        d[d > far + FAR_MARGIN_M] = np.inf  # beyond any object: hides nothing either way (compresses well)
        depths.append(d)
        fars.append(far)
        boxes.append(box)
    # Farthest crop first: where crops overlap, a query reads the one whose +inf cut is the farthest, so
    # the object of any of them sees exact depths (a nearer car's crop cuts closer).
    order = np.argsort(-np.array(fars, dtype=np.float64), kind="stable")
    depths = [depths[i] for i in order]
    box_arr = np.array(boxes, dtype=np.int64).reshape(-1, 4)[order]
    base.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, _encode(box_arr, depths, source.lighting, supersample))
    return CroppedDepth(supersample, box_arr, depths, source.lighting, exact, source)


@dataclass(frozen=True)
class _ExactFactory:
    """Builds the exact provider of one frame (a scene rebuild) when called."""

    root: Path
    frame_id: str

    def __call__(self) -> Any:
        from robustbench3d.synth.scene_depth import dataset_scene_depth

        return dataset_scene_depth(self.root, self.frame_id)


__all__ = ["CACHE_VERSION", "CroppedDepth", "cached_scene_depth", "crop_key", "roof_crop", "sample_offsets",
           "synth_key"]
