"""An attacked copy of a dataset split in KITTI layout, for any detector (``robustbench3d attack apply``), and
one attacked frame as that copy holds it (:func:`attacked_frame`, drawn by ``show --attack`` and the report).

    OUT/training/velodyne/NNNNNN.bin   attacked scan (object returns added, occluded points removed)
    OUT/training/image_2/NNNNNN.png    attacked image 2 (objects composited)
    OUT/training/calib/NNNNNN.txt      copied unchanged (bytes)
    OUT/training/label_2/NNNNNN.txt    copied unchanged (bytes)
    OUT/training/objects/NNNNNN.ply    the frame's placed objects, velodyne frame (m), per-vertex RGB,
                                       float32 positions; object k is vertices [k V, (k + 1) V) and faces
                                       [k F, (k + 1) F) (V, F: the object family's, 162 and 320 for the
                                       default one); none for a frame without cars
    OUT/training/.done/NNNNNN.json     written last: the frame is complete (object count, vertices per object)
    OUT/ImageSets/<split>.txt          the split file (copied unchanged; the first N frames with --max-frames)
    OUT/attack_manifest.json           provenance: attack, object description and sha256, seed, dataset identity

Each frame is attacked exactly as in a benchmark cell (the same generator from (seed, frame id), the same
object placements, exact occlusion on a generated dataset); a frame without target cars is copied byte for
byte. Every file is written atomically and the ``.done`` marker last, so a rerun with the same arguments
resumes: complete frames are kept (the command says how many), any other frame is rewritten. Nothing else
is ever replaced: a rerun with another attack, seed or dataset into the same directory, a directory whose
manifest is not an ``attack apply`` manifest and a non-empty directory without one are refused, before any
frame is attacked. ``--seed`` is in [0, 2**32 - 1] and ``--max-frames`` in [1, 1000000], checked before any work.

Standard library only at module level.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from robustbench3d.attacks import resolve_attack

MANIFEST = "attack_manifest.json"
DONE = ".done"
OBJECTS = "objects"
COPIED = ("calib", "label_2")
TOOL = "robustbench3d attack apply"


def placed_meshes(attack: Any, targets: Any, rng: Any) -> list[tuple[Any, Any, Any]]:
    """(rect vertices, faces, colours) of each object ``attack.apply`` places with ``rng`` (drawn from a copy
    of it, so ``rng`` itself is untouched); none for an attack that places no roof object."""
    import copy

    place = getattr(attack, "place", None)
    if place is None or len(targets) == 0:
        return []
    return [(v, attack.obj.faces, attack.obj.colors) for v, _ in place(targets, copy.deepcopy(rng))]


def mesh_ply_bytes(meshes: list[tuple[Any, Any, Any]], calib: Any) -> bytes:
    """Binary PLY of the meshes joined, in the velodyne frame (float32 positions, uchar RGBA colours)."""
    import numpy as np
    import trimesh

    verts = np.concatenate([calib.rect_to_velo_points(np.asarray(v, np.float64)) for v, _, _ in meshes])
    offsets = np.cumsum([0] + [len(v) for v, _, _ in meshes[:-1]])
    faces = np.concatenate([np.asarray(f, np.int64) + o for (_, f, _), o in zip(meshes, offsets, strict=True)])
    colors = np.concatenate([np.asarray(c, np.float64) for _, _, c in meshes])
    rgba = np.concatenate([np.round(np.clip(colors, 0, 1) * 255), np.full((len(colors), 1), 255)], axis=1)
    mesh = trimesh.Trimesh(verts, faces, vertex_colors=rgba.astype(np.uint8), process=False)
    return mesh.export(file_type="ply", encoding="binary")


def _manifest(name: str, attack: Any, seed: int, identity: dict[str, Any], frames: list[str]) -> dict[str, Any]:
    from robustbench3d import __version__
    from robustbench3d.attacks.base import ATTACK_STREAM

    return {"tool": TOOL, "package_version": __version__, "attack": name,
            "object": attack.describe(), "object_sha256": getattr(attack, "sha256", None), "seed": seed,
            "attack_rng": f"numpy.random.default_rng([seed, int(frame_id), {ATTACK_STREAM:#x}])",
            "exact_occlusion": bool(getattr(attack, "exact_occlusion", False)),
            "dataset": {k: identity[k] for k in ("root", "split", "split_frames", "sha256", "embedded")},
            "frames": frames}


def _existing_manifest(out: Path) -> dict[str, Any] | None:
    """The ``attack apply`` manifest of an existing ``--out`` (None: ``out`` is missing or empty); refuses a
    non-empty directory without one, and a manifest another tool wrote (the written-once rule, module doc)."""
    from robustbench3d.errors import DataFormatError, RobustBenchError
    from robustbench3d.results import read_json

    path = out / MANIFEST
    if not path.exists():
        if out.is_dir() and any(out.iterdir()):
            raise RobustBenchError(f"--out {out}: not empty and not an attacked dataset (no {MANIFEST}); "
                                   "choose another --out (nothing was written)")
        return None
    have = read_json(path)
    if not isinstance(have, dict) or have.get("tool") != TOOL:
        raise DataFormatError(path, f"not a manifest of `attack apply` (expected a JSON object with tool {TOOL!r}); "
                                    "choose another --out (nothing was written)", field="tool")
    return have


def _check_manifest(out: Path, want: dict[str, Any]) -> None:
    from robustbench3d.errors import RobustBenchError
    from robustbench3d.fileio import atomic_write_text

    path = out / MANIFEST
    have = _existing_manifest(out)
    for key in ("attack", "object", "seed", "dataset") if have is not None else ():  # frames may differ
        if have.get(key) != want[key]:
            raise RobustBenchError(f"{path}: field '{key}': this directory holds another attacked dataset "
                                   f"({key} differs); choose another --out")
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps(want, indent=2, default=str) + "\n")


def frame_done(out: Path, frame_id: str) -> bool:
    """True if every file of the frame was written (its marker exists)."""
    return (out / "training" / DONE / f"{frame_id}.json").is_file()


def apply_frame(attack: Any, kitti: Any, frame_id: str, seed: int, out: Path) -> int:
    """Attack one frame and write its files (marker last); returns the number of objects placed."""
    import shutil

    from robustbench3d.attacks.base import attack_rng, target_cars
    from robustbench3d.fileio import atomic_write_bytes, atomic_write_text
    from robustbench3d.kitti.image import write_image
    from robustbench3d.kitti.velodyne import write_scan

    train = out / "training"
    for sub in ("velodyne", "image_2", *COPIED, OBJECTS, DONE):
        (train / sub).mkdir(parents=True, exist_ok=True)
    frame = kitti.frame(frame_id)
    targets = target_cars(frame.labels)
    (train / OBJECTS / f"{frame_id}.ply").unlink(missing_ok=True)
    meshes: list = []
    if len(targets) == 0:  # passes through unchanged, bit for bit
        shutil.copyfile(kitti.path("scan", frame_id), train / "velodyne" / f"{frame_id}.bin")
        shutil.copyfile(kitti.path("image", frame_id), train / "image_2" / f"{frame_id}.png")
    else:
        rng = attack_rng(seed, frame_id)
        meshes = placed_meshes(attack, targets, rng)
        attacked = attack.apply(frame, targets, rng)
        write_scan(train / "velodyne" / f"{frame_id}.bin", attacked.scan)
        write_image(train / "image_2" / f"{frame_id}.png", attacked.image)
        if meshes:
            atomic_write_bytes(train / OBJECTS / f"{frame_id}.ply", mesh_ply_bytes(meshes, frame.calib))
    for sub, kind in zip(COPIED, ("calib", "labels"), strict=True):
        atomic_write_bytes(train / sub / f"{frame_id}.txt", kitti.path(kind, frame_id).read_bytes())
    marker = {"frame": frame_id, "objects": len(meshes),
              "vertices_per_object": len(meshes[0][0]) if meshes else 0,
              "faces_per_object": len(meshes[0][1]) if meshes else 0}
    atomic_write_text(train / DONE / f"{frame_id}.json", json.dumps(marker) + "\n")
    return len(meshes)


def apply_dataset(reference: str, data: str | Path | None, split: str, out: str | Path, seed: int = 0,
                  max_frames: int | None = None, progress: bool = True) -> dict[str, int]:
    """Write the attacked dataset (module doc); returns counts of frames written, kept and objects placed."""
    import sys

    from tqdm import tqdm

    from robustbench3d.attacks.spec import check_max_frames, check_seed
    from robustbench3d.datasets import dataset_identity, load_ground_truth, resolve_dataset
    from robustbench3d.fileio import atomic_write_text, check_output_dir

    out = check_output_dir(out, "--out")
    check_seed(seed)
    check_max_frames(max_frames)
    _existing_manifest(out)  # refuses another's directory before the dataset is resolved (or generated)
    name, attack = resolve_attack(reference)
    dataset = resolve_dataset(data, split, progress=progress)
    gt = load_ground_truth(dataset, max_frames)
    kitti = dataset.kitti()
    attack.bind_dataset(kitti)
    _check_manifest(out, _manifest(name, attack, seed, dataset_identity(dataset, gt), gt.frame_ids))
    counts = {"written": 0, "kept": 0, "objects": 0}
    for fid in tqdm(gt.frame_ids, unit="frame", file=sys.stderr, disable=not progress, desc=f"attack {name}"):
        if frame_done(out, fid):
            counts["kept"] += 1
            continue
        counts["objects"] += apply_frame(attack, kitti, fid, seed, out)
        counts["written"] += 1
    split_text = dataset.split_file.read_text(encoding="utf-8")
    if len(gt.frame_ids) < gt.split_frames:
        split_text = "".join(f"{fid}\n" for fid in gt.frame_ids)
    (out / "ImageSets").mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "ImageSets" / f"{split}.txt", split_text)
    return counts


def attacked_frame(ds, frame, reference, seed: int):
    """(attacked frame, (K, 4) object LiDAR returns) of ``frame`` as ``attack apply`` makes it; ``reference``
    is a registered attack name, an object file ``NAME.ply`` or an attack instance."""
    import numpy as np

    from robustbench3d.attacks.base import attack_rng, target_cars
    from robustbench3d.kitti.velodyne import scan_rows

    attack = resolve_attack(reference)[1] if isinstance(reference, str) else reference
    attack.bind_dataset(ds)
    targets = target_cars(frame.labels)
    if len(targets) == 0:
        return frame, np.zeros((0, 4), np.float32)
    attacked = attack.apply(frame, targets, attack_rng(seed, frame.frame_id))
    return attacked, attacked.scan[~np.isin(scan_rows(attacked.scan), scan_rows(frame.scan))]
