"""Object files: exact round trip, standard PLY content, and every bad file refused naming the file."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from robustbench3d.attacks.object import benign_sphere, random_shape, template_faces
from robustbench3d.attacks.objectfile import (
    FORMAT,
    load_object,
    read_object_file,
    save_object,
    sidecar_path,
    write_sidecar,
)
from robustbench3d.errors import DataFormatError
from robustbench3d.sensors.mesh import icosphere


def test_ply_bytes_are_trimeshs_export_without_importing_trimesh():
    import subprocess
    import sys

    from robustbench3d.attacks.object import N_VERTICES
    from robustbench3d.attacks.objectfile import ply_bytes

    for obj in (benign_sphere(), random_shape(0), random_shape(7)):
        rgba = np.empty((N_VERTICES, 4), dtype=np.uint8)
        rgba[:, :3] = np.round(obj.colors * 255.0).astype(np.uint8)
        rgba[:, 3] = 255
        ref = trimesh.Trimesh(vertices=obj.vertices(), faces=obj.faces, vertex_colors=rgba, process=False)
        assert ply_bytes(obj) == ref.export(file_type="ply", encoding="binary")
    code = ("import sys; from robustbench3d.attacks import create_attack; a = create_attack('random-shape'); "
            "a.describe(); print('trimesh' in sys.modules)")
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout == "False\n"


def test_round_trip_is_bit_for_bit(tmp_path):
    for obj, made_by in ((random_shape(5), {"attack": "random-shape", "seed": 5}), (benign_sphere(), {})):
        path = save_object(tmp_path / "obj.ply", obj, made_by)
        loaded = read_object_file(path)
        for name in ("colors", "displacement", "bounds", "faces"):
            a, b = getattr(obj, name), getattr(loaded.obj, name)
            assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), name
        assert obj.vertices().tobytes() == loaded.obj.vertices().tobytes()
        assert loaded.made_by == made_by
        assert loaded.sha256 == hashlib.sha256(path.read_bytes()).hexdigest()
        # saving the loaded object again writes the same bytes
        again = save_object(tmp_path / "again.ply", loaded.obj, made_by)
        assert again.read_bytes() == path.read_bytes()


def test_ply_is_a_standard_coloured_mesh_in_template_order(tmp_path):
    obj = random_shape(1)
    path = save_object(tmp_path / "o.ply", obj, {"attack": "x"})
    mesh = trimesh.load(path, process=False)
    assert np.array_equal(mesh.faces, template_faces())
    assert np.array_equal(np.asarray(mesh.vertices, np.float64), obj.vertices())
    assert np.array_equal(mesh.visual.vertex_colors[:, :3], np.round(obj.colors * 255).astype(np.uint8))
    side = json.loads(sidecar_path(path).read_text())
    assert side["format"] == FORMAT and side["ply"] == "o.ply"
    assert side["ply_sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
    assert side["placement"]["rule"] == "roof-centre" and side["bounds"] == [0.4, 0.4, 0.4]
    assert side["template"]["level"] == 2 and side["template"]["radius"] == 0.4
    assert side["made_by"] == {"attack": "x"}


def test_save_refuses_a_non_ply_name(tmp_path):
    with pytest.raises(ValueError, match=r"must end in \.ply"):
        save_object(tmp_path / "o.obj", benign_sphere())


def _write_ply(path: Path, vertices: np.ndarray, faces: np.ndarray, colors_u8: np.ndarray | None = None) -> Path:
    """A PLY with a matching sidecar (so the checks after the hash are reached)."""
    kwargs = {} if colors_u8 is None else {"vertex_colors": colors_u8}
    path.write_bytes(trimesh.Trimesh(vertices, faces, process=False, **kwargs).export(file_type="ply"))
    write_sidecar(path, (0.4, 0.4, 0.4), {"attack": "test"})
    return path


def _grey(n: int) -> np.ndarray:
    return np.full((n, 4), 128, dtype=np.uint8)


def _fails(path: Path, pattern: str, named: Path | None = None) -> None:
    with pytest.raises(DataFormatError, match=pattern) as info:
        load_object(path)
    assert info.value.path == (named or path)
    assert str(named or path) in str(info.value)


def test_wrong_vertex_count(tmp_path):
    v, f = icosphere(1, 0.4)
    _fails(_write_ply(tmp_path / "a.ply", v, f, _grey(42)), r"field 'vertices': expected 162 vertices.*got 42")


def test_wrong_faces(tmp_path):
    v, f = icosphere(2, 0.4)
    f2 = f.copy()
    f2[[0, 1]] = f2[[1, 0]]  # same triangles, other order: not the template's topology order
    _fails(_write_ply(tmp_path / "a.ply", v, f2, _grey(162)), r"field 'faces': faces are not the template's")
    _fails(_write_ply(tmp_path / "b.ply", v, f[:-1], _grey(162)), r"field 'faces'.*got 319 faces")


def test_nan_vertices(tmp_path):
    v, f = icosphere(2, 0.4)
    v[10, 1] = np.nan
    _fails(_write_ply(tmp_path / "a.ply", v, f, _grey(162)), r"field 'vertices': non-finite value.*vertex 10")


def test_vertices_outside_the_bounds(tmp_path):
    v, f = icosphere(2, 0.4)
    v[20] = [0.0, 0.0, 0.4 + 2e-6]
    _fails(_write_ply(tmp_path / "a.ply", v, f, _grey(162)), r"field 'vertices': 1 vertices outside the box.*vertex 20")


def test_a_sphere_written_by_another_tool_is_clamped_onto_the_box(tmp_path):
    v, f = icosphere(2, 0.4)  # float32 rounds the coordinates 0.4 up by 6e-9
    assert np.abs(v.astype(np.float32).astype(np.float64)).max() > 0.4
    obj = load_object(_write_ply(tmp_path / "a.ply", v, f, _grey(162)))
    assert np.abs(obj.vertices()).max() <= 0.4
    assert np.max(np.abs(obj.displacement)) < 1e-7


def test_colours_outside_0_1(tmp_path):
    v, f = icosphere(2, 0.4)
    header = ("ply\nformat ascii 1.0\nelement vertex 162\nproperty float x\nproperty float y\nproperty float z\n"
              "property float red\nproperty float green\nproperty float blue\nelement face 320\n"
              "property list uchar int vertex_indices\nend_header\n")
    colors = np.full((162, 3), 0.5)
    colors[33, 2] = 1.5
    rows = [" ".join(f"{x:.9g}" for x in (*v[i], *colors[i])) for i in range(162)]
    rows += ["3 " + " ".join(str(i) for i in face) for face in f]
    path = tmp_path / "a.ply"
    path.write_text(header + "\n".join(rows) + "\n")
    write_sidecar(path, (0.4, 0.4, 0.4))
    _fails(path, r"field 'colors': 1 colours outside \[0, 1\].*vertex 33")
    colors[33, 2] = 0.25  # float colours inside [0, 1] are accepted (rounded to 8 bits)
    rows = [" ".join(f"{x:.9g}" for x in (*v[i], *colors[i])) for i in range(162)] + rows[162:]
    path.write_text(header + "\n".join(rows) + "\n")
    write_sidecar(path, (0.4, 0.4, 0.4))
    assert load_object(path).colors[33, 2] == round(0.25 * 255) / 255


def test_no_colours(tmp_path):
    v, f = icosphere(2, 0.4)
    _fails(_write_ply(tmp_path / "a.ply", v, f), r"field 'colors': no per-vertex colours")


def test_missing_sidecar_and_missing_file(tmp_path):
    path = save_object(tmp_path / "a.ply", benign_sphere())
    sidecar_path(path).unlink()
    _fails(path, r"sidecar of a.ply not found", named=tmp_path / "a.json")
    _fails(tmp_path / "nothing.ply", "object file not found")


def test_sidecar_hash_mismatch(tmp_path):
    path = save_object(tmp_path / "a.ply", random_shape(0))
    data = bytearray(path.read_bytes())
    data[-1] ^= 1  # change the last face index byte
    path.write_bytes(bytes(data))
    _fails(path, r"sha256 [0-9a-f]{64} does not match [0-9a-f]{64} recorded in its sidecar a.json")


def test_malformed_sidecars(tmp_path):
    path = save_object(tmp_path / "a.ply", benign_sphere())
    side = sidecar_path(path)
    good = side.read_text()
    side.write_text(good[:-10])
    _fails(path, r"a.json:\d+: not valid JSON", named=side)
    side.write_bytes(b"\xef\xbb\xbf" + good.encode())
    _fails(path, "byte-order mark", named=side)
    for key, value, pattern in (("format", "robustbench3d.roof_object/0", "field 'format'"),
                                ("bounds", [0.4, 0.4], "field 'bounds'"),
                                ("template", {"level": 5, "radius": 0.4}, "field 'template'"),
                                ("placement", {"rule": "bonnet"}, "field 'placement'"),
                                ("ply_sha256", "abc", "field 'ply_sha256'")):
        data = json.loads(good)
        data[key] = value
        side.write_text(json.dumps(data))
        _fails(path, pattern, named=side)
    side.write_text("[1, 2]")
    _fails(path, "expected a JSON object", named=side)


def test_garbage_ply(tmp_path):
    path = tmp_path / "a.ply"
    path.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 5\nend_header\n\x00\x01")
    write_sidecar(path, (0.4, 0.4, 0.4))
    with pytest.raises(DataFormatError) as info:
        load_object(path)
    assert info.value.path == path
