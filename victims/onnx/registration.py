"""ONNX victim directories in the victim registry.

Shipped ONNX exports (:data:`SHIPPED`, directories under the package's ``victims/weights/``)
register with origin ``onnx shipped``. Users add theirs in two ways, both through
:data:`robustbench3d.victims.VICTIMS`:

* ``robustbench3d victims add-onnx DIR [--name NAME]`` records NAME -> DIR in the user registry
  file ``<cache>/victims/onnx.json`` (:func:`user_registry_file`; origin ``onnx user registry``);
  :func:`register_user_victims` is one of the registry's loaders, so the file is read on the
  first lookup (not when this module is imported). ``victims remove NAME`` deletes an entry.
* a directory given directly to ``run --victims`` is registered under its directory name for the run
  (origin ``onnx directory``): :func:`directory_reference` is the registry's path resolver
  (:meth:`robustbench3d.registry.Registry.resolve`).

Names derived from a directory name (:func:`robustbench3d.registry.sanitise_name`) are folded to ASCII
(NFKD, accents dropped: ``nüscénes-dét`` -> ``nuscenes-det``); a letter or digit with no ASCII form (``日本``)
makes the name underivable, and ``--name`` is then required.

An entry's ``weights_sha256`` is the sha256 of the directory's ``manifest.json`` (which pins every
stage file's sha256), so results record exactly which graphs ran. Nothing is validated at
registration; creating the victim validates everything (:class:`~.runtime.OnnxCascade`).

Standard library only (listing victims stays cheap).
"""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any

from robustbench3d.errors import DataFormatError, RobustBenchError
from robustbench3d.fileio import atomic_write_text, read_user_text, sha256_file
from robustbench3d.paths import cache_dir
from robustbench3d.registry import RegistryError, sanitise_name
from robustbench3d.victims import VICTIMS
from robustbench3d.victims.onnx import MANIFEST_FILE
from robustbench3d.victims.onnx.manifest import POINTPILLARS_FORMAT, manifest_format
from robustbench3d.victims.spec import Capabilities, EntryInfo, VictimSpec

if TYPE_CHECKING:
    from robustbench3d.victims.onnx.runtime import OnnxCascade

REGISTRY_FORMAT = "robustbench3d.onnx_victims/1"
ONNX_CAPABILITIES = Capabilities(modalities=("camera", "lidar"), backend="onnx", gradients=False, deterministic=True)
ONNX_LIDAR_CAPABILITIES = Capabilities(modalities=("lidar",), backend="onnx", gradients=False, deterministic=True)
ORIGIN_SHIPPED = "onnx shipped"
ORIGIN_USER = "onnx user registry"
ORIGIN_DIRECTORY = "onnx directory"


def user_registry_file() -> Path:
    """``<cache>/victims/onnx.json`` (see :func:`robustbench3d.paths.cache_dir`)."""
    return cache_dir() / "victims" / "onnx.json"


class OnnxVictimFactory:
    """Factory of the ONNX victim in one directory.

    Its registry identity (``__module__:__qualname__``) names the resolved directory, so
    registering the same directory twice under a name is a no-op and a different directory under
    a taken name is a collision.
    """

    def __init__(self, directory: str | Path):
        self.directory = Path(directory).expanduser().resolve()
        self.__module__ = __name__
        self.__qualname__ = f"OnnxVictimFactory[{self.directory}]"

    def __call__(self, *, seed: int | None = None, gather: str | None = None, threads: int = 1,
                 score_threshold: float | None = None, max_detections: int | None = None) -> OnnxCascade | Any:
        """The cascade (``seed``, ``gather``, ``threads``) or, for a PointPillars directory, the PointPillars
        twin (``threads``, ``score_threshold``, ``max_detections``; ``seed``, which the runner passes every
        victim taking one, is accepted and unused: the twin draws nothing); an argument of the other kind is
        refused."""
        if manifest_format(self.directory) == POINTPILLARS_FORMAT:
            if gather is not None:
                raise RobustBenchError(f"victim argument 'gather' is for F-PN cascades; {self.directory} holds a "
                                       "PointPillars graph")
            from robustbench3d.victims.onnx.pointpillars import PointPillarsOnnx

            return PointPillarsOnnx(self.directory, threads=threads, score_threshold=score_threshold,
                                    max_detections=max_detections)
        if score_threshold is not None or max_detections is not None:
            raise RobustBenchError(f"victim arguments 'score_threshold' and 'max_detections' are for PointPillars "
                                   f"graphs; {self.directory} holds an F-PN cascade")
        from robustbench3d.victims.onnx.runtime import OnnxCascade

        return OnnxCascade(self.directory, seed=seed, gather=gather, threads=threads)


def victim_spec(directory: str | Path) -> VictimSpec:
    """The registry entry of an ONNX victim directory (not validated here)."""
    factory = OnnxVictimFactory(directory)
    manifest = factory.directory / MANIFEST_FILE
    sha = sha256_file(manifest) if manifest.is_file() else None
    state = "" if sha else " (manifest.json missing)"
    if manifest_format(factory.directory) == POINTPILLARS_FORMAT:
        info = EntryInfo(capabilities=ONNX_LIDAR_CAPABILITIES, weights_sha256=sha,
                         summary=f"ONNX PointPillars (LiDAR only) in {factory.directory}")
    else:
        info = EntryInfo(capabilities=ONNX_CAPABILITIES, weights_sha256=sha,
                         summary=f"ONNX F-PN cascade in {factory.directory}{state}")
    return VictimSpec(factory=factory, info=info)


def register_directory(name: str, directory: str | Path, origin: str = ORIGIN_DIRECTORY) -> str:
    """Register the ONNX victim in ``directory`` as ``name`` (idempotent for the same directory).

    The registry's own entries (in-tree, shipped, user file, plugins) are discovered first, so
    they take precedence over a directory registered for one run.
    """
    VICTIMS.names()
    VICTIMS.register(name, victim_spec(directory), origin=origin)
    return name


def name_for_directory(directory: Path, how: str = "give one with --name NAME") -> str:
    """The victim name derived from ``directory``'s name (:func:`sanitise_name`); raises
    :class:`RobustBenchError` when none can be derived, saying ``how`` to name it instead."""
    name = sanitise_name(directory.name)
    if not name:
        raise RobustBenchError(f"{directory}: no victim name can be derived from the folder name "
                               f"{directory.name!r} (only letters and digits that fold to ASCII make a name); "
                               f"{how}")
    return name


def looks_like_path(reference: str) -> bool:
    """True if a ``--victims`` entry names a directory rather than a registered victim."""
    return (os.sep in reference or "/" in reference or reference.startswith((".", "~"))
            or (Path(reference).is_dir() and (Path(reference) / MANIFEST_FILE).is_file()))


def directory_reference(reference: str) -> str | None:
    """The victim registry's path resolver: None for a name; an ONNX victim directory is registered under
    its sanitised directory name (origin ``onnx directory``), which is returned."""
    if not looks_like_path(reference):
        return None
    directory = Path(reference).expanduser().resolve()
    if not (directory / MANIFEST_FILE).is_file():
        raise DataFormatError(directory / MANIFEST_FILE, "not an ONNX victim directory (no manifest.json); "
                                                         "write one with `robustbench3d victims export-onnx`")
    name = name_for_directory(directory, "register it with `robustbench3d victims add-onnx DIR --name NAME`")
    return VICTIMS.register_reference(
        name, victim_spec(directory), origin=ORIGIN_DIRECTORY,
        taken=f"--victims {reference}: the directory's name {name!r} is already a registered victim; rename the "
              "directory or register it under another name with `robustbench3d victims add-onnx DIR --name NAME`")


def read_user_registry(path: Path | None = None) -> dict[str, str]:
    """NAME -> directory entries of the user registry file ({} if there is none)."""
    path = path or user_registry_file()
    if not path.is_file():
        return {}
    try:
        data = json.loads(read_user_text(path))
    except json.JSONDecodeError as exc:
        raise DataFormatError(path, f"not valid JSON ({exc}); fix or delete the file") from None
    if not isinstance(data, dict) or data.get("format") != REGISTRY_FORMAT or not isinstance(data.get("victims"), dict):
        raise DataFormatError(path, f"expected {{'format': {REGISTRY_FORMAT!r}, 'victims': {{NAME: DIR}}}}; "
                                    "fix or delete the file")
    entries = data["victims"]
    bad = [k for k, v in entries.items() if not isinstance(v, str)]
    if bad:
        raise DataFormatError(path, f"entry {bad[0]!r}: the directory must be a string")
    return dict(entries)


def add_user_victim(name: str, directory: str | Path, *, replace: bool = False) -> Path:
    """Record ``name`` -> ``directory`` in the user registry file (atomically) and register it.

    Raises :class:`RobustBenchError` if ``name`` is taken by another victim (unless ``replace``
    and the other one is a user ONNX entry; a replaced entry takes effect in new processes).
    Returns the registry file.
    """
    path = user_registry_file()
    entries = read_user_registry(path)
    directory = Path(directory).expanduser().resolve()
    if sanitise_name(name) != name:
        fixed = sanitise_name(name)
        raise RobustBenchError(f"victim name {name!r} must be lowercase letters, digits, '.', '_' or '-'"
                               + (f" (e.g. {fixed!r})" if fixed else ""))
    if name in VICTIMS and name not in entries:
        raise RobustBenchError(f"victim name {name!r} is taken by a {VICTIMS.entry(name).origin} victim; choose "
                               "another --name")
    if name in entries and Path(entries[name]) != directory and not replace:
        raise RobustBenchError(f"victim {name!r} already points to {entries[name]} in {path}; pass --replace to "
                               "point it to the new directory")
    entries[name] = str(directory)
    _write_user_registry(path, entries)
    if name not in VICTIMS:
        register_directory(name, directory, ORIGIN_USER)
    return path


def remove_user_victim(name: str) -> tuple[Path, str]:
    """Delete ``name`` from the user registry file (undoing ``victims add-onnx``) and unregister
    it. Returns the file and the directory the entry pointed to.

    Raises :class:`RobustBenchError` for a victim that is registered another way (in-tree,
    shipped, plugin, a directory of this run) and :class:`~robustbench3d.registry.UnknownNameError`
    for an unknown name.
    """
    path = user_registry_file()
    entries = read_user_registry(path)
    if name not in entries:
        origin = VICTIMS.entry(name).origin  # unknown names raise here, with did-you-mean
        if origin.startswith("plugin "):
            how = f"uninstall the plugin's distribution ({origin.split()[1]}) instead"
        elif origin == ORIGIN_DIRECTORY:
            how = "it is registered for this run only"
        else:
            how = "it ships with robustbench3d"
        raise RobustBenchError(f"victim {name!r} ({origin}) was not added with `victims add-onnx`, so it cannot be "
                               f"removed (only entries of {path} can); {how}")
    directory = entries.pop(name)
    _write_user_registry(path, entries)
    if name in VICTIMS and VICTIMS.entry(name).origin == ORIGIN_USER:
        VICTIMS.unregister(name)
    return path, directory


def _write_user_registry(path: Path, entries: dict[str, str]) -> None:
    text = json.dumps({"format": REGISTRY_FORMAT, "victims": dict(sorted(entries.items()))}, indent=2) + "\n"
    atomic_write_text(path, text)


#: shipped ONNX victim name -> its directory under :func:`robustbench3d.victims.shipped.weights_dir`
SHIPPED: dict[str, str] = {"fpointnet-v1-lite-onnx": "fpointnet-v1-lite-onnx",
                           "fpointnet-v1-onnx": "fpointnet-v1-onnx"}
#: shipped PointPillars ONNX twins (one graph each; :mod:`robustbench3d.victims.onnx.pointpillars`), likewise
SHIPPED_POINTPILLARS: dict[str, str] = {"pointpillars-onnx": "pointpillars-onnx"}


def register_shipped_victims() -> None:
    """Register every shipped ONNX export whose directory is present."""
    from robustbench3d.victims.shipped import weights_dir

    for name, sub in {**SHIPPED, **SHIPPED_POINTPILLARS}.items():
        directory = weights_dir() / sub
        if (directory / MANIFEST_FILE).is_file():
            register_directory(name, directory, ORIGIN_SHIPPED)


def register_user_victims() -> None:
    """Register the shipped ONNX victims and every entry of the user registry file (the victim
    registry's loader, run on its first lookup). A broken file or entry is skipped with a warning
    naming it (it must not make every other victim unusable)."""
    register_shipped_victims()
    try:
        entries = read_user_registry()
    except DataFormatError as exc:
        warnings.warn(f"ignoring the ONNX victim registry: {exc}", stacklevel=2)
        return
    for name, directory in entries.items():
        try:
            register_directory(name, directory, ORIGIN_USER)
        except (RegistryError, OSError) as exc:
            warnings.warn(f"{user_registry_file()}: ignoring entry {name!r}: {exc}", stacklevel=2)
