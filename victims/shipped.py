"""Weights that ship inside the package (``robustbench3d/victims/weights/``).

``weights/manifest.json`` lists every shipped file: the victim it belongs to, its sha256 and size,
how it was made (the training commands with their full run configurations, dataset parameters and
identity, seeds, precision and thread counts, library versions, CPU) and the accuracy measured with
it on the embedded val split (the ``robustbench3d run`` summary it was checked with). The registry
takes each victim's ``weights_sha256`` from here and loading checks the file against it.

Standard library only: listing victims reads this manifest without importing torch.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from robustbench3d.errors import DataFormatError, RobustBenchError
from robustbench3d.fileio import sha256_file, upsert_json_entry

MANIFEST_FORMAT = "robustbench3d.shipped_weights/1"
MANIFEST_NAME = "manifest.json"


def weights_dir() -> Path:
    """Directory of the shipped weights and their manifest (inside the installed package)."""
    return Path(__file__).resolve().parent / "weights"


@dataclass(frozen=True)
class ShippedWeights:
    """One manifest entry: ``victim`` name, weights ``path``, its ``sha256`` (lowercase hex) and
    ``size_bytes``, and the whole ``record`` (provenance and measured accuracy)."""

    victim: str
    path: Path
    sha256: str
    size_bytes: int
    record: dict[str, Any]

    def verify(self) -> None:
        """Raise :class:`RobustBenchError` unless the file exists with the recorded size and hash."""
        if not self.path.is_file():
            raise RobustBenchError(f"{self.path}: shipped weights of {self.victim!r} are missing")
        if self.path.stat().st_size != self.size_bytes or sha256_file(self.path) != self.sha256:
            raise RobustBenchError(f"{self.path}: does not match the sha256 {self.sha256} recorded in "
                                   f"{weights_dir() / MANIFEST_NAME}")


def read_manifest(path: Path | None = None) -> dict[str, Any]:
    """The manifest (``{"format", "weights": [entry, ...]}``); an empty one if the file is absent."""
    path = path or weights_dir() / MANIFEST_NAME
    if not path.is_file():
        return {"format": MANIFEST_FORMAT, "weights": []}
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataFormatError(path, f"not valid JSON ({exc})") from None
    if not isinstance(data, dict) or data.get("format") != MANIFEST_FORMAT or not isinstance(data.get("weights"), list):
        raise DataFormatError(path, f"field 'format': expected {MANIFEST_FORMAT!r} with a 'weights' list")
    for i, entry in enumerate(data["weights"]):
        for field in ("victim", "file", "sha256", "size_bytes"):
            if field not in entry:
                raise DataFormatError(path, f"weights[{i}]: field '{field}' is missing")
    return data


def shipped(victim: str, manifest: Path | None = None) -> ShippedWeights | None:
    """The shipped weights of ``victim``, or None if none ship."""
    data = read_manifest(manifest)
    base = (manifest.parent if manifest else weights_dir())
    for entry in data["weights"]:
        if entry["victim"] == victim:
            return ShippedWeights(victim=victim, path=base / entry["file"], sha256=entry["sha256"],
                                  size_bytes=int(entry["size_bytes"]), record=entry)
    return None


def shipped_sha256(victim: str) -> str | None:
    """sha256 of ``victim``'s shipped weights (for its registry entry), None if none ship."""
    entry = shipped(victim)
    return entry.sha256 if entry else None


def upsert_entry(manifest: Path, entry: dict[str, Any]) -> dict[str, Any]:
    """Replace (or add) the entry of ``entry["victim"]`` and write the manifest atomically (entries sorted
    by victim); returns the new content."""
    return upsert_json_entry(manifest, read_manifest(manifest), "weights", "victim", entry)
