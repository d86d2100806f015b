"""Attack objects placed on the roofs of target cars.

``ATTACKS`` is the registry (:class:`robustbench3d.registry.Registry` of
:class:`~robustbench3d.attacks.spec.AttackSpec`). In-tree attacks are declared in
:mod:`robustbench3d.attacks.zoo` with :func:`register_attack`; the universal objects that ship with the
package register from their manifest (:mod:`robustbench3d.attacks.shipped`); installed packages add theirs
through the entry-point group ``robustbench3d.attacks`` (an entry point names an ``AttackSpec``); an object
file given as a reference (``run --attacks F.ply``: ``ATTACKS.resolve("F.ply")``,
:meth:`~robustbench3d.registry.Registry.resolve`) is registered under its file stem by
:func:`robustbench3d.attacks.zoo.object_file_reference`. The contract an attack implements is
:class:`robustbench3d.attacks.base.Attack`; attacks know the victim contract
(:mod:`robustbench3d.victims.base`, :mod:`robustbench3d.victims.spec`), never a victim backend.

    >>> from robustbench3d.attacks import ATTACKS, create_attack
    >>> ATTACKS.names()                                   # doctest: +SKIP
    ['none']
    >>> attack = create_attack("none")                    # doctest: +SKIP

Importing this package imports no numpy or torch.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TypeVar

from robustbench3d.attacks.spec import AttackRequirements, AttackSpec, AttackSpecError
from robustbench3d.registry import Registry

if TYPE_CHECKING:
    from robustbench3d.attacks.base import Attack

ENTRY_POINT_GROUP = "robustbench3d.attacks"

ATTACKS: Registry[AttackSpec] = Registry(
    "attack", group=ENTRY_POINT_GROUP, base=AttackSpec, key=lambda spec: spec.key,
    modules=("robustbench3d.attacks.zoo",),
    loaders=("robustbench3d.attacks.shipped:register_shipped_objects",),
    path_resolvers=("robustbench3d.attacks.zoo:object_file_reference",),
)

#: A factory ``(**params) -> Attack``: an Attack subclass or a function.
AttackFactory = TypeVar("AttackFactory", bound="Callable[..., Attack]")


def register_attack(name: str, *, requirements: AttackRequirements | None = None,
                    summary: str = "") -> Callable[[AttackFactory], AttackFactory]:
    """Decorator: register a factory ``(**params) -> Attack`` (typically the class) under ``name``;
    the factory is returned unchanged."""

    def decorator(factory: AttackFactory) -> AttackFactory:
        ATTACKS.register(name, AttackSpec(factory=factory, requirements=requirements or AttackRequirements(),
                                          summary=summary))
        return factory

    return decorator


def create_attack(name: str, **params: Any) -> Attack:
    """Build the registered attack ``name`` with ``params`` (unknown names: did-you-mean error;
    parameters the factory does not take: :class:`AttackSpecError` naming the attack)."""
    spec = ATTACKS.get(name)
    try:
        return spec.create(**params)
    except AttackSpecError as exc:
        raise AttackSpecError(f"attack {name!r}: {exc}") from None


def resolve_attack(reference: str) -> tuple[str, Attack]:
    """(registered name, the attack instance) of a reference: a registered name or an object file ``.ply``
    (:meth:`~robustbench3d.registry.Registry.resolve`), as ``run --attacks``, ``attack apply`` and ``show``
    take it."""
    name = ATTACKS.resolve(reference)
    return name, create_attack(name)


__all__ = [
    "ATTACKS", "ENTRY_POINT_GROUP", "AttackRequirements", "AttackSpec", "AttackSpecError",
    "create_attack", "register_attack", "resolve_attack",
]
