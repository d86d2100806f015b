"""The roof-object file: a PLY mesh with per-vertex RGB plus a JSON sidecar.

``NAME.ply`` is a standard binary PLY written by trimesh (``process=False``, so the vertex and face
order is the template's): float32 vertex positions in the object frame (m), uchar RGBA colours (alpha
255, ignored on reading), the template's faces (320 for the default family). Reading also accepts float
colour properties (in [0, 1]) and float64 positions (both are then rounded to the object's precision).

``NAME.json`` (the sidecar, same stem) records the format (:data:`FORMAT`), the PLY's sha256, the
template (icosphere level and radius), the object frame, the placement rule, the box bounds and how
the object was made (``made_by``: attack, seed, config). What reading accepts, field by field (anything
else is refused with one line naming the sidecar and the field; other keys are ignored):

=================  ==========================================================================================
``format``         exactly :data:`FORMAT`
``ply``            the PLY's file name when written: a string ending in ``.ply`` (a renamed pair keeps it)
``ply_sha256``     64 lower-case hex digits, equal to the PLY's sha256
``template``       the object's family (:class:`~robustbench3d.attacks.object.Family`), e.g. the default
                   ``{"kind": "icosphere", "level": 2, "radius": 0.4, "vertices": 162, "faces": 320}``:
                   ``level`` one of 2, 3, 4, ``radius`` in [0.2, 0.6] m in whole centimetres
                   (:data:`~robustbench3d.attacks.object.LEVELS`, ``RADIUS_RANGE``); ``kind`` "icosphere",
                   ``vertices`` and ``faces`` the level's counts (10 * 4^level + 2, 20 * 4^level); those three
                   may be absent
``frame``          optional; a string (the description of the object frame)
``placement``      ``{"rule": "roof-centre", ...}``; its ``description``, if any, a string
``bounds``         three numbers, each half extent in [0.001, 1] m (:data:`~robustbench3d.attacks.object.MAX_BOUND_M`:
                   the object fits in a 2 m cube on a car roof)
``box_constraint`` optional; a string
``made_by``        optional; a JSON object
=================  ==========================================================================================

The PLY itself: at most :data:`MAX_FILE_BYTES` (so is the sidecar), exactly the family's number of finite
vertices (162 for the default family) inside the bounds (within :data:`BOUNDS_TOLERANCE_M`), the family
template's faces in template order, colours in [0, 1].

:class:`~robustbench3d.attacks.object.RoofObject` keeps its arrays at exactly this precision, so
``load_object(save_object(path, obj))`` equals ``obj`` bit for bit. Both files are written
atomically (PLY first, then the sidecar): an interrupted save leaves either the old pair or a
sidecar whose hash no longer matches, which :func:`load_object` refuses.
"""

from __future__ import annotations

import hashlib
import io
import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from robustbench3d.attacks.object import (
    DEFAULT_FAMILY,
    Family,
    RoofObject,
    check_bounds,
    object_problems,
    template_faces,
)
from robustbench3d.attacks.placement import PLACEMENT_RULE
from robustbench3d.errors import DataFormatError
from robustbench3d.fileio import (
    atomic_write_bytes,
    atomic_write_text,
    data_file_errors,
    read_data_bytes,
    read_data_text,
)

FORMAT = "robustbench3d.roof_object/1"
#: Vertices may leave the box by this much in a file (m) and are clamped onto it: float32 rounds a
#: coordinate of exactly 0.4 m (a sphere written by another tool) to 0.4 + 6e-9.
BOUNDS_TOLERANCE_M = 1e-6
#: The largest PLY or sidecar accepted (bytes): the binary PLY of a 162-vertex object is 7 KB, of a 2562-vertex
#: (level-4) one 108 KB, an ASCII one with float colours under 40 KB (162 vertices) or 600 KB (2562), a sidecar
#: with its training record a few KB.
MAX_FILE_BYTES = 1 << 20
_TEMPLATE = DEFAULT_FAMILY.record()
OBJECT_FRAME = ("object frame: centre at the origin; x along the car's length (heading), y down, z along its "
                "width (the KITTI box's local frame); metres")
PLACEMENT_DESCRIPTION = ("resting on the roof centre (label location - (0, h, 0), rect frame), yawed with the "
                         "car (rotation_y about rect y), lifted so the lowest vertex touches the roof")


@dataclass(frozen=True)
class ObjectFile:
    """A loaded object file: the object, its PLY's sha256 and the sidecar's contents."""

    path: Path
    obj: RoofObject
    sha256: str
    sidecar: dict[str, Any]

    @property
    def made_by(self) -> dict[str, Any]:
        return dict(self.sidecar.get("made_by") or {})


def sidecar_path(ply_path: str | Path) -> Path:
    """``NAME.json`` next to ``NAME.ply``."""
    return Path(ply_path).with_suffix(".json")


#: The header of :func:`ply_bytes`, as trimesh's binary PLY export writes it for a mesh with vertex colours.
_PLY_HEADER = ("ply\nformat binary_little_endian 1.0\ncomment https://github.com/mikedh/trimesh\n"
               "element vertex {vertices}\nproperty float x\nproperty float y\nproperty float z\n"
               "property uchar red\nproperty uchar green\nproperty uchar blue\nproperty uchar alpha\n"
               "element face {faces}\nproperty list uchar int vertex_indices\nend_header\n")


def ply_bytes(obj: RoofObject) -> bytes:
    """The PLY file content of ``obj`` (binary, float32 positions, uchar RGBA): the bytes of trimesh's export
    (``Trimesh(vertices, faces, vertex_colors=RGBA, process=False).export(file_type="ply", encoding="binary")``),
    written without importing trimesh (and the scipy, networkx and Embree modules it loads, ~60 MB)."""
    vertices = np.zeros(len(obj.colors), dtype=[("vertex", "<f4", (3,)), ("rgba", "<u1", (4,))])
    vertices["vertex"] = obj.vertices()
    vertices["rgba"][:, :3] = np.round(obj.colors * 255.0).astype(np.uint8)
    vertices["rgba"][:, 3] = 255
    faces = np.zeros(len(obj.faces), dtype=[("count", "<u1"), ("index", "<i4", (3,))])
    faces["count"] = 3
    faces["index"] = obj.faces
    header = _PLY_HEADER.format(vertices=len(vertices), faces=len(faces)).encode("ascii")
    return header + vertices.tobytes() + faces.tobytes()


def object_sha256(obj: RoofObject) -> str:
    """sha256 of :func:`ply_bytes` (the identity of an object that has no file)."""
    return hashlib.sha256(ply_bytes(obj)).hexdigest()


def sidecar_dict(ply_name: str, sha256: str, bounds: np.ndarray, made_by: Mapping[str, Any] | None,
                 family: Family = DEFAULT_FAMILY) -> dict[str, Any]:
    """The sidecar of the PLY file ``ply_name`` with content hash ``sha256`` of an object of ``family``."""
    return {
        "format": FORMAT,
        "ply": ply_name,
        "ply_sha256": sha256,
        "template": family.record(),
        "frame": OBJECT_FRAME,
        "placement": {"rule": PLACEMENT_RULE, "description": PLACEMENT_DESCRIPTION},
        "bounds": [float(b) for b in bounds],
        "box_constraint": "every vertex v satisfies |v_i| <= bounds_i in the object frame",
        "made_by": dict(made_by or {}),
    }


def write_sidecar(ply_path: str | Path, bounds: object, made_by: Mapping[str, Any] | None = None,
                  family: Family = DEFAULT_FAMILY) -> Path:
    """Write the sidecar of an existing PLY file of an object of ``family`` (its sha256 computed from the file);
    returns its path."""
    ply_path = Path(ply_path)
    sha = hashlib.sha256(ply_path.read_bytes()).hexdigest()
    side = sidecar_path(ply_path)
    data = sidecar_dict(ply_path.name, sha, check_bounds(bounds), made_by, family)
    atomic_write_text(side, json.dumps(data, indent=2, sort_keys=True) + "\n")
    return side


def save_object(path: str | Path, obj: RoofObject, made_by: Mapping[str, Any] | None = None) -> Path:
    """Write ``obj`` to ``path`` (must end in ``.ply``) and its sidecar; returns the PLY path.

    ``made_by``: JSON-serialisable description of how the object was made (attack, seed, config).
    """
    path = Path(path)
    if path.suffix.lower() != ".ply":
        raise ValueError(f"{path}: an object file must end in .ply")
    json.dumps(dict(made_by or {}))  # refuse a non-serialisable description before writing anything
    atomic_write_bytes(path, ply_bytes(obj))
    write_sidecar(path, obj.bounds, made_by, obj.family)
    return path


def _read_sidecar(ply_path: Path) -> dict[str, Any]:
    """The checked sidecar of ``ply_path`` (the module doc's table); ``bounds`` as a list of floats."""
    side = sidecar_path(ply_path)
    _check_size(side, missing=f"sidecar of {ply_path.name} not found; an object PLY needs its JSON sidecar "
                              "NAME.json (written by save_object)")
    text = read_data_text(side)
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise DataFormatError(side, f"not valid JSON ({exc.msg})", line=exc.lineno) from None
    if not isinstance(data, dict):
        raise DataFormatError(side, "expected a JSON object")
    problems = _sidecar_problems(data)
    if problems:
        name, problem = problems[0]
        raise DataFormatError(side, problem, field=name)
    data["bounds"] = [float(b) for b in data["bounds"]]
    return data


def _sidecar_problems(data: dict[str, Any]) -> list[tuple[str, str]]:
    """(field, problem) of every sidecar field outside its range (the module doc's table), in file order."""
    problems: list[tuple[str, str]] = []
    if data.get("format") != FORMAT:
        problems.append(("format", f"expected {FORMAT!r}, got {data.get('format')!r}"))
    ply = data.get("ply")
    if not isinstance(ply, str) or not ply.lower().endswith(".ply"):
        problems.append(("ply", f"expected the PLY's file name (a string ending in .ply), got {ply!r}"))
    sha = data.get("ply_sha256")
    if not isinstance(sha, str) or len(sha) != 64 or any(c not in "0123456789abcdef" for c in sha):
        problems.append(("ply_sha256", "expected the PLY's sha256 (64 lower-case hex digits)"))
    problem = _template_problem(data.get("template"))
    if problem:
        problems.append(("template", problem))
    placement = data.get("placement")
    if (not isinstance(placement, dict) or placement.get("rule") != PLACEMENT_RULE
            or not isinstance(placement.get("description", ""), str)):
        problems.append(("placement", f"expected {{'rule': {PLACEMENT_RULE!r}, 'description': text}}, got "
                                      f"{placement!r}"))
    bounds = data.get("bounds")
    try:
        if not isinstance(bounds, list) or any(isinstance(b, bool) or not isinstance(b, (int, float)) for b in bounds):
            raise ValueError(f"field 'bounds': expected a list of three numbers, got {bounds!r}")
        check_bounds(bounds)
    except ValueError as exc:
        problems.append(("bounds", str(exc).removeprefix("field 'bounds': ")))
    for name in ("frame", "box_constraint"):
        if not isinstance(data.get(name, ""), str):
            problems.append((name, f"expected a string, got {data[name]!r}"))
    if not isinstance(data.get("made_by", {}), dict):
        problems.append(("made_by", "expected a JSON object"))
    return problems


def template_family(template: object) -> Family:
    """The :class:`~robustbench3d.attacks.object.Family` of a sidecar's ``template`` record (the module doc's
    table); ValueError naming what is wrong otherwise."""
    problem = _template_problem(template)
    if problem:
        raise ValueError(f"field 'template': {problem}")
    assert isinstance(template, dict)
    return Family(template["level"], template["radius"])


def _template_problem(template: object) -> str | None:
    """What is wrong with a ``template`` record (None: nothing)."""
    want = (f"expected an icosphere family like {_TEMPLATE} (level in {{2, 3, 4}}, radius in [0.2, 0.6] m in "
            f"whole centimetres, vertices and faces the level's counts), got {template!r}")
    if not isinstance(template, dict) or {"level", "radius"} - set(template):
        return want
    if isinstance(template["radius"], bool) or not isinstance(template["radius"], (int, float)):
        return want
    try:
        family = Family(template["level"], template["radius"])
    except ValueError as exc:
        return f"{exc}; {want}"
    if any(k in template and (template[k] != v or isinstance(template[k], bool))
           for k, v in family.record().items() if k not in ("level", "radius")):
        return want
    return None


def _check_size(path: Path, missing: str) -> None:
    """Refuse a file larger than :data:`MAX_FILE_BYTES` before reading it (a missing one: ``missing``)."""
    with data_file_errors(path, missing):
        size = path.stat().st_size
    if size > MAX_FILE_BYTES:
        raise DataFormatError(path, f"{size} bytes; an object file or sidecar is at most {MAX_FILE_BYTES} bytes "
                                    f"(a 162-vertex object is about 7 KB, a 2562-vertex one about 108 KB)")


def ply_mesh(path: Path, raw: bytes) -> Any:
    """The one triangle mesh of a PLY file's bytes, as loaded (a ``trimesh.Trimesh``, not processed);
    :class:`DataFormatError` naming ``path`` on unreadable bytes or anything but one triangle mesh."""
    import trimesh

    try:
        mesh = trimesh.load(io.BytesIO(raw), file_type="ply", process=False)
    except Exception as exc:  # trimesh raises many types on bad bytes
        raise DataFormatError(path, f"not a readable PLY mesh ({type(exc).__name__}: {exc})") from None
    if not isinstance(mesh, trimesh.Trimesh):
        raise DataFormatError(path, f"expected one triangle mesh, got a {type(mesh).__name__}")
    return mesh


def _parse_ply(path: Path, raw: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertices, faces, colours in [0, 1]) of a PLY file's bytes."""
    mesh = ply_mesh(path, raw)
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    colors = _raw_colors(mesh)
    if colors is None:
        if mesh.visual.kind != "vertex":
            raise DataFormatError(path, "no per-vertex colours (expected red, green, blue vertex properties)",
                                  field="colors")
        colors = np.asarray(mesh.visual.vertex_colors, dtype=np.float64)[:, :3] / 255.0
    return vertices, faces, colors


def _raw_colors(mesh: Any) -> np.ndarray | None:
    """(V, 3) colours in the file's own scale, before trimesh converts them to clipped uint8: integer
    properties / 255, float properties as they are; None if the raw PLY properties are unavailable."""
    raw = (mesh.metadata.get("_ply_raw") or {}).get("vertex") or {}
    props, data = raw.get("properties") or {}, raw.get("data")
    if data is None or not all(ch in props for ch in ("red", "green", "blue")):
        return None
    channels = []
    for ch in ("red", "green", "blue"):
        values = np.asarray(data[ch], dtype=np.float64).reshape(-1)
        channels.append(values / 255.0 if np.dtype(props[ch]).kind in "ui" else values)
    return np.stack(channels, axis=1)


def read_object_file(path: str | Path) -> ObjectFile:
    """Load and check an object file and its sidecar (:class:`DataFormatError` naming the file)."""
    path = Path(path)
    _check_size(path, missing="object file not found")
    raw = read_data_bytes(path, missing="object file not found")
    sidecar = _read_sidecar(path)
    sha = hashlib.sha256(raw).hexdigest()
    if sha != sidecar["ply_sha256"]:
        raise DataFormatError(path, f"sha256 {sha} does not match {sidecar['ply_sha256']} recorded in its sidecar "
                                    f"{sidecar_path(path).name} (the PLY or the sidecar was changed)")
    vertices, faces, colors = _parse_ply(path, raw)
    family = template_family(sidecar["template"])
    n, level = family.n_vertices, family.level
    if vertices.shape != (n, 3):
        raise DataFormatError(path, f"expected {n} vertices (icosphere level {level}, the sidecar's template), got "
                                    f"{len(vertices)}", field="vertices")
    if not np.array_equal(faces, template_faces(family)):
        raise DataFormatError(path, f"faces are not the template's ({family.n_faces} faces of icosphere level {level} "
                                    f"in template order); got {len(faces)} faces", field="faces")
    bounds = np.asarray(sidecar["bounds"], dtype=np.float64)
    problems = object_problems(vertices, colors, bounds, tolerance=BOUNDS_TOLERANCE_M, n_vertices=n)
    if problems:
        field, problem = problems[0]
        raise DataFormatError(path, problem, field=field)
    obj = RoofObject.from_vertices(np.clip(vertices, -bounds, bounds), colors, bounds, family=family)
    return ObjectFile(path=path, obj=obj, sha256=sha, sidecar=sidecar)


def load_object(path: str | Path) -> RoofObject:
    """The :class:`RoofObject` stored in ``path`` (see :func:`read_object_file`)."""
    return read_object_file(path).obj
