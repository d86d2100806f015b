"""Victim models: the detectors under attack.

``VICTIMS`` is the registry (:class:`robustbench3d.registry.Registry` of
:class:`~robustbench3d.victims.base.VictimSpec`). In-tree victims are declared in
:mod:`robustbench3d.victims.zoo` with :func:`register_victim`; installed packages add theirs
through the entry-point group ``robustbench3d.victims`` (an entry point names a ``VictimSpec``);
ONNX victim directories added with ``victims add-onnx`` come from
:mod:`robustbench3d.victims.onnx.registration`.

    >>> from robustbench3d.victims import VICTIMS, create_victim
    >>> VICTIMS.names()                                   # doctest: +SKIP
    >>> victim = create_victim("fpointnet-v1", weights="runs/cascade")  # doctest: +SKIP

Importing this package does not import torch.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TypeVar

from robustbench3d.registry import Registry
from robustbench3d.victims.spec import Capabilities, EntryInfo, VictimSpec

if TYPE_CHECKING:
    from robustbench3d.victims.base import Detector

ENTRY_POINT_GROUP = "robustbench3d.victims"

VICTIMS: Registry[VictimSpec] = Registry(
    "victim", group=ENTRY_POINT_GROUP, base=VictimSpec, key=lambda spec: spec.key,
    modules=("robustbench3d.victims.zoo",),
    loaders=("robustbench3d.victims.onnx.registration:register_user_victims",),
)

#: A factory ``(**kwargs) -> Detector``.
VictimFactory = TypeVar("VictimFactory", bound="Callable[..., Detector]")


def register_victim(name: str, *, capabilities: Capabilities, weights_sha256: str | None = None,
                    summary: str = "") -> Callable[[VictimFactory], VictimFactory]:
    """Decorator: register a factory ``(**kwargs) -> Detector`` under ``name`` with its metadata;
    the factory is returned unchanged."""
    info = EntryInfo(capabilities=capabilities, weights_sha256=weights_sha256, summary=summary)

    def decorator(factory: VictimFactory) -> VictimFactory:
        VICTIMS.register(name, VictimSpec(factory=factory, info=info))
        return factory

    return decorator


def create_victim(name: str, **kwargs: Any) -> Detector:
    """Build the registered victim ``name`` (kwargs go to its factory) and check that it honours
    the :mod:`~robustbench3d.victims.base` contract its capabilities declare."""
    return VICTIMS.get(name).create(**kwargs)


def resolve_victim_references(references: list[str], victim_args: dict[str, Any]) -> tuple[list[str], dict[str, Any]]:
    """Registered names for ``run --victims`` entries and the keys of its ``--victim-arg`` mapping:
    names pass through; an entry naming a directory (an ONNX export, the one kind of victim given by
    path) is registered for this run under its directory name, which replaces it (so
    ``--victim-arg DIR:threads=2`` follows the directory)."""
    from robustbench3d.victims.onnx.registration import resolve_victim_reference

    return ([resolve_victim_reference(v) for v in references],
            {resolve_victim_reference(k): v for k, v in victim_args.items()})


__all__ = ["ENTRY_POINT_GROUP", "VICTIMS", "create_victim", "register_victim", "resolve_victim_references"]
