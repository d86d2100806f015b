"""Control attacks: the reference cells attacked results are compared against.

``none`` places no object: frames reach the victim unchanged (the clean AP); its record
(:meth:`~robustbench3d.attacks.base.Attack.apply_recorded`) is the nominal one, so the clean cell of the
``gt-object`` protocol gets the default object's union boxes and that of ``gt-append`` the bare GT frustums.
``benign-sphere`` (the undeformed grey sphere) and ``random-shape`` (a seeded random smooth deformation with random
colours, param ``seed`` in [0, 2**32 - 1]) put a physical but unoptimised object on every target car
(:class:`~robustbench3d.attacks.roof.RoofObjectAttack`): how much AP a mere object costs.
``object-file`` (param ``path``) applies any object file (:mod:`robustbench3d.attacks.objectfile`);
:func:`resolve_attack_references` lets ``run --attacks`` name such a file directly. Every roof-object
factory also takes the attack's settings (:data:`~robustbench3d.attacks.roof.SETTINGS`: eot, jitter ranges,
LiDAR noise and dropout, supersample, occlusion, cull) as keyword arguments
(:func:`~robustbench3d.attacks.roof.roof_settings`).
"""

from __future__ import annotations

import inspect
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from robustbench3d.attacks import ATTACKS, register_attack
from robustbench3d.attacks.base import Attack
from robustbench3d.attacks.roof import roof_settings, settings_parameters
from robustbench3d.attacks.spec import MAX_SEED, AttackRequirements, AttackSpec, AttackSpecError
from robustbench3d.errors import RobustBenchError
from robustbench3d.kitti.dataset import Frame
from robustbench3d.kitti.labels import Labels
from robustbench3d.registry import RegistryError

if TYPE_CHECKING:
    from robustbench3d.attacks.roof import RoofObjectAttack


@register_attack("none", requirements=AttackRequirements(),
                 summary="control: no object placed, frames unchanged (clean AP)")
class NoAttack(Attack):
    """No object: :meth:`apply` returns the frame itself, bit for bit."""

    def apply(self, frame: Frame, targets: Labels, rng: np.random.Generator) -> Frame:
        return frame

    def describe(self) -> dict[str, Any]:
        return {"object": None}


@register_attack("benign-sphere", summary="control: the undeformed grey sphere (r 0.40 m) on every target car's roof")
@roof_settings
def benign_sphere_attack(**settings: Any) -> RoofObjectAttack:
    """:func:`~robustbench3d.attacks.object.benign_sphere` on every target car (EOT jitter if ``eot``)."""
    from robustbench3d.attacks.object import benign_sphere
    from robustbench3d.attacks.roof import RoofObjectAttack

    return RoofObjectAttack(benign_sphere(), identity={"attack": "benign-sphere"}, **settings)


@register_attack("random-shape", summary="control: a seeded random smooth shape with random colours (param seed)")
@roof_settings
def random_shape_attack(seed: int = 0, **settings: Any) -> RoofObjectAttack:
    """:func:`~robustbench3d.attacks.object.random_shape` of ``seed`` on every target car."""
    from robustbench3d.attacks.object import random_shape
    from robustbench3d.attacks.roof import RoofObjectAttack

    if not isinstance(seed, bool) and isinstance(seed, int) and seed > MAX_SEED:  # the rest: random_shape's check
        raise AttackSpecError(f"field 'seed': expected an integer in [0, 2**32 - 1], got {seed!r}")
    try:
        obj = random_shape(seed)
    except ValueError as exc:
        raise AttackSpecError(str(exc)) from None
    return RoofObjectAttack(obj, identity={"attack": "random-shape", "seed": seed}, **settings)


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


def resolve_attack_reference(reference: str) -> str:
    """A registered attack name for a ``run --attacks`` entry: names pass through; an entry ending in
    ``.ply`` is an object file, registered for this run under its sanitised file stem (returned)."""
    from robustbench3d.victims.onnx.registration import sanitise_name

    if not reference.lower().endswith(".ply"):
        return reference
    path = Path(reference).expanduser()
    if not path.is_file():
        raise RobustBenchError(f"--attacks {reference}: no such object file")
    name = sanitise_name(path.stem)
    if not name:
        raise RobustBenchError(f"--attacks {reference}: no attack name can be derived from the file name; "
                               "rename the file (letters and digits that fold to ASCII)")
    ATTACKS.names()  # discover the registry's own entries first: they take precedence
    try:
        ATTACKS.register(name, AttackSpec(factory=ObjectFileFactory(path), summary=f"object file {path.resolve()}"),
                         origin="object file")
    except RegistryError:
        raise RobustBenchError(f"--attacks {reference}: the file's name {name!r} is already a registered attack; "
                               "rename the file") from None
    return name


def resolve_attack_references(references: list[str], attack_args: dict[str, Any]) -> tuple[list[str], dict[str, Any]]:
    """Registered names for ``run --attacks`` entries and the keys of its ``--attack-arg`` mapping
    (an object file's path is replaced by its name in both; see :func:`resolve_attack_reference`)."""
    return ([resolve_attack_reference(a) for a in references],
            {resolve_attack_reference(k): v for k, v in attack_args.items()})
