"""In-tree attacks, registered with :func:`robustbench3d.attacks.register_attack` (the home of every attack kind
that ships with the package, as :mod:`robustbench3d.victims.zoo` is for victims).

A new attack kind is an :class:`~robustbench3d.attacks.base.Attack` subclass in its own module, plus a factory
here decorated with :func:`~robustbench3d.attacks.register_attack` (its name, the victim
:class:`~robustbench3d.attacks.spec.AttackRequirements`, a one-line summary). Factories import their
implementation when called. An attack shipped by another package registers through the entry-point group
``robustbench3d.attacks`` instead (``examples/lidar_dropout_attack`` is a complete one).

Registered here:

* the controls (:mod:`robustbench3d.attacks.controls`): ``none`` (:class:`~robustbench3d.attacks.controls.NoAttack`,
  frames unchanged), ``benign-sphere`` (the undeformed grey sphere) and ``random-shape`` (a seeded random smooth
  deformation with random colours, param ``seed`` in [0, 2**32 - 1]) on every target car
  (:class:`~robustbench3d.attacks.roof.RoofObjectAttack`); both take the object family's params ``level`` (2, 3
  or 4) and ``radius`` (m, [0.2, 0.6]; :class:`~robustbench3d.attacks.object.Family`), default 2 and 0.40 (the
  default family), so a sweep places the control of each size: ``--attacks benign-sphere:radius=0.6``;
* ``object-file`` (param ``path``): any object file (:mod:`robustbench3d.attacks.objectfile`). A reference ending
  in ``.ply`` (``run --attacks F.ply``, ``attack apply F.ply``) names such a file directly:
  :func:`object_file_reference` is the registry's path resolver
  (:meth:`~robustbench3d.registry.Registry.resolve`).

Every roof-object factory takes the attack's settings (:data:`~robustbench3d.attacks.roof.SETTINGS`: eot, jitter
ranges, LiDAR noise and dropout, supersample, occlusion, cull) as keyword arguments
(:func:`~robustbench3d.attacks.roof.roof_settings`). The universal objects that ship with the package register
from their manifest (:mod:`robustbench3d.attacks.shipped`, the registry's loader), each as ``object-file`` loads
its PLY.
"""

from __future__ import annotations

import inspect
from pathlib import Path
from typing import TYPE_CHECKING, Any

from robustbench3d.attacks import ATTACKS, register_attack
from robustbench3d.attacks.controls import NoAttack
from robustbench3d.attacks.roof import roof_settings, settings_parameters
from robustbench3d.attacks.spec import MAX_SEED, AttackRequirements, AttackSpec, AttackSpecError
from robustbench3d.errors import RobustBenchError
from robustbench3d.registry import sanitise_name

if TYPE_CHECKING:
    from robustbench3d.attacks.object import Family
    from robustbench3d.attacks.roof import RoofObjectAttack

#: Origin of an object file registered from a reference (listed by ``attack list``, recorded in provenance).
ORIGIN_OBJECT_FILE = "object file"

register_attack("none", requirements=AttackRequirements(),
                summary="control: no object placed, frames unchanged (clean AP)")(NoAttack)


def _family(level: Any, radius: Any) -> tuple[Family, dict[str, Any]]:
    """The object family of a control's ``level`` and ``radius`` params (:class:`AttackSpecError` naming the field
    and its range otherwise) and what its identity records of it: nothing for the default family (so the default
    controls describe themselves as before families existed), else level, radius and the family's name."""
    from robustbench3d.attacks.object import Family

    try:
        family = Family(level, radius)
    except ValueError as exc:
        raise AttackSpecError(str(exc)) from None
    return family, ({} if family.is_default else {"level": family.level, "radius": family.radius,
                                                  "family": family.name})


@register_attack("benign-sphere", summary="control: the undeformed grey sphere (r 0.40 m; params level, radius) on "
                                          "every target car's roof")
@roof_settings
def benign_sphere_attack(level: int = 2, radius: float = 0.40, **settings: Any) -> RoofObjectAttack:
    """:func:`~robustbench3d.attacks.object.benign_sphere` of the family (``level``, ``radius``) on every target
    car (EOT jitter if ``eot``)."""
    from robustbench3d.attacks.object import benign_sphere
    from robustbench3d.attacks.roof import RoofObjectAttack

    family, record = _family(level, radius)
    return RoofObjectAttack(benign_sphere(family), identity={"attack": "benign-sphere", **record}, **settings)


@register_attack("random-shape", summary="control: a seeded random smooth shape with random colours (params seed, "
                                         "level, radius)")
@roof_settings
def random_shape_attack(seed: int = 0, level: int = 2, radius: float = 0.40, **settings: Any) -> RoofObjectAttack:
    """:func:`~robustbench3d.attacks.object.random_shape` of ``seed`` and the family (``level``, ``radius``) on
    every target car."""
    from robustbench3d.attacks.object import random_shape
    from robustbench3d.attacks.roof import RoofObjectAttack

    if not isinstance(seed, bool) and isinstance(seed, int) and seed > MAX_SEED:  # the rest: random_shape's check
        raise AttackSpecError(f"field 'seed': expected an integer in [0, 2**32 - 1], got {seed!r}")
    family, record = _family(level, radius)
    try:
        obj = random_shape(seed, family=family)
    except ValueError as exc:
        raise AttackSpecError(str(exc)) from None
    return RoofObjectAttack(obj, identity={"attack": "random-shape", "seed": seed, **record}, **settings)


@register_attack("object-file", summary="the object in a PLY object file (param path) on every target car")
@roof_settings
def object_file_attack(path: str, **settings: Any) -> RoofObjectAttack:
    """The object of the file ``path`` (checked by :func:`~robustbench3d.attacks.objectfile.read_object_file`)."""
    from robustbench3d.attacks.objectfile import read_object_file
    from robustbench3d.attacks.roof import RoofObjectAttack

    loaded = read_object_file(path)
    return RoofObjectAttack(loaded.obj, identity=loaded.made_by, sha256=loaded.sha256, **settings)


class ObjectFileFactory:
    """Factory of the attack of one object file; its registry identity names the resolved path, so
    registering the same file twice under a name is a no-op and another file under a taken name a collision."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path).expanduser().resolve()
        self.__module__ = __name__
        self.__qualname__ = f"ObjectFileFactory[{self.path}]"
        # what AttackSpec.create binds: the roof-object settings, keyword-only
        self.__signature__ = inspect.Signature(settings_parameters(), return_annotation="RoofObjectAttack")

    def __call__(self, **settings: Any) -> RoofObjectAttack:
        return object_file_attack(str(self.path), **settings)


def object_file_reference(reference: str) -> str | None:
    """The attack registry's path resolver: None for a name; a reference ending in ``.ply`` is an object file,
    registered for this process under its sanitised file stem (origin ``object file``), which is returned."""
    if not reference.lower().endswith(".ply"):
        return None
    path = Path(reference).expanduser()
    if not path.is_file():
        raise RobustBenchError(f"--attacks {reference}: no such object file")
    name = sanitise_name(path.stem)
    if not name:
        raise RobustBenchError(f"--attacks {reference}: no attack name can be derived from the file name; "
                               "rename the file (letters and digits that fold to ASCII)")
    return ATTACKS.register_reference(
        name, AttackSpec(factory=ObjectFileFactory(path), summary=f"object file {path.resolve()}"),
        origin=ORIGIN_OBJECT_FILE,
        taken=f"--attacks {reference}: the file's name {name!r} is already a registered attack; rename the file")


__all__ = [
    "ORIGIN_OBJECT_FILE", "ObjectFileFactory", "benign_sphere_attack", "object_file_attack", "object_file_reference",
    "random_shape_attack",
]
