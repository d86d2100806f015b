"""The one entry update of the shipped-file manifests (robustbench3d.fileio.upsert_json_entry), used by the
weights manifest (victims/shipped.py) and the objects manifest (attacks/shipped.py): replace or add, sorted,
checked before anything is written, the same bytes as a hand-written file."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from robustbench3d.attacks import shipped as shipped_objects
from robustbench3d.errors import DataFormatError
from robustbench3d.fileio import upsert_json_entry
from robustbench3d.victims import shipped as shipped_weights


def test_upsert_replaces_or_adds_sorted_and_writes_indented_sorted_json(tmp_path):
    path = tmp_path / "m.json"
    data = {"format": "f/1", "items": [{"id": "b", "v": 1}, {"id": "c", "v": 2}]}
    out = upsert_json_entry(path, data, "items", "id", {"v": 3, "id": "a"})
    assert out is data and [e["id"] for e in data["items"]] == ["a", "b", "c"]
    upsert_json_entry(path, data, "items", "id", {"id": "b", "v": 9})
    assert data["items"] == [{"id": "a", "v": 3}, {"id": "b", "v": 9}, {"id": "c", "v": 2}]
    want = ('{\n  "format": "f/1",\n  "items": [\n    {\n      "id": "a",\n      "v": 3\n    },\n'
            '    {\n      "id": "b",\n      "v": 9\n    },\n    {\n      "id": "c",\n      "v": 2\n    }\n  ]\n}\n')
    assert path.read_text(encoding="utf-8") == want


def test_a_rejected_update_writes_nothing(tmp_path):
    path = tmp_path / "m.json"
    path.write_text("before\n")

    def check(data):
        if any(e["v"] < 0 for e in data["items"]):
            raise DataFormatError(path, "items[0]: field 'v': negative")

    with pytest.raises(DataFormatError, match="field 'v'"):
        upsert_json_entry(path, {"items": []}, "items", "id", {"id": "a", "v": -1}, check)
    assert path.read_text() == "before\n" and sorted(p.name for p in tmp_path.iterdir()) == ["m.json"]


def test_weights_manifest_entry_is_replaced_by_victim(tmp_path):
    manifest = tmp_path / "weights" / "manifest.json"
    manifest.parent.mkdir()
    entry = {"victim": "z", "file": "z.pt", "sha256": "0" * 64, "size_bytes": 1}
    shipped_weights.upsert_entry(manifest, entry)
    shipped_weights.upsert_entry(manifest, {**entry, "victim": "a", "file": "a.pt"})
    shipped_weights.upsert_entry(manifest, {**entry, "size_bytes": 2})
    data = shipped_weights.read_manifest(manifest)
    assert data["format"] == shipped_weights.MANIFEST_FORMAT
    assert [(e["victim"], e["size_bytes"]) for e in data["weights"]] == [("a", 1), ("z", 2)]
    assert manifest.read_text() == json.dumps(data, indent=2, sort_keys=True) + "\n"


def test_objects_manifest_refuses_a_bad_entry_and_keeps_the_file(tmp_path):
    manifest = tmp_path / "objects" / "manifest.json"
    manifest.parent.mkdir()
    before = json.dumps(shipped_objects.empty_manifest(), indent=2, sort_keys=True) + "\n"
    manifest.write_text(before)
    with pytest.raises(DataFormatError, match=r"objects\[0\]"):
        shipped_objects.upsert_entry(manifest, {"name": "x"})
    assert manifest.read_text() == before
    assert [p.name for p in Path(manifest.parent).iterdir()] == ["manifest.json"]
