"""An independent geometric check of an attacked dataset (``attack apply``); ``robustbench3d attack check`` runs it.

For every frame of the attacked split, against the clean dataset it was made from (the manifest's root,
or ``--clean``), using only the files on disk, the placed meshes (``training/objects/NNNNNN.ply``),
trimesh's point-triangle distance and trimesh's Embree ray test (not the renderer):

* calib and labels are byte-identical; a frame without objects is byte-identical (scan and image);
* scan rows are split by value into kept (in both scans), removed (clean only) and added (attacked only);
* every added point lies on a placed mesh: distance to the nearest triangle <= ``tol_on_mesh_m`` (1e-4 m);
* every removed point was behind a mesh on its beam: the segment from its laser's origin (0, 0, h0 of the
  laser, :mod:`robustbench3d.sensors.hdl64e`; the laser from the clean scan's ring order) to the point
  crosses a mesh before the point (by more than ``tol_depth_m``);
* no kept point is hidden: its segment does not cross a mesh more than ``tol_depth_m`` before it;
* the image changes only inside the objects' projected boxes (pixels whose footprint [p - 1/2, p + 1/2]
  overlaps the bounding box of a mesh's projected vertices; the whole image for a mesh straddling the
  camera plane).

The renderer casts the beam pattern's rays, and a point belongs to a ray within half a firing step in
azimuth (0.09 deg). A point exactly at a mesh's silhouette may therefore see the mesh on its ray but not
on its own segment (or the reverse): such points are counted as ``edge`` cases (the decision is taken
again with the two rays 0.09 deg to either side in azimuth, and holds if either agrees with the renderer)
and reported, and only the points that fail this too count as violations.

Before any frame is checked, every complete frame's files are read and checked (a damaged attacked dataset
is one line naming the file and field, exit 2, not a violation): the manifest (a JSON object written by
``attack apply``, its dataset's ``root`` and ``split``), each ``.done`` marker (a JSON object: ``frame`` the
frame id, ``objects`` an integer >= 0, ``vertices_per_object`` and ``faces_per_object`` integers >= 1 when
there are objects, else 0) and each objects PLY (a readable triangle mesh of exactly ``objects`` x those
vertices and faces, finite positions). ``--max-frames`` is an integer in [1, 1000000].

    robustbench3d attack check ATTACKED_DIR [--clean DIR] [--max-frames N]
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

#: Half the HDL-64E firing step in azimuth, deg (a point's ray is within this of the point).
HALF_STEP_DEG = 0.09


@dataclass
class CheckReport:
    """Counts over the checked frames and one line per violation (empty: the dataset passes)."""

    frames: int = 0
    frames_with_objects: int = 0
    added: int = 0
    removed: int = 0
    kept: int = 0
    changed_pixels: int = 0
    edge_removed: int = 0
    edge_kept: int = 0
    max_added_distance_m: float = 0.0
    violations: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.violations


def surface_distance(points: Any, triangles: Any, chunk: int = 128) -> Any:
    """(K,) distance of each point to the nearest of the (F, 3, 3) triangles: trimesh's point-triangle distance
    to each triangle that can be the nearest. That prefilter is exact: a triangle's centroid lies on it, so the
    nearest centroid's distance ``u`` bounds the answer from above, and a triangle whose centroid is farther than
    ``u`` plus its own radius about the centroid cannot be nearer (so a level-4 object's 5120 faces cost about
    what a level-2 object's 320 do)."""
    import numpy as np
    from trimesh.triangles import closest_point

    tri = np.asarray(triangles, dtype=np.float64)
    centre = tri.mean(axis=1)
    reach = np.linalg.norm(tri - centre[:, None], axis=2).max(axis=1)
    out = np.empty(len(points))
    for s in range(0, len(points), chunk):
        p = np.asarray(points[s:s + chunk], dtype=np.float64)
        d = np.linalg.norm(p[:, None] - centre[None], axis=2)
        near = d - reach <= d.min(axis=1, keepdims=True) * (1 + 1e-9) + 1e-12
        pi, fi = np.nonzero(near)
        dist = np.linalg.norm(closest_point(tri[fi], p[pi]) - p[pi], axis=1)
        best = np.full(len(p), np.inf)
        np.minimum.at(best, pi, dist)
        out[s:s + chunk] = best
    return out


def surface_distance_brute(points: Any, triangles: Any, chunk: int = 128) -> Any:
    """:func:`surface_distance` by brute force (every point against every triangle): its reference."""
    import numpy as np
    from trimesh.triangles import closest_point

    out = np.empty(len(points))
    f = len(triangles)
    for s in range(0, len(points), chunk):
        p = points[s:s + chunk]
        q = closest_point(np.tile(triangles, (len(p), 1, 1)), np.repeat(p, f, axis=0))
        out[s:s + chunk] = np.linalg.norm(q - np.repeat(p, f, axis=0), axis=1).reshape(len(p), f).min(axis=1)
    return out


def _block_distance(points: Any, triangles: Any, blocks: int, pad: float = 1e-3) -> Any:
    """:func:`surface_distance` to the union of ``blocks`` equal triangle blocks (one per object), each
    point measured only against the blocks whose bounding box (+ ``pad``) holds it (+inf if none)."""
    import numpy as np

    out = np.full(len(points), np.inf)
    for tri in np.split(triangles, blocks):
        flat = tri.reshape(-1, 3)
        near = np.all((points >= flat.min(axis=0) - pad) & (points <= flat.max(axis=0) + pad), axis=1)
        if near.any():
            out[near] = np.minimum(out[near], surface_distance(points[near], tri))
    return out


def first_hit(mesh: Any, origins: Any, directions: Any) -> Any:
    """(R,) distance along each unit ray to its first mesh hit (Embree via trimesh), +inf on a miss."""
    import numpy as np
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    t = np.full(len(origins), np.inf)
    if len(origins) == 0:
        return t
    loc, ray, _ = RayMeshIntersector(mesh).intersects_location(origins, directions, multiple_hits=False)
    np.minimum.at(t, ray, np.linalg.norm(loc - origins[ray], axis=1))
    return t


def _segments(points: Any, ring: Any, turn_deg: float = 0.0) -> tuple[Any, Any, Any]:
    """(origins, unit directions, lengths) from each point's laser origin to it, the direction turned by
    ``turn_deg`` about the z axis."""
    import numpy as np

    from robustbench3d.sensors.hdl64e import LASER_ORIGIN_Z_M

    o = np.zeros((len(points), 3))
    o[:, 2] = LASER_ORIGIN_Z_M[ring]
    d = points[:, :3].astype(np.float64) - o
    length = np.linalg.norm(d, axis=1)
    d /= length[:, None]
    if turn_deg:
        c, s = np.cos(np.radians(turn_deg)), np.sin(np.radians(turn_deg))
        d = np.stack([c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1], d[:, 2]], axis=1)
    return o, d, length


def _blocked(mesh: Any, points: Any, ring: Any, tol: float) -> Any:
    """(3, K) bool: the point's own segment, and the rays turned by -/+ HALF_STEP_DEG, cross a mesh more
    than ``tol`` before the point's range."""
    import numpy as np

    out = np.zeros((3, len(points)), bool)
    for i, turn in enumerate((0.0, -HALF_STEP_DEG, HALF_STEP_DEG)):
        o, d, length = _segments(points, ring, turn)
        out[i] = first_hit(mesh, o, d) < length - tol
    return out


def pixel_mask(vertices_velo: Any, blocks: int, calib: Any, size: tuple[int, int]) -> Any:
    """(H, W) bool: pixels that may change (the module doc's projected boxes of each object block)."""
    import numpy as np

    w, h = size
    mask = np.zeros((h, w), bool)
    for v in np.split(vertices_velo, blocks):
        uv, depth = calib.rect_to_image(calib.velo_to_rect_points(v))
        if np.all(depth <= 1e-6):
            continue
        if np.any(depth <= 1e-6):
            mask[:] = True
            continue
        u0, v0 = np.ceil(uv.min(axis=0) - 0.5).astype(int)
        u1, v1 = np.floor(uv.max(axis=0) + 0.5).astype(int) + 1
        mask[max(v0, 0):max(v1, 0), max(u0, 0):max(u1, 0)] = True
    return mask


def marker_path(attacked: Path, frame_id: str) -> Path:
    return attacked / "training" / ".done" / f"{frame_id}.json"


def read_marker(attacked: Path, frame_id: str) -> dict[str, int]:
    """The checked ``.done`` marker of ``frame_id`` (module doc): objects, vertices and faces per object."""
    from robustbench3d.errors import DataFormatError
    from robustbench3d.results import read_json

    path = marker_path(attacked, frame_id)
    data = read_json(path)
    if not isinstance(data, dict):
        raise DataFormatError(path, "expected a JSON object (the frame's completion marker)")
    if data.get("frame") != frame_id:
        raise DataFormatError(path, f"expected the frame id {frame_id!r}, got {data.get('frame')!r}", field="frame")
    out = {}
    for key in ("objects", "vertices_per_object", "faces_per_object"):
        value = data.get(key)
        low = 0 if key == "objects" or not out["objects"] else 1
        high = None if key == "objects" or out["objects"] else 0
        if isinstance(value, bool) or not isinstance(value, int) or value < low or (high is not None and value > high):
            want = f"an integer >= {low}" if high is None else "0 (no objects)"
            raise DataFormatError(path, f"expected {want}, got {value!r}", field=key)
        out[key] = value
    return out


def read_objects(attacked: Path, frame_id: str, marker: dict[str, int]) -> Any:
    """The checked objects PLY of ``frame_id`` (module doc) as a trimesh mesh; ``marker``: its
    :func:`read_marker`."""
    import numpy as np

    from robustbench3d.attacks.objectfile import ply_mesh
    from robustbench3d.errors import DataFormatError
    from robustbench3d.fileio import read_data_bytes

    path = attacked / "training" / "objects" / f"{frame_id}.ply"
    raw = read_data_bytes(path, missing=f"objects PLY not found (its marker {marker_path(attacked, frame_id).name} "
                                        f"records {marker['objects']} objects)")
    mesh = ply_mesh(path, raw)
    n = marker["objects"]
    for what, have, per in (("vertices", len(mesh.vertices), marker["vertices_per_object"]),
                            ("faces", len(mesh.faces), marker["faces_per_object"])):
        if have != n * per:
            raise DataFormatError(path, f"{have} {what}; its marker records {n} objects of {per}", field=what)
    if not np.all(np.isfinite(mesh.vertices)):
        raise DataFormatError(path, "non-finite vertex position (NaN or inf)", field="vertices")
    return mesh


def _same_bytes(a_ds: Any, c_ds: Any, kind: str, frame_id: str) -> bool:
    """Whether the attacked and the clean file of ``kind`` are byte-identical (missing: DataFormatError)."""
    from robustbench3d.fileio import read_data_bytes

    return read_data_bytes(a_ds.path(kind, frame_id)) == read_data_bytes(c_ds.path(kind, frame_id))


def check_frame(attacked: Path, clean: Path, frame_id: str, report: CheckReport, tol_on_mesh_m: float = 1e-4,
                tol_depth_m: float = 1e-4) -> None:
    """Check one frame (module doc), adding its counts and violations to ``report``."""
    import numpy as np

    from robustbench3d.kitti import KittiDataset
    from robustbench3d.kitti.velodyne import scan_rows
    from robustbench3d.sensors.lidar_beams import scan_ring_ids

    a_ds, c_ds = KittiDataset(attacked, split=None), KittiDataset(clean, split=None)
    bad = report.violations.append
    report.frames += 1
    for kind in ("calib", "labels"):
        if not _same_bytes(a_ds, c_ds, kind, frame_id):
            bad(f"{frame_id}: {kind} file differs from the clean one")
    marker = read_marker(attacked, frame_id)
    n_obj = marker["objects"]
    if n_obj == 0:
        for kind in ("scan", "image"):
            if not _same_bytes(a_ds, c_ds, kind, frame_id):
                bad(f"{frame_id}: no object placed but the {kind} file changed")
        return
    report.frames_with_objects += 1
    mesh = read_objects(attacked, frame_id, marker)
    c_scan, a_scan = c_ds.scan(frame_id), a_ds.scan(frame_id)
    c_rows, a_rows = scan_rows(c_scan), scan_rows(a_scan)
    kept = np.isin(c_rows, a_rows)
    added = a_scan[~np.isin(a_rows, c_rows)]
    ring = scan_ring_ids(c_scan)
    report.kept += int(kept.sum())
    report.removed += int((~kept).sum())
    report.added += len(added)

    if len(added):
        dist = _block_distance(added[:, :3].astype(np.float64), mesh.triangles, n_obj)
        report.max_added_distance_m = max(report.max_added_distance_m, float(dist.max()))
        far = int((dist > tol_on_mesh_m).sum())
        if far:
            bad(f"{frame_id}: {far} added point(s) farther than {tol_on_mesh_m} m from the meshes "
                f"(max {dist.max():.3g} m)")
    hit = _blocked(mesh, c_scan[~kept], ring[~kept], tol_depth_m)
    report.edge_removed += int((~hit[0] & hit.any(axis=0)).sum())
    if (~hit.any(axis=0)).any():
        bad(f"{frame_id}: {int((~hit.any(axis=0)).sum())} removed point(s) not behind a mesh on their beam")
    hit = _blocked(mesh, c_scan[kept], ring[kept], tol_depth_m)
    report.edge_kept += int((hit[0] & ~hit.all(axis=0)).sum())
    if hit.all(axis=0).any():
        bad(f"{frame_id}: {int(hit.all(axis=0).sum())} kept point(s) lie behind a mesh on their beam")

    c_img, a_img = c_ds.image(frame_id), a_ds.image(frame_id)
    changed = (c_img != a_img).any(axis=2)
    report.changed_pixels += int(changed.sum())
    outside = changed & ~pixel_mask(np.asarray(mesh.vertices), n_obj, c_ds.calib(frame_id),
                                    (c_img.shape[1], c_img.shape[0]))
    if outside.any():
        bad(f"{frame_id}: {int(outside.sum())} pixel(s) changed outside the objects' projected boxes")


def check_attacked_dataset(attacked: str | Path, clean: str | Path | None = None, split: str | None = None,
                           max_frames: int | None = None) -> CheckReport:
    """Check every complete frame of the attacked dataset (module doc)."""
    from robustbench3d.attacks.spec import check_max_frames
    from robustbench3d.errors import DataFormatError, RobustBenchError
    from robustbench3d.kitti import read_split

    check_max_frames(max_frames)
    attacked = Path(attacked)
    root, split_name = _manifest_dataset(attacked)
    clean_root = Path(clean) if clean is not None else root
    if not (clean_root / "training").is_dir():
        raise RobustBenchError(f"clean dataset {clean_root}: no training/ directory (pass the clean dataset's "
                               "root with --clean)")
    split_file = attacked / "ImageSets" / f"{split or split_name}.txt"
    if not split_file.is_file():
        raise DataFormatError(split_file, "split file not found")
    ids = read_split(split_file)[:max_frames]
    complete = [fid for fid in ids if marker_path(attacked, fid).is_file()]
    for fid in complete:  # up front: a damaged file stops the check before any frame is checked
        marker = read_marker(attacked, fid)
        if marker["objects"]:
            read_objects(attacked, fid, marker)
    report = CheckReport()
    for fid in ids:
        if fid not in complete:
            report.violations.append(f"{fid}: frame incomplete (no .done marker)")
            continue
        check_frame(attacked, clean_root, fid, report)
    return report


def _manifest_dataset(attacked: Path) -> tuple[Path, str]:
    """(clean dataset root, split) recorded in the attacked dataset's manifest (checked: module doc)."""
    from robustbench3d.errors import DataFormatError
    from robustbench3d.results import read_json

    path = attacked / "attack_manifest.json"
    manifest = read_json(path)
    if not isinstance(manifest, dict):
        raise DataFormatError(path, "expected a JSON object (the manifest `attack apply` writes)")
    dataset = manifest.get("dataset")
    if not isinstance(dataset, dict):
        raise DataFormatError(path, f"expected a JSON object with root and split, got {dataset!r}", field="dataset")
    for key in ("root", "split"):
        if not isinstance(dataset.get(key), str) or not dataset[key]:
            raise DataFormatError(path, f"expected a non-empty string, got {dataset.get(key)!r}",
                                  field=f"dataset.{key}")
    return Path(dataset["root"]), dataset["split"]
