"""Resolving a benchmark's dataset argument and reading its ground truth once.

``--data DIR`` names a KITTI-layout directory (``DIR/training/...``, ``DIR/ImageSets/<split>.txt``);
without it the embedded procedural dataset in the cache (``<cache>/datasets/synth``) is used and
generated first where it is missing or incomplete. Its parameters are fixed (:data:`EMBEDDED`): they
are the ``robustbench3d data synth`` defaults, so both commands share one cached copy.

By default the whole embedded dataset is generated (training reads every frame). With ``lazy=True``
(a benchmark run) only the frames the evaluation reads are: the first ``max_frames`` ids of the
split, which is a pure function of the parameters (:func:`embedded_split`), so nothing else needs
to exist; a later run that needs more frames generates the missing ones. Frame i is a pure function
of (seed, i), so a frame made lazily has the bytes of the same frame of a full generation
(:mod:`robustbench3d.synth.writer`, which also records the frames present).

The ground truth of the evaluated frames (labels only: scans and images are streamed by the runner)
is read and hashed in one pass (:class:`GroundTruth`); its identity goes into every result.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from robustbench3d.errors import DataFormatError, RobustBenchError
from robustbench3d.fileio import read_data_bytes
from robustbench3d.kitti.dataset import KittiDataset
from robustbench3d.kitti.labels import Labels, parse_labels
from robustbench3d.kitti.splits import read_split
from robustbench3d.provenance import SplitDigest
from robustbench3d.synth import DEFAULT_FRAMES, DEFAULT_SEED, DEFAULT_VAL_FRACTION

EMBEDDED_NAME = "synth"


@dataclass(frozen=True)
class EmbeddedParams:
    """Generator parameters of the embedded dataset (frames 0..frames-1, val share of frames)."""

    frames: int
    seed: int
    val_fraction: float

    def as_dict(self) -> dict[str, Any]:
        from robustbench3d.synth.writer import GENERATOR_VERSION

        return {"generator": "robustbench3d.synth", "generator_version": GENERATOR_VERSION,
                "frames": self.frames, "seed": self.seed, "val_fraction": self.val_fraction}


#: The embedded default dataset's fixed parameters (recorded in every result that uses it).
EMBEDDED = EmbeddedParams(frames=DEFAULT_FRAMES, seed=DEFAULT_SEED, val_fraction=DEFAULT_VAL_FRACTION)


@dataclass(frozen=True)
class ResolvedDataset:
    """A dataset ready to read: KITTI layout under ``root``, frames listed by ``split``.

    Attributes:
        root: absolute dataset root.
        split: split name (``ImageSets/<split>.txt``).
        embedded: generator parameters when this is the embedded dataset, else None.
        manifest: the generator manifest (``synth_manifest.json``) if the directory has one.
    """

    root: Path
    split: str
    embedded: dict[str, Any] | None
    manifest: dict[str, Any] | None

    @property
    def split_file(self) -> Path:
        return self.root / "ImageSets" / f"{self.split}.txt"

    def kitti(self) -> KittiDataset:
        return KittiDataset(self.root, split=self.split)


def embedded_split(params: EmbeddedParams, split: str) -> list[str] | None:
    """Frame ids of ``split`` (train, val, trainval) of the embedded dataset with ``params``, computed
    without reading any file; None for another split name."""
    from robustbench3d.synth.writer import split_lists

    return split_lists(params.frames, params.seed, params.val_fraction).get(split)


def _embedded_complete(root: Path, params: EmbeddedParams, indices: Sequence[int]) -> bool:
    """True if ``root`` holds this generator's manifest, the frames record, the split lists of
    ``params`` and every frame of ``indices``."""
    from robustbench3d.synth.writer import (
        FRAMES_RECORD,
        frame_complete,
        manifest_content,
        split_lists,
        split_lists_written,
    )

    manifest = _read_manifest(root)
    if manifest != manifest_content(params.seed) or not (root / FRAMES_RECORD).is_file():
        return False
    if not split_lists_written(root, split_lists(params.frames, params.seed, params.val_fraction)):
        return False
    return all(frame_complete(root, i) for i in indices)


def ensure_embedded(root: Path, params: EmbeddedParams, workers: int = 1, progress: bool = True,
                    frame_ids: Sequence[str] | None = None, log: Callable[[str], None] | None = None) -> None:
    """Generate the embedded dataset in ``root`` where it is missing or incomplete: every frame, or
    only the frames ``frame_ids`` (the split lists are always the whole dataset's)."""
    indices = list(range(params.frames)) if frame_ids is None else sorted({int(f) for f in frame_ids})
    if _embedded_complete(root, params, indices):
        return
    from robustbench3d.synth.writer import frame_complete, generate_dataset

    missing = sum(not frame_complete(root, i) for i in indices)
    if missing and log is not None:
        log(f"generating {missing} of the {len(indices)} frames needed from the embedded dataset into {root} "
            f"(about 0.5 s of CPU per frame, {workers} worker(s); each frame is generated once and cached)")
    generate_dataset(root, params.frames, params.seed, params.val_fraction, workers=workers, progress=progress,
                     only=None if frame_ids is None else indices, log=log)


def _read_manifest(root: Path) -> dict[str, Any] | None:
    from robustbench3d.synth.writer import MANIFEST

    path = root / MANIFEST
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataFormatError(path, f"not valid JSON ({exc})") from None


def resolve_dataset(data: str | Path | None, split: str = "val", *, embedded: EmbeddedParams | None = None,
                    workers: int = 1, progress: bool = True, lazy: bool = False, max_frames: int | None = None,
                    log: Callable[[str], None] | None = None) -> ResolvedDataset:
    """The dataset of a ``--data`` argument (None: the embedded dataset, generated where missing).

    ``embedded`` overrides :data:`EMBEDDED` (read at call time). ``lazy`` generates only the embedded
    frames an evaluation of the first ``max_frames`` frames of ``split`` reads (None: the whole
    split); without it the whole embedded dataset is generated. ``log`` receives a line before any
    generation. Raises :class:`DataFormatError` naming the missing directory or split file.
    """
    if max_frames is not None and max_frames < 1:
        raise RobustBenchError(f"--max-frames must be at least 1, got {max_frames}")
    if data is None:
        from robustbench3d.paths import dataset_dir

        params_used = embedded or EMBEDDED
        root = dataset_dir(EMBEDDED_NAME).resolve()
        needed: list[str] | None = None
        if lazy:
            ids = embedded_split(params_used, split)
            if ids is None:
                raise DataFormatError(root / "ImageSets" / f"{split}.txt",
                                      "split file not found (available splits: train, trainval, val)")
            needed = ids if max_frames is None else ids[:max_frames]
        ensure_embedded(root, params_used, workers=workers, progress=progress, frame_ids=needed, log=log)
        params: dict[str, Any] | None = params_used.as_dict()
    else:
        root, params = Path(data).expanduser().resolve(), None
        if not root.is_dir():
            raise DataFormatError(root, "dataset directory not found")
        if not (root / "training").is_dir():
            raise DataFormatError(root / "training", "not a directory; expected the KITTI layout DIR/training/...")
    resolved = ResolvedDataset(root=root, split=split, embedded=params, manifest=_read_manifest(root))
    if not resolved.split_file.is_file():
        sets = root / "ImageSets"
        have = sorted(p.stem for p in sets.glob("*.txt")) if sets.is_dir() else []
        raise DataFormatError(resolved.split_file,
                              f"split file not found (available splits: {', '.join(have) or 'none'})")
    return resolved


@dataclass(frozen=True)
class GroundTruth:
    """The evaluated frames of a split and their labels.

    Attributes:
        frame_ids: evaluated frames (the first ``max_frames`` of the split, in split order).
        labels: ground truth of each evaluated frame (rect frame, KITTI label rows).
        split_frames: number of frames the split lists.
        sha256: :class:`~robustbench3d.provenance.SplitDigest` over the evaluated frames.
    """

    frame_ids: list[str]
    labels: list[Labels]
    split_frames: int
    sha256: str


def load_ground_truth(dataset: ResolvedDataset, max_frames: int | None = None) -> GroundTruth:
    """Read, parse and hash the label files of the first ``max_frames`` frames of the split (all: None).

    Each evaluated frame needs a label file; a missing or malformed one raises
    :class:`DataFormatError` naming it. Frames past ``max_frames`` are not read (a lazily generated
    embedded dataset need not hold them).
    """
    ids = read_split(dataset.split_file)
    if not ids:
        raise DataFormatError(dataset.split_file, "split file lists no frames")
    if max_frames is not None and max_frames < 1:
        raise RobustBenchError(f"--max-frames must be at least 1, got {max_frames}")
    keep = ids if max_frames is None else ids[:max_frames]
    kitti = dataset.kitti()
    digest = SplitDigest(keep)
    labels: list[Labels] = []
    for fid in keep:
        path = kitti.path("labels", fid)
        data = read_data_bytes(path, f"ground-truth label file not found (frame listed in {dataset.split_file})")
        digest.update(fid, data)
        try:
            text = data.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise DataFormatError(path, f"not UTF-8 text ({exc.reason})") from None
        labels.append(parse_labels(text, path, scored=False))
    return GroundTruth(frame_ids=keep, labels=labels, split_frames=len(ids), sha256=digest.hexdigest())


def dataset_identity(dataset: ResolvedDataset, gt: GroundTruth) -> dict[str, Any]:
    """The ``dataset`` record of a result: where, which split, how many frames, which labels.

    ``sha256`` covers the evaluated frames' ids (in split order) and label files (scans and images
    are not hashed: for the embedded dataset ``embedded`` pins the generator that made them). For
    the whole split it is the digest of every frame of the split, as it always was.
    """
    return {"root": str(dataset.root), "split": dataset.split, "frames": len(gt.frame_ids),
            "split_frames": gt.split_frames, "first_frame": gt.frame_ids[0], "last_frame": gt.frame_ids[-1],
            "sha256": gt.sha256, "embedded": dataset.embedded, "manifest": dataset.manifest}


__all__ = [
    "EMBEDDED", "EMBEDDED_NAME", "EmbeddedParams", "GroundTruth", "ResolvedDataset", "dataset_identity",
    "embedded_split", "ensure_embedded", "load_ground_truth", "resolve_dataset",
]
