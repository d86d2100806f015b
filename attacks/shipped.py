"""Universal adversarial objects that ship inside the package (``robustbench3d/attacks/objects/``).

Each shipped object is the pair ``NAME.ply`` + ``NAME.json`` exactly as ``robustbench3d attack train``
wrote it (:mod:`robustbench3d.attacks.objectfile`). ``objects/manifest.json`` lists them: per object its
``name`` (the attack it registers as), ``file``, ``sha256`` and ``size_bytes``, the same for its
``sidecar``, a one-line ``summary``, the ``training`` record (the ``attack train`` command, its config,
seed, victim with its weights sha256, training-data identity, steps and wall time: the sidecar's
``made_by`` plus the command) and, optionally, the ``evaluation`` measured with it. ``tools/ship_object.py``
writes entries; ``objects/reproduce.sh`` retrains the objects.

:func:`register_shipped_objects` is a loader of :data:`robustbench3d.attacks.ATTACKS`: on the first
lookup every entry becomes an attack of that name whose factory (the roof-object settings) checks the files against
the manifest and then loads the PLY as the ``object-file`` attack does.

Standard library only: listing attacks reads this manifest without importing numpy or torch.
"""

from __future__ import annotations

import inspect
import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from robustbench3d.errors import DataFormatError, RobustBenchError
from robustbench3d.fileio import sha256_file, upsert_json_entry

if TYPE_CHECKING:
    from robustbench3d.attacks.roof import RoofObjectAttack
    from robustbench3d.attacks.spec import AttackSpec
    from robustbench3d.registry import Registry

MANIFEST_FORMAT = "robustbench3d.shipped_objects/1"
MANIFEST_NAME = "manifest.json"
ORIGIN = "shipped object"
#: Keys every ``training`` record carries (``command`` plus the sidecar's ``made_by`` fields).
TRAINING_FIELDS: dict[str, type | tuple[type, ...]] = {
    "command": str, "attack": str, "config": dict, "seed": int, "steps": int, "wall_time_s": (int, float),
    "victim": dict, "training_data": dict,
}
_NAME = re.compile(r"^[a-z0-9][a-z0-9._-]*$")
_SHA256 = re.compile(r"^[0-9a-f]{64}$")


def objects_dir() -> Path:
    """Directory of the shipped objects and their manifest (inside the installed package)."""
    return Path(__file__).resolve().parent / "objects"


def manifest_path() -> Path:
    """The package's ``objects/manifest.json``."""
    return objects_dir() / MANIFEST_NAME


@dataclass(frozen=True)
class ShippedObject:
    """One manifest entry: the attack ``name``, the object file ``path`` (its sidecar beside it) with its
    ``sha256`` and ``size_bytes``, the sidecar's, the ``manifest`` it came from and the whole ``record``."""

    name: str
    path: Path
    sha256: str
    size_bytes: int
    sidecar_path: Path
    sidecar_sha256: str
    sidecar_size_bytes: int
    manifest: Path
    record: dict[str, Any]

    @property
    def summary(self) -> str:
        return str(self.record["summary"])

    def verify(self) -> None:
        """Raise :class:`RobustBenchError` naming the file unless the PLY and its sidecar exist with the
        size and sha256 recorded in the manifest."""
        for path, sha, size, what in ((self.path, self.sha256, self.size_bytes, "object file"),
                                      (self.sidecar_path, self.sidecar_sha256, self.sidecar_size_bytes, "sidecar")):
            if not path.is_file():
                raise RobustBenchError(f"{path}: {what} of the shipped attack {self.name!r} is missing "
                                       f"(listed in {self.manifest})")
            actual_size = path.stat().st_size
            if actual_size != size:
                raise RobustBenchError(f"{path}: {actual_size} bytes, but {self.manifest} records {size} bytes "
                                       f"for the {what} of {self.name!r}")
            actual = sha256_file(path)
            if actual != sha:
                raise RobustBenchError(f"{path}: sha256 {actual} does not match the sha256 {sha} recorded in "
                                       f"{self.manifest} for the {what} of {self.name!r}")


def empty_manifest() -> dict[str, Any]:
    return {"format": MANIFEST_FORMAT, "objects": []}


def _check(ok: bool, path: Path, field: str, problem: str) -> None:
    if not ok:
        raise DataFormatError(path, problem, field=field)


def _check_file_record(rec: Any, path: Path, where: str, suffix: str) -> None:
    """``rec`` has a bare ``file`` name ending in ``suffix``, a lowercase hex ``sha256`` and ``size_bytes``."""
    _check(isinstance(rec, dict), path, where, f"expected a JSON object, got {type(rec).__name__}")
    file = rec.get("file")
    _check(isinstance(file, str) and file == Path(file).name and file.endswith(suffix) and file != suffix,
           path, f"{where}.file", f"expected a file name ending in {suffix} (no directory), got {file!r}")
    _check(isinstance(rec.get("sha256"), str) and bool(_SHA256.match(rec["sha256"])), path, f"{where}.sha256",
           f"expected 64 lowercase hex digits, got {rec.get('sha256')!r}")
    size = rec.get("size_bytes")
    _check(isinstance(size, int) and not isinstance(size, bool) and size > 0, path, f"{where}.size_bytes",
           f"expected an integer > 0, got {size!r}")


def validate_manifest(data: Any, path: Path) -> dict[str, Any]:
    """Check a manifest's content (``path`` names it in errors); returns ``data``.

    Raises :class:`DataFormatError` ``<path>: field '<field>': <problem>`` for the first problem, the field
    written as ``objects[i].training.victim.name``.
    """
    _check(isinstance(data, dict), path, "format", "expected a JSON object")
    _check(data.get("format") == MANIFEST_FORMAT, path, "format",
           f"expected {MANIFEST_FORMAT!r}, got {data.get('format')!r}")
    objects = data.get("objects")
    _check(isinstance(objects, list), path, "objects", f"expected a list, got {type(objects).__name__}")
    seen: set[str] = set()
    for i, entry in enumerate(objects):
        where = f"objects[{i}]"
        _check(isinstance(entry, dict), path, where, f"expected a JSON object, got {type(entry).__name__}")
        name = entry.get("name")
        _check(isinstance(name, str) and bool(_NAME.match(name)), path, f"{where}.name",
               f"expected an attack name matching {_NAME.pattern}, got {name!r}")
        _check(name not in seen, path, f"{where}.name", f"{name!r} is listed twice")
        seen.add(name)
        _check_file_record(entry, path, where, ".ply")
        _check_file_record(entry.get("sidecar"), path, f"{where}.sidecar", ".json")
        expected = entry["file"][:-len(".ply")] + ".json"
        _check(entry["sidecar"]["file"] == expected, path, f"{where}.sidecar.file",
               f"expected {expected!r} (the PLY's stem), got {entry['sidecar']['file']!r}")
        _check(isinstance(entry.get("summary"), str) and bool(entry["summary"].strip())
               and "\n" not in entry["summary"], path, f"{where}.summary", "expected one non-empty line")
        training = entry.get("training")
        _check(isinstance(training, dict), path, f"{where}.training",
               f"expected a JSON object, got {type(training).__name__}")
        for key, kind in TRAINING_FIELDS.items():
            value = training.get(key)
            _check(isinstance(value, kind) and not isinstance(value, bool), path, f"{where}.training.{key}",
                   f"expected {_kind_name(kind)}, got {value!r}")
        victim = training["victim"]
        _check(isinstance(victim.get("name"), str) and bool(victim["name"]), path, f"{where}.training.victim.name",
               f"expected the victim's name, got {victim.get('name')!r}")
        wsha = victim.get("weights_sha256")
        _check(wsha is None or (isinstance(wsha, str) and bool(_SHA256.match(wsha))), path,
               f"{where}.training.victim.weights_sha256", f"expected 64 lowercase hex digits or null, got {wsha!r}")
        _check(isinstance(entry.get("evaluation", {}), dict), path, f"{where}.evaluation",
               f"expected a JSON object when present, got {type(entry.get('evaluation')).__name__}")
    return data


def _kind_name(kind: type | tuple[type, ...]) -> str:
    kinds = kind if isinstance(kind, tuple) else (kind,)
    words = {str: "a string", int: "an integer", float: "a number", dict: "a JSON object"}
    return " or ".join(words[k] for k in kinds)


def read_manifest(path: Path | None = None) -> dict[str, Any]:
    """The checked manifest (:func:`validate_manifest`); an empty one if the file is absent."""
    path = path or manifest_path()
    if not path.is_file():
        return empty_manifest()
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataFormatError(path, f"not valid JSON ({exc})") from None
    return validate_manifest(data, path)


def _entry(record: dict[str, Any], manifest: Path) -> ShippedObject:
    base = manifest.parent
    return ShippedObject(name=record["name"], path=base / record["file"], sha256=record["sha256"],
                         size_bytes=record["size_bytes"], sidecar_path=base / record["sidecar"]["file"],
                         sidecar_sha256=record["sidecar"]["sha256"],
                         sidecar_size_bytes=record["sidecar"]["size_bytes"], manifest=manifest, record=record)


def shipped_objects(manifest: Path | None = None) -> list[ShippedObject]:
    """Every entry of the manifest (default: the package's), in manifest order."""
    manifest = (manifest or manifest_path()).resolve()
    return [_entry(rec, manifest) for rec in read_manifest(manifest)["objects"]]


def shipped_object(name: str, manifest: Path | None = None) -> ShippedObject | None:
    """The entry ``name``, or None if no such object ships."""
    return next((e for e in shipped_objects(manifest) if e.name == name), None)


def upsert_entry(manifest: Path, entry: dict[str, Any]) -> dict[str, Any]:
    """Replace (or add) the entry of ``entry["name"]``, check the result and write the manifest atomically
    (entries sorted by name); returns the new content."""
    return upsert_json_entry(manifest, read_manifest(manifest), "objects", "name", entry,
                             lambda data: validate_manifest(data, manifest))


class _SettingsSignature:
    """``__signature__`` of a factory instance: the roof-object settings, keyword-only (what ``AttackSpec.create``
    binds), built on first use (it imports numpy). On the class itself there is none (inspect then reads the
    class's own signature)."""

    def __get__(self, instance: object, owner: type | None = None) -> inspect.Signature:
        if instance is None:
            raise AttributeError("__signature__")
        from robustbench3d.attacks.roof import settings_parameters

        return inspect.Signature(settings_parameters(), return_annotation="RoofObjectAttack")


class ShippedObjectFactory:
    """Factory of the attack of one shipped object; its registry identity names the entry and the manifest,
    so re-registering the same entry is a no-op."""

    def __init__(self, entry: ShippedObject) -> None:
        self.entry = entry
        self.__module__ = __name__
        self.__qualname__ = f"ShippedObjectFactory[{entry.name}@{entry.manifest}:{entry.sha256}]"

    __signature__ = _SettingsSignature()

    def __call__(self, **settings: Any) -> RoofObjectAttack:
        """Verify the files against the manifest, then load the PLY as the ``object-file`` attack does
        (:func:`~robustbench3d.attacks.zoo.object_file_attack`, with the attack's ``settings``:
        :data:`~robustbench3d.attacks.roof.SETTINGS`)."""
        from robustbench3d.attacks.zoo import object_file_attack

        self.entry.verify()
        attack = object_file_attack(str(self.entry.path), **settings)
        if attack.sha256 != self.entry.sha256:  # the file changed between the check and the load
            raise RobustBenchError(f"{self.entry.path}: changed while loading (sha256 {attack.sha256}, "
                                   f"{self.entry.manifest} records {self.entry.sha256})")
        return attack


def attack_spec(entry: ShippedObject) -> AttackSpec:
    """The registry entry of a shipped object (nothing is read or verified here)."""
    from robustbench3d.attacks.spec import AttackSpec

    return AttackSpec(factory=ShippedObjectFactory(entry), summary=entry.summary)


def register_shipped_objects(manifest: Path | None = None, registry: Registry[AttackSpec] | None = None) -> list[str]:
    """Register every object of ``manifest`` (default: the package's) in ``registry`` (default
    :data:`~robustbench3d.attacks.ATTACKS`) under its name; returns the names (none for an empty manifest)."""
    if registry is None:
        from robustbench3d.attacks import ATTACKS

        registry = ATTACKS
    names = []
    for entry in shipped_objects(manifest):
        registry.register(entry.name, attack_spec(entry), origin=ORIGIN)
        names.append(entry.name)
    return names
