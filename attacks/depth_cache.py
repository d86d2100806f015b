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

:func:`warm_scene_depths` computes the files a run will read before it needs them, in worker processes
(``attack train`` does so before its first step, :func:`robustbench3d.attacks.train_run.warm_depths`): the same
files :func:`cached_scene_depth` writes on first use (it computes them), readable ones kept, so it can be
interrupted and rerun.

An attacked frame does not keep such a source as it is (through the exact provider it reaches the dataset's
path and the whole scene: a victim given the frame must find neither): :func:`depth_for_render` keeps its
crops and, for the positions the camera render of the placed objects can query outside them
(:func:`render_positions`; none for an odd supersample and an object within its bounds), the exact
depths, asked when the frame is attacked (:class:`TabulatedDepth`) -- data only, the same values.
"""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
import zlib
from collections.abc import Callable, Sequence
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
#: What reading a missing, truncated or foreign cache file raises (numpy, zipfile, zlib).
_UNREADABLE = (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile, zlib.error)
#: Depths farther than the farthest point an object can reach plus this are stored as +inf.
FAR_MARGIN_M = 0.01
#: Crops larger than this many pixels (e.g. a car straddling the camera plane) are not cached.
MAX_CROP_PIXELS = 200_000
#: :func:`warm_scene_depths` gives each worker process at least this many frames: a worker starts in about 1.5 s
#: of CPU (Python, torch, which the crop geometry imports, the compiled kernels' cache), the time of 5 to 20
#: scene rebuilds (0.07-0.45 s each), so fewer frames per worker would cost more than they save.
FRAMES_PER_WORKER = 8
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
        exact: builds the exact provider for queries outside the crops; None where ``_fallback`` is given
            (:func:`depth_for_render`).
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
                self._fallback = self.exact()  # None only with a _fallback (depth_for_render)
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
    except _UNREADABLE:
        return None


def _readable(path: Path, supersample: int) -> bool:
    """Whether cache file ``path`` exists and its header holds this cache version, ``supersample`` and a depth
    array per box (a quick check: the arrays themselves are read when used; files are written atomically)."""
    try:
        with np.load(path) as z:
            boxes = len(z["boxes"])
            return (int(z["version"]) == CACHE_VERSION and int(z["supersample"]) == supersample
                    and all(f"depth_{i}" in z.files for i in range(boxes)))
    except _UNREADABLE:
        return False


def crop_key(bounds: np.ndarray, margin_m: float) -> str:
    """Key of the crop geometry (module doc)."""
    text = json.dumps({"bounds": [round(float(b), 9) for b in bounds], "margin_m": round(float(margin_m), 9)})
    return hashlib.sha256(text.encode()).hexdigest()[:8]


def depth_path(dataset_key: str, frame_id: str, supersample: int, bounds: np.ndarray, margin_m: float,
               cache_root: Path | None = None) -> Path:
    """The cache file of one frame's roof crops (module doc); ``cache_root`` defaults to the cache directory."""
    from robustbench3d.paths import cache_dir

    base = (cache_root or cache_dir()) / "scene_depth" / dataset_key
    return base / f"{frame_id}_s{supersample}_{crop_key(bounds, margin_m)}.npz"


def _cached(path: Path, supersample: int) -> tuple[int, np.ndarray, list[np.ndarray], Lighting] | None:
    """The crops of cache file ``path`` if it exists, reads and holds ``supersample``; else None."""
    found = _decode(path) if path.is_file() else None
    return found if found is not None and found[0] == supersample else None


def cached_scene_depth(root: Path, dataset_key: str, frame_id: str, calib: Calibration, targets: Labels,
                       image_size: tuple[int, int], supersample: int, bounds: np.ndarray, margin_m: float,
                       cache_root: Path | None = None) -> CroppedDepth:
    """The exact scene depth of frame ``frame_id`` around its target cars' roofs, from the cache or
    computed (one scene rebuild) and cached (module doc)."""
    path = depth_path(dataset_key, frame_id, supersample, bounds, margin_m, cache_root)
    base = path.parent
    exact = _ExactFactory(root, frame_id)
    found = _cached(path, supersample)
    if found is not None:
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
class DepthJob:
    """One cache file to warm (:func:`warm_scene_depths`): what :func:`cached_scene_depth` takes for a frame
    of the bound dataset (picklable, for the worker processes).

    Attributes:
        frame_id: the frame ('000123'); calib: its calibration; targets: the target cars whose roofs are
        cropped, as the consumer passes them; image_size: (width, height) px; supersample, bounds, margin_m:
        the attack's camera samples per pixel side, object half extents (m) and EOT position jitter (m).
    """

    frame_id: str
    calib: Calibration
    targets: Labels
    image_size: tuple[int, int]
    supersample: int
    bounds: tuple[float, float, float]
    margin_m: float

    def path(self, dataset_key: str, cache_root: Path | None = None) -> Path:
        return depth_path(dataset_key, self.frame_id, self.supersample, np.asarray(self.bounds, np.float64),
                          self.margin_m, cache_root)


@dataclass(frozen=True)
class WarmReport:
    """Outcome of :func:`warm_scene_depths`: cache files asked for, kept (already readable), computed (of
    which ``replaced`` replaced an unreadable or other-version file), worker processes used, wall seconds."""

    files: int
    kept: int
    computed: int
    replaced: int
    workers: int
    seconds: float


def warm_scene_depths(root: Path, dataset_key: str, jobs: Sequence[DepthJob], *, workers: int = 1,
                      cache_root: Path | None = None, progress: bool = False,
                      log: Callable[[str], None] | None = None) -> WarmReport:
    """Compute, before they are needed, the cache files of ``jobs`` (frames of the generated dataset in ``root``
    with key ``dataset_key``) that are missing or unreadable, in up to ``workers`` processes
    (:data:`robustbench3d.ranges.PROCESSES_RANGE`; at least :data:`FRAMES_PER_WORKER` frames each, one: in this
    process): each is what :func:`cached_scene_depth` would write on first
    use (the same function computes it), so a consumer then reads it and rebuilds no scene. Readable files are
    kept; each file is written atomically as soon as its frame is done, so an interrupted warm-up resumes where
    it stopped. ``log`` receives one line on what is kept, computed and replaced, and one when done; a tqdm bar
    on stderr with ``progress``. A worker's :class:`~robustbench3d.errors.RobustBenchError` (e.g. a frame
    that does not match the scene its seed rebuilds) is raised here, the other workers stopped."""
    import multiprocessing
    import sys
    import time

    from tqdm import tqdm

    from robustbench3d.errors import RobustBenchError
    from robustbench3d.paths import cache_dir
    from robustbench3d.ranges import PROCESSES_RANGE, check_range

    check_range("--workers", workers, *PROCESSES_RANGE, "worker processes")
    t0 = time.perf_counter()
    cache_root = Path(cache_root or cache_dir())
    unique = list({job.path(dataset_key, cache_root): job for job in jobs}.items())
    pending = [(p, job) for p, job in unique if not _readable(p, job.supersample)]
    replaced = sum(p.exists() for p, _ in pending)
    used = max(1, min(workers, len(pending) // FRAMES_PER_WORKER))
    say = log if log is not None else (lambda line: None)
    where = cache_root / "scene_depth" / dataset_key
    if pending:
        note = f"; replacing {replaced} unreadable or other-version file(s)" if replaced else ""
        how = "in this process" if used == 1 else f"with {used} worker processes"
        say(f"exact occlusion: the scene depths of {len(unique)} frame(s) are needed, {len(unique) - len(pending)} "
            f"cached (kept); computing {len(pending)} {how} into {where}{note}")
    tasks = [(str(root), dataset_key, job, str(cache_root)) for _, job in pending]
    bar = tqdm(total=len(tasks), unit="frame", file=sys.stderr, disable=not progress or not tasks,
               desc="scene depth", dynamic_ncols=True)
    try:
        if used == 1:
            results = map(_warm_one, tasks)
            for problem in results:
                _raise_problem(problem, RobustBenchError)
                bar.update(1)
        else:
            with multiprocessing.get_context("spawn").Pool(used) as pool:
                for problem in pool.imap_unordered(_warm_one, tasks, chunksize=1):
                    _raise_problem(problem, RobustBenchError)
                    bar.update(1)
    finally:
        bar.close()
    report = WarmReport(len(unique), len(unique) - len(pending), len(pending), replaced, used,
                        time.perf_counter() - t0)
    if pending:
        say(f"exact occlusion: computed the scene depths of {report.computed} frame(s) in {report.seconds:.1f} s")
    return report


def attack_depth_jobs(attack: Any, kitti: Any, frame_ids: Sequence[str],
                      labels: Sequence[Labels] | None = None) -> list[DepthJob]:
    """The cache files roof-object ``attack`` (a :class:`~robustbench3d.attacks.roof.RoofObjectAttack` bound
    to ``kitti``) reads for those of ``frame_ids`` that have target cars (its ``scene_depth`` key: its supersample,
    object bounds and position jitter); ``labels`` per frame as the consumer passes them (default: the frames'
    label files); none unless the attack uses exact occlusion."""
    from robustbench3d.attacks.base import target_cars

    if not attack.exact_occlusion:
        return []
    bounds = tuple(float(b) for b in attack.obj.bounds)
    jobs = []
    for i, fid in enumerate(frame_ids):
        targets = target_cars(kitti.labels(fid) if labels is None else labels[i])
        if len(targets):
            jobs.append(DepthJob(fid, kitti.calib(fid), targets, kitti.image_size(fid), attack.supersample, bounds,
                                 attack.position_jitter_m))
    return jobs


def _raise_problem(problem: str | None, error: type[Exception]) -> None:
    if problem is not None:
        raise error(problem)


def _warm_one(task: tuple[str, str, DepthJob, str]) -> str | None:
    """Worker: write one job's cache file (:func:`cached_scene_depth`); the message of a RobustBenchError
    (exceptions with their own constructors do not cross processes), else None."""
    from robustbench3d.errors import RobustBenchError

    root, key, job, cache_root = task
    try:
        cached_scene_depth(Path(root), key, job.frame_id, job.calib, job.targets, job.image_size, job.supersample,
                           np.asarray(job.bounds, np.float64), job.margin_m, Path(cache_root))
    except RobustBenchError as exc:
        return str(exc)
    return None


def _box_pixels(calib: Calibration, vertices: list[np.ndarray],
                image_size: tuple[int, int]) -> tuple[tuple[int, int], np.ndarray]:
    """The pixels of the meshes' boxes (:func:`~robustbench3d.sensors.camera_render.mesh_box`): ((u0, v0), mask)
    with mask (v1 - v0, u1 - u0) bool over the boxes' bounding box (u0, v0, u1, v1) (empty if no box)."""
    from robustbench3d.sensors.camera_render import mesh_box

    boxes = [b for b in (mesh_box(calib, v, image_size)[0] for v in vertices) if b is not None]
    if not boxes:
        return (0, 0), np.zeros((0, 0), bool)
    u0, v0 = min(b[0] for b in boxes), min(b[1] for b in boxes)
    mask = np.zeros((max(b[3] for b in boxes) - v0, max(b[2] for b in boxes) - u0), bool)
    for b in boxes:
        mask[b[1] - v0:b[3] - v0, b[0] - u0:b[2] - u0] = True
    return (u0, v0), mask


def _positions(origin: tuple[int, int], centres: np.ndarray, samples: np.ndarray,
               supersample: int) -> tuple[np.ndarray, np.ndarray]:
    """(u, v) (N,) float64, computed as the camera renderer computes them: the centres of the pixels of mask
    ``centres``, then the s x s sample positions (sample k = (row i, col j)) of those of mask ``samples`` (masks
    of the same shape, pixel (0, 0) at image pixel ``origin`` (u, v))."""
    cv, cu = np.nonzero(centres)
    cu, cv = cu + origin[0], cv + origin[1]
    us, vs = [cu.astype(np.float64)], [cv.astype(np.float64)]
    if supersample > 1:
        sv, su = np.nonzero(samples)
        su, sv = su + origin[0], sv + origin[1]
        off = sample_offsets(supersample)
        us.append((su[:, None] + np.tile(off, supersample)[None, :]).reshape(-1))
        vs.append((sv[:, None] + np.repeat(off, supersample)[None, :]).reshape(-1))
    return np.concatenate(us), np.concatenate(vs)


def render_positions(calib: Calibration, vertices: list[np.ndarray], image_size: tuple[int, int],
                     supersample: int) -> tuple[np.ndarray, np.ndarray]:
    """(u, v) (N,) float64: every image position at which :func:`~robustbench3d.sensors.camera_render.render_camera`
    can ask its depth source about meshes with these rect vertices (each (V, 3)), computed as it computes them:
    the centre and the s x s sample positions of each pixel of the meshes' boxes (a sample outside every box
    hits no mesh, and the render asks the depth only where a sample hits one), with or without ``full_image``."""
    origin, mask = _box_pixels(calib, vertices, image_size)
    return _positions(origin, mask, mask, supersample)


def _lattice_keys(scale: int, columns: int, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(keys (N,) int64, on the lattice (N,) bool) of positions u, v on the lattice of 1 / ``scale`` pixel
    (shifted by one pixel so that every image position has a non-negative index), ``columns`` wide."""
    gu, gv = (np.asarray(u, np.float64) + 1.0) * scale, (np.asarray(v, np.float64) + 1.0) * scale
    iu, iv = np.rint(gu).astype(np.int64), np.rint(gv).astype(np.int64)
    on = (np.abs(gu - iu) < 1e-6) & (np.abs(gv - iv) < 1e-6) & (iu >= 0) & (iu < columns) & (iv >= 0)
    return iv * columns + iu, on


@dataclass(frozen=True, eq=False)
class TabulatedDepth:
    """A :class:`DepthSource` holding another's depths at a fixed set of image positions: data only.

    Positions are pixel centres and s x s sample positions (s = ``scale`` / 2), all on the lattice of
    1 / ``scale`` pixel. A query elsewhere raises ValueError: the positions are all the render can ask.

    Attributes:
        scale: lattice steps per pixel.
        columns: lattice columns (image width + 2 pixels).
        keys: (K,) int64 sorted lattice indices of the positions.
        depths: (K,) float64 camera-2 depths there (m, +inf for none).
        lighting: the scene's lighting, if the source knew it (the renderer shades objects with it).
    """

    scale: int
    columns: int
    keys: np.ndarray
    depths: np.ndarray
    lighting: Lighting | None = None

    @classmethod
    def of(cls, source: DepthSource, u: np.ndarray, v: np.ndarray, supersample: int,
           image_width: int) -> TabulatedDepth:
        """``source``'s depths at positions u, v (N,) (centres and samples of ``supersample``), each asked once."""
        scale = 2 * supersample
        columns = (image_width + 2) * scale
        keys, _ = _lattice_keys(scale, columns, u, v)
        keys, first = np.unique(keys, return_index=True)  # an odd s's middle sample is the pixel centre
        depths = np.asarray(source.depth(u[first], v[first]), np.float64) if len(first) else np.zeros(0)
        return cls(scale, columns, keys, depths, getattr(source, "lighting", None))

    def depth(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        keys, on = _lattice_keys(self.scale, self.columns, u, v)
        at = np.minimum(np.searchsorted(self.keys, keys), max(len(self.keys) - 1, 0))
        found = on & (self.keys[at] == keys) if len(self.keys) else np.zeros(len(keys), bool)
        if not found.all():
            raise ValueError(f"TabulatedDepth: {int((~found).sum())} of {len(found)} positions were not tabulated")
        return self.depths[at]


def depth_for_render(source: DepthSource | None, calib: Calibration, vertices: list[np.ndarray],
                     image_size: tuple[int, int], supersample: int) -> DepthSource | None:
    """What an attacked frame keeps of its occlusion depth ``source`` for the deferred camera render of meshes
    with these rect vertices: data only, answering every query the render can make as ``source`` does (module
    doc). None and a :class:`~robustbench3d.sensors.camera_depth.DepthMap` (an array) are kept; a
    :class:`CroppedDepth` keeps its crops and gets the exact depths of the queries outside them now; any other
    source is asked for every :func:`render_positions`."""
    from robustbench3d.sensors.camera_depth import DepthMap

    if source is None or isinstance(source, DepthMap):
        return source
    if not (isinstance(source, CroppedDepth) and source.supersample == supersample):
        return TabulatedDepth.of(source, *render_positions(calib, vertices, image_size, supersample),
                                 supersample, image_size[0])
    (x0, y0), wanted = _box_pixels(calib, vertices, image_size)
    outside = wanted.copy()  # pixels whose samples no crop holds
    for (u0, v0, u1, v1), d in zip(source.boxes, source.depths, strict=True):
        if not np.isnan(d).any():
            outside[max(v0 - y0, 0):max(v1 - y0, 0), max(u0 - x0, 0):max(u1 - x0, 0)] = False
    # an even s puts the pixel centre between samples: off the crops' grid, so the centres come from outside
    centres = wanted if supersample % 2 == 0 else outside
    rest = TabulatedDepth.of(source, *_positions((x0, y0), centres, outside, supersample), supersample,
                             image_size[0])
    return CroppedDepth(source.supersample, source.boxes, source.depths, source.lighting, None, rest)


@dataclass(frozen=True)
class _ExactFactory:
    """Builds the exact provider of one frame (a scene rebuild) when called."""

    root: Path
    frame_id: str

    def __call__(self) -> Any:
        from robustbench3d.synth.scene_depth import dataset_scene_depth

        return dataset_scene_depth(self.root, self.frame_id)


__all__ = ["CACHE_VERSION", "CroppedDepth", "DepthJob", "TabulatedDepth", "WarmReport", "attack_depth_jobs",
           "cached_scene_depth", "crop_key", "depth_for_render", "depth_path", "render_positions", "roof_crop",
           "sample_offsets", "synth_key", "warm_scene_depths"]
