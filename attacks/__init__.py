"""Attack objects placed on the roofs of target cars.

``ATTACKS`` is the registry (:class:`robustbench3d.registry.Registry` of
:class:`~robustbench3d.attacks.spec.AttackSpec`). In-tree attacks are declared with
:func:`register_attack` (the controls in :mod:`robustbench3d.attacks.controls`); installed
packages add theirs through the entry-point group ``robustbench3d.attacks`` (an entry point names
an ``AttackSpec``). The contract an attack implements is :class:`robustbench3d.attacks.base.Attack`.

    >>> from robustbench3d.attacks import ATTACKS, create_attack
    >>> ATTACKS.names()                                   # doctest: +SKIP
    ['none']
    >>> attack = create_attack("none")                    # doctest: +SKIP

Importing this package imports no numpy or torch.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from robustbench3d.attacks.spec import AttackRequirements, AttackSpec
from robustbench3d.registry import Registry

ENTRY_POINT_GROUP = "robustbench3d.attacks"

ATTACKS: Registry[AttackSpec] = Registry(
    "attack", group=ENTRY_POINT_GROUP, base=AttackSpec, key=lambda spec: spec.key,
    modules=("robustbench3d.attacks.controls",),
)


def register_attack(name: str, *, requirements: AttackRequirements | None = None,
                    summary: str = "") -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """Decorator: register a factory ``(**params) -> Attack`` (typically the class) under ``name``."""

    def decorator(factory: Callable[..., Any]) -> Callable[..., Any]:
        ATTACKS.register(name, AttackSpec(factory=factory, requirements=requirements or AttackRequirements(),
                                          summary=summary))
        return factory

    return decorator


def create_attack(name: str, **params: Any) -> Any:
    """Build the registered attack ``name`` with ``params`` (unknown names: did-you-mean error)."""
    return ATTACKS.get(name).create(name, **params)


__all__ = ["ATTACKS", "ENTRY_POINT_GROUP", "AttackRequirements", "AttackSpec", "create_attack", "register_attack"]
